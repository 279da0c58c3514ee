"""The one rollout: environment, actors and channel in a single ``lax.scan``.

It serves reinforcement learning (the learners act), imitation (an expert acts, or the learners
act and an expert labels: DAgger) and evaluation. The channel itself (routing, dither, the
sender side ``transmit`` and the receiver side ``receive`` of every mode) is
:mod:`sparsecomm.channel.links`, its link rules and their state the team's channel built once
from its config (``channel.build``, :mod:`sparsecomm.channel.team`: one step of a team's
links is its ``exchange``, the rollout's and a team expert's), its noise
:mod:`sparsecomm.channel.lossy`; this module is the scan over them. Each batch element is one
whole episode of ``env.max_steps`` steps; steps after the episode ended
are computed but masked (``valid``).

At step t every agent i reads its observation and the messages decoded at step t-1, and emits
``z^{i->j}`` for every j != i. The channel quantizes each link with the dither key
``dither_key(episode_channel_key, t, i, j)`` and the reconstructions become the received messages
of step t+1. Everything stays differentiable with respect to the actors' parameters: a
receiver's log-probabilities at t+1 depend on the senders' parameters through ``z_hat``, and on
all earlier steps through the GRU states (backpropagation through the episode).

Many agents (``AgentConfig.neighbours`` / ``radius``, :mod:`sparsecomm.scaling`): each step's
links follow the positions of that step (``scaling.routing_mask``, a traced routing mask given
to ``channel.live_links``); a link that does not exist sends z = 0 (the null symbol: 0 bits, 0
penalty, no gradient) and delivers 0, and the receivers get, beside their messages, which links
they heard (``Carry.heard``), for a ``mean`` or ``attention`` inbox. With ``neighbours`` k and
such an inbox only the K k live links are computed, listed by recipient (:func:`listed_links`):
the message head still emits every slot, but the dither, quantizer, bits, penalty and inbox, and
their backward pass, are those of the live links alone.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from sparsecomm import channel, scaling
from sparsecomm.agents import Team
from sparsecomm.channel import ChannelConfig
from sparsecomm.channel.team import LinkState, TeamChannel
from sparsecomm.envs.task import Task
from sparsecomm.sharding import split_episodes


@struct.dataclass
class Expert:
    """An action source that may label or drive episodes (imitation, DAgger).

    ``init(batch) -> carry`` and ``step(carry, key, env_state, obs) -> (carry, actions)`` where
    ``env_state`` is the task's batched state (a centralised expert may read every goal),
    ``obs`` the (B, K, obs_dim) observations, and actions (B, K) int32.
    """

    init: Callable[[int], Any] = struct.field(pytree_node=False)
    step: Callable = struct.field(pytree_node=False)


@struct.dataclass
class Aside:
    """What a step records only when asked (``keep_*``) or when its channel has it; ``None``
    otherwise. Leading axes (T, B)."""

    env_states: Any = None  # the task's batched state per step (``keep_states``)
    hidden: Any = None  # (T, B, K, H) GRU states the messages came from (``keep_hidden``)
    symbols: Any = None  # (T, B, K, K-1, C) int32 symbols of each link (``keep_symbols``)
    lost: Any = None  # (T, B) packets the receivers lost (a noisy channel)
    links: Any = None  # (T, B) links that existed (routing, ``sparsecomm.scaling``)


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
    success: jax.Array  # (T, B) the team succeeded at this step
    penalty: jax.Array  # (T, B) surrogate bit penalty, summed over links and elements
    payload_bits: jax.Array  # (T, B) real payload bits sent by the team
    wire_bits: jax.Array  # (T, B) bits on the wire, framing included
    speaking: jax.Array  # (T, B) links whose packet is not empty (silent links send nothing)
    link_bits: jax.Array  # (T, B, K, K) payload bits sent i -> j (zero diagonal)
    msg_log_probs: jax.Array  # (T, B, K) log-prob of sender i's symbols ("reinforced"; else 0)
    datagram_bits: jax.Array  # (T, B) bits of the frames the speaking links' datagrams carry
    aside: Aside = Aside()  # the optional records


class Carry(NamedTuple):
    """What one step of the scan hands the next, leading axis (B,) episodes."""

    env_state: Any  # the task's batched state
    obs: jax.Array  # (B, K, obs_dim) observations
    msgs: jax.Array  # (B, K, (K-1) C) messages received, by recipient (``channel.deliver``)
    gru: jax.Array  # (B, K, H) the actors' GRU states
    expert: Any  # the expert's carry (None without an expert)
    links: LinkState  # the team's links (``channel.team``: last symbols, held messages)
    wire: Any  # channel.lossy.LinkState of the noisy wire (None on a clean channel)
    heard: Any  # (B, K, K-1) bool which links each recipient heard (None: all, the full team)


def rollout(
    team: Team,
    env: Task,
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
    episodes: jax.Array | None = None,
    actions: jax.Array | None = None,
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
      episodes: (b,) int32 indices: play only these episodes of the ``num_envs`` that ``key``
        draws, with the very randomness they have in the whole batch (a minibatch of a
        replayed batch, ``RLConfig.algo = "ppo"``). Needs a clean channel and no expert.
      actions: (T, b, K) int32 actions to execute instead of the learners' (a replay: the
        episodes of a batch played again with new parameters, their messages recomputed from
        the same dither; ``log_probs`` are the learners' own).

    What a step may be is decided here, once, before the scan: how actions are chosen
    (:func:`_action_rule`: sampled, greedy or replayed, mixed with an expert's), which links
    exist (:func:`_link_rule`: all, masked or listed), what the wire does (a noisy channel's
    ``LossyLinks``) and what is kept (:class:`Aside`). The step itself reads act, talk, step,
    record.
    """
    if episodes is not None and (expert is not None or not channel_cfg.noise.clean):
        raise ValueError("rollout(episodes=...) needs a clean channel and no expert")
    listed = listed_links(team, channel_cfg) and not keep_symbols
    draws = _draws(team, env, channel_cfg, key, num_envs, episodes, actions, expert, listed)
    plan = _Plan(
        team,
        env,
        channel.build(channel_cfg, env.num_agents, reads_sent=team.reads_sent),
        actor_params,
        draws.chan_keys,
        draws.lossy,
        _action_rule(greedy, actions is not None, expert, beta),
        _link_rule(team, env, channel_cfg, draws.chan_keys, draws.num_envs, listed),
        {"env_states": keep_states, "hidden": keep_hidden, "symbols": keep_symbols},
    )
    init = _first_carry(team, env, plan.links, draws, expert, listed, plan.route.masked)
    step = functools.partial(_step, plan)
    if remat:
        step = jax.checkpoint(step)
    _, (traj, priced) = jax.lax.scan(step, init, draws.noise)
    if channel_cfg.prices_later:  # the whole rollout's links priced at once
        z, live = priced
        return traj.replace(penalty=channel.price(channel_cfg, z, live).sum((-2, -1)))
    return traj


class _Plan(NamedTuple):
    """What every step of one :func:`rollout` is, decided before the scan."""

    team: Team
    env: Task
    links: TeamChannel  # the channel's link rules (``channel.build``)
    actor_params: Any
    chan_keys: jax.Array  # (B,) each episode's channel key
    lossy: Any  # channel.lossy.LossyLinks of a noisy channel, else None
    choose: Callable  # how actions are chosen (:func:`_action_rule`)
    route: Any  # which links exist (:class:`_LinkRule`)
    keep: dict  # which optional records are kept (:class:`Aside`)


def _step(plan: _Plan, carry: Carry, noise):
    """One step of every episode: act, talk, step, record."""
    team, env, cfg, route = plan.team, plan.env, plan.links.cfg, plan.route
    t, state = noise["t"], carry.env_state
    # act: the actors read their observations and last step's messages
    gru, logits, z = team.act(plan.actor_params, carry.gru, carry.obs, carry.msgs, carry.heard)
    log_probs = jax.nn.log_softmax(logits)
    acts, labels, expert_carry = plan.choose(logits, log_probs, noise, carry.expert, state, carry)
    # talk: this step's links, the sender side, the wire, the receiver side, the inboxes
    z, u, live, senders = route.links(state, z, t, noise)
    wire = None if plan.lossy is None else _noisy_wire(plan.lossy, noise["loss"], u, carry.wire)
    ex = plan.links.exchange(
        carry.links, z, u, plan.chan_keys, t, live=live, senders=senders, wire=wire
    )
    wire_state, lost = (carry.wire, None) if plan.lossy is None else ex.wire
    # step: the world moves
    valid = ~state.done
    global_state = jax.vmap(env.global_state)(state)
    next_obs, next_state, rewards, dones, info = jax.vmap(env.step)(noise["env"], state, acts)
    # record: the core fields, and aside what is kept (``keep``) or the channel has
    kept = dict(env_states=state, hidden=jax.lax.stop_gradient(gru), symbols=ex.sent.symbols)
    aside = _aside(plan.keep, kept, lost, live)
    record = _record(
        ex.sent,
        route.pairs(ex.sent.payload_bits, senders),
        cfg.prices_later,
        aside,
        log_probs=log_probs,
        actions=acts.astype(jnp.int32),
        expert_actions=labels.astype(jnp.int32),
        rewards=rewards,
        states=global_state,
        valid=valid,
        dones=dones[:, 0] & valid,
        success=info["success"] & valid,
    )
    carry = Carry(
        env_state=next_state,
        obs=next_obs,
        msgs=ex.msgs,
        gru=gru,
        expert=expert_carry,
        links=ex.state,
        wire=wire_state,
        heard=route.heard(live),
    )
    return carry, (record, (ex.z, live) if cfg.prices_later else None)


class _Draws(NamedTuple):
    """A batch's randomness, drawn before the loop in a few large vectorised draws."""

    num_envs: int  # the episodes played (a minibatch's share with ``episodes``)
    reset_keys: jax.Array  # (B,) each episode's reset key
    chan_keys: jax.Array  # (B,) each episode's channel key (split over the mesh)
    noise: dict  # the scan's inputs by step: "t", "env", "dither", "gumbel" or "replay", ...
    lossy: Any  # channel.lossy.LossyLinks of a noisy channel, else None


def _draws(team, env, channel_cfg, key, num_envs, episodes, actions, expert, listed) -> _Draws:
    """Every step's randomness (:func:`world_draws`, :func:`agent_draws`, the dither, the
    expert's and the wire's), a minibatch's share of it with ``episodes``, split over the
    mesh's episodes axis; ``listed`` links draw their dither at each step instead."""
    k, num_steps = env.num_agents, env.max_steps
    reset_keys, env_keys = world_draws(key, num_envs, num_steps)
    chan_keys, gumbel = agent_draws(key, num_envs, num_steps, k, team.num_actions)
    if episodes is not None:  # a minibatch: its episodes' share of the batch's randomness
        reset_keys, chan_keys = reset_keys[episodes], chan_keys[episodes]
        env_keys, gumbel = env_keys[:, episodes], gumbel[:, episodes]
        num_envs = episodes.shape[0]
    noise = {
        "t": jnp.arange(num_steps),
        "env": env_keys,
        "dither": None if listed else channel.link_dither(channel_cfg, chan_keys, num_steps, k),
    }
    noise.update({"replay": actions} if actions is not None else {"gumbel": gumbel})
    if expert is not None:
        keys = _batch_keys(key)
        noise["expert"] = jax.random.split(keys["expert"], num_steps)
        noise["mix"] = jax.random.uniform(keys["mix"], (num_steps, num_envs, 1))
    lossy = None
    if channel_cfg.speaks and not channel_cfg.noise.clean:
        lossy = channel.lossy.LossyLinks(channel_cfg, key, num_envs, k, num_steps)
        noise["loss"] = lossy.step_keys
    # Episodes are independent: split them over the mesh's episodes axis, if there is one.
    batched = ("env", "gumbel", "replay", "dither", "mix")
    noise.update(split_episodes({n: v for n, v in noise.items() if n in batched}, axis=1))
    return _Draws(num_envs, reset_keys, split_episodes(chan_keys, axis=0), noise, lossy)


def _first_carry(team, env, links: TeamChannel, draws: _Draws, expert, listed: bool, masked):
    """The scan's first :class:`Carry`: the episodes reset, empty inboxes and link states."""
    k, num_envs = env.num_agents, draws.num_envs
    obs, state = jax.vmap(env.reset)(draws.reset_keys)
    heard_links = team.cfg.neighbours if listed else k - 1  # links each recipient is listed
    init = Carry(
        env_state=state,
        obs=obs,
        msgs=jnp.zeros((num_envs, k, links.inbox_width(heard_links)), jnp.float32),
        gru=team.initial_carry(num_envs),
        expert=expert.init(num_envs) if expert is not None else None,
        links=links.init((num_envs,), heard_links),
        wire=None if draws.lossy is None else draws.lossy.init,
        heard=jnp.zeros((num_envs, k, heard_links), bool) if masked else None,
    )
    return split_episodes(init._replace(expert=None), axis=0)._replace(expert=init.expert)


def _action_rule(greedy: bool, replay: bool, expert: Expert | None, beta) -> Callable:
    """How a step's actions are chosen, decided once: ``choose(logits, log_probs, noise,
    expert_carry, state, carry) -> (actions, expert labels (-1: none), expert_carry)``. The
    learners' own actions are the batch's (a replay), their most probable (``greedy``) or a
    Gumbel-max sample of ``logits``; with an expert, its action is executed instead with
    probability ``beta``."""
    if replay:  # the batch's own actions, played again

        def own(logits, log_probs, noise):
            return noise["replay"]
    elif greedy:

        def own(logits, log_probs, noise):
            return jnp.argmax(logits, -1)
    else:  # Gumbel-max: a sample of the categorical distribution of ``logits``

        def own(logits, log_probs, noise):
            return jnp.argmax(jax.lax.stop_gradient(log_probs) + noise["gumbel"], -1)

    if expert is None:

        def choose(logits, log_probs, noise, expert_carry, state, carry):
            acts = own(logits, log_probs, noise)
            return acts, jnp.full(acts.shape, -1), expert_carry

        return choose

    def mixed(logits, log_probs, noise, expert_carry, state, carry):
        acts = own(logits, log_probs, noise)
        expert_carry, labels = expert.step(expert_carry, noise["expert"], state, carry.obs)
        return jnp.where(noise["mix"] < beta, labels, acts), labels, expert_carry

    return mixed


class _LinkRule(NamedTuple):
    """Which links exist at a step and how they are laid out, decided once (:func:`_link_rule`)."""

    links: Callable  # (state, z, t, noise) -> (z, dither, live (None: all), senders or None)
    heard: Callable  # live -> what the recipients are told they heard (the carry's ``heard``)
    pairs: Callable  # (payload bits by link, senders) -> (B, K, K) bits sent i -> j
    listed: bool  # only the live links are computed, listed by recipient
    masked: bool  # the recipients are told which links they heard


def _link_rule(team, env, channel_cfg, chan_keys, num_envs: int, listed: bool) -> _LinkRule:
    """The links of a step. The paper's team: every link, ``live`` None. Links that follow
    positions, or an inbox that reads which links arrived (``scaling``): a mask of the links
    that exist, and the receivers are told what they heard. With ``neighbours`` k and such an
    inbox, only the K k live links are computed, listed by recipient
    (``scaling.nearest_senders``, ``channel.listed``): the same messages, bits and penalty as
    the masked K (K - 1) links, at a cost O(K k) (``listed``: :func:`listed_links`, unless
    the symbols of every link are kept)."""
    k, cfg = env.num_agents, team.cfg
    masked = team.routed or cfg.aggregate != "concat"
    positions = jax.vmap(env.positions) if team.routed else None  # (B, K, 2)
    if listed:

        def gathered(state, z, t, noise):
            senders, live = scaling.nearest_senders(
                positions(state), cfg.neighbours, cfg.radius, cfg.hears
            )
            live = live if channel_cfg.speaks else jnp.zeros_like(live)
            u = channel.listed_dither(channel_cfg, chan_keys, t, senders)
            return channel.listed(z, senders, 1), u, live, senders

        return _LinkRule(
            gathered, lambda live: live, channel.listed_pairs, listed=True, masked=masked
        )

    def mask(state):
        if team.routed:
            return scaling.routing_mask(positions(state), cfg.neighbours, cfg.radius, cfg.hears)
        return jnp.broadcast_to(~jnp.eye(k, dtype=bool), (num_envs, k, k))  # every link

    def by_slot(state, z, t, noise):
        routing = mask(state) if masked else None
        return z, noise["dither"], channel.live_links(channel_cfg, routing, k, (num_envs,)), None

    def heard(live):
        return None if live is None else channel.inbox(live)

    return _LinkRule(
        by_slot, heard, lambda bits, senders: channel.pairs(bits), listed=False, masked=masked
    )


def _noisy_wire(lossy, keys, u, state) -> Callable:
    """The wire of a noisy channel at one step: ``wire(sent) -> (arrived, ok, (link state,
    packets lost))`` (packets lost, late or corrupted, ``channel.lossy.LossyLinks.step``)."""

    def wire(sent):
        arrived, ok, links, lost = lossy.step(keys, sent, u, state)
        return arrived, ok, (links, lost)

    return wire


def _aside(keep: dict, kept: dict, lost, live) -> Aside:
    """A step's optional records: those of ``kept`` that ``keep`` asks for, the packets lost
    (a noisy channel) and the number of links that existed (``live``: None, all of them)."""
    links = None if live is None else live.sum((-2, -1)).astype(jnp.float32)
    return Aside(**{n: v if keep[n] else None for n, v in kept.items()}, lost=lost, links=links)


def _record(sent, link_bits, later: bool, aside: Aside, **core) -> Trajectory:
    """One step's record: its ``core`` fields, and what the links sent (``sent``), summed over
    links: the penalty (0 when the channel ``prices_later``), payload and wire bits, the
    speaking links and the bits of the frames their datagrams carry (each its sender's whole
    frame; a channel without frames: the links' wire bits)."""
    frames = sent.wire_bits if sent.frame_bits is None else sent.frame_bits
    return Trajectory(
        **core,
        penalty=jnp.zeros(()) if later else sent.penalty.sum((-2, -1)),
        payload_bits=sent.payload_bits.sum((-2, -1)),
        wire_bits=sent.wire_bits.sum((-2, -1)),
        speaking=(sent.wire_bits > 0).sum((-2, -1)).astype(jnp.float32),
        link_bits=link_bits,
        msg_log_probs=sent.log_prob,
        datagram_bits=frames.sum((-2, -1)),
        aside=aside,
    )


def listed_links(team: Team, channel_cfg: ChannelConfig) -> bool:
    """The rollout computes only the live links, listed by recipient
    (``ExperimentalConfig.live_links_only``): a team that hears its ``neighbours`` nearest (or its
    ``ring``) through a ``mean`` or ``attention`` inbox, on a channel that can list
    them (``ChannelConfig.lists_links``). Otherwise every one of the K (K - 1) links is computed
    and the ones that do not exist are masked (the same numbers, at a cost O(K^2))."""
    return (
        team.experimental.live_links_only
        and team.cfg.neighbours is not None
        and team.cfg.aggregate != "concat"
        and channel_cfg.lists_links
    )


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


def episode_metrics(traj: Trajectory) -> dict[str, jax.Array]:
    """Batch means of the SPEC section 6 metrics (rewards in the paper's units), and
    ``speaking_fraction``, the share of the link-steps (of links that existed) whose packet was
    not empty; ``datagrams_per_step``, the speaking links (one datagram each on a network of
    unicast links) and ``datagram_bits_per_step``, the frames those datagrams carry (each its
    sender's whole frame; with two agents the wire bits); with a noisy channel also
    ``packets_lost_per_step``, with routing ``links_per_step`` (links that existed)."""
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
    k = traj.link_bits.shape[-1]
    links = k * (k - 1) * valid if traj.aside.links is None else traj.aside.links * valid
    metrics["speaking_fraction"] = (traj.speaking * valid).sum() / jnp.maximum(links.sum(), 1.0)
    metrics["datagrams_per_step"] = (traj.speaking * valid).sum() / steps
    metrics["datagram_bits_per_step"] = (traj.datagram_bits * valid).sum() / steps
    if traj.aside.lost is not None:
        metrics["packets_lost_per_step"] = (traj.aside.lost * valid).sum() / steps
    if traj.aside.links is not None:
        metrics["links_per_step"] = (traj.aside.links * valid).sum() / steps
    return metrics
