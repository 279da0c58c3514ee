"""The plug-in layer: the channel between any number of agents, over any routing (docs/plugin.md).

Two pure functions (``jit``, ``vmap`` and ``grad`` go through both) and a routing table, for a
model that is not sparsecomm's own (a JaxMARL or PureJaxRL team, any Flax or Haiku network)::

    from sparsecomm import channel
    routing = channel.Routing.all_to_all(4)                  # or from_neighbours / from_mask
    msgs = channel.send(key, z, routing, t=t, levels=15)     # z (..., K, K, C) in [0, 1]
    loss = task_loss(msgs.inbox) + lam * msgs.penalty.sum()  # gradients reach the senders
    bits = msgs.payload_bits.sum()                           # what the team really sent

Layout. ``z[..., i, j, :]`` is the signal (C elements in [0, 1]) sender i addresses to
recipient j, one link per ordered pair; with ``broadcast=True``, ``z`` is ``(..., K, C)`` and
sender i addresses the same signal to every recipient it may reach. Leading axes ``...`` are a
batch (of episodes, environments, time steps). Outputs indexed by link are ``(..., K, K, ...)``
by sender then recipient; ``inbox`` is by recipient then sender.

Routing. ``routing.mask[i, j]`` says whether link i -> j exists. A link that does not (and every
self-link i -> i) carries the null symbol 0, costs 0 payload bits, 0 wire bits and 0 penalty,
delivers 0 to the recipient's inbox, and passes no gradient: the derivative of anything the
recipient computes with respect to what the sender emitted on that link is exactly zero. The
mask may also be a boolean array (a traced one, for routing that changes with the state, such
as the agents within a radius), broadcast against the batch.

Dither. Link i -> j at step ``t`` draws its dither from ``channel.dither_key(key, t, i, j)``,
with ``key`` the episode's channel key that the whole team knows (docs/spec.md section 1), so a
receiver holding the symbols alone regenerates it: :func:`reconstruct`. All links' dither is
drawn in one vectorised call. Each link is ``channel.quantize(dither_key(key, t, i, j),
z[i, j], levels)``: the same symbols, the same reconstruction (bit for bit against the compiled
``channel.quantize``; ``send`` always runs compiled), whose gradient with respect to ``z`` is
the identity.

This module is a face: it checks its arguments and converts between its ``(K, K)`` layout and
the channel's sender-slot layout; the sending, counting and rebuilding are the channel's one
sender side and receiver side (``channel.links.transmit`` and ``channel.links.receive``), the
same the rollout and every deployed agent run.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.codes import Code, as_code
from sparsecomm.channel.config import ChannelConfig
from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.gate import gate as apply_gate
from sparsecomm.channel.links import dither_links, key_batch_shape, receive, transmit
from sparsecomm.channel.quantizer import (
    MAX_AGENTS,
    MAX_STEPS,
    check_levels,
    check_unit_interval,
)
from sparsecomm.channel.routing import Routing, others, pairs, routing_mask, slots

__all__ = ["Messages", "Routing", "reconstruct", "send"]


class Messages(NamedTuple):
    """What :func:`send` delivered and what it cost. ``...`` is ``z``'s batch shape; link axes
    are (sender, recipient) except in ``inbox``. Every field is 0 on a link that does not exist."""

    symbols: jax.Array
    """(..., K, K, C) int32: the symbols sent on each link, in ``{0, ..., levels}``."""
    z_hat: jax.Array
    """(..., K, K, C) float32: each link's reconstruction ``(m - u) / levels``, by sender; its
    gradient with respect to the link's ``z`` is the identity."""
    inbox: jax.Array
    """(..., K, K, C) float32: what each agent receives, by **recipient** then sender:
    ``inbox[..., j, i] = z_hat[..., i, j]``. Flatten it to ``(..., K, K C)`` for a fixed-size
    input, or use ``inbox_mean``."""
    inbox_mean: jax.Array
    """(..., K, C) float32: recipient j's mean of the reconstructions from the agents it hears
    from (permutation invariant; 0 for an agent that hears from nobody)."""
    penalty: jax.Array
    """(..., K, K) float32: each link's differentiable bit penalty, summed over its elements
    (``channel.bit_penalty``, or a learned code's expected bits)."""
    payload_bits: jax.Array
    """(..., K, K) int32: each link's payload bits under ``code`` (the paper's count)."""
    wire_bits: jax.Array
    """(..., K, K) float32: each link's share of its sender's frame on the wire (``Sent.wire_bits``;
    0 for a silent link): summed over a sender's recipients, ``8 * len(channel.encode_frame(
    ...))`` of its links by recipient slot when computed on the host."""
    mask: jax.Array
    """(..., K, K) bool: the links that existed (the routing, diagonal cleared)."""
    news: jax.Array | None = None
    """(..., K, K) float32 by **recipient** then sender, with ``last`` given to :func:`send`: 1
    where the link spoke (its inbox entry is news), 0 where it was silent and its last message
    is held (``ChannelConfig.on_silence = "hold"``). ``None`` otherwise."""


def _check_static_int(value, name: str, lo: int, hi: int) -> None:
    if isinstance(value, jax.core.Tracer):
        return
    a = np.asarray(value)
    if a.dtype == np.bool_ or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}), got {value!r}")
    if a.size and (a.min() < lo or a.max() >= hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}), got {value!r}")


def _episode_keys(key: jax.Array, t, batch: tuple[int, ...]):
    """Check ``key`` (one key, or one per batch entry) and broadcast ``t`` to the batch."""
    kshape = key_batch_shape(jnp.asarray(key) if not isinstance(key, jax.Array) else key)
    if kshape not in ((), batch):
        raise ValueError(
            f"key must be one key or one per batch entry (batch shape {batch}), got keys of "
            f"batch shape {kshape}"
        )
    try:
        t = jnp.broadcast_to(jnp.asarray(t), batch)
    except ValueError:
        raise ValueError(f"t must be a scalar or broadcast to z's batch shape {batch}") from None
    return key, t


def send(
    key: jax.Array,
    z: jax.Array,
    routing: Routing | jax.Array,
    *,
    t,
    levels: int = 15,
    code: Code | FittedCode | str = "paper",
    gate: str | None = None,
    broadcast: bool = False,
    prev: jax.Array | None = None,
    last: jax.Array | None = None,
) -> Messages:
    """Send every agent's signal over the links ``routing`` allows, through the channel.

    Args:
      key: the episode's channel key, shared by the team (link i -> j at step ``t`` draws its
        dither from ``dither_key(key, t, i, j)``): one key, or one per batch entry (shape
        ``z.shape[:-3]``, or ``z.shape[:-2]`` with ``broadcast``).
      z: ``(..., K, K, C)`` signals in [0, 1], ``z[..., i, j]`` from sender i to recipient j
        (entries of links that do not exist are ignored, and get no gradient); with
        ``broadcast``, ``(..., K, C)``, sender i's one signal to all its recipients. With
        ``gate``, the message head's real-valued output instead, squashed into [0, 1] here.
      routing: a :class:`Routing` for K agents, or a boolean array ``(..., K, K)`` (``mask[...,
        i, j]``: link i -> j exists; may be traced; broadcast against the batch; the diagonal
        is ignored).
      t: the step, an integer in [0, 4096) (a scalar, or one per batch entry; may be traced).
      levels: the paper's |M|: symbols are ``{0, ..., levels}``. Default 15.
      code: the code bits are counted in (``"paper"``, ``"fixed"``, a ``channel.Code`` or a
        ``channel.FittedCode``). Default ``"paper"``.
      gate: ``None`` (``z`` is already in [0, 1]), ``"sigmoid"`` (the paper's) or ``"hard"``
        (``channel.hard_gate``: silence exact and reversible).
      broadcast: ``z`` is ``(..., K, C)``, one signal per sender; each of its links is still its
        own packet with its own dither.
      prev: ``(..., K, K, C)`` each link's symbols at the previous step, for a fitted code's wire
        bits (default all nulls; the other codes ignore it).
      last: ``(..., K, K, C)`` by recipient then sender, the inbox of the previous step
        (``Messages.inbox``; zeros at the first): a link that sends nothing (every symbol null)
        then delivers its last message instead of the null one, and ``Messages.news`` says which
        entries are news (the channel's ``on_silence = "hold"``). Default: the paper's null.

    Returns:
      :class:`Messages`. Values of ``z`` outside [0, 1] are a ``ValueError`` when ``z`` is
      concrete; under ``jit`` they are clipped to symbols in [0, levels] (channel.quantize).
    """
    levels = check_levels(levels)
    code = as_code(code, levels)
    if gate is not None:
        z = apply_gate(gate, z)
    z = jnp.asarray(z, jnp.float32)
    if broadcast:
        if z.ndim < 2:
            raise ValueError(f"z must be (..., K, C) with broadcast=True, got shape {z.shape}")
        k = z.shape[-2]
        z = jnp.broadcast_to(z[..., :, None, :], (*z.shape[:-1], k, z.shape[-1]))
    if z.ndim < 3 or z.shape[-3] != z.shape[-2] or z.shape[-1] < 1:
        raise ValueError(
            f"z must be (..., K, K, C) signals by sender and recipient with C >= 1 (or "
            f"(..., K, C) with broadcast=True), got shape {z.shape}"
        )
    k = z.shape[-2]
    if k > MAX_AGENTS:
        raise ValueError(f"z must have at most {MAX_AGENTS} agents, got {k}")
    _check_static_int(t, "t", 0, MAX_STEPS)
    batch = z.shape[:-3]
    mask = routing_mask(routing, k, batch)
    key, t = _episode_keys(key, t, batch)
    check_unit_interval(jnp.where(mask[..., None], z, 0.0))  # concrete z only
    last = _check_last(last, z.shape)
    return _send(key, z, mask, t, prev, last, levels, code)


def _check_last(last, shape) -> jax.Array | None:
    if last is None:
        return None
    last = jnp.asarray(last, jnp.float32)
    if last.shape != tuple(shape):
        raise ValueError(
            f"last must be the previous inbox, (..., K, K, C) = {tuple(shape)}, got {last.shape}"
        )
    return last


@functools.partial(jax.jit, static_argnums=(6, 7))
def _send(key, z, mask, t, prev, last, levels: int, code) -> Messages:
    """:func:`send` once its arguments are checked (one compiled program, also when eager): the
    channel's own :func:`~sparsecomm.channel.links.transmit` on the links by sender slot."""
    k, c = z.shape[-2], z.shape[-1]
    live = slots(mask)
    u = dither_links(key, t, np.arange(k)[:, None], others(k), c)
    prev = None if prev is None else slots(prev, 1)
    cfg = _discrete(levels, last is not None)
    sent = transmit(cfg, slots(z, 1), u, prev=prev, live=live, code=code)
    z_hat = pairs(sent.z_hat, 1)
    inbox, news = _received(cfg, sent.z_hat, u, last, live, sent.wire_bits == 0)
    heard = mask.sum(-2).astype(jnp.float32)  # senders of each recipient
    mean = inbox.sum(-2) / jnp.maximum(heard, 1.0)[..., None]
    return Messages(
        pairs(sent.symbols, 1),
        z_hat,
        inbox,
        mean,
        pairs(sent.penalty),
        pairs(sent.payload_bits.astype(jnp.int32)),
        pairs(sent.wire_bits),
        mask,
        news,
    )


def _received(cfg, message, u, last, live, silent):
    """The channel's receiver side on links by sender slot, as the layer returns it: the inbox
    ``(..., K, K, C)`` by recipient then sender, and under ``hold`` which entries are news."""
    if last is not None:  # the previous inbox, by recipient: by sender slot
        last = slots(jnp.swapaxes(last, -3, -2), 1)
    got = receive(cfg, message, u, last=last, live=live, silent=silent if cfg.holds else None)
    inbox = jnp.swapaxes(pairs(got.z_hat, 1), -3, -2)
    news = None if got.news is None else jnp.swapaxes(pairs(got.news * live), -2, -1)
    return inbox, news


@functools.lru_cache(maxsize=64)
def _discrete(levels: int, hold: bool = False) -> ChannelConfig:
    """The channel the layer runs: the paper's quantizer with ``levels`` (bits are counted in
    the code the caller gives :func:`send`), holding silent links' last messages with
    ``hold``."""
    return ChannelConfig(levels=levels, on_silence="hold" if hold else "null")


def reconstruct(
    key: jax.Array,
    symbols: jax.Array,
    routing: Routing | jax.Array,
    *,
    t,
    levels: int = 15,
    last: jax.Array | None = None,
) -> jax.Array:
    """Receiver side: every recipient's inbox rebuilt from the symbols alone and the shared key.

    ``symbols`` ``(..., K, K, C)`` by sender and recipient (``Messages.symbols``, or decoded
    packets); ``key``, ``routing``, ``t`` and ``levels`` as given to :func:`send`. Returns
    ``(..., K, K, C)`` by recipient then sender, ``(m - u) / levels`` on the links that exist
    and 0 elsewhere: ``Messages.inbox``'s values (up to float rounding), without its gradient.
    With ``last`` (the previous inbox), a link whose symbols are all null delivers its last
    message, as :func:`send` with ``last``.
    """
    levels = check_levels(levels)
    symbols = jnp.asarray(symbols)
    if symbols.ndim < 3 or symbols.shape[-3] != symbols.shape[-2] or symbols.shape[-1] < 1:
        raise ValueError(
            f"symbols must be (..., K, K, C) by sender and recipient, got shape {symbols.shape}"
        )
    if not jnp.issubdtype(symbols.dtype, jnp.integer):
        raise ValueError(f"symbols must be integers in [0, {levels}], got {symbols.dtype}")
    k = symbols.shape[-2]
    _check_static_int(t, "t", 0, MAX_STEPS)
    batch = symbols.shape[:-3]
    mask = routing_mask(routing, k, batch)
    symbols = jnp.where(mask[..., None], symbols, 0)
    if not isinstance(symbols, jax.core.Tracer) and symbols.size:
        lo, hi = int(symbols.min()), int(symbols.max())
        if lo < 0 or hi > levels:
            raise ValueError(f"symbols must lie in [0, {levels}], got values in [{lo}, {hi}]")
    key, t = _episode_keys(key, t, batch)
    last = _check_last(last, symbols.shape)
    return _reconstruct(key, symbols, mask, t, last, levels)


@functools.partial(jax.jit, static_argnums=(5,))
def _reconstruct(key, symbols, mask, t, last, levels: int) -> jax.Array:
    """:func:`reconstruct` once its arguments are checked: the channel's own
    :func:`~sparsecomm.channel.links.receive` on the links by sender slot."""
    k, c = symbols.shape[-2], symbols.shape[-1]
    u = dither_links(key, t, np.arange(k)[:, None], others(k), c)
    m = slots(symbols, 1)
    cfg = _discrete(levels, last is not None)
    return _received(cfg, m, u, last, slots(mask), ~(m != 0).any(-1))[0]
