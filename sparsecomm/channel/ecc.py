"""Error correction on the wire, as a trade of bits for robustness (docs/noise.md).

``ChannelConfig.ecc = "hamming74"`` protects every packet with a Hamming(7,4) code: each 4-bit
nibble of the packet (CRC-32 included) becomes a 7-bit block that survives any single flipped
bit, and the blocks are zero-padded to a whole byte. A packet of ``n`` bytes becomes
``ceil(14 n / 8)`` bytes (1.75x its bits, plus padding), and the receiver recovers ``n`` from
the length alone (``floor(8 len / 14)``). A block with two or more flipped bits decodes to
wrong data, which the packet's CRC-32 then refuses: under independent flips of probability p a
packet of W bits arrives intact with probability ``((1 - p)^7 + 7 p (1 - p)^6)^(W / 4)``
instead of ``(1 - p)^W``. Silence (no packet) stays free. The redundancy is counted in the wire
bits (:func:`wire_bits`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["ECC_NAMES", "encode", "decode", "wire_bits", "data_bits", "block_survival"]

ECC_NAMES = ("none", "hamming74")

# Codeword bit order [p1, p2, d1, p3, d2, d3, d4]: column j of the parity checks below is the
# binary of j + 1, so a single flipped bit's syndrome is its position + 1.
_G = np.array(
    [
        [1, 1, 1, 0, 0, 0, 0],
        [1, 0, 0, 1, 1, 0, 0],
        [0, 1, 0, 1, 0, 1, 0],
        [1, 1, 0, 1, 0, 0, 1],
    ],
    np.uint8,
)  # rows: d1..d4
_H = np.array([[(j + 1) >> b & 1 for j in range(7)] for b in range(3)], np.uint8)
_DATA = [2, 4, 5, 6]  # positions of d1..d4 in a block


def _check(ecc: str) -> None:
    if ecc not in ECC_NAMES:
        raise ValueError(f"ecc must be one of {ECC_NAMES}, got {ecc!r}")


def encode(packet: bytes, ecc: str = "hamming74") -> bytes:
    """The packet as sent under ``ecc`` (``b""`` stays ``b""``: silence has nothing to protect)."""
    _check(ecc)
    if ecc == "none" or not packet:
        return packet
    nibbles = np.unpackbits(np.frombuffer(packet, np.uint8)).reshape(-1, 4)
    blocks = (nibbles @ _G) % 2
    return np.packbits(blocks.reshape(-1)).tobytes()


def decode(data: bytes, ecc: str = "hamming74") -> bytes:
    """The packet inside ``data``, each block's single flipped bit corrected (more flips give
    wrong bytes, which the packet's CRC-32 refuses). The padding bits are ignored."""
    _check(ecc)
    if ecc == "none" or not data:
        return data
    n = 8 * len(data) // 14  # bytes of the packet inside
    bits = np.unpackbits(np.frombuffer(data, np.uint8))[: 14 * n].reshape(-1, 7).copy()
    syndrome = (bits @ _H.T % 2) @ np.array([1, 2, 4])
    rows = np.flatnonzero(syndrome)
    bits[rows, syndrome[rows] - 1] ^= 1
    return np.packbits(bits[:, _DATA].reshape(-1)).tobytes()


def wire_bits(packet_bits, ecc: str):
    """Bits on the wire of packets of ``packet_bits`` bits (a multiple of 8; 0 for silence)
    under ``ecc``, jnp: ``8 * len(encode(packet))``."""
    _check(ecc)
    if ecc == "none":
        return packet_bits
    n = jnp.asarray(packet_bits) // 8
    return 8 * ((14 * n + 7) // 8)


def data_bits(sent_bits, ecc: str):
    """Inverse of :func:`wire_bits`: the packet's own bits inside ``sent_bits`` on the wire."""
    _check(ecc)
    if ecc == "none":
        return sent_bits
    return 8 * ((jnp.asarray(sent_bits) // 8 * 8) // 14)


def block_survival(p):
    """Probability that a Hamming(7,4) block with independent flips of probability ``p``
    decodes correctly (at most one flip)."""
    return (1 - p) ** 7 + 7 * p * (1 - p) ** 6
