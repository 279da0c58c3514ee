"""Many agents: who talks to whom, and an inbox whose size does not grow with K (docs/scaling.md).

Switches in :class:`sparsecomm.configs.AgentConfig` (defaults: the all-to-all team with
the concatenated inbox) and one in the task (``NavConfig.goal_view``: who sees whose goal):

- **routing** (``neighbours``, ``radius``, ``hears``): at each step, from the positions the
  agents have then, link i -> j exists when i is one of the ``neighbours`` agents nearest to j
  (ties to the lower index; every agent hears at most ``neighbours`` others; with ``hears =
  "ring"`` instead the k agents j - 1, ..., j - k, who see j's goal under the ``ring`` goal
  view) and, with ``radius``, when ``||pos_i - pos_j|| <= radius``. :func:`routing_mask` is
  that (..., K, K) mask, a traced routing input of the channel (``channel.live_links``), as a
  static ``channel.Routing`` is: a link that does not exist sends z = 0, so it carries the null
  symbol, costs 0 payload bits, 0 wire bits and 0 penalty and passes no gradient; the recipient
  receives 0 there. Bits and the penalty stay per link, counted by
  :func:`sparsecomm.channel.transmit` from the real symbols as for the full team. With
  ``neighbours`` and a ``mean`` or ``attention`` inbox, :func:`nearest_senders` lists the live
  links by recipient and the rollout computes only those (``ExperimentalConfig.live_links_only``).
- **aggregate** (``aggregate``): ``concat`` feeds the actor every link's message in a fixed
  order, (K - 1) C inputs (the paper's). ``mean`` feeds the mean of the messages of the senders
  it heard (C inputs) and ``attention`` a softmax-weighted sum of them (:class:`AttentionPool`,
  query from the receiver's GRU state); both add the fraction of the team it heard (1 input)
  and are invariant to the order of the senders. The senders' message heads stay per link
  (K - 1 slots of C elements), so a sender may still tell each neighbour something else.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

HEARS = ("nearest", "ring")
"""Which ``neighbours`` agents a recipient hears (``AgentConfig.hears``)."""

AGGREGATES = ("concat", "mean", "attention")
"""How an actor reads its received messages (``AgentConfig.aggregate``)."""

ATTENTION_DIM = 32
"""Width of the attention's query, keys and values. ours (half the default hidden width)."""


def ring_senders(num_agents: int, neighbours: int):
    """(K, k) int32: recipient j hears agents j - 1, ..., j - k (mod K), in increasing index
    order: under ``NavConfig.goal_view = "ring"`` with ``goal_view_count`` k, exactly the agents
    that see j's goal."""
    j = np.arange(num_agents)[:, None]
    return np.sort((j - np.arange(1, neighbours + 1)) % num_agents, axis=-1).astype(np.int32)


def routing_mask(
    pos: jax.Array, neighbours: int | None, radius: float | None, hears: str = "nearest"
) -> jax.Array:
    """(..., K, K) bool, ``mask[..., i, j]``: link sender i -> recipient j exists, for agents at
    ``pos`` (..., K, 2). ``None`` for both: every link but the self-links (the paper's).
    ``hears``: which ``neighbours`` agents a recipient hears (:data:`HEARS`)."""
    k = pos.shape[-2]
    dist = jnp.linalg.norm(pos[..., :, None, :] - pos[..., None, :, :], axis=-1)
    mask = jnp.broadcast_to(~jnp.eye(k, dtype=bool), dist.shape)
    if radius is not None:
        mask &= dist <= radius
    if neighbours is not None and hears == "ring":
        ring = np.zeros((k, k), bool)
        ring[ring_senders(k, neighbours), np.arange(k)[:, None]] = True
        mask &= ring
    elif neighbours is not None:  # recipient j's nearest others (lax.top_k: ties to lower index)
        d = jnp.where(jnp.eye(k, dtype=bool), jnp.inf, jnp.swapaxes(dist, -1, -2))  # (j, i)
        nearest = jax.lax.top_k(-d, neighbours)[1]  # (..., K recipients, neighbours)
        chosen = jax.nn.one_hot(nearest, k, dtype=bool).any(-2)  # (..., j, i)
        mask &= jnp.swapaxes(chosen, -1, -2)
    return mask


def nearest_senders(
    pos: jax.Array, neighbours: int, radius: float | None, hears: str = "nearest"
) -> tuple[jax.Array, jax.Array]:
    """The live links of :func:`routing_mask` listed by recipient, for ``neighbours`` k: recipient
    j's k nearest others (or its ``ring`` senders) ``senders[..., j, :]`` (..., K, k) int32, in
    increasing index order, and ``live`` (..., K, k) bool, those within ``radius`` (all of them
    without one). Link ``senders[..., j, r] -> j`` exists exactly where ``live[..., j, r]`` and
    where ``routing_mask`` is True (the same ``lax.top_k`` and tie rule)."""
    k = pos.shape[-2]
    dist = jnp.linalg.norm(pos[..., :, None, :] - pos[..., None, :, :], axis=-1)  # symmetric
    if hears == "ring":
        senders = jnp.broadcast_to(ring_senders(k, neighbours), (*pos.shape[:-2], k, neighbours))
    else:
        d = jnp.where(jnp.eye(k, dtype=bool), jnp.inf, dist)  # (..., j, i)
        senders = jnp.sort(jax.lax.top_k(-d, neighbours)[1], axis=-1).astype(jnp.int32)
    live = jnp.ones(senders.shape, bool)
    if radius is not None:
        live = jnp.take_along_axis(dist, senders, axis=-1) <= radius
    return senders, live


def inbox_features(
    msgs: jax.Array, heard: jax.Array, aggregate: str, others: int | None = None
) -> jax.Array:
    """What the actor reads of its inbox besides :class:`AttentionPool`. ``msgs`` (..., K, S,
    C) by recipient (zero where not heard), ``heard`` (..., K, S) bool: the K - 1 other agents
    (S = K - 1), or only the senders a gathered layout lists (``others`` = K - 1 then).
    ``mean``: the mean of the heard messages and the fraction of the K - 1 others heard, (...,
    K, C + 1); ``attention``: that fraction, (..., K, 1)."""
    count = heard.sum(-1, keepdims=True).astype(jnp.float32)
    frac = count / (heard.shape[-1] if others is None else others)
    if aggregate == "attention":
        return frac
    total = jnp.where(heard[..., None], msgs, 0.0).sum(-2)
    return jnp.concatenate([total / jnp.maximum(count, 1.0), frac], -1)


class AttentionPool(nn.Module):
    """Single-head attention of a receiver over the senders it heard: query from its GRU state,
    keys and values from each message; 0 when it heard nobody. Permutation invariant."""

    dim: int = ATTENTION_DIM

    @nn.compact
    def __call__(self, carry: jax.Array, msgs: jax.Array, heard: jax.Array) -> jax.Array:
        q = nn.Dense(self.dim, name="query")(carry)  # (..., D)
        kv = nn.Dense(2 * self.dim, name="key_value")(msgs)  # (..., S, 2D)
        keys, values = kv[..., : self.dim], kv[..., self.dim :]
        scores = jnp.einsum("...sd,...d->...s", keys, q) / math.sqrt(self.dim)
        weights = jax.nn.softmax(jnp.where(heard, scores, -1e9), -1)
        weights = jnp.where(heard, weights, 0.0)
        return jnp.einsum("...s,...sd->...d", weights, values)


def check_agent_fields(neighbours, radius, aggregate, hears: str = "nearest") -> None:
    """Refuse bad values of ``AgentConfig``'s routing and aggregate fields (any K)."""
    if hears not in HEARS:
        raise ValueError(f"AgentConfig.hears must be one of {HEARS}, got {hears!r}")
    if hears == "ring" and neighbours is None:
        raise ValueError("AgentConfig.hears 'ring' needs AgentConfig.neighbours (an integer >= 1)")
    if neighbours is not None and (
        isinstance(neighbours, bool) or not isinstance(neighbours, int) or neighbours < 1
    ):
        raise ValueError(
            f"AgentConfig.neighbours must be None or an integer >= 1, got {neighbours!r}"
        )
    if radius is not None and not (
        isinstance(radius, int | float) and not isinstance(radius, bool) and 0 < radius < math.inf
    ):
        raise ValueError(f"AgentConfig.radius must be None or finite and > 0, got {radius!r}")
    if aggregate not in AGGREGATES:
        raise ValueError(f"AgentConfig.aggregate must be one of {AGGREGATES}, got {aggregate!r}")


def check_fits(agent, num_agents: int) -> None:
    """Refuse ``AgentConfig.neighbours`` above K - 1 for a team of ``num_agents``."""
    if agent.neighbours is not None and agent.neighbours > num_agents - 1:
        raise ValueError(
            f"AgentConfig.neighbours must be in [1, {num_agents - 1}] (K - 1) for "
            f"{num_agents} agents, got {agent.neighbours!r}"
        )
