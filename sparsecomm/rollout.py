"""The one rollout: environment, actors and channel in a single ``lax.scan``.

It serves reinforcement learning (the learners act), imitation (an expert acts, or the learners
act and an expert labels: DAgger) and evaluation. The channel itself (routing, dither, every
mode's transmit) is :mod:`sparsecomm.channel.links`; this module is the scan over them. Each
batch element is one whole episode of ``env.max_steps`` steps; steps after the episode ended
are computed but masked (``valid``).

At step t every agent i reads its observation and the messages decoded at step t-1, and emits
``z^{i->j}`` for every j != i. The channel quantizes each link with the dither key
``dither_key(episode_channel_key, t, i, j)`` and the reconstructions become the received messages
of step t+1. Everything stays differentiable with respect to the actors' parameters: a
receiver's log-probabilities at t+1 depend on the senders' parameters through ``z_hat``, and on
all earlier steps through the GRU states (backpropagation through the episode).

Many agents (``AgentConfig.neighbours`` / ``radius``, :mod:`sparsecomm.scaling`): each step's
links follow the positions of that step (``scaling.routing_mask``); a link that does not exist
sends z = 0 (the null symbol: 0 bits, 0 penalty, no gradient) and delivers 0, and the receivers
get, beside their messages, which links arrived (``heard``), for a ``mean`` or ``attention``
inbox.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from sparsecomm import channel, scaling
from sparsecomm.agents import Team
from sparsecomm.channel import ChannelConfig
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
    symbols: Any = None  # (T, B, K, K-1, C) int32 symbols of each link (only ``keep_symbols``)
    lost: Any = None  # (T, B) packets the receivers lost (only with ``ChannelConfig.noise``)
    links: Any = None  # (T, B) links that existed (only with routing, ``sparsecomm.scaling``)


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
    keep_symbols: bool = False,
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
      keep_symbols: also return the symbols of every link (for measuring and fitting codes,
        ``sparsecomm.codestats``).
    """
    k = env.num_agents
    num_steps = env.config.max_steps
    reset_keys, env_keys = world_draws(key, num_envs, num_steps)
    chan_keys, gumbel = agent_draws(key, num_envs, num_steps, k, team.num_actions)
    obs, state = jax.vmap(env.reset)(reset_keys)
    c = channel_cfg.num_elements
    msgs = jnp.zeros((num_envs, k, (k - 1) * c), jnp.float32)
    prev = jnp.zeros((num_envs, k, k - 1, c), jnp.int32)  # each link's symbols at t - 1
    carry = team.initial_carry(num_envs)
    # which messages arrived, by recipient (None: all of them, the paper's full team)
    masked = team.routed or team.cfg.aggregate != "concat"
    heard = jnp.zeros((num_envs, k, k - 1), bool) if masked else None
    expert_carry = expert.init(num_envs) if expert is not None else None
    # All the step's randomness is drawn before the loop, in a few large vectorised draws.
    noise = {
        "t": jnp.arange(num_steps),
        "env": env_keys,
        "gumbel": gumbel,
        "dither": channel.link_dither(channel_cfg, chan_keys, num_steps, k),
    }
    if expert is not None:
        keys = _batch_keys(key)
        noise["expert"] = jax.random.split(keys["expert"], num_steps)
        noise["mix"] = jax.random.uniform(keys["mix"], (num_steps, num_envs, 1))
    wire = _Wire(channel_cfg, key, num_envs, k, num_steps) if _noisy(channel_cfg) else None
    if wire is not None:
        noise["loss"] = wire.step_keys
    # Episodes are independent: split them over the mesh's episodes axis, if there is one.
    batched = ("env", "gumbel", "dither", "mix")
    noise.update(split_episodes({n: v for n, v in noise.items() if n in batched}, axis=1))
    state, obs, msgs, prev, carry, chan_keys, heard = split_episodes(
        (state, obs, msgs, prev, carry, chan_keys, heard), axis=0
    )
    wire_state = None if wire is None else split_episodes(wire.init, axis=0)

    def step(loop, noise):
        state, obs, msgs, carry, expert_carry, prev, wire_state, heard = loop
        t = noise["t"]
        carry, logits, z = team.act(actor_params, carry, obs, msgs, heard)
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
        links = None
        if masked:  # the links of this step; the others send z = 0: null, 0 bits, no gradient
            mask = scaling.routing_mask(state.pos, team.cfg.neighbours, team.cfg.radius)
            if channel_cfg.mode == "off":  # nothing is sent, nothing arrives
                mask = jnp.zeros_like(mask)
            live = scaling.by_sender(mask)
            z = jnp.where(live[..., None], z, 0.0)
            links = live.sum((-2, -1)).astype(jnp.float32)
        sent = channel.transmit(channel_cfg, z, noise["dither"], chan_keys, t, prev)
        received, lost = sent.z_hat, None
        if wire is not None:  # packets lost, late, or replaced by the null or last message
            received, wire_state, lost = wire.step(noise["loss"], sent, noise["dither"], wire_state)
        if masked:  # a link that does not exist costs nothing and delivers 0
            sent = _only_live(sent, live)
            received = jnp.where(live[..., None], received, 0.0)
            heard = scaling.by_recipient(mask)
        next_msgs = channel.deliver(received)
        global_state = jax.vmap(env.global_state)(state)
        valid = ~state.done
        next_obs, next_state, rewards, dones, info = jax.vmap(env.step)(
            noise["env"], state, actions
        )
        full_link = jnp.zeros((num_envs, k, k), jnp.float32)
        full_link = full_link.at[:, jnp.arange(k)[:, None], channel.others(k)].set(sent.link)
        record = Trajectory(
            log_probs=log_probs,
            actions=actions.astype(jnp.int32),
            expert_actions=expert_actions.astype(jnp.int32),
            rewards=rewards,
            states=global_state,
            valid=valid,
            dones=dones[:, 0] & valid,
            success=info["success"] & valid,
            penalty=sent.penalty,
            payload_bits=sent.payload,
            wire_bits=sent.wire,
            link_bits=full_link,
            msg_log_probs=sent.log_prob,
            env_states=state if keep_states else None,
            hidden=jax.lax.stop_gradient(carry) if keep_hidden else None,
            symbols=sent.symbols if keep_symbols else None,
            lost=lost,
            links=links,
        )
        loop = (next_state, next_obs, next_msgs, carry, expert_carry, sent.symbols, wire_state)
        loop = (*loop, heard)
        return loop, record

    if remat:
        step = jax.checkpoint(step)
    init = (state, obs, msgs, carry, expert_carry, prev, wire_state, heard)
    _, traj = jax.lax.scan(step, init, noise)
    return traj


def _batch_keys(key: jax.Array) -> dict[str, jax.Array]:
    """The six keys of a batch of episodes, by name, in the order the rollout splits them."""
    names = ("reset", "chan", "act", "env", "expert", "mix")
    return dict(zip(names, jax.random.split(key, len(names)), strict=True))


def world_draws(key: jax.Array, num_envs: int, num_steps: int) -> tuple[jax.Array, jax.Array]:
    """The world's randomness in :func:`rollout` of the batch ``key``: each episode's reset key
    (N,) and every step's environment keys (T, N). A deployed world draws the same
    (``sparsecomm.deploy``), so it plays the very episodes of ``sparsecomm eval``."""
    keys = _batch_keys(key)
    return (
        jax.random.split(keys["reset"], num_envs),
        jax.random.split(keys["env"], (num_steps, num_envs)),
    )


def agent_draws(
    key: jax.Array, num_envs: int, num_steps: int, num_agents: int, num_actions: int
) -> tuple[jax.Array, jax.Array]:
    """The agents' randomness in :func:`rollout` of the batch ``key``: each episode's channel
    key (N,), from which every link's dither is drawn (``channel.dither_key``), and the Gumbel
    noise of every action (T, N, K, A). Every deployed agent draws the same."""
    keys = _batch_keys(key)
    gumbel = jax.random.gumbel(keys["act"], (num_steps, num_envs, num_agents, num_actions))
    return jax.random.split(keys["chan"], num_envs), gumbel


def _only_live(sent: channel.Sent, live: jax.Array) -> channel.Sent:
    """``sent`` with the bits of the links that do not exist (``live`` False) set to 0: the
    null symbol is free in the paper's code, but not in ``fixed`` or ``continuous`` ones."""
    link = jnp.where(live, sent.link, 0.0)
    link_wire = jnp.where(live, sent.link_wire, 0.0)
    return sent._replace(
        link=link,
        payload=link.sum((-2, -1)),
        link_wire=link_wire,
        wire=link_wire.sum((-2, -1)),
        z_hat=jnp.where(live[..., None], sent.z_hat, 0.0),
    )


def _noisy(cfg: ChannelConfig) -> bool:
    return not cfg.noise.clean and cfg.mode != "off"


class _Wire:
    """The noise between senders and receivers inside the scan (``ChannelConfig.noise``): which
    packets are lost (``channel.noise.lost_packets``), what a receiver uses instead (the null
    message, i.e. the reconstruction of all-null symbols, or its last good message), and the
    delay line; under ``code = "permuted"`` flips corrupt symbols instead of losing packets
    (``channel.permuted.corrupt``). Its keys come from ``fold_in(key, 7)``, outside the
    rollout's six splits, so a clean channel keeps every other draw, and results, bit for
    bit."""

    def __init__(self, cfg: ChannelConfig, key, num_envs: int, k: int, num_steps: int):
        self.cfg, self.noise = cfg, cfg.noise
        k_bad, k_steps = jax.random.split(jax.random.fold_in(key, 7))
        self.step_keys = jax.random.split(k_steps, num_steps)
        links = (num_envs, k, k - 1)
        c, d = cfg.num_elements, self.noise.delay
        self.init = {
            "last": jnp.zeros((*links, c), jnp.float32),
            "bad": channel.noise.initial_bad(k_bad, self.noise, links),
            "queue": jnp.zeros((num_envs, d, k, k - 1, c), jnp.float32),
            "queue_ok": jnp.zeros((num_envs, d, k, k - 1), bool),
        }

    def step(self, key, sent, u, heard):
        permuted = self.cfg.code == "permuted"
        if permuted:  # flips corrupt symbols instead of losing packets
            key, k_symbols = jax.random.split(key)
        lost, bad = channel.noise.lost_packets(
            key, self.noise, sent.link_wire, heard["bad"], self.cfg.ecc, flips_lose=not permuted
        )
        now = self._corrupt(k_symbols, sent, u, heard["bad"]) if permuted else sent.z_hat
        got, ok = now, ~lost
        heard = {**heard, "bad": bad}
        if self.noise.delay:  # what arrives now was sent ``delay`` steps ago
            queue, queue_ok = heard["queue"], heard["queue_ok"]
            got, ok = queue[:, 0], queue_ok[:, 0]
            heard["queue"] = jnp.concatenate([queue[:, 1:], now[:, None]], 1)
            heard["queue_ok"] = jnp.concatenate([queue_ok[:, 1:], ~lost[:, None]], 1)
        if self.noise.on_drop == "last":
            instead = heard["last"]
        elif self.cfg.mode == "discrete":  # all-null symbols, reconstructed with this step's dither
            instead = jax.lax.stop_gradient(-u / self.cfg.levels)
        else:
            instead = jnp.zeros_like(got)
        got = jnp.where(ok[..., None], got, instead)
        heard["last"] = jnp.where(ok[..., None], got, heard["last"])
        return got, heard, lost.sum((-2, -1)).astype(jnp.float32)

    def _corrupt(self, key, sent, u, bad):
        """The reconstructions of the symbols that cross the permuted channel
        (``channel.permuted``), with the gradient of their expectation, ``alpha`` times the
        sent message's."""
        cfg, noise = self.cfg, self.noise
        if noise.burst:  # each link's state sets the flip rate of all its elements
            p01 = p10 = jnp.where(bad, noise.burst_flip_bad, noise.burst_flip_good)[..., None]
        else:
            p01, p10 = noise.flip_rates
        r = channel.permuted.corrupt(key, sent.symbols, cfg.levels, p01, p10)
        z_hat = r / cfg.levels if u is None else (r - u) / cfg.levels
        slope = channel.permuted.gradient_scale(cfg.levels, noise) * sent.z_hat
        return slope + jax.lax.stop_gradient(z_hat - slope)


def episode_metrics(traj: Trajectory) -> dict[str, jax.Array]:
    """Batch means of the SPEC section 6 metrics (rewards in the paper's units); with a noisy
    channel also ``packets_lost_per_step``, with routing ``links_per_step`` (links that
    existed)."""
    valid = traj.valid.astype(jnp.float32)
    steps = valid.sum()
    metrics = {
        "group_reward": (traj.rewards.sum(-1) * valid).sum(0).mean(),
        "episode_length": valid.sum(0).mean(),
        "success_rate": traj.success.any(0).astype(jnp.float32).mean(),
        "bits_per_step": (traj.payload_bits * valid).sum() / steps,
        "wire_bits_per_step": (traj.wire_bits * valid).sum() / steps,
        "penalty": (traj.penalty * valid).sum() / steps,
    }
    if traj.lost is not None:
        metrics["packets_lost_per_step"] = (traj.lost * valid).sum() / steps
    if traj.links is not None:
        metrics["links_per_step"] = (traj.links * valid).sum() / steps
    return metrics
