"""The task interface every sparsecomm task implements, and the one check that holds it.

A **task** is a class built from its config, ``Task(config)``, with the pure JaxMARL-style API
that the rollout, the learners, the run folders and ``sparsecomm deploy`` call (arrays carry a
leading agent axis K; nothing is a per-agent dict):

- ``reset(key) -> (obs (K, obs_dim) float32, state)``;
- ``step(key, state, actions (K,) int32) -> (obs, state, rewards (K,) float32, dones (K,) bool,
  info)``, ``info["success"]`` a () bool: the team succeeded at this step;
- ``global_state(state) -> (state_dim,) float32``, the centralised critic's input;
- the sizes ``num_agents``, ``num_actions``, ``obs_dim``, ``state_dim`` and ``max_steps`` (the
  episode's length limit in steps);
- ``state.done``, a () bool that turns True at the episode's last step and stays True (the
  rollout masks every later step); stepping a finished state is allowed.

Every function is pure and traceable (``jit``, ``vmap`` over episodes, ``lax.scan`` over
steps). A task may also offer, each optional, read only where it is needed:

- ``positions(state) -> (K, 2)``: where the agents are, for a team whose links follow
  positions (``AgentConfig.neighbours`` / ``radius``, :mod:`sparsecomm.scaling`);
- ``expert_actions(state) -> (K,) int32``: a centralised scripted expert that reads the whole
  state and sends no messages (``ILConfig.expert = "oracle"``);
- ``render(states, link_bits) -> list of (H, W, 3) uint8 frames`` (``states``: one episode's
  states with a leading time axis, numpy; ``link_bits``: (T, K, K) payload bits sent i -> j):
  the GIFs of ``sparsecomm train`` and ``sparsecomm render``.
- ``active(state) -> (K,) bool``: the agents in play now, for a task whose agents come and go
  within the fixed K (Traffic Junction's cars, :mod:`sparsecomm.envs.traffic_junction`): an
  inactive agent's observation is what the task gives it (zeros there), its action is ignored
  and its reward is 0. Nothing in the rollout or the learners reads it yet: they treat every
  agent as in play.

Its config is a frozen (hashable) dataclass that subclasses :class:`TaskConfig`, every field
with a docstring (they are the command line's ``--config.env.*`` flags), checked in
``__post_init__``, and exposes ``num_agents`` (a field or a property). The registry
(:mod:`sparsecomm.envs.registry`) names each task; :func:`check_task` is the conformance check
that every registered task passes (``tests/test_env.py``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """The base of every task's config: a frozen dataclass of documented fields that exposes
    ``num_agents`` (a field or a property; ``envs.registry.register`` refuses a config without
    it). ``LearnerConfig.env`` holds one; its class names the task in the registry."""


@runtime_checkable
class Task(Protocol):
    """What the rollout, the learners and deployment call (see the module docstring)."""

    config: Any
    num_agents: int
    num_actions: int
    obs_dim: int
    state_dim: int
    max_steps: int

    def reset(self, key: jax.Array) -> tuple[jax.Array, Any]: ...

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> tuple: ...

    def global_state(self, state: Any) -> jax.Array: ...


def _expect(ok: bool, what: str, task) -> None:
    if not ok:
        raise AssertionError(f"{type(task).__name__}: {what}")


def _shape(x, shape: tuple, dtype, what: str, task) -> None:
    x = jnp.asarray(x)
    _expect(x.shape == shape, f"{what} must have shape {shape}, got {x.shape}", task)
    _expect(
        jnp.issubdtype(x.dtype, dtype),
        f"{what} must be of dtype {dtype.__name__}, got {x.dtype}",
        task,
    )


def check_task(task, key: jax.Array | None = None, episodes: int = 3) -> None:
    """The conformance check of the task interface (Jumanji's ``check_env_does_not_smoke``,
    stricter): the sizes are positive integers; ``reset`` and ``step`` give the documented
    shapes and dtypes, jitted and vmapped over ``episodes`` episodes; the same key gives the
    same episode; a random team's episodes end by ``max_steps`` and ``done`` stays True; the
    optional ``positions``, ``expert_actions``, ``active`` and ``render``, where the task has
    them, give their shapes. Raises ``AssertionError`` naming the task and what failed."""
    key = jax.random.key(0) if key is None else key
    _expect(isinstance(task, Task), "does not have the task interface (envs/task.py)", task)
    for name in ("num_agents", "num_actions", "obs_dim", "state_dim", "max_steps"):
        value = getattr(task, name)
        _expect(
            isinstance(value, int | np.integer) and value >= 1,
            f"{name} must be an integer >= 1, got {value!r}",
            task,
        )
    _expect(task.num_agents >= 2, f"num_agents must be >= 2, got {task.num_agents}", task)
    _expect(
        task.config.num_agents == task.num_agents,
        f"config.num_agents ({task.config.num_agents}) must equal num_agents ({task.num_agents})",
        task,
    )
    k, b, t = task.num_agents, episodes, task.max_steps
    reset = jax.jit(jax.vmap(task.reset))
    step = jax.jit(jax.vmap(task.step))
    keys = jax.random.split(key, 3)
    obs, state = reset(jax.random.split(keys[0], b))
    _shape(obs, (b, k, task.obs_dim), jnp.floating, "reset's observations", task)
    _shape(state.done, (b,), jnp.bool_, "state.done", task)
    _expect(not bool(jnp.any(state.done)), "a fresh episode must not be done", task)
    _shape(
        jax.vmap(task.global_state)(state),
        (b, task.state_dim),
        jnp.floating,
        "global_state",
        task,
    )

    def play(key):
        obs, state = reset(jax.random.split(key, b))
        dones, successes, firsts = [], [], []
        first_state = state
        for i in range(t + 1):
            act_key, step_key = jax.random.split(jax.random.fold_in(key, i))
            actions = jax.random.randint(act_key, (b, k), 0, task.num_actions)
            obs, state, rewards, done_k, info = step(jax.random.split(step_key, b), state, actions)
            if i == 0:
                _shape(obs, (b, k, task.obs_dim), jnp.floating, "step's observations", task)
                _shape(rewards, (b, k), jnp.floating, "step's rewards", task)
                _shape(done_k, (b, k), jnp.bool_, "step's dones", task)
                _shape(info["success"], (b,), jnp.bool_, 'info["success"]', task)
                firsts = (obs, rewards)
            dones.append(np.asarray(state.done))
            successes.append(np.asarray(info["success"]))
        return np.stack(dones), np.stack(successes), firsts, first_state

    dones, _, firsts, first_state = play(keys[1])
    _expect(bool(dones[t - 1].all()), f"every episode must be done after max_steps ({t})", task)
    _expect(bool((dones[1:] >= dones[:-1]).all()), "state.done must stay True once True", task)
    again = play(keys[1])
    same = jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), (dones, firsts), again[:3:2])
    _expect(all(jax.tree.leaves(same)), "the same keys must give the same episode", task)
    _check_optional(task, jax.tree.map(lambda x: x[0], first_state))


def _check_optional(task, one) -> None:
    """The optional parts of the interface, where ``task`` has them, on one state ``one``:
    ``positions`` (K, 2), ``expert_actions`` (K,) valid actions, ``active`` (K,) bool,
    ``render`` one RGB frame per state."""
    k = task.num_agents
    if hasattr(task, "positions"):
        _shape(jax.jit(task.positions)(one), (k, 2), jnp.floating, "positions", task)
    if hasattr(task, "expert_actions"):
        acts = jax.jit(task.expert_actions)(one)
        _shape(acts, (k,), jnp.integer, "expert_actions", task)
        _expect(
            bool(((acts >= 0) & (acts < task.num_actions)).all()),
            f"expert_actions must be in [0, {task.num_actions})",
            task,
        )
    if hasattr(task, "active"):
        _shape(jax.jit(task.active)(one), (k,), jnp.bool_, "active", task)
    if hasattr(task, "render"):
        states = jax.tree.map(lambda *x: np.stack(x), one, one)
        frames = task.render(states, np.zeros((2, k, k), np.float32))
        _expect(len(frames) == 2, f"render must give one frame per state, got {len(frames)}", task)
        f = np.asarray(frames[0])
        _expect(
            f.ndim == 3 and f.shape[-1] == 3 and f.dtype == np.uint8,
            f"render's frames must be (H, W, 3) uint8, got {f.shape} {f.dtype}",
            task,
        )
