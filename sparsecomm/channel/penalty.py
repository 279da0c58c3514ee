"""The differentiable bit penalty of paper eq. (2) and SPEC section 3.

Per message element ``l(z) = log2(levels * z + 1)``. It bounds the expected length of the paper's
code from above: ``E[L(m) | z] <= E[log2(m + 1) | z] <= log2(E[m | z] + 1) = log2(levels z + 1)``
(``L(m) = floor(log2(m + 1))``, then Jensen). Learners sum it over senders, recipients and
elements of a step; how they normalise it over steps and episodes is documented where it is used
(:mod:`sparsecomm.rl`, :mod:`sparsecomm.imitation`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.quantizer import check_levels, check_unit_interval

__all__ = ["bit_penalty", "expected_bits", "expected_wire_bits"]


def bit_penalty(z: jax.Array, levels: int) -> jax.Array:
    """Elementwise surrogate bit cost ``log2(levels * z + 1)`` of signals ``z`` in [0, 1]."""
    levels = check_levels(levels)
    check_unit_interval(z)
    return jnp.log2(levels * jnp.asarray(z, jnp.float32) + 1.0)


def expected_bits(z: jax.Array, levels: int, lengths) -> jax.Array:
    """Exact expected codeword bits of dithered symbols of ``z`` (..., C) under a code whose
    element k spends ``lengths[k, m]`` bits on symbol m (``(C, levels + 1)``, e.g. a learned
    code's ``Code.lengths()``).

    With the dither, ``m = floor(levels z) + 1`` with probability ``f``, the fractional part of
    ``levels z``, else ``floor(levels z)``, so the expectation is ``(1 - f) lengths[lo] +
    f lengths[lo + 1]``: piecewise linear in z, its gradient the price of moving toward the
    next symbol (0 where neighbouring symbols cost the same). For the paper's code it is the
    quantity ``log2(levels z + 1)`` bounds from above.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    x = levels * jnp.asarray(z, jnp.float32)
    lo = jnp.clip(jnp.floor(jax.lax.stop_gradient(x)), 0, levels).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, levels)
    frac = x - lo
    table = jnp.asarray(lengths, jnp.float32)
    k = jnp.arange(table.shape[0])
    return (1.0 - frac) * table[k, lo] + frac * table[k, hi]


_COS8 = np.cos(2 * np.pi * np.arange(8) / 8).astype(np.float32)  # numpy: no device at import
_SIN8 = np.sin(2 * np.pi * np.arange(8) / 8).astype(np.float32)


def expected_wire_bits(
    z: jax.Array, levels: int, wire_lengths, frame_bits: int | None = None
) -> jax.Array:
    """Exact expected packet bits of one link under the dithered quantizer: ``E[8 *
    len(encode(m))]`` for signals ``z`` (..., C), differentiable (piecewise linear in each
    element between symbol boundaries). Returns (...).

    ``wire_lengths`` (C, levels + 1): the bits each element's symbol adds to the packet's body
    (``Code.wire_lengths``; 0 for the null). A link of all-null symbols sends nothing; any
    other packet is the C-bit presence bitmap, the codewords (S bits), zero padding to a byte
    and the 32-bit CRC (``frame_bits``, default ``C + 32``, is everything but the codewords and
    the padding). So with ``p0 = P(every symbol is null)``::

        E[W] = (1 - p0) frame_bits + E[S] + E[pad(C + S); some symbol not null]

    Element k's symbol is ``floor(levels z_k)`` or one more (probability ``f_k``, the
    fractional part), independently across elements (each has its own dither), so ``p0`` is the
    product of ``P(m_k = 0) = max(0, 1 - levels z_k)`` and the padding's distribution, that of
    the codeword bits modulo 8, is the product of the elements' characteristic functions on the
    8 residues. The cliff: ``p0`` is 0,
    with no gradient, as soon as one element has ``levels z_k >= 1``.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    x = levels * jnp.asarray(z, jnp.float32)
    c = x.shape[-1]
    lo = jnp.clip(jnp.floor(jax.lax.stop_gradient(x)), 0, levels).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, levels)
    f = x - lo
    table = jnp.asarray(wire_lengths, jnp.int32)
    k = jnp.arange(c)
    len_lo, len_hi = table[k, lo], table[k, hi]
    codewords = ((1.0 - f) * len_lo + f * len_hi).sum(-1)
    p0 = jnp.prod(jnp.where(lo == 0, 1.0 - f, 0.0), -1)
    # E[pad(C + S)] from the characteristic function of S mod 8, Phi(w) = E[exp(-2 pi i w S /
    # 8)]: the product over elements of each one's (two symbols, two lengths), in real
    # arithmetic. Then E[pad] = sum_w Phi(w) Q(w), Q the inverse DFT of the padding table; S is
    # real, so Phi(8 - w) is Phi(w)'s conjugate and w = 1..4 suffice (Phi(0) = 1).
    omega = np.arange(1, 5)
    cos8, sin8 = jnp.asarray(_COS8), jnp.asarray(_SIN8)
    re, im = jnp.ones((*x.shape[:-1], 4)), jnp.zeros((*x.shape[:-1], 4))
    for j in range(c):
        lo_turn = (len_lo[..., j, None] * omega) % 8  # (..., 4): w * length mod 8, in eighths
        hi_turn = (len_hi[..., j, None] * omega) % 8
        fj = f[..., j, None]
        a = (1.0 - fj) * cos8[lo_turn] + fj * cos8[hi_turn]
        b = -((1.0 - fj) * sin8[lo_turn] + fj * sin8[hi_turn])
        re, im = re * a - im * b, re * b + im * a
    frame = c + 32 if frame_bits is None else frame_bits
    r = np.arange(8)
    pad = (-(c + r)) % 8  # padding after a body of C + r bits, r = S mod 8
    q_re = (pad * np.cos(2 * np.pi * np.outer(omega, r) / 8)).sum(1) / 8
    q_im = (pad * np.sin(2 * np.pi * np.outer(omega, r) / 8)).sum(1) / 8
    twice = np.array([2.0, 2.0, 2.0, 1.0])  # w and 8 - w, and w = 4 once
    q_re, q_im = jnp.asarray(twice * q_re, jnp.float32), jnp.asarray(twice * q_im, jnp.float32)
    mean_pad = pad.mean()  # Phi(0) Q(0)
    padding = mean_pad + (re * q_re - im * q_im).sum(-1) - p0 * pad[0]  # S = 0 if all null
    return (1.0 - p0) * frame + codewords + padding


def code_penalty(z: jax.Array, levels: int, code) -> jax.Array:
    """The differentiable bit cost of each element of ``z`` under ``code``: the paper's
    :func:`bit_penalty`, or for a learned code (a ``channel.Code`` with ``remap``) the exact
    expected bits of its codewords (:func:`expected_bits`)."""
    if getattr(code, "remap", ()):
        return expected_bits(z, levels, code.lengths())
    return bit_penalty(z, levels)
