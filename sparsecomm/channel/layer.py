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
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.codes import Code, as_code, payload_bits, wire_bits
from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.gate import gate as apply_gate
from sparsecomm.channel.penalty import code_penalty
from sparsecomm.channel.quantizer import (
    MAX_AGENTS,
    MAX_STEPS,
    check_levels,
    check_unit_interval,
    dequantize,
    dither,
    dither_key,
    quantize_dithered,
)

__all__ = ["Messages", "Routing", "reconstruct", "send"]


@dataclasses.dataclass(frozen=True)
class Routing:
    """Which links exist: ``mask[i, j]`` is True when sender i may send to recipient j.

    Hashable, so it can be a static argument of ``jax.jit`` or a field of a frozen config. Build
    it with :meth:`all_to_all`, :meth:`from_neighbours` or :meth:`from_mask`. Self-links do not
    exist: the diagonal is always False.
    """

    rows: tuple[tuple[bool, ...], ...]
    """``rows[i][j]``: link i -> j exists. K rows of K booleans, the diagonal False."""

    def __post_init__(self):
        k = len(self.rows)
        if not 1 <= k <= MAX_AGENTS:
            raise ValueError(f"Routing needs between 1 and {MAX_AGENTS} agents, got {k}")
        if any(len(row) != k for row in self.rows):
            lengths = sorted({len(row) for row in self.rows})
            raise ValueError(
                f"Routing.rows must be {k} rows of {k} booleans, got lengths {lengths}"
            )
        if any(self.rows[i][i] for i in range(k)):
            raise ValueError(
                "Routing.mask must have a False diagonal (an agent does not send to itself); "
                "use mask & ~numpy.eye(K, dtype=bool)"
            )

    @property
    def mask(self) -> np.ndarray:
        """(K, K) bool: ``mask[i, j]`` when link sender i -> recipient j exists."""
        return np.array(self.rows, dtype=bool).reshape(len(self.rows), len(self.rows))

    @property
    def num_agents(self) -> int:
        """K, the number of agents."""
        return len(self.rows)

    @property
    def num_links(self) -> int:
        """The number of links that exist (directed)."""
        return int(self.mask.sum())

    def recipients(self, sender: int) -> list[int]:
        """The agents ``sender`` may send to, in increasing order."""
        return [int(j) for j in np.flatnonzero(self.mask[sender])]

    def senders(self, recipient: int) -> list[int]:
        """The agents ``recipient`` hears from, in increasing order."""
        return [int(i) for i in np.flatnonzero(self.mask[:, recipient])]

    @classmethod
    def all_to_all(cls, num_agents: int) -> Routing:
        """Every agent sends to every other agent (the paper's team), K (K - 1) links."""
        if isinstance(num_agents, bool) or not isinstance(num_agents, (int, np.integer)):
            raise ValueError(
                f"num_agents must be an integer in [1, {MAX_AGENTS}], got {num_agents!r}"
            )
        if not 1 <= num_agents <= MAX_AGENTS:
            raise ValueError(
                f"num_agents must be an integer in [1, {MAX_AGENTS}], got {num_agents}"
            )
        return cls.from_mask(~np.eye(int(num_agents), dtype=bool))

    @classmethod
    def from_neighbours(cls, neighbours) -> Routing:
        """Routing from out-neighbour lists: ``neighbours[i]`` lists the agents sender i sends to
        (K lists, one per agent, each of distinct agents in [0, K) other than i). For an
        undirected graph list each edge in both directions."""
        lists = [list(row) for row in neighbours]
        k = len(lists)
        if not 1 <= k <= MAX_AGENTS:
            raise ValueError(f"neighbours must be 1 to {MAX_AGENTS} lists, one per agent, got {k}")
        mask = np.zeros((k, k), dtype=bool)
        for i, row in enumerate(lists):
            for j in row:
                if isinstance(j, bool) or not isinstance(j, (int, np.integer)) or not 0 <= j < k:
                    raise ValueError(
                        f"neighbours[{i}] must hold agent indices in [0, {k}), got {j!r}"
                    )
                if j == i:
                    raise ValueError(f"neighbours[{i}] must not hold {i} itself (no self-links)")
                if mask[i, j]:
                    raise ValueError(f"neighbours[{i}] lists agent {j} twice")
                mask[i, j] = True
        return cls.from_mask(mask)

    @classmethod
    def from_mask(cls, mask) -> Routing:
        """Routing from a concrete (K, K) boolean array, ``mask[i, j]``: link i -> j exists."""
        a = np.asarray(mask)
        if a.ndim != 2 or a.shape[0] != a.shape[1] or a.dtype != np.bool_:
            raise ValueError(
                f"mask must be a square (K, K) boolean array, got {a.dtype} of shape {a.shape}"
            )
        return cls(tuple(tuple(bool(x) for x in row) for row in a))


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
    """(..., K, K) int32: each link's packet on the wire, framing and CRC-32 included
    (``channel.wire_bits``; 0 for a silent link). ``8 * len(channel.encode(symbols[..., i, j,
    :], code))`` when computed on the host."""
    mask: jax.Array
    """(..., K, K) bool: the links that existed (the routing, diagonal cleared)."""


def _check_static_int(value, name: str, lo: int, hi: int) -> None:
    if isinstance(value, jax.core.Tracer):
        return
    a = np.asarray(value)
    if a.dtype == np.bool_ or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}), got {value!r}")
    if a.size and (a.min() < lo or a.max() >= hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}), got {value!r}")


def _mask_array(routing, num_agents: int, batch: tuple[int, ...]) -> jax.Array:
    """The routing as a jnp bool array broadcast to ``batch + (K, K)``, diagonal cleared."""
    if isinstance(routing, Routing):
        if routing.num_agents != num_agents:
            raise ValueError(
                f"routing must be for {num_agents} agents (z's agent axes), got a Routing for "
                f"{routing.num_agents}"
            )
        mask = jnp.asarray(routing.mask)
    else:
        mask = jnp.asarray(routing)
        if mask.dtype != jnp.bool_ or mask.ndim < 2 or mask.shape[-2:] != (num_agents,) * 2:
            raise ValueError(
                f"routing must be a Routing or a boolean array of shape (..., {num_agents}, "
                f"{num_agents}), got {mask.dtype} of shape {mask.shape}"
            )
        mask = mask & ~jnp.eye(num_agents, dtype=bool)
    try:
        return jnp.broadcast_to(mask, (*batch, num_agents, num_agents))
    except ValueError:
        raise ValueError(
            f"routing's leading axes {mask.shape[:-2]} must broadcast to z's batch shape {batch}"
        ) from None


def _key_batch_shape(key: jax.Array) -> tuple[int, ...]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key.shape
    if key.dtype != jnp.uint32 or key.ndim < 1:
        raise ValueError(f"key must be a PRNG key (typed or raw uint32), got {key.dtype}")
    return key.shape[:-1]


def _episode_keys(key: jax.Array, t, batch: tuple[int, ...]):
    """Check ``key`` (one key, or one per batch entry) and broadcast ``t`` to the batch."""
    kshape = _key_batch_shape(jnp.asarray(key) if not isinstance(key, jax.Array) else key)
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


def _over_links(fn, key: jax.Array, t: jax.Array, num_agents: int, *arrays):
    """``fn(dither_key(key, t, i, j), *link_arrays)`` for every link i -> j of every batch entry,
    in one ``vmap`` over all links (one level of ``vmap``: nested ones compile ~3x slower).

    ``key`` is one key (shared by the batch) or one per batch entry; ``t`` has the batch shape;
    each of ``arrays`` is ``(*batch, K, K, ...)``. Returns ``(*batch, K, K, ...)``."""
    batch = t.shape
    n, links = math.prod(batch), num_agents * num_agents
    senders, recipients = np.meshgrid(np.arange(num_agents), np.arange(num_agents), indexing="ij")
    i = jnp.asarray(np.tile(senders.ravel(), n))
    j = jnp.asarray(np.tile(recipients.ravel(), n))
    steps = jnp.repeat(t.reshape(n), links)
    flat = [a.reshape(n * links, *a.shape[len(batch) + 2 :]) for a in arrays]
    if _key_batch_shape(key):  # one key per batch entry: repeat it for each of its links
        key = jnp.repeat(key.reshape(n, *key.shape[len(batch) :]), links, axis=0)
        key_axis = 0
    else:
        key_axis = None

    def one_link(k, tt, ii, jj, *xs):
        return fn(dither_key(k, tt, ii, jj), *xs)

    out = jax.vmap(one_link, (key_axis, 0, 0, 0, *([0] * len(flat))))(key, steps, i, j, *flat)
    return out.reshape(*batch, num_agents, num_agents, *out.shape[1:])


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
    mask = _mask_array(routing, k, batch)
    key, t = _episode_keys(key, t, batch)
    check_unit_interval(jnp.where(mask[..., None], z, 0.0))  # concrete z only
    return _send(key, z, mask, t, prev, levels, code)


@functools.partial(jax.jit, static_argnums=(5, 6))
def _send(key, z, mask, t, prev, levels: int, code) -> Messages:
    """:func:`send` once its arguments are checked (one compiled program, also when eager)."""
    k, c = z.shape[-2], z.shape[-1]
    live = mask[..., None]
    z_sent = jnp.where(live, z, 0.0)  # a missing link sends z = 0: m = 0 always, no gradient
    u = _over_links(lambda link_key: dither(link_key, (c,)), key, t, k)
    m, z_hat = quantize_dithered(z_sent, u, levels)
    m = jnp.where(live, m, 0)
    z_hat = jnp.where(live, z_hat, 0.0)
    penalty = jnp.where(mask, code_penalty(z_sent, levels, code).sum(-1), 0.0)
    payload = jnp.where(mask, payload_bits(m, code).sum(-1), 0).astype(jnp.int32)
    wire = jnp.where(mask, wire_bits(m, code, prev=prev), 0).astype(jnp.int32)
    inbox = jnp.swapaxes(z_hat, -3, -2)
    heard = mask.sum(-2).astype(jnp.float32)  # senders of each recipient
    mean = inbox.sum(-2) / jnp.maximum(heard, 1.0)[..., None]
    return Messages(m, z_hat, inbox, mean, penalty, payload, wire, mask)


def reconstruct(
    key: jax.Array, symbols: jax.Array, routing: Routing | jax.Array, *, t, levels: int = 15
) -> jax.Array:
    """Receiver side: every recipient's inbox rebuilt from the symbols alone and the shared key.

    ``symbols`` ``(..., K, K, C)`` by sender and recipient (``Messages.symbols``, or decoded
    packets); ``key``, ``routing``, ``t`` and ``levels`` as given to :func:`send`. Returns
    ``(..., K, K, C)`` by recipient then sender, ``(m - u) / levels`` on the links that exist
    and 0 elsewhere: ``Messages.inbox``'s values (up to float rounding), without its gradient.
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
    mask = _mask_array(routing, k, batch)
    symbols = jnp.where(mask[..., None], symbols, 0)
    if not isinstance(symbols, jax.core.Tracer) and symbols.size:
        lo, hi = int(symbols.min()), int(symbols.max())
        if lo < 0 or hi > levels:
            raise ValueError(f"symbols must lie in [0, {levels}], got values in [{lo}, {hi}]")
    key, t = _episode_keys(key, t, batch)
    return _reconstruct(key, symbols, mask, t, levels)


@functools.partial(jax.jit, static_argnums=(4,))
def _reconstruct(key, symbols, mask, t, levels: int) -> jax.Array:
    """:func:`reconstruct` once its arguments are checked."""
    k = symbols.shape[-2]
    z_hat = _over_links(lambda link_key, m: dequantize(link_key, m, levels), key, t, k, symbols)
    return jnp.swapaxes(jnp.where(mask[..., None], z_hat, 0.0), -3, -2)
