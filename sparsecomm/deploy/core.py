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
rollout's action rule and ``channel.transmit`` of the agent's own links, so every number comes
from the library's own functions.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from sparsecomm import channel, rollout
from sparsecomm.channel import ChannelConfig
from sparsecomm.configs import ILConfig, RLConfig, from_dict
from sparsecomm.envs.navigation import NavigationEnv
from sparsecomm.learner import make_team

KINDS = {"train": RLConfig, "imitate": ILConfig}
MODES = ("discrete", "continuous", "off")
"""Channel modes a deployed team can use (``reinforced`` samples its symbols inside the
channel and is not deployed)."""
MAX_AGENTS = 255
"""Agents are numbered by one byte in the datagram header."""


class DeployedTeam(NamedTuple):
    """An exported team (``sparsecomm export``: ``team.json`` and ``actor.msgpack``) loaded
    without building a learner: what an agent or world process needs, in a second."""

    config: RLConfig | ILConfig
    env: NavigationEnv
    team: object  # sparsecomm.agents.Team
    actor: dict  # the actor's parameters (numpy), no run axis


def read_team(folder: str | Path, weights: bool = True) -> DeployedTeam:
    """Load the exported team in ``folder``. ``weights=False``: the config only (the world)."""
    folder = Path(folder)
    meta_path = folder / "team.json"
    if not meta_path.exists():
        raise ValueError(f"team must be an exported team folder (team.json), got {folder}")
    meta = json.loads(meta_path.read_text())
    if meta.get("kind") not in KINDS:
        raise ValueError(f"{meta_path} holds a {meta.get('kind')!r} team, not one of {list(KINDS)}")
    config = from_dict(KINDS[meta["kind"]], meta["config"])
    check_deployable(config)
    env, team = make_team(config)
    actor = None
    if weights:
        actor = serialization.msgpack_restore((folder / "actor.msgpack").read_bytes())
    return DeployedTeam(config, env, team, actor)


def check_deployable(config) -> None:
    """Refuse a team whose channel or size the runtime does not carry."""
    if config.channel.mode not in MODES:
        raise ValueError(
            f"Deploy: the team's ChannelConfig.mode must be one of {MODES}, got "
            f"{config.channel.mode!r}"
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
    signal: jax.Array  # (K-1, C) float32 z (the ``continuous`` mode sends it)
    payload: jax.Array  # (K-1,) payload bits of each link (the library's count)
    wire: jax.Array  # (K-1,) bits of each link's packet (the library's count)


@functools.lru_cache(maxsize=16)
def agent_step(team, cfg: ChannelConfig, greedy: bool):
    """The jitted step of an agent: ``(params, i, carry (H,), obs, msgs ((K-1) C,), gumbel
    (A,), t, u (K-1, C), prev (K-1, C)) -> StepOut`` for agent ``i`` (a traced argument: every
    agent runs the same compiled program); ``u``: the dither of its links at ``t``, zeros
    unless discrete; ``prev``: its links' symbols at ``t - 1``."""
    k = team.num_agents

    def step(params, i, carry, obs, msgs, gumbel, t, u, prev):
        def one_row(x):  # a batch of one episode whose only real row is agent i's
            return jnp.zeros((1, k, *x.shape), x.dtype).at[0, i].set(x)

        carry, logits, z = team.act(params, one_row(carry), one_row(obs), one_row(msgs))
        log_probs = jax.nn.log_softmax(logits[0, i])
        if greedy:
            action = jnp.argmax(logits[0, i], -1)
        else:  # as rollout: a Gumbel-max sample of the policy
            action = jnp.argmax(log_probs + gumbel, -1)
        keys = None  # the deployable modes need no channel keys
        sent = channel.transmit(cfg, one_row(z[0, i]), one_row(u), keys, t, one_row(prev))
        return StepOut(
            carry[0, i],
            action.astype(jnp.int32),
            sent.symbols[0, i],
            z[0, i],
            sent.link[0, i],
            sent.link_wire[0, i],
        )

    return jax.jit(step)


@functools.lru_cache(maxsize=16)
def link_dither(cfg: ChannelConfig, num_agents: int):
    """Jitted ``(chan_key, t, sender) -> (K-1, C)``: the dither of sender's links at step
    ``t``, each from ``channel.dither_key(chan_key, t, sender, recipient)`` (zeros unless
    discrete)."""
    table = jnp.asarray(channel.others(num_agents))
    c = cfg.num_elements

    def draw(chan_key, t, sender):
        recipients = table[sender]
        if cfg.mode != "discrete":
            return jnp.zeros((num_agents - 1, c), jnp.float32)
        one = lambda j: channel.dither(channel.dither_key(chan_key, t, sender, j), (c,))  # noqa: E731
        return jax.vmap(one)(recipients)

    return jax.jit(draw)


@functools.lru_cache(maxsize=16)
def reconstruct(cfg: ChannelConfig, num_agents: int):
    """Jitted receiver side ``(chan_key, t, recipient, symbols (K-1, C), values (K-1, C), ok
    (K-1,), last (K-1, C), use_last) -> (msgs ((K-1) C,), heard (K-1, C))`` of an agent.

    Link ``s`` (its senders in increasing order, ``channel.others``) sent at step ``t``:
    ``discrete``: ``channel.dequantize`` with the dither of ``dither_key(chan_key, t, s,
    recipient)``, regenerated here; ``continuous``: the float values. A link not ``ok`` (its
    datagram missing at the deadline) is the null message (discrete: null symbols
    reconstructed with this step's dither, as ``rollout`` does; else zeros) or, with
    ``use_last``, the link's last good reconstruction ``last`` (zeros before the first)."""
    table = jnp.asarray(channel.others(num_agents))

    def rebuild(chan_key, t, recipient, symbols, values, ok, last, use_last):
        senders = table[recipient]
        if cfg.mode == "discrete":
            symbols = jnp.where(ok[:, None], symbols, 0)

            def one(s, m):
                key = channel.dither_key(chan_key, t, s, recipient)
                return channel.dequantize(key, m, cfg.levels)

            got = jax.vmap(one)(senders, symbols)
        elif cfg.mode == "continuous":
            got = jnp.where(ok[:, None], values, 0.0)
        else:
            got = jnp.zeros(values.shape, jnp.float32)
        got = jnp.where(ok[:, None] | ~use_last, got, last)
        return got.reshape(-1), got

    return jax.jit(rebuild)


@functools.lru_cache(maxsize=4)
def world_fns(env: NavigationEnv):
    """Jitted ``reset(key)`` and ``step(key, state, actions)`` of the task (unbatched)."""
    return jax.jit(env.reset), jax.jit(env.step)


def code_of(cfg: ChannelConfig):
    """The code that frames each link's packet (``channel.encode``/``decode``)."""
    return cfg.code_obj


def encode_link(cfg: ChannelConfig, symbols: np.ndarray, signal: np.ndarray, prev) -> bytes:
    """One link's packet, exactly as the channel frames it (``b""``: silence; ecc applied)."""
    if cfg.mode == "off":
        return b""
    message = np.asarray(signal, np.float32) if cfg.mode == "continuous" else symbols
    packet = channel.encode(message, code_of(cfg), prev=prev)
    if packet and cfg.ecc != "none":
        packet = channel.ecc.encode(packet, cfg.ecc)
    return packet


def decode_link(cfg: ChannelConfig, packet: bytes, prev) -> np.ndarray:
    """The message of one link's packet (symbols, or floats for ``continuous``). Raises
    ``channel.PacketError`` for anything that is not a packet of this channel."""
    shape = (cfg.num_elements,)
    if packet and cfg.ecc != "none":
        try:
            packet = channel.ecc.decode(packet, cfg.ecc)
        except ValueError as e:
            raise channel.PacketError(str(e)) from None
        if not packet:  # too short to hold a protected packet; silence is sent as b""
            raise channel.PacketError("an ecc-protected packet too short to hold a packet")
    return channel.decode(packet, code_of(cfg), shape, prev=prev)


def with_channel(config, **changes):
    """``config`` with its channel's fields replaced."""
    return dataclasses.replace(config, channel=dataclasses.replace(config.channel, **changes))
