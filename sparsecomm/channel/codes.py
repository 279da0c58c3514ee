"""Codes: how symbols become real bit strings on the wire (SPEC section 2).

Four codes, each with two bit counts per message element:

============  =====================================  ==========================================
code          payload bits (what the paper counts)   wire bits (self-delimiting, on the network)
============  =====================================  ==========================================
``paper``     ``L(m) = floor(log2(m + 1))``           ``2 L(m) + 1`` (Elias-gamma of ``m + 1``)
``fixed``     ``ceil(log2(levels + 1))``              same
``float32``   32                                      same
============  =====================================  ==========================================

The paper's code maps ``m = 0`` to the null message (nothing sent) and ``m >= 1`` to the binary
strings in shortlex order: 1 -> "0", 2 -> "1", 3 -> "00", 4 -> "01", ... It is not prefix-free,
so a packet of several elements needs framing. Elias-gamma of ``m + 1`` is exactly that framing:
``L(m)`` zeros (the codeword length in unary), a ``1``, then the paper codeword. Its length
``2 L + 1`` differs from the paper's by an affine map, so the bit penalty stays a valid objective
(paper, section IV).

A packet (:func:`encode`) is the concatenation of the elements' wire codewords, zero-padded to a
whole byte, followed by a CRC-16/CCITT of those bytes (2 bytes, on by default) so that a corrupted
packet raises instead of decoding to wrong symbols. Wire bits per element exclude that per-packet
padding and checksum; :func:`packet_bits` gives the full packet size.

The message shape is agreed a priori (like the paper's C = 10 elements per link), so
:func:`decode` takes it as an argument. ``payload_bits`` and ``wire_bits`` are ``jnp`` functions,
usable under ``jit`` and ``vmap``; ``encode`` and ``decode`` are host-side (numpy, bytes).
"""

from __future__ import annotations

import binascii
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.quantizer import check_levels

__all__ = [
    "CODE_NAMES",
    "Code",
    "as_code",
    "paper_length",
    "payload_bits",
    "wire_bits",
    "encode",
    "decode",
    "packet_bits",
]

CODE_NAMES = ("paper", "fixed", "float32")
_CRC_BYTES = 2


@dataclasses.dataclass(frozen=True)
class Code:
    """A code for message elements with symbols in ``{0, ..., levels}`` (hashable, jit-static)."""

    name: str = "paper"
    """One of ``CODE_NAMES``: ``paper`` (the paper's variable-length code, Elias-gamma framed on
    the wire), ``fixed`` (fixed-width binary) or ``float32`` (raw IEEE floats, the unquantized
    baseline)."""
    levels: int = 15
    """The paper's |M| (SPEC section 1 default 15): symbols are integers in [0, levels]."""

    def __post_init__(self):
        if self.name not in CODE_NAMES:
            raise ValueError(f"code must be one of {CODE_NAMES}, got {self.name!r}")
        check_levels(self.levels)

    @property
    def fixed_width(self) -> int:
        """``ceil(log2(levels + 1))``: bits per element of the fixed-width code."""
        return int(self.levels).bit_length()

    @property
    def max_paper_length(self) -> int:
        """Longest paper codeword, ``floor(log2(levels + 1))``."""
        return (int(self.levels) + 1).bit_length() - 1


def as_code(code: Code | str, levels: int = 15) -> Code:
    """Accept a :class:`Code` or a code name (with ``levels``)."""
    if isinstance(code, Code):
        return code
    if not isinstance(code, str):
        raise ValueError(f"code must be a Code or one of {CODE_NAMES}, got {code!r}")
    return Code(code, levels)


def paper_length(m: jax.Array) -> jax.Array:
    """Exact paper codeword length ``floor(log2(m + 1))`` of integer symbols (int32, jittable)."""
    m = jnp.asarray(m, jnp.int32)
    return (31 - jax.lax.clz(m + 1)).astype(jnp.int32)


def payload_bits(m: jax.Array, code: Code | str = "paper") -> jax.Array:
    """Payload bits of each element (the paper's measure for ``paper``), int32, jittable."""
    code = as_code(code)
    m = jnp.asarray(m)
    if code.name == "paper":
        return paper_length(m)
    width = code.fixed_width if code.name == "fixed" else 32
    return jnp.full(m.shape, width, jnp.int32)


def wire_bits(m: jax.Array, code: Code | str = "paper") -> jax.Array:
    """Bits each element takes on the wire with self-delimiting framing, int32, jittable."""
    code = as_code(code)
    if code.name == "paper":
        return 2 * paper_length(m) + 1
    return payload_bits(m, code)


def _check_symbols(m: np.ndarray, code: Code) -> np.ndarray:
    if code.name == "float32":
        return np.asarray(m, np.float32).reshape(-1)
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


def encode(m, code: Code | str = "paper", *, crc: bool = True) -> bytes:
    """Pack message elements into a packet of bytes (see the module docstring for the format).

    ``m``: integer symbols in [0, levels] (any shape, flattened in C order), or floats for
    ``float32``. Raises ``ValueError`` for symbols out of range.
    """
    code = as_code(code)
    flat = _check_symbols(m, code)
    if code.name == "float32":
        body = flat.astype(">f4").tobytes()
    else:
        if code.name == "paper":
            values, lengths = flat + 1, 2 * (_np_bit_length(flat + 1) - 1) + 1
        else:
            values, lengths = flat, np.full(flat.shape, code.fixed_width)
        body = np.packbits(_write_bits(values, lengths)).tobytes()
    if crc:
        body += binascii.crc_hqx(body, 0xFFFF).to_bytes(_CRC_BYTES, "big")
    return body


def _np_bit_length(x: np.ndarray) -> np.ndarray:
    out = np.zeros(x.shape, np.int64)
    x = x.copy()
    while np.any(x):
        nz = x > 0
        out[nz] += 1
        x >>= 1
    return out


def decode(data: bytes, code: Code | str, shape, *, crc: bool = True) -> np.ndarray:
    """Unpack a packet made by :func:`encode` into an array of the agreed ``shape``.

    Returns int64 symbols (float32 values for ``float32``). Raises ``ValueError`` when the packet
    is truncated, too long, fails its checksum, holds an invalid codeword or symbols outside
    [0, levels], or has non-zero padding. Runs in time linear in ``len(data)``.
    """
    code = as_code(code)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f"data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    shape = tuple(int(s) for s in np.atleast_1d(np.asarray(shape, np.int64))) if shape != () else ()
    if any(s < 0 for s in shape):
        raise ValueError(f"shape must have non-negative sizes, got {shape}")
    count = int(np.prod(shape, dtype=np.int64))
    if crc:
        if len(data) < _CRC_BYTES:
            raise ValueError(f"packet truncated: {len(data)} bytes, shorter than its checksum")
        data, tail = data[:-_CRC_BYTES], data[-_CRC_BYTES:]
        if binascii.crc_hqx(data, 0xFFFF).to_bytes(_CRC_BYTES, "big") != tail:
            raise ValueError("packet corrupted: CRC-16 checksum mismatch")
    if code.name == "float32":
        if len(data) != 4 * count:
            raise ValueError(
                f"packet has {len(data)} bytes, expected {4 * count} for {count} floats"
            )
        return np.frombuffer(data, ">f4").astype(np.float32).reshape(shape)
    bits = np.unpackbits(np.frombuffer(data, np.uint8))
    out = np.zeros(count, np.int64)
    pos = 0
    n = bits.size
    if code.name == "fixed":
        w = code.fixed_width
        need = w * count
        if need > n:
            raise ValueError(f"packet truncated: {count} elements need {need} bits, got {n}")
        if count:
            weights = 1 << np.arange(w - 1, -1, -1)
            out = bits[:need].reshape(count, w).astype(np.int64) @ weights
        pos = need
    else:
        max_zeros = code.max_paper_length
        for k in range(count):
            zeros = 0
            while pos < n and bits[pos] == 0 and zeros <= max_zeros:
                zeros += 1
                pos += 1
            if zeros > max_zeros:
                raise ValueError(
                    f"invalid codeword at element {k}: length prefix exceeds {max_zeros} bits"
                )
            if pos + zeros >= n:
                raise ValueError(f"packet truncated inside element {k} of {count}")
            value = 0
            for b in bits[pos : pos + zeros + 1]:
                value = (value << 1) | int(b)
            pos += zeros + 1
            out[k] = value - 1
    if count and out.max() > code.levels:
        raise ValueError(f"decoded symbol {out.max()} outside [0, {code.levels}]")
    rest = bits[pos:]
    if rest.size >= 8 or np.any(rest):
        raise ValueError(
            f"packet has {rest.size} trailing bits after {count} elements (not padding)"
        )
    return out.reshape(shape)


def packet_bits(m, code: Code | str = "paper", *, crc: bool = True) -> int:
    """Size in bits of the packet :func:`encode` makes for ``m`` (padding and CRC included)."""
    return 8 * len(encode(m, code, crc=crc))
