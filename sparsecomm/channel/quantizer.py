"""Dithered stochastic quantizer: the differentiable discrete channel of SPEC section 1.

A sender turns a real signal ``z`` in [0, 1] into integer symbols ``m`` in {0, ..., levels}; the
receiver turns them back into a reconstruction ``z_hat``. Both draw the same dither ``u`` from a
key they share, so ``u`` never travels on the wire::

    u     ~ U[-1/2, 1/2)                  (from ``dither_key(key, t, sender, recipient)``)
    m     = clip(floor(levels * z + u + 1/2), 0, levels)          # round(levels z + u)
    z_hat = (m - u) / levels

Subtractive dither makes the reconstruction error ``z_hat - z`` uniform on
(-1/(2 levels), 1/(2 levels)], zero-mean and independent of ``z``; ``E[m | z] = levels z`` and
``z = 0`` always gives the null message ``m = 0``. Downstream code uses
``z + stop_gradient(z_hat - z)``, so ``d z_hat / d z = 1``: to the gradient the channel is an
analog channel with additive, independent uniform noise.

Argument checks run on concrete arrays only. Inside ``jax.jit`` the values of ``z`` are not
known when the checks run, so they are skipped: a ``z`` outside [0, 1] then yields symbols
clipped to [0, levels] and a reconstruction error that is no longer uniform, and a non-finite
``z`` propagates NaN into ``z_hat``. ``levels`` is a Python int and is always checked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "dither",
    "dither_key",
    "quantize",
    "quantize_dithered",
    "dequantize",
    "check_levels",
    "check_unit_interval",
]


def check_levels(levels, name: str = "levels") -> int:
    """Validate ``levels`` (the paper's |M|): an integer >= 1, the one check every part of the
    channel uses (``name`` is the field named in the error). Returns it as a Python int."""
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {levels!r}")
    return int(levels)


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_unit_interval(z, name: str = "z") -> None:
    """Raise ``ValueError`` unless the concrete array ``z`` is non-empty, finite and in [0, 1].

    Does nothing for traced values (inside ``jit``/``vmap``/``grad``), see the module docstring.
    """
    if not _is_concrete(z):
        return
    a = np.asarray(z)
    if a.size == 0:
        raise ValueError(f"{name} must be a non-empty array in [0, 1], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite with values in [0, 1], got NaN or inf")
    lo, hi = float(a.min()), float(a.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got values in [{lo}, {hi}]")


MAX_AGENTS = 1024
"""Most agents a team may have: :func:`dither_key` keeps links distinct below 1024 agents."""
MAX_STEPS = 4096
"""Steps ``t`` lie in ``[0, MAX_STEPS)``: :func:`dither_key` keeps steps distinct below 4096."""


def dither_key(key: jax.Array, t, sender, recipient) -> jax.Array:
    """The shared key of one link at one step: ``key`` folded with the link-step index.

    ``key`` is the episode's channel key, known to every agent of the team. Sender and receiver
    both call this with the same arguments and so draw the same dither. The index
    ``(t * 2**10 + sender) * 2**10 + recipient`` (modulo 2**32) is distinct for every step
    ``t < 4096`` and agents ``< 1024``: one hash per link instead of three chained ``fold_in``.
    Works with traced integers, so it can be ``vmap``-ped over senders, recipients and steps.
    """
    t, sender, recipient = (jnp.asarray(x, jnp.uint32) for x in (t, sender, recipient))
    index = (t << 20) | (sender << 10) | recipient
    return jax.random.fold_in(key, index)


def dither(key: jax.Array, shape) -> jax.Array:
    """Dither ``u ~ U[-1/2, 1/2)`` of the given shape, float32."""
    return jax.random.uniform(key, shape, jnp.float32, minval=-0.5, maxval=0.5)


def quantize(key: jax.Array, z: jax.Array, levels: int) -> tuple[jax.Array, jax.Array]:
    """Quantize ``z`` (values in [0, 1]) into symbols ``m`` and the receiver's reconstruction.

    Args:
      key: the link's dither key (see :func:`dither_key`).
      z: real signal in [0, 1], any non-empty shape.
      levels: the paper's |M|; symbols are integers in ``{0, ..., levels}``.

    Returns:
      ``(m, z_hat)``: ``m`` int32 symbols of ``z``'s shape; ``z_hat`` float32 reconstruction whose
      value is ``(m - u) / levels`` and whose gradient with respect to ``z`` is the identity.
    """
    z = jnp.asarray(z, jnp.float32)
    return quantize_dithered(z, dither(key, z.shape), levels)


def quantize_dithered(z: jax.Array, u: jax.Array, levels: int) -> tuple[jax.Array, jax.Array]:
    """:func:`quantize` with the dither ``u`` (same shape as ``z``) drawn by the caller.

    For batched senders that draw the dither of many links and steps in one vectorised call
    (the rollout does), instead of one small random draw per link inside the time loop.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    z = jnp.asarray(z, jnp.float32)
    m = jnp.clip(jnp.floor(levels * z + u + 0.5), 0, levels)
    z_hat = (m - u) / levels
    return m.astype(jnp.int32), z + jax.lax.stop_gradient(z_hat - z)


def dequantize(key: jax.Array, m: jax.Array, levels: int) -> jax.Array:
    """Receiver side: rebuild ``z_hat = (m - u) / levels`` from symbols and the shared key."""
    levels = check_levels(levels)
    m = jnp.asarray(m)
    if _is_concrete(m) and m.size and (int(np.min(m)) < 0 or int(np.max(m)) > levels):
        raise ValueError(f"m must hold symbols in [0, {levels}], got [{np.min(m)}, {np.max(m)}]")
    u = dither(key, m.shape)
    return (m.astype(jnp.float32) - u) / levels
