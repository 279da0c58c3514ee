"""PettingZoo ``ParallelEnv`` wrapper around :class:`~sparsecomm.envs.navigation.NavigationEnv`.

NumPy in, NumPy out, agents named ``agent_0 .. agent_{K-1}``. The episode *terminates* on success
and is *truncated* at ``max_steps``. The JAX reset/step functions are jitted once per instance.
The wrapper is for interoperability and inspection (one environment, one step per call); train
with the pure JAX environment.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from sparsecomm.envs.navigation import NUM_ACTIONS, NavConfig, NavigationEnv, NavState


class NavigationParallelEnv(ParallelEnv):
    """Hidden-goal navigation as a PettingZoo parallel environment."""

    metadata = {
        "name": "sparsecomm_navigation_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: NavConfig | None = None,
        render_mode: str | None = None,
        render_size: int = 256,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, "
                f"got {render_mode!r}"
            )
        self.config = NavConfig() if config is None else config
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.env = NavigationEnv(self.config)
        self.possible_agents = [f"agent_{i}" for i in range(self.config.num_agents)]
        self.agents: list[str] = []
        self._reset_fn = jax.jit(self.env.reset)
        self._step_fn = jax.jit(self.env.step)
        self._key: jax.Array | None = None
        self.state_: NavState | None = None

        cfg = self.config
        vmax = cfg.max_speed if np.isfinite(cfg.max_speed) else np.inf
        # Small margins so float32 round-off never leaves the box.
        pos_hi = np.float32(cfg.position_limit * (1 + 1e-5))
        vel_hi = np.float32(vmax * (1 + 1e-3) + 1e-6)
        goal_hi = np.float32(cfg.arena_half_width * (1 + 1e-5))
        high = np.concatenate(
            [
                np.full(2, pos_hi, np.float32),
                np.full(2, vel_hi, np.float32),
                np.full(self.env.obs_dim - 4, goal_hi, np.float32),
            ]
        )
        self._observation_space = spaces.Box(-high, high, dtype=np.float32)
        self._action_space = spaces.Discrete(NUM_ACTIONS)
        self.state_space = spaces.Box(-np.inf, np.inf, (self.env.state_dim,), np.float32)

    def observation_space(self, agent: str) -> spaces.Box:
        # The same object for every call, as PettingZoo's API test requires.
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._action_space

    def _obs_dict(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        elif self._key is None:
            self._key = jax.random.PRNGKey(np.random.SeedSequence().entropy % (2**32))
        self._key, key_reset = jax.random.split(self._key)
        obs, self.state_ = self._reset_fn(key_reset)
        self.agents = list(self.possible_agents)
        obs = np.asarray(obs)
        return self._obs_dict(obs), {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        if self.state_ is None or not self.agents:
            raise RuntimeError("call reset() before step() (the episode is over)")
        act = np.zeros(self.config.num_agents, np.int32)
        for i, agent in enumerate(self.possible_agents):
            if agent in actions:
                act[i] = int(actions[agent])
        self._key, key_step = jax.random.split(self._key)
        obs, self.state_, rewards, _, info = self._step_fn(key_step, self.state_, act)
        obs, rewards = np.asarray(obs), np.asarray(rewards)
        success = bool(info["success"])
        truncated = (not success) and int(self.state_.time) >= self.config.max_steps
        in_radius = np.asarray(info["in_radius"])
        dist = np.asarray(info["dist"])
        agents = self.agents
        obs_d = {a: obs[i] for i, a in enumerate(self.possible_agents) if a in agents}
        rew_d = {a: float(rewards[i]) for i, a in enumerate(self.possible_agents) if a in agents}
        term_d = dict.fromkeys(agents, success)
        trunc_d = dict.fromkeys(agents, truncated)
        info_d = {
            a: {"in_radius": bool(in_radius[i]), "dist": float(dist[i]), "success": success}
            for i, a in enumerate(self.possible_agents)
            if a in agents
        }
        if success or truncated:
            self.agents = []
        return obs_d, rew_d, term_d, trunc_d, info_d

    def state(self) -> np.ndarray:
        """Global state (for a centralised critic), see ``NavigationEnv.global_state``."""
        if self.state_ is None:
            raise RuntimeError("call reset() first")
        return np.asarray(self.env.global_state(self.state_))

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self.state_ is None:
            raise RuntimeError("call reset() before render()")
        from sparsecomm.envs.render import render_frames

        return render_frames([self.state_], self.config, size=self.render_size)[0]

    def close(self) -> None:
        pass
