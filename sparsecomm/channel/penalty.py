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

from sparsecomm.channel.quantizer import check_levels, check_unit_interval

__all__ = ["bit_penalty", "expected_bits"]


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


def code_penalty(z: jax.Array, levels: int, code) -> jax.Array:
    """The differentiable bit cost of each element of ``z`` under ``code``: the paper's
    :func:`bit_penalty`, or for a learned code (a ``channel.Code`` with ``remap``) the exact
    expected bits of its codewords (:func:`expected_bits`)."""
    if getattr(code, "remap", ()):
        return expected_bits(z, levels, code.lengths())
    return bit_penalty(z, levels)
