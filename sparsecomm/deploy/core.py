"""What one process computes: a team's config and weights, the episode's shared draws, one
agent's step, one receiver's reconstruction and the world's step (no sockets here).

Every process regenerates the randomness of ``sparsecomm.rollout.rollout`` from the batch key
alone (:func:`episode_draws`: the rollout's own draws), so a deployed team plays the very
episodes ``sparsecomm eval`` plays: episode ``b`` of a batch of ``N`` starts from
``reset[b]``, agent ``i`` acts with the Gumbel noise ``gumbel[t, b, i]``, the world steps with
``env[t, b]``, and link ``i -> j`` at step ``t`` is quantized by the sender and reconstructed
by the receiver with the dither of ``channel.dither_key(chan[b], t, i, j)``: the dither never
crosses the wire.

An agent's step is :meth:`sparsecomm.agents.Team.act` on a batch of one episode in which only
the agent's own row is real (the other rows are zeros and thrown away), followed by the
rollout's action rule and the channel's sender side (``channel.transmit``) on the agent's own
links; its receiver side is the channel's (``channel.receive``, with the news inputs of
``on_silence = "hold"`` appended as the rollout appends them), and its frames are
``channel.encode_sender`` / ``channel.decode_sender``: this module draws no dither and rebuilds
no message of its own, so every number comes from the library's own functions.

Which links speak (:attr:`StepOut.spoke`, :func:`link_speaks`) is the rollout's rule: a link
speaks when its share of its sender's frame is not empty (``Sent.wire_bits > 0``); a silent link
sends no datagram.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp

from sparsecomm import channel, rollout, runfolder
from sparsecomm.channel import ChannelConfig
from sparsecomm.envs.task import Task

MAX_AGENTS = 255
"""Agents are numbered by one byte in the datagram header."""


def read_team(folder: str | Path, weights: bool = True) -> runfolder.ExportedTeam:
    """The exported team in ``folder`` (:func:`sparsecomm.runfolder.read_team`), refused unless
    the runtime carries it (:func:`check_deployable`). ``weights=False``: the config only (the
    world)."""
    loaded = runfolder.read_team(folder, weights)
    check_deployable(loaded.config)
    return loaded


def check_deployable(config) -> None:
    """Refuse a team whose channel or size the runtime does not carry: the channel must be
    ``ChannelConfig.deployable`` (the channel's own rule), at most :data:`MAX_AGENTS` agents, the
    ``concat`` inbox and no routing."""
    cfg = config.channel
    if not cfg.deployable:
        deployable = [m for m in channel.CHANNEL_MODES if channel.ChannelConfig(m).deployable]
        raise ValueError(
            "Deploy: the team's ChannelConfig must be deployable (ChannelConfig.deployable: "
            f"ChannelConfig.mode one of {deployable}, a mode whose symbols need no draw but the "
            "shared dither, and ChannelConfig.code one that frames carry, not 'fitted'), got "
            f"mode {cfg.mode!r}, code {cfg.code!r}"
        )
    if config.env.num_agents > MAX_AGENTS:
        raise ValueError(f"Deploy: at most {MAX_AGENTS} agents, got {config.env.num_agents}")
    # Teams that route links by position or aggregate an inbox (``sparsecomm.scaling``) read
    # which links arrived; the runtime does not carry that yet: refuse them rather than differ.
    aggregate = getattr(config.agent, "aggregate", "concat")
    routed = any(getattr(config.agent, name, None) for name in ("neighbours", "radius"))
    if aggregate != "concat" or routed:
        raise ValueError(
            "Deploy: the team's AgentConfig must use aggregate 'concat' and no routing "
            f"(neighbours, radius), got aggregate {aggregate!r}"
        )


class Draws(NamedTuple):
    """The randomness of a batch of ``N`` episodes, as ``rollout`` draws it."""

    reset: jax.Array  # (N,) keys: env.reset of each episode
    chan: jax.Array  # (N,) keys: each episode's channel key (dither_key's first argument)
    gumbel: jax.Array  # (T, N, K, A) action noise
    env: jax.Array  # (T, N) keys: env.step of each step


def episode_draws(
    key: jax.Array, num_episodes: int, num_steps: int, num_agents: int, num_actions: int
) -> Draws:
    """The draws of ``rollout(team, env, cfg, params, key, num_episodes)``: the rollout's own
    functions (``rollout.world_draws``, ``rollout.agent_draws``), so the two cannot drift. The
    world needs ``reset`` and ``env`` only (:func:`world_draws`), an agent ``chan`` and
    ``gumbel`` (:func:`agent_draws`): each is one compiled program."""
    world = world_draws(key, num_episodes, num_steps)
    agents = agent_draws(key, num_episodes, num_steps, num_agents, num_actions)
    return Draws(world[0], agents[0], agents[1], world[1])


world_draws = jax.jit(rollout.world_draws, static_argnums=(1, 2))
"""``(reset (N,), env (T, N))`` keys, as :func:`episode_draws` (``rollout.world_draws``)."""

agent_draws = jax.jit(rollout.agent_draws, static_argnums=(1, 2, 3, 4))
"""``(chan (N,), gumbel (T, N, K, A))``, as :func:`episode_draws` (``rollout.agent_draws``)."""


def use_compile_cache(folder: str) -> None:
    """Keep this process's compiled programs in ``folder`` (JAX's persistent cache) and reuse
    the ones there: a restarted agent, and every agent after the first, start without
    compiling. Empty: no cache."""
    if folder:
        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def batch_key(seed: int) -> jax.Array:
    """The key of a batch: ``sparsecomm eval`` evaluates run ``r`` of a run folder with
    ``seed = config.seed + EVAL_SEED_OFFSET + r`` (``experiment.evaluate_runs``)."""
    return jax.random.key(seed)


class StepOut(NamedTuple):
    """One agent's step."""

    carry: jax.Array  # (H,) its new GRU state
    action: jax.Array  # () int32
    symbols: jax.Array  # (K-1, C) int32 symbols of its links, by slot (zeros unless discrete)
    signal: jax.Array  # (K-1, C') float32 z (the ``continuous`` mode sends it; C' with a gate)
    payload: jax.Array  # (K-1,) payload bits of each link (the library's count)
    wire: jax.Array  # () bits of its frame: Sent.wire_bits summed over its links
    spoke: jax.Array  # (K-1,) bool: the link speaks this step (module docstring)
    delivered: jax.Array  # (K-1, C) float32 what each link last delivered (``reads_sent``)


def link_speaks(sent: channel.Sent) -> jax.Array:
    """(..., K-1) bool: the links of ``sent`` (``channel.transmit``) that speak, so that a copy
    of their sender's frame must reach their recipients: those whose frame share is not empty
    (``Sent.wire_bits > 0``), the rollout's own rule (it counts them ``speaking`` and, under
    ``hold``, holds the others). A closed gate, and an open one whose symbols are all null, is
    silent (``Sent.speak`` is 0 there too)."""
    return sent.wire_bits > 0


@functools.lru_cache(maxsize=16)
def agent_step(team, cfg: ChannelConfig, greedy: bool):
    """The jitted step of an agent: ``(params, i, carry (H,), obs, msgs ((K-1) C,), gumbel
    (A,), t, chan_key, prev (K-1, C), delivered (K-1, C)) -> StepOut`` for agent ``i`` (a
    traced argument: every agent runs the same compiled program); ``msgs``: its inbox, ``(K-1)
    C`` messages then, under ``on_silence = "hold"``, ``K-1`` news inputs (:func:`receive`);
    ``chan_key``: the episode's channel key, from which the dither of its links at ``t`` is
    drawn; ``prev``: its links' symbols at ``t - 1``; ``delivered``: what each of its links
    last delivered (zeros before; read by a team with ``AgentConfig.reads_sent``, appended to
    ``msgs`` as the rollout appends it). The links are the channel's sender side,
    ``channel.transmit``, on the agent's own row."""
    k = team.num_agents
    links = channel.build(cfg, k, reads_sent=team.reads_sent, lossy=True)

    def step(params, i, carry, obs, msgs, gumbel, t, chan_key, prev, delivered):
        def one_row(x):  # a batch of one episode whose only real row is agent i's
            return jnp.zeros((1, k, *x.shape), x.dtype).at[0, i].set(x)

        state = links.init_agent()._replace(prev=prev, own=delivered)
        msgs = links.agent_inbox(msgs, state)
        carry, logits, z = team.act(params, one_row(carry), one_row(obs), one_row(msgs))
        log_probs = jax.nn.log_softmax(logits[0, i])
        if greedy:
            action = jnp.argmax(logits[0, i], -1)
        else:  # as rollout: a Gumbel-max sample of the policy
            action = jnp.argmax(log_probs + gumbel, -1)
        recipients = jnp.asarray(channel.others(k))[i]
        u = None
        if cfg.quantizes:
            u = channel.dither_links(chan_key, t, i, recipients, cfg.signal_elements)[None]
        sent, signal, state = links.agent_send(z[0, i], u, state)  # as the rollout
        spoke = link_speaks(sent)[0]
        return StepOut(
            carry[0, i],
            action.astype(jnp.int32),
            sent.symbols[0],
            signal,
            sent.payload_bits[0],
            sent.wire_bits[0].sum(),
            spoke,
            state.own,
        )

    return jax.jit(step)


@functools.lru_cache(maxsize=16)
def receive(cfg: ChannelConfig, num_agents: int, on_drop: str):
    """Jitted receiver side of an agent, the channel's own (``channel.receive``):
    ``(chan_key, t, recipient, message (K-1, C), ok (K-1,), silent (K-1,), last (K-1, C)) ->
    (msgs, last (K-1, C))``, ``msgs`` the actor's inbox as the rollout builds it: the ``(K-1) C``
    messages, then under ``on_silence = "hold"`` the ``K-1`` news inputs (1: news, 0: held).

    Link ``s`` (its senders in increasing order, ``channel.others``) sent ``message[s]`` at
    step ``t``: symbols (rebuilt with the dither of ``dither_key(chan_key, t, s, recipient)``,
    regenerated here) or the float values of a ``continuous`` channel. ``silent``: the links
    that sent nothing (no datagram; their ``message`` rows are the null symbols): the null
    message, or under ``on_silence = "hold"`` the link's last message with news 0. A link not
    ``ok`` (a frame it promised missing at the deadline: a loss) is the null message or, with
    ``on_drop = "last"`` or under ``hold``, the link's last good reconstruction ``last``
    (zeros before the first); a silent link is ``ok``. As the rollout, a gated channel hands
    ``channel.receive`` the gate (``speak``: 0 where silent) and a holding one ``silent``."""
    table = jnp.asarray(channel.others(num_agents))
    links = channel.build(cfg, num_agents, lossy=True, on_drop=on_drop)

    def rebuild(chan_key, t, recipient, message, ok, silent, last):
        u = None
        if cfg.quantizes:
            senders = table[recipient]
            u = channel.dither_links(chan_key, t, senders, recipient, cfg.num_elements)
        state = links.init_agent()._replace(last=last)
        msgs, state = links.agent_receive(message, u, ok, silent, state)
        return msgs, state.last

    return jax.jit(rebuild)


def inbox_size(cfg: ChannelConfig, num_agents: int) -> int:
    """Length of an actor's inbox (:func:`receive`'s ``msgs``): ``(K-1) C`` messages, plus
    ``K-1`` news inputs under ``on_silence = "hold"`` (``TeamChannel.received_width``)."""
    return channel.build(cfg, num_agents).received_width()


def frame_slot(sender: int, recipient: int) -> int:
    """The row of link ``sender -> recipient`` in the sender's frame: the recipient's slot
    among ``channel.others(K)[sender]`` (the other agents in increasing order)."""
    if sender == recipient:
        raise ValueError(f"recipient must differ from sender {sender}, got {recipient}")
    return recipient - int(recipient > sender)


@functools.lru_cache(maxsize=4)
def world_fns(env: Task):
    """Jitted ``reset(key)`` and ``step(key, state, actions)`` of the task (unbatched)."""
    return jax.jit(env.reset), jax.jit(env.step)


def with_channel(config, **changes):
    """``config`` with its channel's fields replaced."""
    return dataclasses.replace(config, channel=dataclasses.replace(config.channel, **changes))
