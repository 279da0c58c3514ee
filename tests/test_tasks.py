"""A task is a plug-in: the registry, the conformance check over every registered task, and a toy
task defined in this file alone that the commands train, evaluate, render, export, imitate and
deploy without any change to the package.

The deployed processes find the toy task the way a user's own module is found: this module is
named in ``SPARSECOMM_TASKS`` (``envs.registry.PLUGINS_VAR``) and its folder is on the path.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from sparsecomm import cli
from sparsecomm.configs import RLConfig, from_dict, to_dict
from sparsecomm.envs import registry
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.envs.task import TaskConfig, check_task

# -- the toy task: two agents, each must tell the other its hidden digit -------------------------


@dataclasses.dataclass(frozen=True)
class ToyConfig(TaskConfig):
    """Each agent has a hidden digit that only the other agent sees; each must name its own."""

    digits: int = 3
    """Possible digits (>= 2), also the number of actions."""
    max_steps: int = 6
    """Steps per episode (>= 1)."""

    @property
    def num_agents(self) -> int:
        return 2

    def __post_init__(self):
        if self.digits < 2:
            raise ValueError(f"ToyConfig.digits must be >= 2, got {self.digits}")
        if self.max_steps < 1:
            raise ValueError(f"ToyConfig.max_steps must be >= 1, got {self.max_steps}")


@struct.dataclass
class ToyState:
    digits: jax.Array  # (2,) int32 each agent's hidden digit
    guess: jax.Array  # (2,) int32 the last actions (-1 before the first)
    time: jax.Array
    done: jax.Array
    success: jax.Array


class Toy:
    """Rewards 1 per agent that names its own digit; success: both do at one step."""

    def __init__(self, config: ToyConfig):
        self.config = config
        self.num_agents, self.num_actions = 2, config.digits
        self.obs_dim, self.state_dim = config.digits + 1, 2 * config.digits + 1
        self.max_steps = config.max_steps

    def _obs(self, state):
        seen = jax.nn.one_hot(state.digits[::-1], self.config.digits)  # the other's digit
        time = jnp.full((2, 1), state.time / self.max_steps)
        return jnp.concatenate([seen, time], -1).astype(jnp.float32)

    def reset(self, key):
        digits = jax.random.randint(key, (2,), 0, self.config.digits)
        zero = jnp.zeros((), jnp.int32)
        state = ToyState(digits, jnp.full((2,), -1), zero, zero > 0, zero > 0)
        return self._obs(state), state

    def step(self, key, state, actions):
        right = actions == state.digits
        success = jnp.all(right) & ~state.done
        time = state.time + 1
        done = state.done | success | (time >= self.max_steps)
        state = ToyState(state.digits, actions, time, done, state.success | success)
        return (
            self._obs(state),
            state,
            right.astype(jnp.float32),
            jnp.full((2,), done),
            {"success": success},
        )

    def global_state(self, state):
        one_hot = jax.nn.one_hot(state.digits, self.config.digits).reshape(-1)
        return jnp.concatenate([one_hot, (state.time / self.max_steps)[None]]).astype(jnp.float32)

    def expert_actions(self, state):
        return state.digits.astype(jnp.int32)

    def render(self, states, link_bits=None):
        frames = []
        for t in range(np.asarray(states.time).shape[0]):
            frame = np.zeros((8, 16, 3), np.uint8)
            for i in range(2):
                right = states.guess[t][i] == states.digits[t][i]
                frame[:, 8 * i : 8 * i + 8, 1 if right else 0] = 255
            frames.append(frame)
        return frames


registry.register("toy", Toy, ToyConfig)  # the one line a task adds


# -- the registry and the conformance check --------------------------------------------------------


def _buildable(name: str):
    spec = registry.spec(name)
    try:
        return spec.env(spec.config())
    except ImportError as e:  # an optional extra (e.g. jaxmarl) is not installed
        pytest.skip(f"task {name!r}: {e}")


@pytest.mark.parametrize("name", registry.names())
def test_every_registered_task_passes_the_conformance_check(name):
    check_task(_buildable(name), jax.random.key(1))


def test_the_check_catches_a_task_that_breaks_the_interface():
    class Endless(Toy):  # never done
        def step(self, key, state, actions):
            obs, state, r, d, info = super().step(key, state, actions)
            state = state.replace(done=jnp.zeros((), bool))
            return obs, state, r, d, info

    class WrongObs(Toy):
        @property
        def obs_dim(self):
            return 7

        @obs_dim.setter
        def obs_dim(self, value):
            pass

    with pytest.raises(AssertionError, match="done after max_steps"):
        check_task(Endless(ToyConfig()))
    with pytest.raises(AssertionError, match="reset's observations must have shape"):
        check_task(WrongObs(ToyConfig()))


def test_registry_names_makes_and_refuses():
    assert {"navigation", "simple_reference", "toy"} <= set(registry.names())
    assert registry.task_of(NavConfig()) == "navigation"
    assert type(registry.make(ToyConfig(digits=4))) is Toy
    registry.register("toy", Toy, ToyConfig)  # the same pair again: a no-op
    with pytest.raises(ValueError, match="registered already"):
        registry.register("toy", Toy.__base__, ToyConfig)
    with pytest.raises(ValueError, match="config of task 'toy' already"):
        registry.register("toy2", Toy, ToyConfig)
    with pytest.raises(TypeError, match="TaskConfig"):
        registry.register("plain", Toy, dict)

    @dataclasses.dataclass(frozen=True)
    class Headless(TaskConfig):
        size: int = 1

    with pytest.raises(TypeError, match="must expose num_agents"):
        registry.register("headless", Toy, Headless)
    with pytest.raises(ValueError, match=r"registered tasks \[.*'navigation'.*\], got 'nope'"):
        registry.spec("nope")


def test_a_config_names_its_task_and_an_unknown_task_is_refused():
    config = RLConfig(env=ToyConfig(digits=4), num_envs=4)
    assert config.task == "toy"
    data = to_dict(config)
    assert data["task"] == "toy" and data["env"] == {"digits": 4, "max_steps": 6}
    assert from_dict(RLConfig, json.loads(json.dumps(data))) == config
    old = {k: v for k, v in to_dict(RLConfig()).items() if k != "task"}  # before tasks had names
    assert from_dict(RLConfig, old) == RLConfig()
    with pytest.raises(ValueError, match=r"RLConfig\.task must be one of the registered .*'nope'"):
        from_dict(RLConfig, {**data, "task": "nope"})
    with pytest.raises(ValueError, match="ToyConfig has no field"):
        from_dict(RLConfig, {**data, "task": "toy", "env": to_dict(NavConfig())})

    @dataclasses.dataclass(frozen=True)
    class Unregistered(TaskConfig):
        num_agents: int = 2

    with pytest.raises(ValueError, match="RLConfig.env must be the config of a registered task"):
        RLConfig(env=Unregistered())
    with pytest.raises(ValueError, match="RLConfig.agent.neighbours .* no positions"):
        RLConfig(env=ToyConfig(), agent=dataclasses.replace(RLConfig().agent, neighbours=1))


def test_the_command_line_refuses_an_unknown_task_before_any_work(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--task", "nope", "--out", str(tmp_path / "r")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "registered tasks" in err and "'navigation'" in err and "'toy'" in err
    assert not (tmp_path / "r").exists()
    with pytest.raises(SystemExit):
        cli.main(["eval", "--task", "toy"])
    assert "--task must follow 'sparsecomm train'" in capsys.readouterr().err
    # a run folder whose config names an unregistered task
    meta = {"kind": "train", "config": {**to_dict(RLConfig()), "task": "gone"}, "run": {}}
    team = tmp_path / "team"
    team.mkdir()
    (team / "team.json").write_text(json.dumps(meta))
    with pytest.raises(SystemExit) as e:
        cli.main(["eval", "--run", str(team), "--out", str(tmp_path / "e.json")])
    assert "'gone'" in capsys.readouterr().err


# -- the toy task through every command ------------------------------------------------------------


@pytest.mark.slow  # a learning test with agent processes (CI runs the slow set too)
def test_a_task_in_one_file_trains_evaluates_renders_exports_imitates_and_deploys(
    tmp_path, monkeypatch
):
    here = str(Path(__file__).parent)
    monkeypatch.setenv(registry.PLUGINS_VAR, Path(__file__).stem)
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")]))
    )
    run = tmp_path / "run"
    small = [
        "--config.num-envs",
        "16",
        "--eval-episodes",
        "64",
        "--no-tensorboard",
        "--no-progress",
    ]
    cli.main(
        [
            "train",
            "--task",
            "toy",
            "--config.env.digits",
            "3",
            "--config.num-updates",
            "150",
            "--config.lr",
            "3e-3",
            "--out",
            str(run),
            *small,
        ]
    )
    results = json.loads((run / "results.json").read_text())
    meta = json.loads((run / "checkpoint" / "config.json").read_text())
    assert meta["config"]["task"] == "toy" and meta["config"]["env"]["digits"] == 3
    assert (run / "team.gif").stat().st_size > 0 and (run / "curves.png").exists()
    # it learned to talk: guessing blind succeeds 1/9 per step (~0.5 in 6 steps), talking in 2
    (row,) = results["runs"]
    assert row["episode/success_rate"] >= 0.9 and row["episode/episode_length"] <= 3.0, row

    cli.main(["eval", "--run", str(run), "--episodes", "32", "--out", str(tmp_path / "e.json")])
    ev = json.loads((tmp_path / "e.json").read_text())["runs"][0]
    assert ev["episode/success_rate"] >= 0.9
    cli.main(["render", "--run", str(run), "--out", str(tmp_path / "t.gif")])
    assert (tmp_path / "t.gif").stat().st_size > 0
    cli.main(["export", "--run", str(run), "--out", str(tmp_path / "team")])
    assert json.loads((tmp_path / "team" / "team.json").read_text())["config"]["task"] == "toy"

    imitate = tmp_path / "imitate"
    cli.main(
        ["imitate", "--task", "toy", "--config.num-updates", "3", "--out", str(imitate), *small]
    )
    assert json.loads((imitate / "checkpoint" / "config.json").read_text())["kind"] == "imitation"

    episodes = 5
    out = tmp_path / "deploy"
    cli.main(
        ["deploy", "--run", str(tmp_path / "team"), "--episodes", str(episodes), "--out", str(out)]
    )
    (row,) = json.loads((out / "deploy.json").read_text())["runs"]
    assert row["episodes"] == episodes
    assert row["simulation"]["identical_episodes"] == episodes, row["simulation"]
