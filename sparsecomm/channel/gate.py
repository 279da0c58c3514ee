"""The message gate: from a message head's real output to the signal ``z`` in [0, 1].

The paper squashes the message head with a sigmoid. Under a bit penalty that has a trap: the
penalty pushes ``z`` toward 0, the sigmoid saturates, its derivative ``z (1 - z)`` vanishes, and
Adam keeps stepping the pre-activation further down (it normalises the vanishing gradient). A link
silenced that way never reopens, even when the price of a bit later falls to nothing: the task
gradient reaches the sender multiplied by ``~0`` (measured in ``tests/test_budget.py``).

:func:`hard_gate` makes silence exact and reversible. Forward it is the hard sigmoid
``clip(a / 4 + 1/2, 0, 1)`` (the sigmoid's slope at 0), so a link below the edge sends ``z = 0``:
the null message, exactly 0 bits. Backward, at a clipped element, it passes only the gradient that
points back inside: where ``z = 0`` a cotangent that asks for a larger ``z`` reaches the sender
with slope 1/4 and one that asks for a smaller ``z`` is dropped (so nothing drifts further into
silence); symmetrically at ``z = 1``. Since the penalty and the task share that cotangent, a
silent element reopens exactly when the receivers' gain from a larger ``z`` outweighs the price of
its bits.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["GATES", "hard_gate", "gate"]

GATES = ("sigmoid", "hard")


@jax.custom_vjp
def hard_gate(a: jax.Array) -> jax.Array:
    """``clip(a / 4 + 1/2, 0, 1)`` with one-sided gradients at the clipped edges (see module)."""
    return jnp.clip(a * 0.25 + 0.5, 0.0, 1.0)


def _fwd(a):
    s = a * 0.25 + 0.5
    return jnp.clip(s, 0.0, 1.0), s


def _bwd(s, g):
    # Gradient descent moves s by -g: at the lower edge keep g < 0 (s up), at the upper g > 0.
    inside = ((s > 0.0) | (g < 0.0)) & ((s < 1.0) | (g > 0.0))
    return (jnp.where(inside, 0.25 * g, 0.0),)


hard_gate.defvjp(_fwd, _bwd)


def gate(name: str, a: jax.Array) -> jax.Array:
    """The named gate (one of :data:`GATES`) applied to the message head's output ``a``."""
    if name == "sigmoid":
        return jax.nn.sigmoid(a)
    if name == "hard":
        return hard_gate(a)
    raise ValueError(f"gate must be one of {GATES}, got {name!r}")
