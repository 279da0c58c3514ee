"""Fuzz every decoder of ``sparsecomm.channel`` with malformed packets; measure the wire format.

Fuzzing (default): for each code, builds valid packets of random links (``--elements`` symbols
each, a random share of them null) and feeds ``decode`` ``--packets`` malformed packets, in equal
shares of six kinds (seven for ``fitted``):

* ``random``: random bytes, 1 to 2x the longest valid packet;
* ``truncated``: a valid packet cut to 1 .. len - 1 bytes (a cut to 0 bytes is the empty packet,
  i.e. silence, by design: telling a lost packet from a silent link is the transport's job);
* ``bit-flipped``: a valid packet with 1 to 8 distinct bits flipped;
* ``spliced``: a non-empty prefix of one valid packet followed by a suffix of another (possibly
  empty, possibly the whole packet: appended packets), never equal to either;
* ``wrong shape``: a valid packet decoded with another claimed shape (0 .. 4 C elements but not
  C, or a huge one, 2^25 .. 2^62 elements);
* ``re-checksummed``: one of the first four mutations applied to a packet's body, followed by a
  valid CRC-32 (seeded with the packet's implicit header, as the code does), so that only the
  parser's checks stand in the way;
* ``wrong prev`` (``fitted`` only): a valid packet decoded with another previous message (the
  packet's with one element changed, or another packet's).

``fitted``: a :class:`~sparsecomm.channel.fitted.FittedCode` fitted (seeded) to a sticky
synthetic source like a trained team's (400 links x 60 steps); the pool's links are steps of a
fresh source, each coded given its previous step (3/4) or a random valid message (1/4), and every
mutated packet is decoded with its packet's previous message (random bytes: any packet's).

Each decode gets a time limit (``--time-limit`` seconds, SIGALRM). Counts: clean errors
(``PacketError``); valid decodes (``re-checksummed``: the packet is the valid packet of another
link, re-encoding the result gives it back; other kinds: the result is the original link,
impossible with a canonical encoding); silent wrong decodes (any other successful decode: for
the other kinds, a result that is not the original link, or any result of random bytes;
for ``re-checksummed``, a packet accepted that its result does not re-encode to); other
exceptions; hangs. Only CRC-32 collisions should decode wrongly: ~2^-32 = 2.3e-10 per packet
(for ``fitted``, ``wrong shape`` is always a clean error: it holds only C elements).

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
from sparsecomm.channel.fitted import FittedCode, fit

NAMES = (*channel.CODE_NAMES, "fitted")


@dataclasses.dataclass
class Args:
    packets: int = 1_000_000
    """Malformed packets per code."""
    codes: tuple[str, ...] = NAMES
    """Codes whose decoders to fuzz (``fitted``: a code fitted to a sticky synthetic source)."""
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
FITTED_KINDS = (*KINDS, "wrong prev")


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


def sticky_links(rng: np.random.Generator, n: int, steps: int, c: int, levels: int) -> np.ndarray:
    """(n, steps, c) symbols like a trained team's (``sticky_source`` of the fitted code's
    tests): the first elements mostly null, the last mostly busy; each element keeps its symbol
    with probability 0.8, else is redrawn (null with the element's probability, else 1 + a
    geometric number)."""
    null_p = np.linspace(0.95, 0.1, c)

    def draw():
        busy = rng.random((n, c)) > null_p
        return np.where(busy, np.minimum(rng.geometric(0.35, (n, c)), levels), 0)

    out = np.zeros((n, steps, c), np.int64)
    out[:, 0] = draw()
    for t in range(1, steps):
        out[:, t] = np.where(rng.random((n, c)) < 0.8, out[:, t - 1], draw())
    return out


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
    if kind == "wrong prev":  # the packet itself: the caller changes its previous message
        return p, i, c
    if kind == "spliced":
        while True:
            q = pool[r.randrange(len(pool))]
            out = p[: r.randint(1, len(p))] + q[r.randint(0, len(q)) :]
            if out != p and out != q:
                return out, i, c
    if r.random() < 0.5:  # wrong shape: huge, or small and != C
        return p, i, 1 << r.randint(25, 62)
    return p, i, r.choice([k for k in range(4 * c + 1) if k != c])


def _crc(body: bytes, c: int, code, prev) -> bytes:
    """The CRC-32 of a packet's body, seeded with its implicit header: the count C and the
    code's fingerprint (the CRC of sparsecomm.channel.codes), then for a fitted code the
    previous message (``FittedCode._crc``)."""
    header = c.to_bytes(4, "big") + code.fingerprint
    if isinstance(code, FittedCode):
        header += prev.astype(np.uint8).tobytes()
    return zlib.crc32(body, zlib.crc32(header)).to_bytes(4, "big")


def _other_prev(r: random.Random, prevs: list, prev: np.ndarray, levels: int) -> np.ndarray:
    """A valid previous message other than ``prev``: ``prev`` with one element changed, or
    another packet's."""
    while True:
        if r.random() < 0.5:
            other = prev.copy()
            other[r.randrange(other.size)] = r.randint(0, levels)
        else:
            other = prevs[r.randrange(len(prevs))]
        if not np.array_equal(other, prev):
            return other


def fuzz_code(args: Args, name: str) -> dict:
    c = args.elements
    rng = np.random.default_rng([args.seed, NAMES.index(name)])
    if name == "fitted":
        source = sticky_links(rng, 400, 60, c, args.levels)
        code = fit(source, levels=args.levels, group=min(5, c))
        steps = sticky_links(rng, args.pool, 2, c, args.levels)  # (previous step, step)
        links = steps[:, 1]
        random_prev = random_links(rng, args.pool, c, args.levels, "paper")
        prev_all = np.where(rng.random((args.pool, 1)) < 0.75, steps[:, 0], random_prev)
    else:
        code = channel.Code(name, args.levels)
        links = random_links(rng, args.pool, c, args.levels, name)
        prev_all = [None] * args.pool  # the named codes have no previous message
    encoded = [channel.encode(m, code, prev=q) for m, q in zip(links, prev_all, strict=True)]
    keep = [k for k, p in enumerate(encoded) if p]
    packets = [encoded[k] for k in keep]
    originals = [links[k] for k in keep]
    prevs = [prev_all[k] for k in keep]
    for p, m, q in zip(packets, originals, prevs, strict=True):  # the pool itself round-trips
        assert _same(channel.decode(p, code, (c,), prev=q), m)
        assert _crc(p[:-4], c, code, q) == p[-4:]  # and re-checksumming computes its CRC
    longest = max(map(len, packets))
    bodies = [p[:-4] for p in packets]
    r = random.Random(args.seed * 1_000_003 + NAMES.index(name))
    kinds = FITTED_KINDS if name == "fitted" else KINDS
    counts = {
        kind: dict.fromkeys(("packets", "clean", "wrong", "valid", "other", "hang"), 0)
        for kind in kinds
    }
    others: dict[str, int] = {}
    slowest = 0.0
    old = signal.signal(signal.SIGALRM, _alarm)
    try:
        for n in range(args.packets):
            kind = kinds[n % len(kinds)]
            if kind == "re-checksummed":  # a mutated body with a valid CRC-32
                data, i, count = _mutate(r, r.choice(KINDS[:4]), bodies, longest - 4, c)
            else:
                data, i, count = _mutate(r, kind, packets, longest, c)
            prev = prevs[i if i >= 0 else n % len(prevs)]  # random bytes: any packet's
            if kind == "re-checksummed":
                data += _crc(data, c, code, prev)
            elif kind == "wrong prev":
                prev = _other_prev(r, prevs, prev, args.levels)
            row = counts[kind]
            row["packets"] += 1
            t0 = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, args.time_limit)
            try:
                out = channel.decode(data, code, (count,), prev=prev)
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
                    ok = channel.encode(out, code, prev=prev) == data  # a non-canonical one (a bug)
                else:  # decoded to the original: impossible, the encoding is canonical
                    ok = count == c and _same(out, originals[i])
                row["valid" if ok else "wrong"] += 1
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            slowest = max(slowest, time.perf_counter() - t0)
    finally:
        signal.signal(signal.SIGALRM, old)
    fingerprint = code.fingerprint.hex() if name == "fitted" else None
    return {"counts": counts, "others": others, "slowest": slowest, "fingerprint": fingerprint}


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
            + (f", code fingerprint {res['fingerprint']}" if res["fingerprint"] else "")
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
