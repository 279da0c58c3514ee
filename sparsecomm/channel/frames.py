"""Frames: one frame per sender and step, carrying all its non-silent links (wire format).

Instead of one packet per link (:func:`~sparsecomm.channel.codes.encode`, each with its own
CRC-32), a sender writes **one frame** per step for its ``L = K - 1`` links (its recipient slots,
in ``channel.others`` order), ``C`` elements each, with symbols in ``{0, ..., levels}`` (0 is the
null) and an integrity check of a configurable width. Format (exact):

* **Silence is free**: when every link is silent (all its symbols null; for ``float32``, every
  bit pattern +0.0), there is no frame: ``b""``, 0 bits.
* Otherwise the **body** is the bit concatenation of

  1. an ``L``-bit **recipient map**: bit ``l`` set when link ``l`` speaks (has at least one
     non-null element);
  2. for each speaking link, in slot order: its ``C``-bit **presence bitmap** (bit ``k`` set
     when element ``k`` is not null), then its present elements' **codewords**, written exactly
     as :func:`~sparsecomm.channel.codes.encode` writes them inside one packet: ``paper``,
     ``m + 1`` in ``2 L(m)`` bits (``L(m) - 1`` zeros, a one, the ``L(m)``-bit paper codeword),
     with ``Code.remap`` the mapped symbol ``remap[k][m]`` instead of ``m``; ``fixed``,
     ``fixed_width`` bits; ``float32``, the 32-bit IEEE big-endian word of each present value
     (no byte padding inside the body, unlike a ``float32`` packet);

  with no padding between links, then zero padding to a whole byte.
* Then the **check**: the top ``check_bits`` bits (big-endian, ``check_bits // 8`` bytes) of
  ``zlib.crc32`` over an implicit header, agreed and never sent, followed by the body. The
  implicit header is the code's 4-byte :attr:`~sparsecomm.channel.codes.Code.fingerprint` (the
  SHA-256 of its identity: name, levels, remap; layout in :mod:`sparsecomm.channel.codes`),
  4-byte big-endian ``L``, 4-byte big-endian ``C`` and 1 byte ``check_bits`` (13 bytes), so a
  receiver agreed on another code, shape or width gets a mismatch instead of a wrong message.
  ``check_bits`` is one of :data:`CHECK_BITS`; 0 means no check (a baseline for
  ``benchmarks/frame_fuzz.py``, not for use). Under a 32-bit check, two agreements of the same
  width that differ in one 4-byte field of the header (code, ``L`` or ``C``) disagree on the
  check of every frame (a CRC-32 detects any change within 32 bits), and other mismatches pass
  with probability ~2^-32; an 8- or 16-bit check, like any check of that width, passes a
  mismatched frame that the canonical parse accepts with probability ~2^-check_bits.

Frame bits: ``8 * ceil((L + sum over speaking links of (C + codeword bits)) / 8) + check_bits``,
0 when silent. :func:`link_bits` gives each link's share of the body (0 if silent, else ``C`` +
its codeword bits), :func:`frame_bits` the frame's size; both are ``jnp`` functions, usable
under ``jit`` and ``vmap``. With ``L = 1`` the body is one bit (the map) longer than the link's
packet body for the symbol codes.

The encoding is canonical (exactly one frame per message): :func:`decode_frame` rejects a
truncated or too long frame, a check mismatch, an invalid codeword (a null codeword, a length
prefix longer than the longest codeword, +0.0 for ``float32``), a symbol above ``levels``,
non-zero padding, a speaking link with no element present, a non-empty frame whose recipient map
is all zeros, and trailing bits or bytes. So, with a 32-bit check, a corrupted frame decodes to a
wrong message only if it passed the check by chance (~2^-32). Every malformed frame raises
:class:`FrameError` (a :class:`~sparsecomm.channel.codes.PacketError`), and the claimed shape is
checked against the frame's size before anything is allocated. Decoding takes time linear in the
frame's length.

Fitted codes (:class:`~sparsecomm.channel.fitted.FittedCode`) keep their own per-link packets:
their codewords depend on the link's previous message, which a frame does not carry. A symbol
code's ``levels`` is at most :data:`MAX_LEVELS` (int32 symbols).
``encode_frame`` and ``decode_frame`` are host-side (numpy, bytes).
"""

from __future__ import annotations

import operator
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.codes import MAX_ELEMENTS, Code, PacketError, as_code, paper_length
from sparsecomm.channel.fitted import FittedCode

__all__ = [
    "CHECK_BITS",
    "MAX_LEVELS",
    "FrameError",
    "check_width",
    "encode_frame",
    "decode_frame",
    "frame_bits",
    "link_bits",
]

CHECK_BITS = (0, 8, 16, 32)
"""Allowed widths of a frame's check, in bits: the top bits of its CRC-32 (0: no check)."""


MAX_LEVELS = (1 << 31) - 1
"""Largest ``levels`` of a code in a frame: symbols are int32 in :func:`frame_bits` (codewords
then fit in 62 bits)."""


class FrameError(PacketError):
    """A frame :func:`decode_frame` cannot decode into the agreed ``(L, C)`` links: truncated,
    too long, corrupted (check mismatch), malformed, or a claimed shape it cannot hold."""


def check_width(check_bits, name: str = "check_bits") -> int:
    """Validate a check width in bits: one of :data:`CHECK_BITS` (``name`` is the field named in
    the error). Returns it as a Python int; raises ``ValueError`` otherwise."""
    ok = isinstance(check_bits, (int, np.integer)) and not isinstance(check_bits, bool)
    if not ok or int(check_bits) not in CHECK_BITS:
        raise ValueError(f"{name} must be one of {CHECK_BITS} (bits), got {check_bits!r}")
    return int(check_bits)


def _frame_code(code: Code | FittedCode | str) -> Code:
    code = as_code(code)
    if isinstance(code, FittedCode):
        raise ValueError(
            "frames do not support fitted codes: fitted codes keep their own per-link packets "
            "(their codewords depend on each link's previous message)"
        )
    if code.name != "float32" and code.levels > MAX_LEVELS:
        raise ValueError(f"frames carry levels <= {MAX_LEVELS} (int32 symbols), got {code.levels}")
    return code


def _remap_rows(code: Code, num_elements: int, error=ValueError) -> int:
    """Rows of ``code.remap`` (0 without one); ``C`` must be a multiple of them."""
    rows = len(code.remap)
    if rows and num_elements % rows:
        raise error(
            f"a remapped code's links have a multiple of {rows} elements, got num_elements "
            f"{num_elements}"
        )
    return rows


def link_bits(m: jax.Array, code: Code | str) -> jax.Array:
    """Bits each link adds to its sender's frame body, int32, jittable.

    Args:
        m: (..., L, C) symbols in [0, levels] (float values for ``float32``), a sender's ``L``
            links of ``C`` elements each. Symbols are assumed valid (:func:`encode_frame`
            checks them; this function cannot under ``jit``).
        code: a :class:`~sparsecomm.channel.codes.Code` or a code name (not a fitted code).

    Returns:
        (..., L) int32 bits: 0 for a silent link; else ``C`` (its presence bitmap) plus its
        present elements' codeword bits (``2 L(m)`` each for ``paper``, with ``Code.remap`` of
        the mapped symbol; ``fixed_width`` for ``fixed``; 32 for ``float32``). The recipient
        map, the padding and the check are the frame's (:func:`frame_bits`).
    """
    code = _frame_code(code)
    m = jnp.asarray(m)
    if m.ndim < 2:
        raise ValueError(f"m must be (..., L, C) links, got shape {m.shape}")
    c = m.shape[-1]
    if code.name == "float32":
        present = jax.lax.bitcast_convert_type(m.astype(jnp.float32), jnp.uint32) != 0
        per_element = jnp.where(present, 32, 0)
    else:
        present = m != 0
        if code.name == "paper":
            rows = _remap_rows(code, c)
            if rows:
                grouped = m.reshape(*m.shape[:-1], c // rows, rows)
                index = code.mapped(grouped).reshape(m.shape)
            else:
                index = m
            per_element = 2 * paper_length(index)
        else:
            per_element = jnp.where(present, code.fixed_width, 0)
    body = c + per_element.sum(-1, dtype=jnp.int32)
    return jnp.where(present.any(-1), body, 0).astype(jnp.int32)


def frame_bits(m: jax.Array, code: Code | str, check_bits: int = 32) -> jax.Array:
    """Bits of each sender's frame: ``8 * len(encode_frame(m[idx], code, check_bits=...))``.

    Args:
        m: (..., L, C) symbols (float values for ``float32``): per sender, its ``L`` links of
            ``C`` elements. Symbols are assumed valid, as in :func:`link_bits`.
        code: a :class:`~sparsecomm.channel.codes.Code` or a code name (not a fitted code).
        check_bits: width of the check, one of :data:`CHECK_BITS` (static under ``jit``).

    Returns:
        (...) int32 bits, jittable: 0 when every link is silent (no frame), else
        ``8 * ceil((L + sum(link_bits)) / 8) + check_bits``.
    """
    per_link = link_bits(m, code)
    return frame_bits_of(
        per_link.sum(-1, dtype=jnp.int32), (per_link > 0).any(-1), m.shape[-2], check_bits
    )


def frame_bits_of(body, speaks, num_links: int, check_bits: int = 32) -> jax.Array:
    """:func:`frame_bits` from a sender's sums: ``body`` (...) int, the :func:`link_bits` of its
    links summed; ``speaks`` (...) bool, any of them is not silent; ``num_links``, its L link
    slots (the recipient map's bits). (...) int32."""
    check_bits = check_width(check_bits)
    frame = 8 * ((num_links + body + 7) // 8) + check_bits
    return jnp.where(speaks, frame, 0).astype(jnp.int32)


def _symbols(links, code: Code) -> np.ndarray:
    """``links`` as a checked (L, C) array: float32 for ``float32``, else int64 in [0, levels]."""
    if code.name == "float32":
        m = np.ascontiguousarray(links, np.float32)
    else:
        m = np.asarray(links)
        if m.size and not np.issubdtype(m.dtype, np.integer):
            if m.dtype == bool or not np.all(np.isfinite(m)) or np.any(m != np.round(m)):
                raise ValueError(
                    f"links must hold integer symbols in [0, {code.levels}], got {m.dtype}"
                )
        m = m.astype(np.int64)
        if m.size and (m.min() < 0 or m.max() > code.levels):
            raise ValueError(
                f"links must hold symbols in [0, {code.levels}], got values in "
                f"[{m.min()}, {m.max()}]"
            )
    if m.ndim != 2 or m.shape[0] < 1 or m.shape[1] < 1:
        raise ValueError(f"links must be (L, C) with L >= 1 and C >= 1, got shape {m.shape}")
    if m.size > MAX_ELEMENTS:
        raise ValueError(f"a frame carries at most {MAX_ELEMENTS} elements, got {m.size}")
    return m


def _bit_length(x: np.ndarray) -> np.ndarray:
    """``int.bit_length`` of int64 values ``x >= 1``, exact: the exponent of ``frexp``, less
    one where the conversion to float64 rounded ``x`` up to a power of two."""
    e = np.frexp(x.astype(np.float64))[1].astype(np.int64)
    return e - ((x >> (e - 1)) == 0)


def _codeword_bits(values: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bits of codewords ``values`` (..., C) in ``lengths`` bits each (0: no codeword), as
    (..., C * W) uint8 0/1 and the (..., C * W) mask of the bits sent: element k's bits, most
    significant first, are its row's columns ``[k W + W - lengths[k], (k + 1) W)``, ``W`` the
    smallest of 8, 16, 32, 64 that holds the longest codeword."""
    width = int(lengths.max(initial=0))
    nbytes = next(b for b in (1, 2, 4, 8) if 8 * b >= width)
    raw = np.ascontiguousarray(values, f">u{nbytes}").view(np.uint8)
    bits = np.unpackbits(raw, axis=-1)  # (..., C * nbytes * 8)
    column = np.arange(8 * nbytes)
    sent = column >= 8 * nbytes - lengths[..., None]  # (..., C, W)
    return bits, sent.reshape(bits.shape)


def _check(code: Code, num_links: int, num_elements: int, check_bits: int, body: bytes) -> bytes:
    """The frame's check: the top ``check_bits`` bits of the CRC-32 of the implicit header
    (the code's 4-byte fingerprint; L, C: 4 bytes big-endian each; ``check_bits``: 1 byte) and
    the body."""
    if check_bits == 0:
        return b""
    header = (
        code.fingerprint
        + num_links.to_bytes(4, "big")
        + num_elements.to_bytes(4, "big")
        + bytes([check_bits])
    )
    crc = zlib.crc32(body, zlib.crc32(header))
    return (crc >> (32 - check_bits)).to_bytes(check_bits // 8, "big")


def encode_frame(links, code: Code | str, *, check_bits: int = 32) -> bytes:
    """One sender's frame for one step (format: module docstring).

    Args:
        links: (L, C) integer symbols in [0, levels] (float32 values for ``float32``): the
            sender's ``L >= 1`` links in recipient-slot order, ``C >= 1`` elements each, at most
            :data:`~sparsecomm.channel.codes.MAX_ELEMENTS` elements in all.
        code: a :class:`~sparsecomm.channel.codes.Code` or a code name (not a fitted code).
        check_bits: width of the check in bits, one of :data:`CHECK_BITS`.

    Returns:
        The frame: ``b""`` when every link is silent, else the body and ``check_bits // 8``
        check bytes. Raises ``ValueError`` for symbols out of range or a bad argument.
    """
    code = _frame_code(code)
    check_bits = check_width(check_bits)
    m = _symbols(links, code)
    num_links, num_elements = m.shape
    if code.name == "float32":
        words = m.view(np.uint32)
        present = words != 0
        values, lengths = words, np.where(present, 32, 0)
    else:
        present = m != 0
        rows = _remap_rows(code, num_elements)
        index = code.mapped(m.reshape(-1, rows)).reshape(m.shape) if rows else m
        if code.name == "paper":  # m + 1 in 2 L(m) bits: L - 1 zeros, a one, the codeword
            values = index + 1
            lengths = np.where(present, 2 * (_bit_length(values) - 1), 0)
        else:
            values, lengths = index, np.where(present, code.fixed_width, 0)
    speaks = present.any(1)
    if not speaks.any():
        return b""
    # The map, then each speaking link's bitmap and its present elements' codewords.
    codewords, sent = _codeword_bits(values[speaks], lengths[speaks])
    present = present[speaks]
    blocks = np.concatenate([present.astype(np.uint8), codewords], axis=1)
    keep = np.concatenate([np.ones(present.shape, bool), sent], axis=1)
    bits = np.concatenate([speaks.astype(np.uint8), blocks[keep]])
    body = np.packbits(bits).tobytes()
    return body + _check(code, num_links, num_elements, check_bits, body)


def _check_count(value, name: str) -> int:
    try:
        if isinstance(value, bool):
            raise TypeError
        value = operator.index(value)
    except TypeError:
        raise FrameError(f"{name} must be an integer >= 1, got {value!r}") from None
    if value < 1:
        raise FrameError(f"{name} must be an integer >= 1, got {value}")
    return value


def decode_frame(
    data: bytes, code: Code | str, num_links: int, num_elements: int, *, check_bits: int = 32
) -> np.ndarray:
    """Unpack a frame made by :func:`encode_frame` into the sender's ``(L, C)`` links.

    Args:
        data: the frame (``bytes``, ``bytearray`` or ``memoryview``); ``b""`` is silence.
        code: a :class:`~sparsecomm.channel.codes.Code` or a code name (not a fitted code).
        num_links: ``L >= 1``, the agreed number of links (recipient slots) of the sender.
        num_elements: ``C >= 1``, the agreed elements per link (``L * C`` at most
            :data:`~sparsecomm.channel.codes.MAX_ELEMENTS`).
        check_bits: the agreed check width in bits, one of :data:`CHECK_BITS`.

    Returns:
        (L, C) int64 symbols (float32 values for ``float32``); all nulls for ``b""``.

    Raises :class:`FrameError` for any malformed ``data`` (not bytes, truncated, too long, check
    mismatch, invalid codeword, symbol above ``levels``, non-zero padding, a speaking link with
    no element present, an all-zero recipient map, trailing bits or bytes) and for a claimed
    shape that is invalid or that the frame cannot hold (checked before allocating). Time
    linear in ``len(data)``.
    """
    code = _frame_code(code)
    check_bits = check_width(check_bits)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise FrameError(f"data must be bytes, got {type(data).__name__}")
    num_links = _check_count(num_links, "num_links")
    num_elements = _check_count(num_elements, "num_elements")
    if num_links * num_elements > MAX_ELEMENTS:
        raise FrameError(
            f"claimed shape ({num_links}, {num_elements}) has {num_links * num_elements} "
            f"elements, over {MAX_ELEMENTS}"
        )
    rows = _remap_rows(code, num_elements, FrameError)
    try:
        data = bytes(data)  # a memoryview of non-bytes items may not convert
    except (TypeError, ValueError):
        raise FrameError("data must be a contiguous bytes-like object") from None
    dtype = np.float32 if code.name == "float32" else np.int64
    if not data:
        return np.zeros((num_links, num_elements), dtype)
    check_bytes = check_bits // 8
    if len(data) <= check_bytes:
        raise FrameError(f"frame truncated: {len(data)} bytes, no room for its body and check")
    body = data[: len(data) - check_bytes]
    if _check(code, num_links, num_elements, check_bits, body) != data[len(body) :]:
        raise FrameError(f"frame corrupted: {check_bits}-bit check mismatch")
    nbits = 8 * len(body)
    if num_links > nbits:
        raise FrameError(
            f"frame truncated or claimed shape too large: a {num_links}-bit recipient map, "
            f"the body has {nbits} bits"
        )
    bits = format(int.from_bytes(body, "big"), f"0{nbits}b")  # '0'/'1' string, linear time
    speaking = [slot for slot, b in enumerate(bits[:num_links]) if b == "1"]
    if not speaking:
        raise FrameError("non-empty frame with no link speaking (silence is sent as no frame)")
    if len(speaking) * (num_elements + 1) > nbits - num_links:
        raise FrameError(
            f"frame truncated or claimed shape too large: {len(speaking)} speaking links of "
            f"{num_elements} elements need over {len(speaking) * (num_elements + 1)} bits "
            f"after the map, the body has {nbits - num_links}"
        )
    pos = num_links
    bitmaps, segments, values = [], [], []
    width = code.fixed_width if code.name == "fixed" else 32
    max_len = code.max_paper_length
    for link in speaking:
        if pos + num_elements > nbits:
            raise FrameError(f"frame truncated inside the presence bitmap of link {link}")
        k = bits.count("1", pos, pos + num_elements)
        if k == 0:
            raise FrameError(f"link {link} speaks with no element present (invalid frame)")
        bitmaps.append(bits[pos : pos + num_elements])
        pos += num_elements
        if code.name == "paper":
            for i in range(k):
                one = bits.find("1", pos, min(pos + max_len, nbits))
                if one < 0:
                    if pos + max_len > nbits:
                        raise FrameError(f"frame truncated inside element {i} of link {link}")
                    raise FrameError(f"invalid codeword: length prefix exceeds {max_len} bits")
                end = 2 * one - pos + 2  # the one, then one - pos + 1 codeword bits
                if end > nbits:
                    raise FrameError(f"frame truncated inside element {i} of link {link}")
                values.append(int(bits[one:end], 2) - 1)
                pos = end
        else:
            end = pos + width * k
            if end > nbits:
                raise FrameError(
                    f"frame truncated: link {link}'s {k} present elements need {end} bits, "
                    f"the body has {nbits}"
                )
            segments.append(bits[pos:end])
            pos = end
    if nbits - pos >= 8 or "1" in bits[pos:]:
        raise FrameError(f"frame has {nbits - pos} trailing bits after its last link (not padding)")
    present = np.frombuffer("".join(bitmaps).encode(), np.uint8).reshape(-1, num_elements) == 49
    if code.name == "paper":
        symbols = np.array(values, np.int64)
    else:
        digits = np.frombuffer("".join(segments).encode(), np.uint8) - ord("0")
        digits = digits.reshape(-1, width).astype(np.int64)
        symbols = digits @ (1 << np.arange(width - 1, -1, -1, dtype=np.int64))
        if code.name == "fixed" and symbols.min() == 0:
            raise FrameError("a present element holds the null symbol 0 (invalid codeword)")
        if code.name == "float32" and symbols.min() == 0:
            raise FrameError("a present element holds +0.0, the null value (invalid codeword)")
    if code.name != "float32" and symbols.max() > code.levels:
        raise FrameError(f"decoded symbol {symbols.max()} outside [0, {code.levels}]")
    out = np.zeros((num_links, num_elements), np.int64)
    block = np.zeros(present.shape, np.int64)
    block[present] = symbols
    out[speaking] = block
    if code.name == "float32":
        return out.astype(np.uint32).view(np.float32)
    if rows:
        out = code.unmapped(out.reshape(-1, rows)).reshape(out.shape)
    return out
