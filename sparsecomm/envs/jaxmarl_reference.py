"""JaxMARL's MPE ``simple_reference`` as a sparsecomm task (a foreign environment).

Two agents and three coloured landmarks. Each agent sees the colour of the landmark the *other*
agent must reach, and is rewarded by how close the other gets there (JaxMARL:
``-||p_other - p_goal(other)||``, mixed half and half with the team mean, ``local_ratio = 0.5``),
so each must tell the other where to go. In JaxMARL an action is one of 50: a move (5) and a
word (10, the environment's own communication: the other agent reads the word, one-hot, in its
next observation).

This adapter gives the environment the task interface (:mod:`sparsecomm.envs.task`: ``reset``,
``step`` on arrays, ``global_state``, sizes) and registers it as ``simple_reference``
(:mod:`sparsecomm.envs.registry`), with a choice of how the agents talk
(``ReferenceConfig.comm``):

- ``channel``: 5 move actions; the environment's word slot is cut from the observations and the
  agents talk through sparsecomm's channel (learned messages, real bits, a bit budget);
- ``env``: the environment's own communication, as JaxMARL defines it (50 actions, the other's
  word in the observation); run it with ``channel.mode = "off"``;
- ``none``: 5 move actions and no words (a lower bound); with ``channel.mode = "off"``.

``jaxmarl`` is an optional dependency (``pip install "sparsecomm[jaxmarl]"``), imported when the
task is built. Train with ``sparsecomm train --task simple_reference`` (or a config whose ``env``
is a :class:`ReferenceConfig`);
``benchmarks/jaxmarl_reference.py`` runs the comparison of docs/plugin.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from sparsecomm.envs.task import TaskConfig

COMMS = ("channel", "env", "none")
MOVES = 5
"""JaxMARL's discrete moves: none, -x, +x, -y, +y (``action mod 5``)."""
WORDS = 10
"""JaxMARL's vocabulary in simple_reference (``dim_c``; ``action // 5``)."""


@dataclasses.dataclass(frozen=True)
class ReferenceConfig(TaskConfig):
    """The task. Defaults are JaxMARL's ``MPE_simple_reference_v3`` unless a field says ours."""

    comm: str = "channel"
    """How the agents talk: ``channel`` (sparsecomm's channel), ``env`` (the environment's
    10-word say action) or ``none`` (see the module docstring). ours."""
    max_steps: int = 25
    """Steps per episode. JaxMARL's MPE default (``MAX_STEPS``)."""
    local_ratio: float = 0.5
    """Weight of an agent's own term in its reward (the rest is the team mean). JaxMARL."""

    @property
    def num_agents(self) -> int:
        """Two agents (JaxMARL's)."""
        return 2

    def __post_init__(self):
        if self.comm not in COMMS:
            raise ValueError(f"ReferenceConfig.comm must be one of {COMMS}, got {self.comm!r}")
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(
                f"ReferenceConfig.max_steps must be an integer >= 1, got {self.max_steps!r}"
            )
        if not 0.0 <= self.local_ratio <= 1.0:
            raise ValueError(
                f"ReferenceConfig.local_ratio must be in [0, 1], got {self.local_ratio!r}"
            )


@struct.dataclass
class ReferenceState:
    """JaxMARL's state and the episode's bookkeeping (the rollout reads ``done``)."""

    mpe: object
    """JaxMARL's ``State`` (positions, velocities, words, goals, step)."""
    time: jax.Array
    """() int32 steps taken."""
    done: jax.Array
    """() bool, the episode is over (``max_steps`` taken); sticky."""


class SimpleReference:
    """JaxMARL's ``simple_reference`` with the rollout's interface (see the module docstring)."""

    def __init__(self, config: ReferenceConfig | None = None):
        try:
            from jaxmarl.environments.mpe.simple_reference import SimpleReferenceMPE
        except ImportError as e:  # the optional extra is missing
            raise ImportError(
                "the simple_reference task needs JaxMARL: pip install 'sparsecomm[jaxmarl]'"
            ) from e
        self.config = ReferenceConfig() if config is None else config
        self.mpe = SimpleReferenceMPE(
            local_ratio=self.config.local_ratio, max_steps=self.config.max_steps
        )
        self._agents = tuple(self.mpe.agents)

    def __repr__(self) -> str:
        return f"SimpleReference({self.config!r})"

    @property
    def num_agents(self) -> int:
        return 2

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    @property
    def num_actions(self) -> int:
        return MOVES * WORDS if self.config.comm == "env" else MOVES

    @property
    def obs_dim(self) -> int:
        """JaxMARL's 21 (own velocity 2, landmarks relative 6, goal colour 3, the other's word
        10), without the word unless ``comm = "env"``."""
        return 11 + (WORDS if self.config.comm == "env" else 0)

    @property
    def state_dim(self) -> int:
        """Size of :meth:`global_state`: both observations, the agents' positions, both goals
        (one-hot) and the time."""
        return 2 * self.obs_dim + 4 + 6 + 1

    def _obs(self, mpe_state) -> jax.Array:
        obs = self.mpe.get_obs(mpe_state)
        return jnp.stack([obs[a][: self.obs_dim] for a in self._agents])

    def reset(self, key: jax.Array) -> tuple[jax.Array, ReferenceState]:
        _, mpe_state = self.mpe.reset(key)
        state = ReferenceState(mpe_state, jnp.zeros((), jnp.int32), jnp.zeros((), bool))
        return self._obs(mpe_state), state

    def global_state(self, state: ReferenceState) -> jax.Array:
        """(state_dim,) float32 for the centralised critic."""
        goals = jax.nn.one_hot(state.mpe.goal, 3).reshape(-1)
        time = (state.time / self.config.max_steps)[None]
        return jnp.concatenate(
            [self._obs(state.mpe).reshape(-1), state.mpe.p_pos[:2].reshape(-1), goals, time]
        ).astype(jnp.float32)

    def positions(self, state: ReferenceState) -> jax.Array:
        """(2, 2) the agents' positions."""
        return state.mpe.p_pos[:2]

    def goal_distances(self, state: ReferenceState) -> jax.Array:
        """(2,) each agent's distance to its goal landmark."""
        goals = state.mpe.p_pos[2 + state.mpe.goal]
        return jnp.linalg.norm(state.mpe.p_pos[:2] - goals, axis=-1)

    def at_goals(self, state: ReferenceState) -> jax.Array:
        """() bool: each agent is nearer to its goal landmark than to the other two. The
        environment defines no success (its measure is the return); this is ours: an agent that
        knows nothing of its goal and waits among the landmarks is at its goal one time in
        three."""
        pos = state.mpe.p_pos
        dist = jnp.linalg.norm(pos[:2, None] - pos[None, 2:], axis=-1)  # (agent, landmark)
        return jnp.all(jnp.argmin(dist, -1) == state.mpe.goal)

    def step(self, key: jax.Array, state: ReferenceState, actions: jax.Array):
        """One step: ``actions`` (2,) int, moves (or move + 5 x word under ``comm = "env"``).
        Returns ``(obs, state, rewards (2,), dones (2,), info)``; ``info["success"]``: the
        episode ends now with each agent at its goal landmark (:meth:`at_goals`)."""
        acts = {a: actions[i] for i, a in enumerate(self._agents)}
        _, mpe_state, rewards, _, _ = self.mpe.step_env(key, state.mpe, acts)
        time = state.time + 1
        ends = time >= self.config.max_steps
        state = ReferenceState(mpe_state, time, state.done | ends)
        rewards = jnp.stack([rewards[a] for a in self._agents]).astype(jnp.float32)
        dones = jnp.full((2,), state.done)
        info = {"success": ends & self.at_goals(state)}
        return self._obs(mpe_state), state, rewards, dones, info
