"""Codes: how symbols become real bit strings on the wire (SPEC section 2).

Three codes. Payload bits are counted per message element (what the paper counts); wire bits
per link, as the exact size of the packet :func:`encode` writes for the link's ``C`` elements:

============  =====================================  =============================================
code          payload bits per element               a present (non-null) element in the packet
============  =====================================  =============================================
``paper``     ``L(m) = floor(log2(m + 1))``           ``2 L(m)`` bits (unary length, codeword)
``fixed``     ``ceil(log2(levels + 1))``              ``ceil(log2(levels + 1))`` bits
``float32``   32                                      32 bits (IEEE big-endian)
============  =====================================  =============================================

The paper's code maps ``m = 0`` to the null message (nothing sent) and ``m >= 1`` to the binary
strings in shortlex order: 1 -> "0", 2 -> "1", 3 -> "00", 4 -> "01", ... It is not prefix-free,
so a packet of several elements needs framing: a present element is written as ``L - 1`` zeros
and a one (its length in unary), then its paper codeword (``L`` bits), together ``2 L`` bits
(Elias-gamma of ``m + 1`` without its first zero, which the presence bit makes redundant). Its
length differs from the paper's by an affine map, so the bit penalty stays a valid objective
(paper, section IV).

Packet of one link (:func:`encode`, docs/channel.md):

* **Silence is free**: a link whose elements are all null (symbol 0; for ``float32``, the bit
  pattern of +0.0) sends no packet, ``b""``, 0 wire bits.
* Otherwise: a presence bitmap of ``C`` bits (bit k set when element k is not null), then the
  present elements' codewords in order, zero-padded to a whole byte (for ``float32`` the bitmap
  is padded to a byte and the floats follow, 4 bytes each), then a CRC-32 (``zlib.crc32``, 4
  bytes, big-endian) of an implicit header, agreed and not sent, and everything before it. The
  implicit header is the element count ``C`` (4 bytes big-endian) followed by the code's
  :attr:`Code.fingerprint` (4 bytes), so a receiver agreed on another shape or another code
  (name, levels or remap) gets a mismatch instead of a wrong message. No length field: the
  decoder knows where the packet must end and rejects any other length. Wire bits:
  ``8 * ceil((C + codeword bits) / 8) + 32``.

The code's **identity** (:attr:`Code.identity`), the canonical bytes of what sender and
receiver agree on, is (all integers big-endian, unsigned):

1. 1 byte, the length of the name, then the name in ASCII (``paper``, ``fixed``, ``float32``);
2. 1 byte ``n``, then ``levels`` in ``n`` bytes (``n >= 1`` minimal: ``ceil(bits / 8)``);
3. 4 bytes, the number ``R`` of rows of ``Code.remap`` (0: no remap);
4. ``R * (levels + 1)`` entries ``remap[k][m]``, row by row, ``n`` bytes each.

Its **fingerprint** (:attr:`Code.fingerprint`) is the first 4 bytes of its SHA-256. Two
agreements that differ only in the code (or only in ``C``) change the header in one 4-byte word,
and a CRC-32 detects every such change, so every packet of one is refused under the other
(unless their fingerprints collide, ~2^-32 per pair of codes); when both differ, a mismatch
passes with probability ~2^-32 per pair of agreements.

The message shape is agreed a priori (like the paper's C = 10 elements per link), so
:func:`decode` takes it as an argument. The encoding is canonical (one packet per message): a
decoder rejects trailing bytes, non-zero padding, a non-empty packet with no element present and
a present element with a null codeword, so a packet that decodes to a wrong message must have
passed the CRC-32 by chance (probability ~2^-32 for a corrupted packet). Every malformed packet
raises :class:`PacketError` (a ``ValueError``), and the claimed shape is checked against the
packet's size before anything is allocated.

``payload_bits`` and ``wire_bits`` are ``jnp`` functions, usable under ``jit`` and ``vmap``;
``encode`` and ``decode`` are host-side (numpy, bytes).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import operator
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.quantizer import check_levels

__all__ = [
    "CODE_NAMES",
    "MAX_ELEMENTS",
    "Code",
    "PacketError",
    "as_code",
    "frequency_remap",
    "paper_length",
    "payload_bits",
    "wire_bits",
    "encode",
    "decode",
    "packet_bits",
]

CODE_NAMES = ("paper", "fixed", "float32")
CRC_BYTES = 4
MAX_ELEMENTS = 1 << 24
"""Most elements one packet may carry (and :func:`decode` may be asked for): 16,777,216. An
all-null message of any size is the empty packet, so its size cannot bound the claimed shape."""


class PacketError(ValueError):
    """A packet :func:`decode` cannot decode into the agreed shape: truncated, too long,
    corrupted (CRC-32 mismatch), malformed, or a claimed shape the packet cannot hold."""


@dataclasses.dataclass(frozen=True)
class Code:
    """A code for message elements with symbols in ``{0, ..., levels}`` (hashable, jit-static)."""

    name: str = "paper"
    """One of ``CODE_NAMES``: ``paper`` (the paper's variable-length code, length-framed on
    the wire), ``fixed`` (fixed-width binary) or ``float32`` (raw IEEE floats, the unquantized
    baseline)."""
    levels: int = 15
    """The paper's |M| (SPEC section 1 default 15): symbols are integers in [0, levels]."""
    remap: tuple[tuple[int, ...], ...] = ()
    """``paper`` only, a learned code (docs/channel.md): row k maps element k's symbol m to the
    paper codeword ``remap[k][m]`` sent for it (a permutation of 0..levels keeping 0, the null), so
    the symbols a team sends most get the shortest codewords (:func:`frequency_remap`). Empty:
    the paper's code. Payload bits are then ``L(remap[k][m])``."""

    def __post_init__(self):
        if self.name not in CODE_NAMES:
            raise ValueError(f"code must be one of {CODE_NAMES}, got {self.name!r}")
        check_levels(self.levels)
        if self.remap:
            if self.name != "paper":
                raise ValueError(f"Code.remap is for the paper code only, got {self.name!r}")
            for k, row in enumerate(self.remap):
                if sorted(row) != list(range(self.levels + 1)) or row[0] != 0:
                    raise ValueError(
                        f"Code.remap[{k}] must be a permutation of 0..{self.levels} with "
                        f"remap[{k}][0] = 0, got {row}"
                    )

    def mapped(self, m):
        """The codeword indices of symbols ``m`` (..., C): ``remap[k][m]``, or ``m`` itself."""
        if not self.remap:
            return m
        table = np.asarray(self.remap)
        if isinstance(m, np.ndarray):
            return table[np.arange(table.shape[0]), m]
        return jnp.asarray(table, jnp.int32)[jnp.arange(table.shape[0]), m]

    def unmapped(self, index: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`mapped` (host side)."""
        if not self.remap:
            return index
        inverse = np.argsort(np.asarray(self.remap), axis=1)
        return inverse[np.arange(inverse.shape[0]), index]

    def lengths(self) -> np.ndarray:
        """(C, levels + 1) payload bits of each element's symbols (remapped paper code)."""
        table = np.asarray(self.remap)
        return np.floor(np.log2(table + 1)).astype(np.int32)

    def wire_lengths(self, num_elements: int) -> np.ndarray:
        """(C, levels + 1) bits each element's symbol adds to a packet's body beyond the
        presence bitmap (0 for the null, which is absent): ``2 L(remap[k][m])`` for the paper
        code, ``fixed_width`` for the fixed one. Not for ``float32``, which sends values."""
        if self.name == "float32":
            raise ValueError("Code.wire_lengths is for symbol codes ('paper', 'fixed')")
        m = np.broadcast_to(np.arange(self.levels + 1), (num_elements, self.levels + 1))
        if self.name == "fixed":
            return np.where(m > 0, self.fixed_width, 0).astype(np.int32)
        if self.remap and len(self.remap) != num_elements:
            raise ValueError(f"a remapped code's links have {len(self.remap)} elements")
        index = np.asarray(self.remap) if self.remap else m  # remap[k][m] for every m
        return (2 * np.floor(np.log2(index + 1))).astype(np.int32)

    @functools.cached_property
    def identity(self) -> bytes:
        """The code's canonical bytes: name, levels and remap (layout: module docstring)."""
        n = max(1, -(-int(self.levels).bit_length() // 8))
        name = self.name.encode("ascii")
        out = [bytes([len(name)]), name, bytes([n]), int(self.levels).to_bytes(n, "big")]
        out.append(len(self.remap).to_bytes(4, "big"))
        out.extend(int(x).to_bytes(n, "big") for row in self.remap for x in row)
        return b"".join(out)

    @functools.cached_property
    def fingerprint(self) -> bytes:
        """First 4 bytes of the SHA-256 of :attr:`identity`, in every packet's and frame's
        implicit header (so a receiver with another code refuses the packet)."""
        return hashlib.sha256(self.identity).digest()[:4]

    @property
    def fixed_width(self) -> int:
        """``ceil(log2(levels + 1))``: bits per element of the fixed-width code."""
        return int(self.levels).bit_length()

    @property
    def max_paper_length(self) -> int:
        """Longest paper codeword, ``floor(log2(levels + 1))``."""
        return (int(self.levels) + 1).bit_length() - 1


def frequency_remap(counts) -> tuple[tuple[int, ...], ...]:
    """A learned code's ``Code.remap`` from each element's symbol counts ``(C, levels)`` (index
    m - 1): the most frequent symbol gets codeword 1 (1 bit), the next two 2 and 3, and so on
    (ties by symbol); the null stays 0."""
    counts = np.asarray(counts, np.float64)
    rows = []
    for row in counts:
        order = np.argsort(-row, kind="stable")  # symbols (minus 1), most frequent first
        remap = np.zeros(row.size + 1, np.int64)
        remap[order + 1] = np.arange(1, row.size + 1)
        rows.append(tuple(int(x) for x in remap))
    return tuple(rows)


def as_code(code: Code | FittedCode | str, levels: int = 15) -> Code | FittedCode:
    """Accept a :class:`Code`, a :class:`~sparsecomm.channel.fitted.FittedCode` or a code name
    (with ``levels``; a fitted code has no name alone: it is its tables)."""
    if isinstance(code, (Code, FittedCode)):
        return code
    if not isinstance(code, str) or code == "fitted":
        raise ValueError(f"code must be a Code, a FittedCode or one of {CODE_NAMES}, got {code!r}")
    return Code(code, levels)


def paper_length(m: jax.Array) -> jax.Array:
    """Exact paper codeword length ``floor(log2(m + 1))`` of integer symbols (int32, jittable)."""
    m = jnp.asarray(m, jnp.int32)
    return (31 - jax.lax.clz(m + 1)).astype(jnp.int32)


def payload_bits(m: jax.Array, code: Code | str = "paper") -> jax.Array:
    """Payload bits of each element (the paper's measure for ``paper``), int32, jittable."""
    code = as_code(code)
    m = jnp.asarray(m)
    if code.name in ("paper", "fitted"):  # the paper's count, whatever the wire code
        return paper_length(code.mapped(m) if code.name == "paper" else m)
    width = code.fixed_width if code.name == "fixed" else 32
    return jnp.full(m.shape, width, jnp.int32)


def wire_bits(
    m: jax.Array, code: Code | FittedCode | str = "paper", *, crc: bool = True, prev=None
) -> jax.Array:
    """Bits on the wire of each link: ``8 * len(encode(link, code, crc=crc))``, int32, jittable.

    ``m`` (..., C): the last axis holds one link's elements (a scalar is a link of one element);
    returns (...). 0 for an all-null link (no packet); else the presence bitmap, the present
    elements' codewords, the padding to a byte and the CRC-32. Symbols are assumed valid (in
    [0, levels]; :func:`encode` checks them, this function cannot under ``jit``). ``prev``
    (same shape): each link's previous message, for a fitted code (default: all nulls).
    """
    code = as_code(code)
    m = jnp.asarray(m)
    if isinstance(code, FittedCode):
        return code.wire_bits(m, jnp.zeros_like(m) if prev is None else prev, crc)
    if m.ndim == 0:
        m = m[None]
    c = m.shape[-1]
    if code.name == "float32":
        words = jax.lax.bitcast_convert_type(m.astype(jnp.float32), jnp.uint32)
        present = words != 0
        body = 8 * (-(-c // 8)) + 32 * present.sum(-1, dtype=jnp.int32)
    else:
        present = m != 0
        if code.name == "paper":
            per_element = 2 * paper_length(code.mapped(m))
        else:
            per_element = jnp.where(present, code.fixed_width, 0)
        body = c + per_element.sum(-1, dtype=jnp.int32)
    packet = 8 * ((body + 7) // 8) + (8 * CRC_BYTES if crc else 0)
    return jnp.where(present.any(-1), packet, 0).astype(jnp.int32)


def _check_symbols(m: np.ndarray, code: Code) -> np.ndarray:
    if code.name == "float32":
        return np.ascontiguousarray(np.asarray(m, np.float32).reshape(-1))
    m = np.asarray(m)
    if m.size and not np.issubdtype(m.dtype, np.integer):
        if not np.all(np.isfinite(m)) or np.any(m != np.round(m)):
            raise ValueError(f"m must hold integer symbols in [0, {code.levels}], got {m.dtype}")
    m = m.astype(np.int64).reshape(-1)
    if m.size and (m.min() < 0 or m.max() > code.levels):
        raise ValueError(
            f"m must hold symbols in [0, {code.levels}], got values in [{m.min()}, {m.max()}]"
        )
    return m


def _write_bits(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Big-endian bits of ``values[k]`` in ``lengths[k]`` bits each, concatenated (uint8 0/1)."""
    if values.size == 0:
        return np.zeros(0, np.uint8)
    width = int(lengths.max())
    pos = np.arange(width)
    shift = np.maximum(lengths[:, None] - 1 - pos[None, :], 0)
    bits = (values[:, None] >> shift) & 1
    return bits[pos[None, :] < lengths[:, None]].astype(np.uint8)


def _np_bit_length(x: np.ndarray) -> np.ndarray:
    out = np.zeros(x.shape, np.int64)
    x = x.copy()
    while np.any(x):
        nz = x > 0
        out[nz] += 1
        x >>= 1
    return out


def encode(m, code: Code | FittedCode | str = "paper", *, crc: bool = True, prev=None) -> bytes:
    """Pack one link's message elements into a packet of bytes (format: module docstring).

    ``m``: integer symbols in [0, levels] (any shape, flattened in C order, at most
    :data:`MAX_ELEMENTS`), or floats for ``float32``. Returns ``b""`` when every element is
    null. Raises ``ValueError`` for symbols out of range. ``prev``: the link's previous
    message, for a fitted code (default: all nulls; ignored by the other codes).
    """
    code = as_code(code)
    if isinstance(code, FittedCode):
        return code.encode(m, prev, crc)
    flat = _check_symbols(m, code)
    if flat.size > MAX_ELEMENTS:
        raise ValueError(f"a packet carries at most {MAX_ELEMENTS} elements, got {flat.size}")
    if code.name == "float32":
        present = flat.view(np.uint32) != 0
        if not present.any():
            return b""
        body = np.packbits(present).tobytes() + flat[present].astype(">f4").tobytes()
    else:
        present = flat != 0
        if not present.any():
            return b""
        if code.remap:
            if flat.size % len(code.remap):
                raise ValueError(f"a remapped code's links have {len(code.remap)} elements")
            flat = code.mapped(flat.reshape(-1, len(code.remap))).reshape(-1)
        values = flat[present]
        if code.name == "paper":
            # L - 1 zeros, a one, the L-bit paper codeword: m + 1 written in 2 L bits.
            values, lengths = values + 1, 2 * (_np_bit_length(values + 1) - 1)
        else:
            lengths = np.full(values.shape, code.fixed_width)
        bits = np.concatenate([present.astype(np.uint8), _write_bits(values, lengths)])
        body = np.packbits(bits).tobytes()
    if crc:
        body += _crc(code, flat.size, body)
    return body


def _crc(code: Code, count: int, body: bytes) -> bytes:
    """CRC-32 of the implicit header (the element count, 4 bytes big-endian, then the code's
    fingerprint; agreed, not sent) and the body."""
    header = count.to_bytes(4, "big") + code.fingerprint
    return zlib.crc32(body, zlib.crc32(header)).to_bytes(CRC_BYTES, "big")


def _check_shape(shape) -> tuple[int, ...]:
    try:
        dims = (shape,) if isinstance(shape, (int, np.integer)) else tuple(shape)
        dims = tuple(operator.index(s) for s in dims)
    except TypeError:
        raise PacketError(f"shape must be a tuple of integers, got {shape!r}") from None
    if any(s < 0 for s in dims):
        raise PacketError(f"shape must have non-negative sizes, got {dims}")
    return dims


def decode(
    data: bytes, code: Code | FittedCode | str, shape, *, crc: bool = True, prev=None
) -> np.ndarray:
    """Unpack a packet made by :func:`encode` into an array of the agreed ``shape``.

    Returns int64 symbols (float32 values for ``float32``); ``b""`` decodes to all nulls.
    Raises :class:`PacketError` when the packet is truncated, too long, fails its checksum,
    holds an invalid codeword, symbols outside [0, levels], non-zero padding or a non-canonical
    encoding, or cannot hold ``shape`` (checked before allocating). Time linear in
    ``len(data)``. ``prev``: the receiver's previous message on this link, for a fitted code
    (default: all nulls; a packet coded with another previous message fails its CRC).
    """
    code = as_code(code)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise PacketError(f"data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    shape = _check_shape(shape)
    count = math.prod(shape)
    if isinstance(code, FittedCode):
        if count != code.elements:
            raise PacketError(f"a fitted code's link has {code.elements} elements, shape {shape}")
        try:
            return code.decode(data, prev, crc).reshape(shape)
        except PacketError:
            raise
        except ValueError as e:
            raise PacketError(str(e)) from None
    dtype = np.float32 if code.name == "float32" else np.int64
    if count > MAX_ELEMENTS:
        raise PacketError(f"claimed shape {shape} has {count} elements, over {MAX_ELEMENTS}")
    if not data:
        return np.zeros(shape, dtype)
    body = data
    if crc:
        if len(data) <= CRC_BYTES:
            raise PacketError(f"packet truncated: {len(data)} bytes, no room for its CRC-32")
        body, tail = data[:-CRC_BYTES], data[-CRC_BYTES:]
        if _crc(code, count, body) != tail:
            raise PacketError("packet corrupted: CRC-32 mismatch")
    if count == 0:
        raise PacketError(f"a message of no elements is sent as no packet, got {len(data)} bytes")
    if count > 8 * len(body):
        raise PacketError(
            f"packet truncated or claimed shape too large: {shape} needs a {count}-bit "
            f"presence bitmap, the packet has {8 * len(body)} bits"
        )
    if code.name == "float32":
        out = _decode_float32(body, count)
    else:
        out = _decode_symbols(body, code, count)
        if code.remap:
            if count % len(code.remap):
                raise PacketError(f"a remapped code's links have {len(code.remap)} elements")
            out = code.unmapped(out.reshape(-1, len(code.remap))).reshape(-1)
    return out.reshape(shape)


def _decode_float32(body: bytes, count: int) -> np.ndarray:
    nmap = -(-count // 8)
    bitmap = np.unpackbits(np.frombuffer(body[:nmap], np.uint8))
    if bitmap[count:].any():
        raise PacketError("non-zero padding after the presence bitmap")
    present = bitmap[:count].astype(bool)
    k = int(np.count_nonzero(present))
    if k == 0:
        raise PacketError("packet with no element present (silence is sent as no packet)")
    if len(body) != nmap + 4 * k:
        what = "truncated" if len(body) < nmap + 4 * k else "too long"
        raise PacketError(
            f"packet {what}: {k} present floats need {nmap + 4 * k} bytes, got {len(body)}"
        )
    words = np.frombuffer(body[nmap:], ">u4").astype(np.uint32)
    if not words.all():
        raise PacketError("a present element holds +0.0, the null value (invalid codeword)")
    out = np.zeros(count, np.float32)
    out[present] = words.view(np.float32)
    return out


def _decode_symbols(body: bytes, code: Code, count: int) -> np.ndarray:
    nbits = 8 * len(body)
    bits = format(int.from_bytes(body, "big"), f"0{nbits}b")  # '0'/'1' string, linear time
    k = bits.count("1", 0, count)
    if k == 0:
        raise PacketError("packet with no element present (silence is sent as no packet)")
    pos = count
    if code.name == "fixed":
        w = code.fixed_width
        end = pos + w * k
        if end > nbits:
            raise PacketError(f"packet truncated: {k} present elements need {end} bits of {nbits}")
        digits = np.frombuffer(bits[pos:end].encode(), np.uint8).reshape(k, w) - ord("0")
        values = digits.astype(np.int64) @ (1 << np.arange(w - 1, -1, -1, dtype=np.int64))
        pos = end
        if values.min() == 0:
            raise PacketError("a present element holds the null symbol 0 (invalid codeword)")
    else:
        max_len = code.max_paper_length
        values = np.empty(k, np.int64)
        for i in range(k):
            one = bits.find("1", pos, min(pos + max_len, nbits))
            if one < 0:
                if pos + max_len > nbits:
                    raise PacketError(f"packet truncated inside present element {i} of {k}")
                raise PacketError(f"invalid codeword: length prefix exceeds {max_len} bits")
            length = one - pos + 1
            pos = one + 1 + length
            if pos > nbits:
                raise PacketError(f"packet truncated inside present element {i} of {k}")
            values[i] = int(bits[one:pos], 2) - 1
    if values.max() > code.levels:
        raise PacketError(f"decoded symbol {values.max()} outside [0, {code.levels}]")
    if nbits - pos >= 8 or "1" in bits[pos:]:
        raise PacketError(
            f"packet has {nbits - pos} trailing bits after {k} present elements (not padding)"
        )
    out = np.zeros(count, np.int64)
    out[np.frombuffer(bits[:count].encode(), np.uint8) == ord("1")] = values
    return out


def packet_bits(m, code: Code | FittedCode | str = "paper", *, crc: bool = True, prev=None) -> int:
    """Size in bits of the packet :func:`encode` makes for ``m`` (padding and CRC included)."""
    return 8 * len(encode(m, code, crc=crc, prev=prev))
