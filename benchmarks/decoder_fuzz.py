"""Fuzz every decoder of ``sparsecomm.channel`` with malformed packets; measure the wire format.

Fuzzing (default): for each code, builds valid packets of random links (``--elements`` symbols
each, a random share of them null) and feeds ``decode`` ``--packets`` malformed packets, in equal
shares of six kinds:

* ``random``: random bytes, 1 to 2x the longest valid packet;
* ``truncated``: a valid packet cut to 1 .. len - 1 bytes (a cut to 0 bytes is the empty packet,
  i.e. silence, by design: telling a lost packet from a silent link is the transport's job);
* ``bit-flipped``: a valid packet with 1 to 8 distinct bits flipped;
* ``spliced``: a non-empty prefix of one valid packet followed by a suffix of another (possibly
  empty, possibly the whole packet: appended packets), never equal to either;
* ``wrong shape``: a valid packet decoded with another claimed shape (0 .. 4 C elements but not
  C, or a huge one, 2^25 .. 2^62 elements);
* ``re-checksummed``: one of the first four mutations applied to a packet's body, followed by a
  valid CRC-32, so that only the parser's checks stand in the way.

Each decode gets a time limit (``--time-limit`` seconds, SIGALRM). Counts: clean errors
(``PacketError``); valid decodes (``re-checksummed``: the packet is the valid packet of another
link, re-encoding the result gives it back; other kinds: the result is the original link,
impossible with a canonical encoding); silent wrong decodes (any other successful decode: for
the first five kinds, a result that is not the original link, or any result of random bytes;
for ``re-checksummed``, a packet accepted that its result does not re-encode to); other
exceptions; hangs. Only CRC-32 collisions should decode wrongly: ~2^-32 = 2.3e-10 per packet.

    python benchmarks/decoder_fuzz.py --packets 1000000

``--compare``: average wire bits per link of the presence encodings considered (a bitmap of C
bits against run lengths of nulls, next to the previous format), on sparse and uniform links.

    python benchmarks/decoder_fuzz.py --compare
"""

from __future__ import annotations

import dataclasses
import random
import signal
import time
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import tyro

from sparsecomm import channel


@dataclasses.dataclass
class Args:
    packets: int = 1_000_000
    """Malformed packets per code."""
    codes: tuple[str, ...] = channel.CODE_NAMES
    """Codes whose decoders to fuzz."""
    elements: int = 10
    """C, elements per link (paper: 10)."""
    levels: int = 15
    """|M|, symbols per element are {0, ..., levels}."""
    pool: int = 4096
    """Valid packets to mutate, per code."""
    time_limit: float = 1.0
    """Seconds one decode may take before it counts as a hang."""
    seed: int = 0
    """Seed of the messages and mutations."""
    compare: bool = False
    """Print the wire-bits comparison of presence encodings instead of fuzzing."""
    links: int = 100_000
    """``--compare``: links per distribution."""


KINDS = ("random", "truncated", "bit-flipped", "spliced", "wrong shape", "re-checksummed")


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang


def random_links(rng: np.random.Generator, n: int, c: int, levels: int, name: str) -> np.ndarray:
    """n links of c elements: each link draws a share of present elements in [0, 1]."""
    share = rng.random((n, 1))
    share[rng.random(n) < 0.1] = 0.0  # some silent links
    present = rng.random((n, c)) < share
    if name == "float32":
        values = rng.standard_normal((n, c)).astype(np.float32)
        values[values == 0] = 1.0
        return np.where(present, values, np.float32(0.0))
    return np.where(present, rng.integers(1, levels + 1, (n, c)), 0)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.shape != b.shape:
        return False
    if a.dtype == np.float32:
        return bool(np.array_equal(a.view(np.uint32), b.view(np.uint32)))
    return bool(np.array_equal(a, b))


def _mutate(r: random.Random, kind: str, pool: list[bytes], longest: int, c: int):
    """(packet, index of the original in the pool or -1, claimed element count)."""
    if kind == "random":
        return r.randbytes(r.randint(1, 2 * longest)), -1, c
    i = r.randrange(len(pool))
    p = pool[i]
    if kind == "truncated" and len(p) > 1:
        return p[: r.randint(1, len(p) - 1)], i, c
    if kind in ("truncated", "bit-flipped"):
        q = bytearray(p)
        for b in r.sample(range(8 * len(p)), min(r.randint(1, 8), 8 * len(p))):
            q[b // 8] ^= 1 << (b % 8)
        return bytes(q), i, c
    if kind == "spliced":
        while True:
            q = pool[r.randrange(len(pool))]
            out = p[: r.randint(1, len(p))] + q[r.randint(0, len(q)) :]
            if out != p and out != q:
                return out, i, c
    if r.random() < 0.5:  # wrong shape: huge, or small and != C
        return p, i, 1 << r.randint(25, 62)
    return p, i, r.choice([k for k in range(4 * c + 1) if k != c])


def _rechecksum(r: random.Random, bodies: list[bytes], longest: int, c: int):
    """A mutated body (random, truncated, bit-flipped or spliced) with a valid CRC-32 (the
    count-seeded CRC of sparsecomm.channel.codes): only the parser stands in the way."""
    body, i, _ = _mutate(r, r.choice(KINDS[:4]), bodies, longest - 4, c)
    crc = zlib.crc32(body, zlib.crc32(c.to_bytes(4, "big")))
    return body + crc.to_bytes(4, "big"), i, c


def fuzz_code(args: Args, name: str) -> dict:
    code = channel.Code(name, args.levels)
    c = args.elements
    rng = np.random.default_rng([args.seed, channel.CODE_NAMES.index(name)])
    links = random_links(rng, args.pool, c, args.levels, name)
    encoded = [channel.encode(link, code) for link in links]
    keep = [k for k, p in enumerate(encoded) if p]
    packets = [encoded[k] for k in keep]
    originals = [links[k] for k in keep]
    for p, m in zip(packets, originals, strict=True):  # the pool itself round-trips
        assert _same(channel.decode(p, code, (c,)), m)
    longest = max(map(len, packets))
    bodies = [p[:-4] for p in packets]
    r = random.Random(args.seed * 1_000_003 + channel.CODE_NAMES.index(name))
    counts = {
        kind: dict.fromkeys(("packets", "clean", "wrong", "valid", "other", "hang"), 0)
        for kind in KINDS
    }
    others: dict[str, int] = {}
    slowest = 0.0
    old = signal.signal(signal.SIGALRM, _alarm)
    try:
        for n in range(args.packets):
            kind = KINDS[n % len(KINDS)]
            if kind == "re-checksummed":
                data, i, count = _rechecksum(r, bodies, longest, c)
            else:
                data, i, count = _mutate(r, kind, packets, longest, c)
            row = counts[kind]
            row["packets"] += 1
            t0 = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, args.time_limit)
            try:
                out = channel.decode(data, code, (count,))
            except channel.PacketError:
                row["clean"] += 1
            except _Hang:
                row["hang"] += 1
            except Exception as e:  # noqa: BLE001 - counting every other failure is the point
                row["other"] += 1
                key = f"{type(e).__name__}: {e}"[:120]
                others[key] = others.get(key, 0) + 1
            else:
                if kind == "re-checksummed":  # a valid packet of another link, or accepted
                    ok = channel.encode(out, code) == data  # a non-canonical one (a bug)
                else:  # decoded to the original: impossible, the encoding is canonical
                    ok = count == c and _same(out, originals[i])
                row["valid" if ok else "wrong"] += 1
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            slowest = max(slowest, time.perf_counter() - t0)
    finally:
        signal.signal(signal.SIGALRM, old)
    return {"counts": counts, "others": others, "slowest": slowest}


def _gamma_bits(x: np.ndarray) -> np.ndarray:
    """Elias-gamma length of integers x >= 1."""
    return 2 * (np.floor(np.log2(x)).astype(np.int64)) + 1


def _paper_len(m: np.ndarray) -> np.ndarray:
    return np.floor(np.log2(m + 1)).astype(np.int64)


def _run_bits(present: np.ndarray) -> np.ndarray:
    """Run-length presence: gamma(r + 1) of the nulls before each present element, then of the
    trailing nulls unless the last element is present."""
    n, c = present.shape
    total = np.zeros(n, np.int64)
    run = np.zeros(n, np.int64)
    for k in range(c):
        p = present[:, k]
        total += np.where(p, _gamma_bits(run + 1), 0)
        run = np.where(p, 0, run + 1)
    return total + np.where(run > 0, _gamma_bits(run + 1), 0)


def _packet(silent: np.ndarray, body_bits: np.ndarray) -> np.ndarray:
    return np.where(silent, 0, 8 * -(-body_bits // 8) + 32)


def compare(args: Args) -> None:
    """Mean wire bits per link (silent links count 0) of the presence encodings."""
    rng = np.random.default_rng(args.seed)
    n, c, levels = args.links, args.elements, args.levels
    dists = {}
    for p in (0.05, 0.1, 0.2, 0.5):
        present = rng.random((n, c)) < p
        dists[f"sparse p={p}"] = np.where(present, rng.integers(1, levels + 1, (n, c)), 0)
    z = np.where(rng.random((n, c)) < 0.2, rng.random((n, c)), 0.0)  # 80% of z exactly 0
    m, _ = channel.quantize(jax.random.key(args.seed), jnp.asarray(z, jnp.float32), levels)
    dists["quantized z, 80% z = 0"] = np.asarray(m, np.int64)
    dists["uniform 0..15"] = rng.integers(0, levels + 1, (n, c))
    print(f"C={c} levels={levels} links/distribution={n} seed={args.seed}")
    print(
        "| links | code | silent links | payload | before: logged | before: packet | "
        "bitmap | runs of nulls | wire_bits |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for label, m in dists.items():
        present = m != 0
        silent = ~present.any(1)
        for name in ("paper", "fixed"):
            code = channel.Code(name, levels)
            if name == "paper":
                cw, old_el = 2 * _paper_len(m), 2 * _paper_len(m) + 1
            else:
                cw = np.where(present, code.fixed_width, 0)
                old_el = np.full(m.shape, code.fixed_width)
            payload = np.asarray(channel.payload_bits(m, code)).sum(1)
            logged = old_el.sum(1)
            old = 8 * -(-logged // 8) + 16

            bitmap = _packet(silent, c + cw.sum(1))
            runs = _packet(silent, _run_bits(present) + cw.sum(1))
            sent = np.asarray(channel.wire_bits(m, code))
            assert np.array_equal(sent, bitmap)
            print(
                f"| {label} | {name} | {silent.mean():.3f} | {payload.mean():.2f} | "
                f"{logged.mean():.2f} | {old.mean():.2f} | {bitmap.mean():.2f} | {runs.mean():.2f} "
                f"| {sent.mean():.2f} |"
            )


def main(args: Args) -> None:
    if args.compare:
        compare(args)
        return
    print(
        f"packets/code={args.packets} C={args.elements} levels={args.levels} "
        f"pool={args.pool} time limit={args.time_limit}s seed={args.seed}"
    )
    results = {}
    for name in args.codes:
        t0 = time.perf_counter()
        results[name] = fuzz_code(args, name)
        results[name]["seconds"] = time.perf_counter() - t0
    print(
        "| code | kind | packets | clean errors | valid decodes | silent wrong decodes (rate) | "
        "other exceptions | hangs |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, res in results.items():
        total = dict.fromkeys(("packets", "clean", "wrong", "valid", "other", "hang"), 0)
        for kind, row in res["counts"].items():
            for key in total:
                total[key] += row[key]
            print(_row(name, kind, row))
        print(_row(name, "**all**", total))
    for name, res in results.items():
        print(
            f"{name}: {res['seconds']:.1f} s, slowest decode {1e3 * res['slowest']:.2f} ms"
            + "".join(f"\n  other: {n} x {k}" for k, n in res["others"].items())
        )


def _row(name: str, kind: str, row: dict) -> str:
    rate = row["wrong"] / max(row["packets"], 1)
    return (
        f"| {name} | {kind} | {row['packets']:,} | {row['clean']:,} | {row['valid']:,} | "
        f"{row['wrong']} ({rate:.1e}) | {row['other']} | {row['hang']} |"
    )


if __name__ == "__main__":
    main(tyro.cli(Args))
