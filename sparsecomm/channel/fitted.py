"""A code fitted to a team's symbols, agreed before deployment (docs/channel.md).

The paper's code gives symbol ``m`` a codeword of ``floor(log2(m + 1))`` bits whatever the team
sends. A trained team's symbols are far from uniform and change little from one step to the
next, so a code fitted to their statistics sends fewer bits. Like the paper's code, the fitted
code is agreed a priori: it is fitted once to a trained team's episodes (:func:`fit`), written
as JSON (:meth:`FittedCode.to_json`) and shared by every sender and receiver.

Each link's packet is coded given the link's previous message (what the receiver decoded at the
previous step on this link; all nulls at an episode's start), in two parts:

1. the **presence pattern** (which of the C elements are not null, a C-bit number with element 0
   as its most significant bit) with a Huffman code chosen by the previous step's pattern: each
   of the ``contexts`` previous patterns seen most often when fitting has its own code, all
   other previous patterns share one;
2. each present element's **symbol** (1..levels) with a Huffman code chosen by the element and
   its previous symbol (``C x (levels + 1)`` codes).

An all-null link still sends no packet (0 bits). A packet is the codewords, zero-padded to a
byte, and a CRC-32 (4 bytes) of the implicit header (the element count C, the code's 4-byte
fingerprint and the previous message, never sent) and the body: a receiver whose previous
message differs from the sender's (a lost packet), or that holds another code, fails the check
instead of decoding a wrong message. Wire bits: ``8 * ceil(codeword bits / 8) + 32``.

Counts are smoothed (``alpha`` added to every cell) so that every pattern and every symbol has
a codeword, including those never seen when fitting. The codes are canonical Huffman codes
built deterministically from the counts, so the JSON (counts) fixes the code bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import heapq
import json
import math
import zlib

import jax.numpy as jnp
import numpy as np

__all__ = ["FittedCode", "fit", "previous", "huffman_lengths", "canonical_codes"]

FORMAT = "sparsecomm.fitted_code"
MAX_ELEMENTS = 12
"""Most elements per link a fitted code supports (its pattern alphabet has 2^C - 1 symbols)."""
MAX_LEVELS = 255
MAX_GROUP = 8
CRC_BYTES = 4


class _PacketError(ValueError):
    pass


def huffman_lengths(weights) -> np.ndarray:
    """Huffman codeword lengths of symbols with positive ``weights`` (ties broken by index, so
    the result is deterministic). One symbol gets length 0 (it needs no bits)."""
    w = np.asarray(weights, np.float64)
    n = w.size
    if n == 0 or not np.all(w > 0) or not np.all(np.isfinite(w)):
        raise ValueError("huffman_lengths needs one or more finite weights > 0")
    if n == 1:
        return np.zeros(1, np.int64)
    heap = [(float(w[i]), i) for i in range(n)]
    heapq.heapify(heap)
    parent = np.full(2 * n - 1, -1, np.int64)
    node = n
    while len(heap) > 1:
        wa, a = heapq.heappop(heap)
        wb, b = heapq.heappop(heap)
        parent[a] = parent[b] = node
        heapq.heappush(heap, (wa + wb, node))
        node += 1
    depth = np.zeros(2 * n - 1, np.int64)
    for i in range(2 * n - 3, -1, -1):  # parents are numbered after their children
        depth[i] = depth[parent[i]] + 1
    return depth[:n]


def canonical_codes(lengths) -> np.ndarray:
    """Canonical prefix codewords (as integers, read MSB first in ``lengths[i]`` bits)."""
    lengths = np.asarray(lengths, np.int64)
    codes = np.zeros(lengths.size, object)
    code, prev = 0, 0
    for i in sorted(range(lengths.size), key=lambda i: (lengths[i], i)):
        code <<= int(lengths[i]) - prev
        codes[i] = code
        prev = int(lengths[i])
        code += 1
    return codes


class _Decoder:
    """Canonical Huffman decoding table of one code (symbols 0..n-1)."""

    def __init__(self, lengths: np.ndarray):
        order = sorted(range(lengths.size), key=lambda i: (lengths[i], i))
        self.symbols = np.asarray(order, np.int64)
        self.max_len = int(lengths.max())
        counts = np.bincount(lengths, minlength=self.max_len + 1)
        self.count, self.first_code, self.first_index = [], [], []
        code = index = 0
        for length in range(self.max_len + 1):
            self.first_code.append(code)
            self.first_index.append(index)
            self.count.append(int(counts[length]))
            code = (code + int(counts[length])) << 1
            index += int(counts[length])

    def read(self, bits: str, pos: int) -> tuple[int, int]:
        """The symbol whose codeword starts at ``bits[pos]``, and the position after it."""
        code = 0
        if self.count[0]:  # a one-symbol code: no bits
            return int(self.symbols[0]), pos
        for length in range(1, self.max_len + 1):
            if pos >= len(bits):
                raise _PacketError("packet truncated inside a codeword")
            code = (code << 1) | (bits[pos] == "1")
            pos += 1
            offset = code - self.first_code[length]
            if 0 <= offset < self.count[length]:
                return int(self.symbols[self.first_index[length] + offset]), pos
        raise _PacketError("invalid codeword")  # unreachable for a complete Huffman code


def groups_of(elements: int, group: int) -> list[range]:
    """The elements split into ``ceil(elements / group)`` consecutive groups of near-equal size."""
    n = -(-elements // group)
    edges = [round(i * elements / n) for i in range(n + 1)]
    return [range(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


@dataclasses.dataclass(frozen=True, eq=False)
class FittedCode:
    """A conditional Huffman code fitted to a team's symbols (module docstring).

    Hashable (by its fingerprint), so it can sit in a jit-static config.
    """

    levels: int
    """The paper's |M|: symbols in [0, levels]."""
    elements: int
    """C, elements per link."""
    group: int
    """Elements per presence group: the presence pattern is coded in groups of (at most) this
    many elements, each group's pattern given that group's previous pattern."""
    pattern_counts: tuple[tuple[tuple[float, ...], ...], ...]
    """(groups, 2^group, 2^group): counts of each group's pattern by its previous pattern (a
    group of fewer elements uses the leading 2^size x 2^size block)."""
    symbol_counts: tuple[tuple[tuple[float, ...], ...], ...]
    """(C, levels + 1, levels): counts of each present element's symbol (index m - 1) by
    element and previous symbol of that element."""
    alpha: float = 0.5
    """Added to every count before the codes are built, so unseen patterns and symbols still
    have codewords. ours."""
    name: str = "fitted"

    def __post_init__(self):
        if not 1 <= self.elements <= MAX_ELEMENTS:
            raise ValueError(
                f"FittedCode.elements must be in [1, {MAX_ELEMENTS}], got {self.elements}"
            )
        if not 1 <= self.levels <= MAX_LEVELS:
            raise ValueError(f"FittedCode.levels must be in [1, {MAX_LEVELS}], got {self.levels}")
        if not 1 <= self.group <= min(self.elements, MAX_GROUP):
            raise ValueError(
                f"FittedCode.group must be in [1, {min(self.elements, MAX_GROUP)}], "
                f"got {self.group}"
            )
        if not (self.alpha > 0 and math.isfinite(self.alpha)):
            raise ValueError(f"FittedCode.alpha must be finite and > 0, got {self.alpha}")
        n_groups, width = len(groups_of(self.elements, self.group)), 1 << self.group
        pat = np.asarray(self.pattern_counts, np.float64)
        sym = np.asarray(self.symbol_counts, np.float64)
        if pat.shape != (n_groups, width, width):
            raise ValueError(
                f"FittedCode.pattern_counts must have shape {(n_groups, width, width)}, "
                f"got {pat.shape}"
            )
        if sym.shape != (self.elements, self.levels + 1, self.levels):
            raise ValueError(
                f"FittedCode.symbol_counts must have shape "
                f"{(self.elements, self.levels + 1, self.levels)}, got {sym.shape}"
            )
        finite = np.all(np.isfinite(pat)) and np.all(np.isfinite(sym))
        if not (finite and np.all(pat >= 0) and np.all(sym >= 0)):
            raise ValueError("FittedCode counts must be finite and >= 0")

    # -- identity -------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
            "levels": self.levels,
            "elements": self.elements,
            "group": self.group,
            "alpha": self.alpha,
            "pattern_counts": [[list(r) for r in g] for g in self.pattern_counts],
            "symbol_counts": [[list(r) for r in e] for e in self.symbol_counts],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str) -> FittedCode:
        """Read a code written by :meth:`to_json` (JSON only), checking every field."""
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"fitted code: not JSON ({e})") from None
        if not isinstance(d, dict) or d.get("format") != FORMAT or d.get("version") != 1:
            raise ValueError(f"fitted code: not a {FORMAT} version 1 file")
        try:
            return cls(
                levels=int(d["levels"]),
                elements=int(d["elements"]),
                group=int(d["group"]),
                alpha=float(d["alpha"]),
                pattern_counts=tuple(
                    tuple(tuple(float(x) for x in r) for r in g) for g in d["pattern_counts"]
                ),
                symbol_counts=tuple(
                    tuple(tuple(float(x) for x in r) for r in e) for e in d["symbol_counts"]
                ),
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"fitted code: missing or malformed field ({e})") from None

    @functools.cached_property
    def fingerprint(self) -> bytes:
        """First 4 bytes of the SHA-256 of the code's canonical JSON."""
        return hashlib.sha256(self.to_json().encode()).digest()[:4]

    def __hash__(self):
        return hash(self.fingerprint)

    def __eq__(self, other):
        return isinstance(other, FittedCode) and self.fingerprint == other.fingerprint

    # -- tables ---------------------------------------------------------------------------------
    @functools.cached_property
    def _tables(self):
        groups = groups_of(self.elements, self.group)
        pat = np.asarray(self.pattern_counts, np.float64) + self.alpha
        sym = np.asarray(self.symbol_counts, np.float64) + self.alpha
        width = 1 << self.group
        pat_len = np.zeros((len(groups), width, width), np.int64)
        pat_code, pat_dec = [], []
        for g, elems in enumerate(groups):
            n = 1 << len(elems)
            pat_len[g, :n, :n] = [huffman_lengths(r[:n]) for r in pat[g, :n]]
            pat_code.append([canonical_codes(r[:n]) for r in pat_len[g, :n]])
            pat_dec.append([_Decoder(r[:n]) for r in pat_len[g, :n]])
        sym_len = np.stack([np.stack([huffman_lengths(r) for r in e]) for e in sym])
        # element k's weight in its group's pattern (the group's first element is the MSB)
        weight = np.zeros(self.elements, np.int64)
        index = np.zeros(self.elements, np.int64)
        for g, elems in enumerate(groups):
            for j, k in enumerate(elems):
                weight[k], index[k] = 1 << (len(elems) - 1 - j), g
        return {
            "groups": groups,
            "weight": weight,
            "group_of": index,
            "pattern_len": pat_len,
            "symbol_len": sym_len,
            "pattern_code": pat_code,
            "symbol_code": [[canonical_codes(r) for r in e] for e in sym_len],
            "pattern_dec": pat_dec,
            "symbol_dec": [[_Decoder(r) for r in e] for e in sym_len],
        }

    @property
    def max_packet_bits(self) -> int:
        """The longest packet (bits): the longest pattern and symbol codewords, padding, CRC."""
        t = self._tables
        body = int(t["pattern_len"].max(axis=(1, 2)).sum())
        body += int(t["symbol_len"].max(axis=(1, 2)).sum())
        return 8 * (-(-body // 8)) + 8 * CRC_BYTES

    def _patterns(self, present):
        """Each group's pattern, (..., groups), numpy or jnp."""
        t = self._tables
        xp = jnp if isinstance(present, jnp.ndarray) else np
        one_hot = np.asarray(t["group_of"])[:, None] == np.arange(len(t["groups"]))[None, :]
        per = xp.asarray(one_hot * t["weight"][:, None])  # (C, groups)
        return (present.astype(xp.int32)[..., :, None] * per).sum(-2)

    # -- jnp: bits under jit ----------------------------------------------------------------------
    def code_bits(self, m, prev):
        """Codeword bits of each link (no padding, no CRC), jnp, ``(..., C) -> (...)``; 0 for a
        silent link."""
        t = self._tables
        m = jnp.asarray(m, jnp.int32)
        prev = jnp.asarray(prev, jnp.int32)
        present = m != 0
        p, pp = self._patterns(present), self._patterns(prev != 0)
        groups = jnp.arange(len(t["groups"]))
        plen = jnp.asarray(t["pattern_len"], jnp.int32)[groups, pp, p].sum(-1)
        slen = jnp.asarray(t["symbol_len"], jnp.int32)[
            jnp.arange(self.elements), prev, jnp.maximum(m - 1, 0)
        ]
        return jnp.where(present.any(-1), plen + jnp.where(present, slen, 0).sum(-1), 0)

    def ideal_bits(self, m, prev) -> np.ndarray:
        """``-log2`` of each link's probability under the code's smoothed model (numpy, bits;
        0 for a silent link): what an ideal entropy coder of the same model would spend."""
        t = self._tables
        m, prev = np.asarray(m, np.int64), np.asarray(prev, np.int64)
        present = m != 0
        p, pp = self._patterns(present), self._patterns(prev != 0)
        bits = np.zeros(m.shape[:-1])
        for g, elems in enumerate(t["groups"]):
            n = 1 << len(elems)
            probs = np.asarray(self.pattern_counts[g], np.float64)[:, :n] + self.alpha
            probs /= probs.sum(-1, keepdims=True)
            bits -= np.log2(probs[pp[..., g], p[..., g]])
        sym = np.asarray(self.symbol_counts, np.float64) + self.alpha
        sym /= sym.sum(-1, keepdims=True)
        ks = np.arange(self.elements)
        each = -np.log2(sym[ks, prev, np.maximum(m - 1, 0)])
        bits += np.where(present, each, 0.0).sum(-1)
        return np.where(present.any(-1), bits, 0.0)

    def wire_bits(self, m, prev, crc: bool = True):
        """Packet bits of each link, ``8 * len(encode(...))``, jnp, ``(..., C) -> (...)``."""
        body = self.code_bits(m, prev)
        packet = 8 * ((body + 7) // 8) + (8 * CRC_BYTES if crc else 0)
        return jnp.where(jnp.any(jnp.asarray(m) != 0, -1), packet, 0).astype(jnp.int32)

    # -- host: bytes ------------------------------------------------------------------------------
    def _crc(self, prev: np.ndarray, body: bytes) -> bytes:
        header = (
            self.elements.to_bytes(4, "big") + self.fingerprint + prev.astype(np.uint8).tobytes()
        )
        return zlib.crc32(body, zlib.crc32(header)).to_bytes(CRC_BYTES, "big")

    def _prev(self, prev) -> np.ndarray:
        if prev is None:
            return np.zeros(self.elements, np.int64)
        p = np.asarray(prev).reshape(-1).astype(np.int64)
        if p.size != self.elements or p.min() < 0 or p.max() > self.levels:
            raise ValueError(
                f"prev must hold {self.elements} symbols in [0, {self.levels}], got {prev!r}"
            )
        return p

    def encode(self, m, prev=None, crc: bool = True) -> bytes:
        """One link's packet; ``b""`` when every element is null."""
        m = np.asarray(m).reshape(-1).astype(np.int64)
        if m.size != self.elements:
            raise ValueError(f"a fitted code's link has {self.elements} elements, got {m.size}")
        if m.min() < 0 or m.max() > self.levels:
            raise ValueError(f"m must hold symbols in [0, {self.levels}], got {m.tolist()}")
        prev = self._prev(prev)
        present = m != 0
        if not present.any():
            return b""
        t = self._tables
        parts = []
        for g, (p, pp) in enumerate(
            zip(self._patterns(present), self._patterns(prev != 0), strict=True)
        ):
            n = int(t["pattern_len"][g, pp, p])
            parts.append(format(t["pattern_code"][g][pp][p], f"0{n}b") if n else "")
        for k in np.flatnonzero(present):
            n = int(t["symbol_len"][k, prev[k], m[k] - 1])
            parts.append(format(t["symbol_code"][k][prev[k]][m[k] - 1], f"0{n}b") if n else "")
        bits = "".join(parts)
        bits += "0" * (-len(bits) % 8)
        body = int(bits, 2).to_bytes(len(bits) // 8, "big") if bits else b""
        return body + (self._crc(prev, body) if crc else b"")

    def decode(self, data: bytes, prev=None, crc: bool = True) -> np.ndarray:
        """Invert :meth:`encode` (int64, shape (C,)); raises ``ValueError`` subclasses for any
        malformed packet (the caller, :func:`sparsecomm.channel.decode`, re-raises them as
        ``PacketError``)."""
        prev = self._prev(prev)
        if not data:
            return np.zeros(self.elements, np.int64)
        body = data
        if crc:
            if len(data) <= CRC_BYTES:
                raise _PacketError(f"packet truncated: {len(data)} bytes, no room for its CRC-32")
            body, tail = data[:-CRC_BYTES], data[-CRC_BYTES:]
            if self._crc(prev, body) != tail:
                raise _PacketError(
                    "packet corrupted, or decoded with another previous message "
                    "or code: CRC-32 mismatch"
                )
        if len(body) * 8 > self.max_packet_bits:
            raise _PacketError(f"packet too long: {len(body)} bytes before the CRC")
        bits = format(int.from_bytes(body, "big"), f"0{8 * len(body)}b") if body else ""
        t = self._tables
        present = np.zeros(self.elements, bool)
        pos = 0
        for g, (elems, pp) in enumerate(zip(t["groups"], self._patterns(prev != 0), strict=True)):
            p, pos = t["pattern_dec"][g][pp].read(bits, pos)
            present[list(elems)] = (p >> np.arange(len(elems) - 1, -1, -1)) & 1
        if not present.any():
            raise _PacketError("packet with no element present (silence is sent as no packet)")
        out = np.zeros(self.elements, np.int64)
        for k in np.flatnonzero(present):
            s, pos = t["symbol_dec"][k][prev[k]].read(bits, pos)
            out[k] = s + 1
        if len(bits) - pos >= 8 or "1" in bits[pos:]:
            raise _PacketError(f"packet has {len(bits) - pos} trailing bits (not padding)")
        return out


def previous(links: np.ndarray) -> np.ndarray:
    """Each step's previous message on its link, ``(N, T, C)``: all nulls at t = 0."""
    return np.concatenate([np.zeros_like(links[:, :1]), links[:, :-1]], axis=1)


def fit(symbols, valid=None, *, levels: int, group: int = 5, alpha: float = 0.5) -> FittedCode:
    """Fit a :class:`FittedCode` to links' symbol sequences.

    ``symbols`` (N, T, C): N links' (episodes x senders x recipients) symbols over T steps;
    ``valid`` (N, T): the steps that belong to the episode (a prefix of each row; default all).
    The previous message at t = 0 is all nulls. Only non-silent links are counted (a silent
    link sends no packet).
    """
    m = np.asarray(symbols, np.int64)
    if m.ndim != 3:
        raise ValueError(f"symbols must be (links, steps, elements), got shape {m.shape}")
    n, steps, c = m.shape
    valid = np.ones((n, steps), bool) if valid is None else np.asarray(valid, bool)
    prev = previous(m)
    busy = valid & (m != 0).any(-1)
    cur, prev = m[busy], prev[busy]
    groups = groups_of(c, group)
    pat_counts = np.zeros((len(groups), 1 << group, 1 << group))
    for g, elems in enumerate(groups):
        w = 1 << np.arange(len(elems) - 1, -1, -1)
        p = ((cur[:, list(elems)] != 0) * w).sum(-1)
        pp = ((prev[:, list(elems)] != 0) * w).sum(-1)
        np.add.at(pat_counts[g], (pp, p), 1)
    sym_counts = np.zeros((c, levels + 1, levels))
    i, k = np.nonzero(cur != 0)
    np.add.at(sym_counts, (k, prev[i, k], cur[i, k] - 1), 1)
    return FittedCode(
        levels=levels,
        elements=c,
        group=group,
        pattern_counts=tuple(tuple(tuple(r) for r in g) for g in pat_counts.tolist()),
        symbol_counts=tuple(tuple(tuple(r) for r in e) for e in sym_counts.tolist()),
        alpha=alpha,
    )
