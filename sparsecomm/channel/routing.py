"""Who may talk to whom, and how links are laid out: one layout and one routing representation
for the whole channel (``channel.links``), the rollout, the plug-in layer and deploy.

Layout. Every array indexed by link is laid out by **sender slot**, ``(..., K, K-1, ...)``:
sender i's slot r goes to recipient ``others(K)[i, r]`` (the other agents in increasing order).
:func:`slots` and :func:`pairs` convert to and from the ``(..., K, K, ...)`` layout by sender
and recipient (zero diagonal); :func:`inbox` re-orders links by recipient (recipient j's s-th
link comes from ``others(K)[j, s]``) and :func:`deliver` flattens it to the actors' input,
``(..., K, (K-1) C)``. A deployed agent holds one row of it: its own K - 1 sender slots, or as a
receiver its K - 1 incoming links.

A routed team that hears only its k nearest (``AgentConfig.neighbours``) may instead **list** its
live links by recipient, ``(..., K, k, ...)``: entry ``[j, r]`` is the link ``senders[j, r] ->
j`` (:func:`listed` from the sender-slot layout, :func:`listed_pairs` to the pair layout), so the
rollout computes K k links, not K (K - 1). ``channel.transmit`` takes that listing
(``senders``) and counts each sender's frame over the links it has in it: the same numbers on
every live link (``tests/test_scaling.py``).

Routing. Which links exist is one boolean array by sender and recipient, ``mask[..., i, j]``:
a static :class:`Routing` (hashable, a jit static argument) and a traced mask (links that follow
the agents' positions, ``sparsecomm.scaling.routing_mask``) are two inputs of
:func:`live_links`, which turns either into the sender-slot ``live`` mask that
``channel.transmit`` and ``channel.receive`` take. A link that does not exist sends z = 0 (the
null symbol), costs 0 payload bits, 0 wire bits and 0 penalty, passes no gradient and delivers
0.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.config import ChannelConfig
from sparsecomm.channel.quantizer import MAX_AGENTS

# -- layout ---------------------------------------------------------------------------------


def others(num_agents: int) -> np.ndarray:
    """(K, K-1): row i lists the other agents in increasing order. Read by sender, it is the
    recipient of sender i's slot r; read by receiver, the sender of receiver j's s-th link."""
    k = num_agents
    return np.array([[j for j in range(k) if j != i] for i in range(k)]).reshape(k, k - 1)


def link_tables(num_agents: int) -> tuple[np.ndarray, np.ndarray]:
    """Static routing tables ``(sender, slot)``, each (K, K-1): receiver j's s-th incoming link
    comes from ``sender[j, s]``, which wrote it into its output slot ``slot[j, s]``."""
    sender = others(num_agents)
    receiver = np.arange(num_agents)[:, None]
    return sender, np.where(receiver > sender, receiver - 1, receiver)


def _at(trailing: int, rows, cols) -> tuple:
    """An index of the two link axes followed by ``trailing`` other axes."""
    return (Ellipsis, rows, cols, *([slice(None)] * trailing))


def slots(by_pair: jax.Array, trailing: int = 0) -> jax.Array:
    """(..., K, K, *e) by sender and recipient -> (..., K, K-1, *e) by sender slot (the
    diagonal dropped); ``e`` is ``trailing`` axes, e.g. 1 for a link's C elements."""
    k = by_pair.shape[by_pair.ndim - trailing - 1]
    return by_pair[_at(trailing, np.arange(k)[:, None], others(k))]


def pairs(by_slot: jax.Array, trailing: int = 0) -> jax.Array:
    """(..., K, K-1, *e) by sender slot -> (..., K, K, *e) by sender and recipient, zero on
    the diagonal (an agent sends nothing to itself)."""
    axis = by_slot.ndim - trailing - 2  # the sender axis
    k = by_slot.shape[axis]
    shape = (*by_slot.shape[: axis + 1], k, *by_slot.shape[axis + 2 :])
    out = jnp.zeros(shape, by_slot.dtype)
    return out.at[_at(trailing, jnp.arange(k)[:, None], others(k))].set(by_slot)


def inbox(by_slot: jax.Array, trailing: int = 0) -> jax.Array:
    """(..., K, K-1, *e) by sender slot -> (..., K, K-1, *e) by recipient: row j, entry s is
    the link from ``others(K)[j, s]`` to j."""
    sender, slot = link_tables(by_slot.shape[by_slot.ndim - trailing - 2])
    return by_slot[_at(trailing, sender, slot)]


def listed(by_slot: jax.Array, senders: jax.Array, trailing: int = 0) -> jax.Array:
    """(..., K, K-1, *e) by sender slot -> (..., K, k, *e) listed by recipient: entry ``[...,
    j, r]`` is the link ``senders[..., j, r] -> j`` (``senders`` (..., K, k) int, the same
    leading axes; ``sparsecomm.scaling.nearest_senders``)."""
    k = senders.shape[-2]
    recipient = jnp.arange(k)[:, None]
    slot = jnp.where(recipient > senders, recipient - 1, recipient)
    lead = senders.shape[:-2]
    flat = by_slot.reshape(-1, *by_slot.shape[len(lead) :])  # (N, K, K-1, *e)
    rows = jnp.arange(flat.shape[0])[:, None, None]
    out = flat[rows, senders.reshape(-1, k, senders.shape[-1]), slot.reshape(-1, k, slot.shape[-1])]
    return out.reshape(*lead, *out.shape[1:])


def listed_pairs(by_listing: jax.Array, senders: jax.Array) -> jax.Array:
    """(..., K, k) listed by recipient -> (..., K, K) by sender and recipient (the layout of
    :func:`pairs`), zero where no listed link is."""
    k = senders.shape[-2]
    lead = senders.shape[:-2]
    flat_s = senders.reshape(-1, k, senders.shape[-1])
    rows = jnp.arange(flat_s.shape[0])[:, None, None]
    out = jnp.zeros((flat_s.shape[0], k, k), by_listing.dtype)
    out = out.at[rows, flat_s, jnp.arange(k)[:, None]].set(by_listing.reshape(flat_s.shape))
    return out.reshape(*lead, k, k)


def deliver(z_hat: jax.Array) -> jax.Array:
    """Route decoded links to their recipients: (..., K, K-1, C) by sender -> (..., K,
    (K-1) C), receiver j's row holding the messages of the other agents in increasing order."""
    k, c = z_hat.shape[-3], z_hat.shape[-1]
    return inbox(z_hat, 1).reshape(*z_hat.shape[:-3], k, (k - 1) * c)


# -- routing --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Routing:
    """Which links exist, known before the episode: ``mask[i, j]`` is True when sender i may
    send to recipient j.

    Hashable, so it can be a static argument of ``jax.jit`` or a field of a frozen config. Build
    it with :meth:`all_to_all`, :meth:`from_neighbours` or :meth:`from_mask`. Self-links do not
    exist: the diagonal is always False. Routing that changes with the state is a traced
    boolean array of the same layout instead (:func:`live_links` takes either).
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


def routing_mask(routing: Routing | jax.Array, num_agents: int, batch=()) -> jax.Array:
    """The routing as a bool array ``batch + (K, K)`` by sender and recipient, diagonal
    cleared: a :class:`Routing`, or a boolean array ``(..., K, K)`` (may be traced) whose
    leading axes broadcast to ``batch``."""
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


def live_links(cfg: ChannelConfig, routing, num_agents: int, batch=()) -> jax.Array | None:
    """The links that carry anything this step, (..., K, K-1) by sender slot: the routing's
    (:func:`routing_mask`), and none at all on a channel that does not speak. ``None`` for
    ``routing=None``: every link (the paper's full team; nothing to mask)."""
    if routing is None:
        return None
    live = slots(routing_mask(routing, num_agents, batch))
    return live if cfg.speaks else jnp.zeros_like(live)
