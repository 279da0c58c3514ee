"""Many agents: who talks to whom, and an inbox whose size does not grow with K (docs/scaling.md).

Three switches in :class:`sparsecomm.configs.AgentConfig` (defaults: today's all-to-all team with
the concatenated inbox) and one in the task (``NavConfig.goal_view``: who sees whose goal):

- **routing** (``neighbours``, ``radius``): at each step, from the positions the agents have
  then, link i -> j exists when i is one of the ``neighbours`` agents nearest to j (ties to the
  lower index; every agent hears at most ``neighbours`` others) and, with ``radius``, when
  ``||pos_i - pos_j|| <= radius``. :func:`routing_mask` is that (..., K, K) mask, a traced
  routing input of the channel (``channel.live_links``), as a static ``channel.Routing`` is:
  a link that does not exist sends z = 0, so it carries the null symbol, costs 0 payload bits,
  0 wire bits and 0 penalty and passes no gradient; the recipient receives 0 there. Bits and
  the penalty stay per link, counted by :func:`sparsecomm.channel.transmit` from the real
  symbols as for the full team.
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

AGGREGATES = ("concat", "mean", "attention")
"""How an actor reads its received messages (``AgentConfig.aggregate``)."""

ATTENTION_DIM = 32
"""Width of the attention's query, keys and values. ours (half the default hidden width)."""


def routing_mask(pos: jax.Array, neighbours: int | None, radius: float | None) -> jax.Array:
    """(..., K, K) bool, ``mask[..., i, j]``: link sender i -> recipient j exists, for agents at
    ``pos`` (..., K, 2). ``None`` for both: every link but the self-links (the paper's)."""
    k = pos.shape[-2]
    dist = jnp.linalg.norm(pos[..., :, None, :] - pos[..., None, :, :], axis=-1)
    mask = jnp.broadcast_to(~jnp.eye(k, dtype=bool), dist.shape)
    if radius is not None:
        mask &= dist <= radius
    if neighbours is not None:  # recipient j's nearest others (lax.top_k: ties to lower index)
        d = jnp.where(jnp.eye(k, dtype=bool), jnp.inf, jnp.swapaxes(dist, -1, -2))  # (j, i)
        nearest = jax.lax.top_k(-d, neighbours)[1]  # (..., K recipients, neighbours)
        chosen = jax.nn.one_hot(nearest, k, dtype=bool).any(-2)  # (..., j, i)
        mask &= jnp.swapaxes(chosen, -1, -2)
    return mask


def inbox_features(msgs: jax.Array, heard: jax.Array, aggregate: str) -> jax.Array:
    """What the actor reads of its inbox besides :class:`AttentionPool`. ``msgs`` (..., K, K-1,
    C) by recipient (zero where not heard), ``heard`` (..., K, K-1) bool. ``mean``: the mean of
    the heard messages and the fraction of the K - 1 others heard, (..., K, C + 1);
    ``attention``: that fraction, (..., K, 1)."""
    count = heard.sum(-1, keepdims=True).astype(jnp.float32)
    frac = count / heard.shape[-1]
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


def check_agent_fields(neighbours, radius, aggregate) -> None:
    """Refuse bad values of ``AgentConfig``'s routing and aggregate fields (any K)."""
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
