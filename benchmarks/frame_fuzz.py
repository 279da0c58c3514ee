"""Fuzz the per-sender frame (``sparsecomm.channel.frames``) at every check width: how often a
corrupted frame is accepted as a wrong message.

For each width in ``channel.CHECK_BITS`` and each team size K in ``--agents`` (equal shares of
``--frames``), builds valid frames of one sender's L = K - 1 links of ``--elements`` symbols,
drawn like a trained team's: each link silent with probability ``--silent``, else each element
non-null with probability ``--busy``, a non-null symbol being min(geometric(0.35), levels)
(small symbols most often). Silent senders send no frame and are redrawn. Each frame is then
corrupted, in equal shares of four kinds:

* ``flips``: 1 to 3 distinct bits flipped;
* ``burst``: a burst of b bits, b uniform in 1 .. min(16, frame bits), at a uniform position:
  its first and last bits flipped, the bits between at random;
* ``resize``: truncated or extended (equal odds) by 1 to 3 bytes; a truncation keeps at least
  one byte (a cut to ``b""`` is silence by design: telling a lost frame from a silent sender is
  the transport's job, not the check's), an extension appends random bytes;
* ``random``: random bytes of the frame's length.

and decoded with the agreed shape and width. Counts: refused (``FrameError``), accepted and
correct (the decoded links are the original's: impossible with a canonical encoding, since the
corrupted frame differs from the original), accepted but **wrong** (the silent failure), other
exceptions (a bug), and no-op corruptions (random bytes equal to the frame), excluded from the
rest. The accepted-wrong rate gets a 95% Clopper-Pearson interval, next to 2^-width (what a
check of that width lets through of frames the parser alone cannot refuse; width 0 is no check,
the parser alone).

    python benchmarks/frame_fuzz.py --frames 1000000 --out docs/results/wire/frame_fuzz.json

Work is split into seeded chunks (``--chunk`` frames of one width and K, each its own seed), run
by ``--workers`` processes: the counts do not depend on the number of workers.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import random
import time
from pathlib import Path

import numpy as np
import tyro
from scipy import stats

from sparsecomm import channel
from sparsecomm.jsonfile import write_json

KINDS = ("flips", "burst", "resize", "random")
COUNTS = ("frames", "refused", "correct", "wrong", "other", "noop")


@dataclasses.dataclass
class Args:
    frames: int = 1_000_000
    """Corrupted frames per check width (split equally between the team sizes)."""
    widths: tuple[int, ...] = channel.CHECK_BITS
    """Check widths in bits to fuzz (each one of ``channel.CHECK_BITS``)."""
    agents: tuple[int, ...] = (2, 4)
    """Team sizes K: a sender's frame carries L = K - 1 links."""
    elements: int = 10
    """C, elements per link (paper: 10)."""
    levels: int = 15
    """|M|, symbols per element are {0, ..., levels}."""
    code: str = "paper"
    """Code of the elements: ``paper``, ``fixed`` or ``float32``."""
    busy: float = 0.3
    """Probability that an element of a speaking link is non-null."""
    silent: float = 0.5
    """Probability that a link is silent."""
    seed: int = 0
    """Seed of the messages and corruptions."""
    workers: int = 2
    """Processes decoding in parallel."""
    chunk: int = 25_000
    """Frames per unit of work (one width, one K, one seed)."""
    out: Path | None = None
    """Write the counts and the summary to this JSON file."""


def team_links(rng: np.random.Generator, n: int, args: Args, num_links: int) -> np.ndarray:
    """``n`` senders' (L, C) links, none of them all silent (a silent sender sends no frame)."""
    code = channel.Code(args.code, args.levels)
    shape = (num_links, args.elements)
    kept, have = [], 0
    while have < n:
        batch = 2 * (n - have) + 16
        present = rng.random((batch, *shape)) < args.busy
        present &= ~(rng.random((batch, num_links)) < args.silent)[..., None]
        if code.name == "float32":
            values = rng.standard_normal((batch, *shape)).astype(np.float32)
            values[values == 0] = 1.0
            m = np.where(present, values, np.float32(0.0)).astype(np.float32)
        else:
            values = np.minimum(rng.geometric(0.35, (batch, *shape)), args.levels)
            m = np.where(present, values, 0)
        m = m[present.any((1, 2))]
        kept.append(m[: n - have])
        have += len(kept[-1])
    return np.concatenate(kept)


def corrupt(r: random.Random, kind: str, frame: bytes) -> bytes:
    """``frame`` corrupted by one mutation of ``kind`` (see the module docstring)."""
    nbits = 8 * len(frame)
    if kind == "flips":
        x = int.from_bytes(frame, "big")
        for p in r.sample(range(nbits), min(r.randint(1, 3), nbits)):
            x ^= 1 << p
        return x.to_bytes(len(frame), "big")
    if kind == "burst":
        b = r.randint(1, min(16, nbits))
        pattern = 1 if b == 1 else (1 << (b - 1)) | 1 | (r.getrandbits(b - 2) << 1 if b > 2 else 0)
        start = r.randint(0, nbits - b)  # the burst's first bit, from the frame's first
        x = int.from_bytes(frame, "big") ^ (pattern << (nbits - start - b))
        return x.to_bytes(len(frame), "big")
    if kind == "resize":
        k = r.randint(1, 3)
        if r.random() < 0.5 and len(frame) > 1:
            return frame[: len(frame) - min(k, len(frame) - 1)]
        return frame + r.randbytes(k)
    return r.randbytes(len(frame))


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype == np.float32:
        return bool(np.array_equal(a.view(np.uint32), b.view(np.uint32)))
    return bool(np.array_equal(a, b))


def run_chunk(task: tuple) -> tuple:
    """Fuzz one chunk: ``(args, width, K, index, n)`` -> ``(width, K, counts by kind, others)``."""
    args, width, agents, index, n = task
    seq = np.random.SeedSequence([args.seed, width, agents, index])
    rng = np.random.default_rng(seq)
    r = random.Random(int(seq.generate_state(1, np.uint64)[0]))
    code = channel.Code(args.code, args.levels)
    num_links = agents - 1
    links = team_links(rng, n, args, num_links)
    counts = {kind: dict.fromkeys(COUNTS, 0) for kind in KINDS}
    others: dict[str, int] = {}
    for i, m in enumerate(links):
        frame = channel.encode_frame(m, code, check_bits=width)
        kind = KINDS[(index * n + i) % len(KINDS)]
        row = counts[kind]
        data = corrupt(r, kind, frame)
        if data == frame:
            row["noop"] += 1
            continue
        row["frames"] += 1
        try:
            out = channel.decode_frame(data, code, num_links, args.elements, check_bits=width)
        except channel.FrameError:
            row["refused"] += 1
        except Exception as e:  # noqa: BLE001 - counting every other failure is the point
            row["other"] += 1
            key = f"{type(e).__name__}: {e}"[:120]
            others[key] = others.get(key, 0) + 1
        else:
            row["correct" if _same(out, m) else "wrong"] += 1
    return width, agents, counts, others


def _total(rows) -> dict:
    total = dict.fromkeys(COUNTS, 0)
    for row in rows:
        for key in COUNTS:
            total[key] += row[key]
    return total


def _summary(row: dict, width: int) -> dict:
    n, k = row["frames"], row["wrong"]
    ci = stats.binomtest(k, n).proportion_ci(0.95, method="exact") if n else None
    return {
        **row,
        "wrong_rate": k / n if n else None,
        "wrong_ci95": [ci.low, ci.high] if ci else None,
        "two_to_minus_width": 2.0**-width,
    }


def main(args: Args) -> None:
    for width in args.widths:
        channel.check_width(width, "widths")
    print(
        f"frames/width={args.frames:,} K={args.agents} C={args.elements} levels={args.levels} "
        f"code={args.code} busy={args.busy} silent={args.silent} seed={args.seed} "
        f"workers={args.workers}",
        flush=True,
    )
    tasks = []
    for width in args.widths:
        for j, agents in enumerate(args.agents):
            share = args.frames // len(args.agents) + (j < args.frames % len(args.agents))
            for index, start in enumerate(range(0, share, args.chunk)):
                tasks.append((args, width, agents, index, min(args.chunk, share - start)))
    counts = {
        w: {a: {kind: dict.fromkeys(COUNTS, 0) for kind in KINDS} for a in args.agents}
        for w in args.widths
    }
    others: dict[str, int] = {}
    t0 = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        for done, (width, agents, chunk, chunk_others) in enumerate(
            pool.imap_unordered(run_chunk, tasks), 1
        ):
            for kind, row in chunk.items():
                for key in COUNTS:
                    counts[width][agents][kind][key] += row[key]
            for key, v in chunk_others.items():
                others[key] = others.get(key, 0) + v
            if done % max(1, len(tasks) // 20) == 0 or done == len(tasks):
                print(f"  {done}/{len(tasks)} chunks, {time.perf_counter() - t0:.0f} s", flush=True)
    seconds = time.perf_counter() - t0
    summary = {}
    print(
        "| check bits | K | corrupted frames | refused | accepted, correct | accepted, WRONG | "
        "wrong rate | 95% CI (Clopper-Pearson) | 2^-width |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---|---:|")
    for width in args.widths:
        rows = {str(a): _total(counts[width][a].values()) for a in args.agents}
        rows["all"] = _total(rows.values())
        summary[str(width)] = {
            "by_agents": {a: _summary(row, width) for a, row in rows.items()},
            "by_kind": {
                kind: _summary(_total(counts[width][a][kind] for a in args.agents), width)
                for kind in KINDS
            },
        }
        for a, s in summary[str(width)]["by_agents"].items():
            print(_row(width, a if a == "all" else f"K={a}", s))
    print()
    print("accepted-wrong frames by corruption (all K; rate):")
    print("| check bits | " + " | ".join(KINDS) + " |")
    print("|---:|" + "---:|" * len(KINDS))
    for width in args.widths:
        cells = [summary[str(width)]["by_kind"][kind] for kind in KINDS]
        print(
            f"| {width} | "
            + " | ".join(f"{c['wrong']:,} / {c['frames']:,} ({c['wrong_rate']:.1e})" for c in cells)
            + " |"
        )
    noop = sum(_total(counts[w][a].values())["noop"] for w in args.widths for a in args.agents)
    print(f"{seconds:.0f} s, {args.workers} workers; no-op corruptions excluded: {noop}")
    for key, v in others.items():
        print(f"  other: {v} x {key}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(
            args.out,
            {
                "args": {**dataclasses.asdict(args), "out": str(args.out)},
                "seconds": seconds,
                "summary": summary,
                "counts": {
                    str(w): {str(a): counts[w][a] for a in args.agents} for w in args.widths
                },
                "other_exceptions": others,
            },
        )
        print(f"wrote {args.out}")


def _row(width: int, label: str, s: dict) -> str:
    lo, hi = s["wrong_ci95"]
    return (
        f"| {width} | {label} | {s['frames']:,} | {s['refused']:,} | {s['correct']:,} | "
        f"{s['wrong']:,} | {s['wrong_rate']:.2e} | [{lo:.2e}, {hi:.2e}] | "
        f"{s['two_to_minus_width']:.2e} |"
    )


if __name__ == "__main__":
    main(tyro.cli(Args))
