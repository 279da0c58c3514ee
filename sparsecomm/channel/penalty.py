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

__all__ = ["bit_penalty"]


def bit_penalty(z: jax.Array, levels: int) -> jax.Array:
    """Elementwise surrogate bit cost ``log2(levels * z + 1)`` of signals ``z`` in [0, 1]."""
    levels = check_levels(levels)
    check_unit_interval(z)
    return jnp.log2(levels * jnp.asarray(z, jnp.float32) + 1.0)
