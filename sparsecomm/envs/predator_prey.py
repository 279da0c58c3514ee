"""The field's Predator-Prey (IC3Net, Singh, Jain and Sukhbaatar, ICLR 2019) as a sparsecomm
task, in pure JAX: ported from ic3net-envs of the IC3Net repository
(https://github.com/IC3Net/IC3Net, ``ic3net-envs/ic3net_envs/predator_prey_env.py``), MIT
licence, Copyright (c) 2019 Amanpreet Singh, Tushar Jain and Sainbayar Sukhbaatar (the
repository's LICENSE; ``ic3net-envs/LICENSE.md`` is the same MIT licence, "Copyright 2018,
Anonymous"). The licence, as the repository gives it::

    MIT License

    Copyright (c) 2019 Amanpreet Singh, Tushar Jain and Sainbayar Sukhbaatar

    Permission is hereby granted, free of charge, to any person obtaining a copy of this
    software and associated documentation files (the "Software"), to deal in the Software
    without restriction, including without limitation the rights to use, copy, modify, merge,
    publish, distribute, sublicense, and/or sell copies of the Software, and to permit persons
    to whom the Software is furnished to do so, subject to the following conditions:

    The above copyright notice and this permission notice shall be included in all copies or
    substantial portions of the Software.

    THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND, EXPRESS OR IMPLIED,
    INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY, FITNESS FOR A PARTICULAR
    PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE AUTHORS OR COPYRIGHT HOLDERS BE LIABLE
    FOR ANY CLAIM, DAMAGES OR OTHER LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR
    OTHERWISE, ARISING FROM, OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER
    DEALINGS IN THE SOFTWARE.

K predators on a ``dim x dim`` grid look for one stationary prey. The dynamics, step by step as
the original's ``step``:

1. each predator that has not reached the prey moves by its action, ``0`` up (row - 1), ``1``
   right (column + 1), ``2`` down, ``3`` left, ``4`` stay, clamped to the grid (several
   predators may share a cell); a predator that has reached the prey stays there for good;
2. the observations are read (below);
3. ``reward_i = timestep_penalty`` (-0.05) for a predator off the prey; on the prey
   ``prey_reward`` (0) under ``reward_mode = "mixed"``, ``pos_prey_reward * n_on`` under
   ``"cooperative"`` and ``pos_prey_reward / n_on`` under ``"competitive"`` (``n_on`` the
   predators on the prey now); those on the prey are marked as having reached it;
4. under ``"mixed"`` the episode is over once every predator has reached the prey; in every
   mode it ends after ``max_steps`` steps (IC3Net's trainer, ``--max_steps``).

**Observation** (the original's, flattened as IC3Net's ``GymWrapper`` does): a predator sees the
``(2 vision + 1)^2`` window of cells around it, row-major, each cell a vector over a vocabulary of
``dim^2 + 4`` entries: the one-hot of the cell's index ``row * dim + col`` (entry ``dim^2 + 1``
for a cell outside the grid; entry ``dim^2`` is never set), plus the number of prey at entry
``dim^2 + 2`` and the number of predators at entry ``dim^2 + 3``. ``obs_dim = (2 vision + 1)^2
(dim^2 + 4)``, float32.

**Levels** (``PredatorPreyConfig.level``, IC3Net's README): ``easy`` 5x5, 3 predators, vision 0,
20 steps; ``medium`` 10x10, 5 predators, vision 1, 40 steps; ``hard`` 20x20, 10 predators,
vision 1, 80 steps.

**Success** (``info["success"]``): every predator is on the prey at this step, the original's
``stat["success"]`` (under ``"mixed"`` it ends the episode). The field's headline is the number
of steps the team takes to get there (the episode's length).

Kept apart on purpose: the initial positions are drawn with JAX's random numbers (the original
draws K + 1 distinct cells with numpy's global generator; :meth:`PredatorPrey.state_from` starts
from given positions, for the parity test); a finished episode may be stepped (nothing moves,
rewards are 0; the original raises); the original's options that it leaves unimplemented or
that change the team (moving prey, several prey, prey that communicate, no stay action) are not
ported. ``tests/test_predator_prey.py`` replays episodes recorded with the original
(``scripts/record_ic3net_parity.py``) and asserts the same observations, rewards, dones and
successes; docs/field.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sparsecomm.envs.task import TaskConfig

LEVELS = {"easy": (5, 3, 0, 20), "medium": (10, 5, 1, 40), "hard": (20, 10, 1, 80)}
"""IC3Net's README: level -> (dim, predators, vision, max_steps)."""
MODES = ("mixed", "cooperative", "competitive")
"""The original's reward modes (``--mode``)."""
NUM_ACTIONS = 5
"""Up, right, down, left, stay (the original's order)."""
MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1], [0, 0]], np.int32)
"""(row, column) displacement of each action."""


@dataclasses.dataclass(frozen=True)
class PredatorPreyConfig(TaskConfig):
    """IC3Net's Predator-Prey; the grid, the team and the episode's length come from ``level``."""

    level: str = "easy"
    """``easy``, ``medium`` or ``hard`` (grid, predators, vision, steps: see the module
    docstring). ic3net-envs: IC3Net's README's three versions; ``easy`` is its first."""
    reward_mode: str = "mixed"
    """Reward mode: ``mixed``, ``cooperative`` or ``competitive``. ic3net-envs: ``--mode``,
    default ``mixed``."""
    timestep_penalty: float = -0.05
    """Reward of a predator off the prey, each step. ic3net-envs: ``TIMESTEP_PENALTY``."""
    prey_reward: float = 0.0
    """Reward of a predator on the prey under ``mixed``. ic3net-envs: ``PREY_REWARD``."""
    pos_prey_reward: float = 0.05
    """On-prey reward unit under ``cooperative`` (times the predators on it) and
    ``competitive`` (divided by them). ic3net-envs: ``POS_PREY_REWARD``."""

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueError(
                f"PredatorPreyConfig.level must be one of {tuple(LEVELS)}, got {self.level!r}"
            )
        if self.reward_mode not in MODES:
            raise ValueError(
                f"PredatorPreyConfig.reward_mode must be one of {MODES}, got {self.reward_mode!r}"
            )
        for name in ("timestep_penalty", "prey_reward", "pos_prey_reward"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise ValueError(f"PredatorPreyConfig.{name} must be a real number, got {value!r}")
            if not np.isfinite(value):
                raise ValueError(f"PredatorPreyConfig.{name} must be finite, got {value!r}")

    @property
    def dim(self) -> int:
        """The grid's side (the level's)."""
        return LEVELS[self.level][0]

    @property
    def num_agents(self) -> int:
        """The predators (the level's)."""
        return LEVELS[self.level][1]

    @property
    def vision(self) -> int:
        """How many cells a predator sees on each side (the level's)."""
        return LEVELS[self.level][2]

    @property
    def max_steps(self) -> int:
        """The episode's length limit (the level's)."""
        return LEVELS[self.level][3]


@struct.dataclass
class PredatorPreyState:
    """The grid's state and the episode's bookkeeping."""

    predators: jax.Array
    """(K, 2) int32 (row, column) of each predator."""
    prey: jax.Array
    """(2,) int32 (row, column) of the prey."""
    reached: jax.Array
    """(K,) bool: the predator has reached the prey (it stays there)."""
    time: jax.Array
    """() int32 steps taken."""
    done: jax.Array
    """() bool, the episode is over; sticky."""


class PredatorPrey:
    """IC3Net's Predator-Prey with the task interface (see the module docstring)."""

    def __init__(self, config: PredatorPreyConfig | None = None):
        self.config = PredatorPreyConfig() if config is None else config
        d, v = self.config.dim, self.config.vision
        base = d * d
        self.vocab = base + 4
        self.outside, self.prey_class, self.predator_class = base + 1, base + 2, base + 3
        # The original's padded grid of cell classes: each cell's index, OUTSIDE around it.
        self._classes = np.pad(
            np.arange(base, dtype=np.int32).reshape(d, d), v, constant_values=self.outside
        )

    def __repr__(self) -> str:
        return f"PredatorPrey({self.config!r})"

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
        """``(2 vision + 1)^2 (dim^2 + 4)``: the window's cells, each over the vocabulary."""
        return (2 * self.config.vision + 1) ** 2 * self.vocab

    @property
    def state_dim(self) -> int:
        """Size of :meth:`global_state`: the predators' and the prey's cells, the reached
        flags and the time."""
        return 3 * self.num_agents + 3

    def _obs(self, predators: jax.Array, prey: jax.Array) -> jax.Array:
        v = self.config.vision
        w = 2 * v + 1
        n = self._classes.shape[0]
        pred_count = jnp.zeros((n, n), jnp.float32).at[predators[:, 0] + v, predators[:, 1] + v]
        pred_count = pred_count.add(1.0)
        prey_count = jnp.zeros((n, n), jnp.float32).at[prey[0] + v, prey[1] + v].set(1.0)
        classes = jnp.asarray(self._classes)

        def window(p):
            def cut(x):
                return jax.lax.dynamic_slice(x, (p[0], p[1]), (w, w))

            cells = jax.nn.one_hot(cut(classes), self.vocab, dtype=jnp.float32)
            cells = cells.at[..., self.prey_class].add(cut(prey_count))
            cells = cells.at[..., self.predator_class].add(cut(pred_count))
            return cells.reshape(-1)

        return jax.vmap(window)(predators)

    def state_from(self, predators, prey) -> tuple[jax.Array, PredatorPreyState]:
        """``(obs, state)`` of a fresh episode with the predators at ``predators`` (K, 2) and the
        prey at ``prey`` (2,), (row, column) cells: the parity test starts the original's
        episodes from their recorded positions."""
        predators = jnp.asarray(predators, jnp.int32).reshape(self.num_agents, 2)
        prey = jnp.asarray(prey, jnp.int32).reshape(2)
        state = PredatorPreyState(
            predators,
            prey,
            jnp.zeros((self.num_agents,), bool),
            jnp.zeros((), jnp.int32),
            jnp.zeros((), bool),
        )
        return self._obs(predators, prey), state

    def reset(self, key: jax.Array) -> tuple[jax.Array, PredatorPreyState]:
        """K + 1 distinct cells, uniformly: the predators', then the prey's (as the original)."""
        d = self.config.dim
        cells = jax.random.choice(key, d * d, (self.num_agents + 1,), replace=False)
        pos = jnp.stack([cells // d, cells % d], -1).astype(jnp.int32)
        return self.state_from(pos[:-1], pos[-1])

    def step(self, key: jax.Array, state: PredatorPreyState, actions: jax.Array):
        """One step (the module docstring's 1-4). Returns ``(obs, state, rewards (K,), dones
        (K,), info)``; ``info["success"]``: every predator is on the prey. Stepping a finished
        state moves nothing and gives 0 rewards."""
        c = self.config
        moves = jnp.asarray(MOVES)[jnp.clip(actions.astype(jnp.int32), 0, NUM_ACTIONS - 1)]
        moved = jnp.clip(state.predators + moves, 0, c.dim - 1)
        frozen = state.reached | state.done
        predators = jnp.where(frozen[:, None], state.predators, moved)
        on = jnp.all(predators == state.prey, -1)
        n_on = jnp.sum(on)
        if c.reward_mode == "mixed":
            on_reward = jnp.float32(c.prey_reward)
        elif c.reward_mode == "cooperative":
            on_reward = c.pos_prey_reward * n_on.astype(jnp.float32)
        else:
            on_reward = c.pos_prey_reward / jnp.maximum(n_on, 1).astype(jnp.float32)
        rewards = jnp.where(on, on_reward, jnp.float32(c.timestep_penalty))
        rewards = jnp.where(state.done, 0.0, rewards).astype(jnp.float32)
        reached = state.reached | on
        time = state.time + jnp.where(state.done, 0, 1).astype(jnp.int32)
        over = jnp.all(reached) if c.reward_mode == "mixed" else jnp.zeros((), bool)
        done = state.done | over | (time >= c.max_steps)
        state = PredatorPreyState(predators, state.prey, reached, time, done)
        dones = jnp.full((self.num_agents,), done)
        info = {"success": n_on == self.num_agents}
        return self._obs(predators, state.prey), state, rewards, dones, info

    def global_state(self, state: PredatorPreyState) -> jax.Array:
        """(state_dim,) float32 for the centralised critic: every cell scaled to [0, 1], the
        reached flags and the time."""
        scale = 1.0 / (self.config.dim - 1)
        return jnp.concatenate(
            [
                state.predators.reshape(-1) * scale,
                state.prey * scale,
                state.reached,
                (state.time / self.config.max_steps)[None],
            ]
        ).astype(jnp.float32)

    def positions(self, state: PredatorPreyState) -> jax.Array:
        """(K, 2) float32 the predators' (row, column) cells."""
        return state.predators.astype(jnp.float32)

    def expert_actions(self, state: PredatorPreyState) -> jax.Array:
        """(K,) int32: a centralised chaser that sees the prey: each predator closes the row
        gap first, then the column gap, and stays on the prey."""
        dr = state.prey[0] - state.predators[:, 0]
        dc = state.prey[1] - state.predators[:, 1]
        col = jnp.where(dc > 0, 1, jnp.where(dc < 0, 3, 4))
        return jnp.where(dr > 0, 2, jnp.where(dr < 0, 0, col)).astype(jnp.int32)
