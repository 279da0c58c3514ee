"""Cooperative goal navigation with hidden goals (paper section V.A, SPEC section 4).

K point-mass agents move in the plane. Each agent has a goal, uniform in the square
``[-arena_half_width, arena_half_width]^2``, that it never observes: it observes only the goals of
the other agents, so the team has to communicate to succeed. Each goal independently jumps to a
new uniform location with probability ``goal_jump_prob`` per step.

The environment is written in the JaxMARL style: :class:`NavigationEnv` has pure ``reset`` and
``step`` methods that can be jitted, vmapped and scanned. Arrays carry a leading agent axis (no
per-agent dicts). The environment does not add message slots to observations; a learner's rollout
appends decoded messages itself.

Actions (int32, one per agent): ``0`` no force, ``1`` up (+y), ``2`` down (-y), ``3`` left (-x),
``4`` right (+x).

Observation of agent ``i`` (float32, ``obs_dim = 4 + 2 G``): own position (2), own velocity
(2), then the goals of the ``G`` agents that ``NavConfig.goal_view`` shows it. ``"others"`` (the
paper's, default): the other ``G = K - 1`` agents in increasing agent index order, skipping ``i``.
``"ring"`` (for many agents, docs/scaling.md): ``G = goal_view_count`` goals, those of agents
``i + 1, ..., i + G`` (mod K) in that order, so each goal is seen by the ``G`` agents before its
owner and by nobody else. :func:`goal_view_index` is the table.

Step order, from a state at time ``t`` with goals ``g_t``:

1. ``dir`` = unit force direction from the action (zero for action 0);
2. ``vel' = (1 - damping) * vel + accel * dt * dir``;
3. ``pos' = clip(pos + dt * vel', -position_limit, position_limit)`` (per coordinate; the velocity
   is not changed by the clipping);
4. ``dist_i = ||pos'_i - g_t,i||``, ``in_radius_i = dist_i < success_radius``,
   ``success = all(in_radius)``;
5. ``individual_i = in_radius_bonus if in_radius_i else -dist_i ** 2``;
   ``reward_i = success_bonus if success else
   individual_weight * individual_i + group_weight * sum_j individual_j``;
6. ``time' = time + 1``; ``done' = done or success or time' >= max_steps``;
7. if the episode goes on (``not done'``), each goal independently jumps with probability
   ``goal_jump_prob`` to a new uniform location in the arena; these are the goals of step
   ``t + 1``. Goals are frozen once the episode is over, so a terminal state shows the goals the
   success was scored against.

Under ``success_rule = "each"`` (the many-agent task, docs/scaling.md) a parked agent's ``vel'``
is 0 in step 2; in step 4 an agent parks when ``in_radius_i`` and ``||vel'_i|| < park_speed``, a
parked agent counts as ``in_radius`` from then on, and ``success = all(parked)``; in step 7 a
parked agent's goal does not jump.

There is no auto-reset. Stepping a state that is already done is allowed (the physics keeps
running and rewards keep being computed; ``done`` and ``success`` stay ``True``): rollouts mask
everything after the first ``done`` themselves.

Physics defaults (SPEC section 5, calibration): ``dt = 0.1``, ``damping = 0.25``, ``accel = 3.0``,
so the terminal speed under a constant force is ``accel * dt / damping = 1.2`` units/s (0.12 units
per step) and an agent crosses the 2 x 2 arena in about 20 steps, well within the 256-step episode.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sparsecomm.envs.task import TaskConfig

GOAL_VIEWS = ("others", "ring")
"""The rules of who observes whose goal (``NavConfig.goal_view``)."""

SUCCESS_RULES = ("together", "each")
"""When the team succeeds (``NavConfig.success_rule``)."""

NUM_ACTIONS = 5
"""Number of discrete actions: no force, up, down, left, right."""

ACTION_DIRECTIONS = np.array(
    [[0.0, 0.0], [0.0, 1.0], [0.0, -1.0], [-1.0, 0.0], [1.0, 0.0]], dtype=np.float32
)
"""Unit force direction of each action (rows indexed by action id)."""


@dataclasses.dataclass(frozen=True)
class NavConfig(TaskConfig):
    """Configuration of the hidden-goal navigation task (hashable: usable as a static jit arg)."""

    num_agents: int = 3
    """Number of agents K (>= 2). Paper: 3."""

    max_steps: int = 256
    """Episode length limit in steps (>= 1). Paper: 256."""

    goal_jump_prob: float = 0.05
    """Per-step probability that each goal jumps to a new uniform spot, in [0, 1]. Paper: 0.05."""

    success_radius: float = 0.1
    """An agent is at its goal when strictly closer than this (> 0). Paper: 0.1."""

    arena_half_width: float = 1.0
    """Goals and starts are uniform in [-a, a]^2 for this a (> 0). Paper: square of side 2."""

    position_limit: float = 1.5
    """Positions are clipped to [-L, L] (L >= arena_half_width). SPEC calibration: 1.5."""

    dt: float = 0.1
    """Integration time step in seconds (> 0). SPEC calibration: 0.1."""

    damping: float = 0.25
    """Velocity is multiplied by (1 - damping) each step, in [0, 1). SPEC calibration: 0.25."""

    accel: float = 3.0
    """Acceleration per unit force (force / mass) in units/s^2 (> 0). SPEC calibration: 3.0."""

    success_bonus: float = 1200.0
    """Reward of every agent when all are at their goals (ends the episode). Paper: 1200."""

    in_radius_bonus: float = 250.0
    """Individual term of an agent within success_radius of its goal. Paper: 250."""

    individual_weight: float = 0.5
    """Weight of the agent's own individual term in its reward. SPEC calibration: 0.5."""

    group_weight: float = 0.5 / 3
    """Weight of the group term, the SUM of the individual terms. SPEC calibration: 0.5 / 3
    (= 0.5 * mean for K = 3; not rescaled with K)."""

    goal_view: str = "others"
    """Who observes whose goal. ``others``: agent i sees the goals of every other agent (paper).
    ``ring``: agent i sees the goals of agents i+1, ..., i+goal_view_count (mod K), so the
    observation no longer grows with K and each goal is known to goal_view_count agents only
    (ours, for the many-agent task of docs/scaling.md). Nobody ever sees its own goal."""

    goal_view_count: int = 1
    """``goal_view = ring`` only: how many goals each agent sees, an integer in [1, K - 1].
    ours: 1 (each goal is known to exactly one other agent)."""

    success_rule: str = "together"
    """When the team succeeds. ``together``: all K agents inside their radius at the same step
    (paper). ``each``: an agent *parks* at the first step it is inside its radius at a speed
    below ``park_speed``: it stops there (velocity 0, its actions ignored, its goal frozen,
    its individual term ``in_radius_bonus`` from then on; it still observes and talks), and the
    team succeeds when every agent has parked. Each agent's part of the task is then the same
    at K = 3 and K = 30 (ours, for the many-agent task of docs/scaling.md: with ``together`` a
    jump of any of the K goals undoes the others' arrival, docs/scaling.md)."""

    park_speed: float = 0.3
    """``success_rule = each`` only: an agent parks only when its speed is below this, in
    units/s (>= 0; 0 never parks). ours: a quarter of the default terminal speed (1.2 units/s),
    so a team cannot park by sweeping the arena at full speed without knowing its goals; the
    oracle brakes to it in 2-3 steps (docs/scaling.md)."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the offending field and its allowed range."""

        def bad(name: str, allowed: str) -> ValueError:
            return ValueError(f"NavConfig.{name} must be {allowed}, got {getattr(self, name)!r}")

        integers = ("num_agents", "max_steps", "goal_view_count")
        words = ("goal_view", "success_rule")
        for name in integers:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise bad(name, "an integer")
        if self.goal_view not in GOAL_VIEWS:
            raise bad("goal_view", f"one of {GOAL_VIEWS}")
        if self.success_rule not in SUCCESS_RULES:
            raise bad("success_rule", f"one of {SUCCESS_RULES}")
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name in (*integers, *words):
                continue
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise bad(field.name, "a real number")
            if not math.isfinite(value):
                raise bad(field.name, "finite")
        if self.num_agents < 2:
            raise bad("num_agents", ">= 2")
        if self.max_steps < 1:
            raise bad("max_steps", ">= 1")
        if not 0.0 <= self.goal_jump_prob <= 1.0:
            raise bad("goal_jump_prob", "in [0, 1]")
        for name in ("success_radius", "arena_half_width", "dt", "accel"):
            if getattr(self, name) <= 0.0:
                raise bad(name, "> 0")
        if self.position_limit < self.arena_half_width:
            raise bad("position_limit", f">= arena_half_width ({self.arena_half_width})")
        if not 0.0 <= self.damping < 1.0:
            raise bad("damping", "in [0, 1)")
        if self.park_speed < 0.0:
            raise bad("park_speed", ">= 0")
        if not 1 <= self.goal_view_count <= self.num_agents - 1:
            raise bad("goal_view_count", f"in [1, {self.num_agents - 1}] (K - 1)")

    @property
    def max_speed(self) -> float:
        """Terminal speed along an axis under a constant force (inf without damping)."""
        if self.damping == 0.0:
            return math.inf
        return self.accel * self.dt / self.damping


@struct.dataclass
class NavState:
    """Full environment state (a pytree; add leading axes freely with vmap/scan)."""

    pos: jax.Array
    """(K, 2) float32 positions."""
    vel: jax.Array
    """(K, 2) float32 velocities."""
    goals: jax.Array
    """(K, 2) float32 goals of the current step."""
    time: jax.Array
    """() int32 number of steps taken."""
    done: jax.Array
    """() bool, the episode is over (success or time limit); sticky."""
    success: jax.Array
    """() bool, the episode ended in success; sticky."""
    parked: jax.Array
    """(K,) bool, the agent has parked at its goal (``success_rule = each``; always False
    under ``together``); sticky."""


def other_agent_index(num_agents: int) -> np.ndarray:
    """(K, K-1) int array: row i lists the other agents in increasing order, skipping i."""
    return np.array(
        [[j for j in range(num_agents) if j != i] for i in range(num_agents)], dtype=np.int32
    ).reshape(num_agents, num_agents - 1)


def goal_view_index(config: NavConfig) -> np.ndarray:
    """(K, G) int array: row i lists the agents whose goals agent i observes, in observation
    order (``NavConfig.goal_view``)."""
    k = config.num_agents
    if config.goal_view == "others":
        return other_agent_index(k)
    shifts = np.arange(1, config.goal_view_count + 1)
    return ((np.arange(k)[:, None] + shifts[None, :]) % k).astype(np.int32)


class NavigationEnv:
    """Hidden-goal cooperative navigation, JaxMARL-style pure functional API."""

    def __init__(self, config: NavConfig | None = None):
        self.config = NavConfig() if config is None else config
        self._seen = goal_view_index(self.config)
        self._directions = jnp.asarray(ACTION_DIRECTIONS)

    def __repr__(self) -> str:
        return f"NavigationEnv({self.config!r})"

    @property
    def num_agents(self) -> int:
        return self.config.num_agents

    @property
    def num_actions(self) -> int:
        return NUM_ACTIONS

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    @property
    def obs_dim(self) -> int:
        return 4 + 2 * self._seen.shape[1]

    @property
    def state_dim(self) -> int:
        """Size of :meth:`global_state`: positions, velocities, goals (2K each) and time."""
        return 6 * self.config.num_agents + 1

    def _uniform_points(self, key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        a = self.config.arena_half_width
        return jax.random.uniform(key, (*shape, 2), jnp.float32, -a, a)

    def reset(self, key: jax.Array) -> tuple[jax.Array, NavState]:
        """Start positions and goals uniform in the arena, zero velocities."""
        k = self.config.num_agents
        key_pos, key_goal = jax.random.split(key)
        state = NavState(
            pos=self._uniform_points(key_pos, (k,)),
            vel=jnp.zeros((k, 2), jnp.float32),
            goals=self._uniform_points(key_goal, (k,)),
            time=jnp.zeros((), jnp.int32),
            done=jnp.zeros((), bool),
            success=jnp.zeros((), bool),
            parked=jnp.zeros((k,), bool),
        )
        return self.get_obs(state), state

    def positions(self, state: NavState) -> jax.Array:
        """(K, 2) the agents' positions (for links that follow them, ``sparsecomm.scaling``)."""
        return state.pos

    def get_obs(self, state: NavState) -> jax.Array:
        """(K, obs_dim) float32: own position, own velocity, the goals ``goal_view`` shows."""
        other_goals = state.goals[self._seen].reshape(self.config.num_agents, -1)
        return jnp.concatenate([state.pos, state.vel, other_goals], axis=-1)

    def global_state(self, state: NavState) -> jax.Array:
        """(state_dim,) float32 full state for a centralised critic.

        Layout: positions (2K, agent-major), velocities (2K), goals (2K), time / max_steps.
        """
        t = state.time.astype(jnp.float32) / self.config.max_steps
        return jnp.concatenate(
            [state.pos.reshape(-1), state.vel.reshape(-1), state.goals.reshape(-1), t[None]]
        )

    def step(
        self, key: jax.Array, state: NavState, actions: jax.Array
    ) -> tuple[jax.Array, NavState, jax.Array, jax.Array, dict[str, Any]]:
        """Advance one step; see the module docstring for the exact order of operations.

        ``actions``: (K,) integers in 0..4 (out-of-range values are clamped into range, as JAX
        indexing does; nothing can raise inside jit). Returns ``(obs, state, rewards, dones,
        info)`` with ``rewards`` (K,) float32 in the paper's units, ``dones`` (K,) bool (all
        equal to the new ``state.done``), and ``info``
        holding ``success`` (() bool, all agents within the radius this step, or all parked:
        ``success_rule``), ``in_radius`` (K,)
        bool, ``dist`` (K,) float32 and ``goal_jumped`` (K,) bool.
        """
        cfg = self.config
        k = cfg.num_agents
        direction = self._directions[jnp.asarray(actions, jnp.int32)]
        vel = (1.0 - cfg.damping) * state.vel + (cfg.accel * cfg.dt) * direction
        each = cfg.success_rule == "each"
        if each:  # a parked agent stays where it stopped
            vel = jnp.where(state.parked[:, None], 0.0, vel)
        pos = jnp.clip(state.pos + cfg.dt * vel, -cfg.position_limit, cfg.position_limit)

        dist = jnp.linalg.norm(pos - state.goals, axis=-1)
        in_radius = dist < cfg.success_radius
        parked = state.parked
        if each:
            slow = jnp.linalg.norm(vel, axis=-1) < cfg.park_speed
            parked = parked | (in_radius & slow & ~state.done)
            in_radius = in_radius | parked
            success = jnp.all(parked)
        else:
            success = jnp.all(in_radius)
        individual = jnp.where(in_radius, jnp.float32(cfg.in_radius_bonus), -(dist**2))
        shaped = cfg.individual_weight * individual + cfg.group_weight * jnp.sum(individual)
        rewards = jnp.where(success, jnp.float32(cfg.success_bonus), shaped).astype(jnp.float32)

        time = state.time + 1
        done = state.done | success | (time >= cfg.max_steps)

        key_jump, key_goal = jax.random.split(key)
        jumped = (jax.random.uniform(key_jump, (k,)) < cfg.goal_jump_prob) & ~done & ~parked
        goals = jnp.where(jumped[:, None], self._uniform_points(key_goal, (k,)), state.goals)

        new_state = NavState(
            pos=pos,
            vel=vel,
            goals=goals,
            time=time,
            done=done,
            success=state.success | success,
            parked=parked,
        )
        info = {
            "success": success,
            "in_radius": in_radius,
            "dist": dist,
            "goal_jumped": jumped,
        }
        return self.get_obs(new_state), new_state, rewards, jnp.full((k,), done), info
