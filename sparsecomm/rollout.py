"""The one rollout: environment, actors and channel in a single ``lax.scan``.

It serves reinforcement learning (the learners act), imitation (an expert acts, or the learners
act and an expert labels: DAgger) and evaluation. Each batch element is one whole episode of
``env.max_steps`` steps; steps after the episode ended are computed but masked (``valid``).

At step t every agent i reads its observation and the messages decoded at step t-1, and emits
``z^{i->j}`` for every j != i. The channel quantizes each link with the dither key
``dither_key(episode_channel_key, t, i, j)`` and the reconstructions become the received messages
of step t+1. Everything stays differentiable with respect to the actors' parameters: a
receiver's log-probabilities at t+1 depend on the senders' parameters through ``z_hat``, and on
all earlier steps through the GRU states (backpropagation through the episode).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.scipy.special import gammaln

from sparsecomm import channel
from sparsecomm.agents import Team
from sparsecomm.configs import ChannelConfig
from sparsecomm.envs.navigation import NavigationEnv
from sparsecomm.sharding import split_episodes


@struct.dataclass
class Expert:
    """An action source that may label or drive episodes (imitation, DAgger).

    ``init(batch) -> carry`` and ``step(carry, key, env_state, obs) -> (carry, actions)`` where
    ``env_state`` is the batched :class:`NavState` (a centralised expert may read every goal),
    ``obs`` the (B, K, obs_dim) observations, and actions (B, K) int32.
    """

    init: Callable[[int], Any] = struct.field(pytree_node=False)
    step: Callable = struct.field(pytree_node=False)


@struct.dataclass
class Trajectory:
    """Per-step records, leading axes (T, B)."""

    log_probs: jax.Array  # (T, B, K, A) log pi(. | o_<=t), differentiable
    actions: jax.Array  # (T, B, K) actions executed
    expert_actions: jax.Array  # (T, B, K) expert labels (-1 when there is no expert)
    rewards: jax.Array  # (T, B, K) in the paper's units
    states: jax.Array  # (T, B, state_dim) global state before the step (critic input)
    valid: jax.Array  # (T, B) the step belongs to the episode
    dones: jax.Array  # (T, B) the episode ended at this step
    success: jax.Array  # (T, B) all agents at their goals after this step
    penalty: jax.Array  # (T, B) surrogate bit penalty, summed over links and elements
    payload_bits: jax.Array  # (T, B) real payload bits sent by the team
    wire_bits: jax.Array  # (T, B) bits on the wire, framing included
    link_bits: jax.Array  # (T, B, K, K) payload bits sent i -> j (zero diagonal)
    msg_log_probs: jax.Array  # (T, B, K) log-prob of sender i's symbols ("reinforced"; else 0)
    env_states: Any = None  # batched NavState per step (only when ``keep_states``)
    hidden: Any = None  # (T, B, K, H) GRU states the messages came from (only ``keep_hidden``)


def link_tables(num_agents: int) -> tuple[np.ndarray, np.ndarray]:
    """Static routing tables ``(sender, slot)``, each (K, K-1).

    Receiver j's s-th incoming link comes from ``sender[j, s]`` (the other agents in increasing
    order), which wrote it into output slot ``slot[j, s]`` of its message head (the slot of
    recipient j among the sender's K-1 recipients).
    """
    sender = np.array([[i for i in range(num_agents) if i != j] for j in range(num_agents)])
    slot = np.where(
        np.arange(num_agents)[:, None] > sender,
        np.arange(num_agents)[:, None] - 1,
        np.arange(num_agents)[:, None],
    )
    return sender.reshape(num_agents, num_agents - 1), slot.reshape(num_agents, num_agents - 1)


def deliver(z_hat: jax.Array) -> jax.Array:
    """Route decoded links to their recipients: (B, K, K-1, C) by sender -> (B, K, (K-1) C),
    receiver j's row holding the messages of the other agents in increasing order."""
    b, k, _, c = z_hat.shape
    sender, slot = link_tables(k)
    return z_hat[:, sender, slot].reshape(b, k, (k - 1) * c)


def recipients(num_agents: int) -> np.ndarray:
    """(K, K-1): the recipient of sender i's output slot r."""
    return np.array([[j for j in range(num_agents) if j != i] for i in range(num_agents)])


def step_dither(cfg: ChannelConfig, keys: jax.Array, t, num_agents: int):
    """The dither of every link of a batch at step ``t``: (B, K, K-1, C), ``None`` unless the
    channel quantizes. Link i -> j of episode b uses ``dither_key(keys[b], t, i, j)`` (SPEC
    section 1), so its receiver can regenerate it alone."""
    if cfg.mode != "discrete":
        return None

    def one_link(key, i, j):
        return channel.dither(channel.dither_key(key, t, i, j), (cfg.num_elements,))

    links = jax.vmap(jax.vmap(one_link, (None, None, 0)), (None, 0, 0))
    senders, recv = jnp.arange(num_agents), jnp.asarray(recipients(num_agents))
    return jax.vmap(lambda key: links(key, senders, recv))(keys)


def link_dither(cfg: ChannelConfig, keys: jax.Array, num_steps: int, num_agents: int):
    """:func:`step_dither` of every step, (T, B, K, K-1, C), in one vectorised draw: drawing
    them before the time loop instead of inside it replaces many tiny random draws per step by
    one large one (docs/benchmarks.md)."""
    if cfg.mode != "discrete":
        return None
    if num_steps > 4096 or num_agents > 1024:
        raise ValueError(
            f"the dither keys support max_steps <= 4096 and num_agents <= 1024, got "
            f"{num_steps} and {num_agents}"
        )
    return jax.vmap(lambda t: step_dither(cfg, keys, t, num_agents))(jnp.arange(num_steps))


def transmit(cfg: ChannelConfig, u: jax.Array | None, z: jax.Array):
    """Send every link of a batch through the channel.

    ``u`` (B, K, K-1, C) the links' dither (:func:`link_dither`, ``None`` unless the channel
    quantizes); ``z`` (B, K, K-1, C). Returns ``(z_hat, penalty (B,), payload (B,), wire (B,),
    link_payload (B, K, K-1))``.
    """
    b, k, r, c = z.shape
    zeros_b = jnp.zeros((b,), jnp.float32)
    if cfg.mode == "reinforced":
        raise ValueError(
            "ChannelConfig.mode 'reinforced' samples its symbols with the episode "
            "keys: use transmit_reinforced(cfg, keys, t, z)"
        )
    if cfg.mode == "off":
        z0 = jnp.zeros_like(z)
        return z0, zeros_b, zeros_b, zeros_b, jnp.zeros((b, k, r), jnp.float32)
    if cfg.mode == "continuous":
        link = jnp.full((b, k, r), 32.0 * c)
        total = jnp.full((b,), 32.0 * c * k * r)
        return z, zeros_b, total, total, link
    m, z_hat = channel.quantize_dithered(z, u, cfg.levels)
    code = cfg.code_obj
    link = channel.payload_bits(m, code).sum(-1).astype(jnp.float32)
    wire = channel.wire_bits(m, code).sum((-3, -2, -1)).astype(jnp.float32)
    penalty = channel.bit_penalty(z, cfg.levels).sum((-3, -2, -1))
    return z_hat, penalty, link.sum((-2, -1)), wire, link


def transmit_reinforced(cfg: ChannelConfig, keys: jax.Array, t: jax.Array, z: jax.Array):
    """Reinforced communication learning (``mode = "reinforced"``, a baseline): symbols are
    actions.

    ``keys`` (B,) episode channel keys, ``t`` the step, ``z`` (B, K, K-1, C). Each element's
    symbol is sampled as m ~ Binomial(levels, z) (the number of ``levels`` uniforms below z,
    drawn with the link's key ``dither_key(keys[b], t, i, j)``): full support on {0, ...,
    levels}, mean ``levels * z``. The receiver gets ``stop_gradient(m / levels)``, so no gradient
    crosses the channel; the sender learns from the log-probability of what it sent (z clipped
    to [1e-6, 1 - 1e-6] there). Returns :func:`transmit`'s five values and that log-probability
    per sender, (B, K), summed over its recipients and elements.
    """
    k = z.shape[1]
    z_sample = jax.lax.stop_gradient(z)

    def one_link(key, i, j, z_link):
        u = jax.random.uniform(channel.dither_key(key, t, i, j), (*z_link.shape, cfg.levels))
        return (u < z_link[..., None]).sum(-1)

    per_link = jax.vmap(jax.vmap(one_link, (None, None, 0, 0)), (None, 0, 0, 0))
    m = jax.vmap(per_link, (0, None, None, 0))(
        keys, jnp.arange(k), jnp.asarray(recipients(k)), z_sample
    )
    n, mf = float(cfg.levels), m.astype(jnp.float32)
    zc = jnp.clip(z, 1e-6, 1.0 - 1e-6)
    log_comb = gammaln(n + 1.0) - gammaln(mf + 1.0) - gammaln(n - mf + 1.0)
    log_prob = (log_comb + mf * jnp.log(zc) + (n - mf) * jnp.log1p(-zc)).sum((-2, -1))
    code = cfg.code_obj
    link = channel.payload_bits(m, code).sum(-1).astype(jnp.float32)
    wire = channel.wire_bits(m, code).sum((-3, -2, -1)).astype(jnp.float32)
    penalty = channel.bit_penalty(z, cfg.levels).sum((-3, -2, -1))
    z_hat = jax.lax.stop_gradient(mf / n)
    return z_hat, penalty, link.sum((-2, -1)), wire, link, log_prob


def rollout(
    team: Team,
    env: NavigationEnv,
    channel_cfg: ChannelConfig,
    actor_params,
    key: jax.Array,
    num_envs: int,
    *,
    expert: Expert | None = None,
    beta: jax.Array | float = 0.0,
    greedy: bool = False,
    remat: bool = False,
    keep_states: bool = False,
    keep_hidden: bool = False,
) -> Trajectory:
    """Play ``num_envs`` whole episodes.

    Args:
      team, env, channel_cfg: the actors, the task and the channel.
      actor_params: the actors' parameters (gradients flow back into them).
      key: PRNG key of the whole batch.
      num_envs: batch of parallel episodes.
      expert: optional :class:`Expert` that labels every step (``expert_actions``).
      beta: probability that the expert's action is executed instead of the learners' (1:
        behaviour cloning, the expert drives; 0: the learners drive; between: DAgger mixing).
      greedy: learners take their most probable action instead of sampling.
      remat: recompute each step in the backward pass (``jax.checkpoint``) to save memory.
      keep_states: also return the environment states (for rendering and tests).
      keep_hidden: also return the GRU states each step's messages came from (for a penalty
        step outside the optimiser, ``sparsecomm.budget.penalty_step``).
    """
    k = env.num_agents
    num_steps = env.config.max_steps
    k_reset, k_chan, k_act, k_env, k_exp, k_mix = jax.random.split(key, 6)
    obs, state = jax.vmap(env.reset)(jax.random.split(k_reset, num_envs))
    c = channel_cfg.num_elements
    msgs = jnp.zeros((num_envs, k, (k - 1) * c), jnp.float32)
    carry = team.initial_carry(num_envs)
    expert_carry = expert.init(num_envs) if expert is not None else None
    # All the step's randomness is drawn before the loop, in a few large vectorised draws.
    chan_keys = jax.random.split(k_chan, num_envs)
    noise = {
        "t": jnp.arange(num_steps),
        "env": jax.random.split(k_env, (num_steps, num_envs)),
        "gumbel": jax.random.gumbel(k_act, (num_steps, num_envs, k, team.num_actions)),
        "dither": link_dither(channel_cfg, chan_keys, num_steps, k),
    }
    if expert is not None:
        noise["expert"] = jax.random.split(k_exp, num_steps)
        noise["mix"] = jax.random.uniform(k_mix, (num_steps, num_envs, 1))
    # Episodes are independent: split them over the mesh's episodes axis, if there is one.
    batched = ("env", "gumbel", "dither", "mix")
    noise.update(split_episodes({n: v for n, v in noise.items() if n in batched}, axis=1))
    state, obs, msgs, carry, chan_keys = split_episodes(
        (state, obs, msgs, carry, chan_keys), axis=0
    )

    def step(loop, noise):
        state, obs, msgs, carry, expert_carry = loop
        t = noise["t"]
        carry, logits, z = team.act(actor_params, carry, obs, msgs)
        log_probs = jax.nn.log_softmax(logits)
        if greedy:
            actions = jnp.argmax(logits, -1)
        else:  # Gumbel-max: a sample of the categorical distribution of ``logits``
            actions = jnp.argmax(jax.lax.stop_gradient(log_probs) + noise["gumbel"], -1)
        if expert is not None:
            expert_carry, expert_actions = expert.step(expert_carry, noise["expert"], state, obs)
            use_expert = noise["mix"] < beta
            actions = jnp.where(use_expert, expert_actions, actions)
        else:
            expert_actions = jnp.full(actions.shape, -1)
        if channel_cfg.mode == "reinforced":
            z_hat, penalty, payload, wire, link, msg_logp = transmit_reinforced(
                channel_cfg, chan_keys, t, z
            )
        else:
            z_hat, penalty, payload, wire, link = transmit(channel_cfg, noise["dither"], z)
            msg_logp = jnp.zeros((num_envs, k), jnp.float32)
        next_msgs = deliver(z_hat)
        global_state = jax.vmap(env.global_state)(state)
        valid = ~state.done
        next_obs, next_state, rewards, dones, info = jax.vmap(env.step)(
            noise["env"], state, actions
        )
        full_link = jnp.zeros((num_envs, k, k), jnp.float32)
        full_link = full_link.at[:, jnp.arange(k)[:, None], jnp.asarray(recipients(k))].set(link)
        record = Trajectory(
            log_probs=log_probs,
            actions=actions.astype(jnp.int32),
            expert_actions=expert_actions.astype(jnp.int32),
            rewards=rewards,
            states=global_state,
            valid=valid,
            dones=dones[:, 0] & valid,
            success=info["success"] & valid,
            penalty=penalty,
            payload_bits=payload,
            wire_bits=wire,
            link_bits=full_link,
            msg_log_probs=msg_logp,
            env_states=state if keep_states else None,
            hidden=jax.lax.stop_gradient(carry) if keep_hidden else None,
        )
        return (next_state, next_obs, next_msgs, carry, expert_carry), record

    if remat:
        step = jax.checkpoint(step)
    init = (state, obs, msgs, carry, expert_carry)
    _, traj = jax.lax.scan(step, init, noise)
    return traj


def episode_metrics(traj: Trajectory) -> dict[str, jax.Array]:
    """Batch means of the SPEC section 6 metrics (rewards in the paper's units)."""
    valid = traj.valid.astype(jnp.float32)
    steps = valid.sum()
    return {
        "group_reward": (traj.rewards.sum(-1) * valid).sum(0).mean(),
        "episode_length": valid.sum(0).mean(),
        "success_rate": traj.success.any(0).astype(jnp.float32).mean(),
        "bits_per_step": (traj.payload_bits * valid).sum() / steps,
        "wire_bits_per_step": (traj.wire_bits * valid).sum() / steps,
        "penalty": (traj.penalty * valid).sum() / steps,
    }
