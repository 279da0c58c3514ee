"""Tests of the PettingZoo ParallelEnv wrapper."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test

from sparsecomm.envs import NavConfig, NavigationParallelEnv, oracle_actions


@pytest.fixture(scope="module")
def env():
    return NavigationParallelEnv(NavConfig(max_steps=64), render_mode="rgb_array")


def test_parallel_api_test_passes(env):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the API test reports problems as warnings too
        parallel_api_test(env, num_cycles=200)


def test_spaces_and_agents(env):
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2"]
    assert env.metadata["name"] and "rgb_array" in env.metadata["render_modes"]
    obs_space = env.observation_space("agent_1")
    assert isinstance(obs_space, spaces.Box) and obs_space.shape == (8,)
    assert obs_space.dtype == np.float32
    assert env.action_space("agent_0") == spaces.Discrete(5)
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(infos) == set(env.possible_agents)
    rng = np.random.default_rng(0)
    for _ in range(64):  # random actions until truncation; every observation is in the box
        assert all(obs_space.contains(o) for o in obs.values())
        obs, rewards, terms, truncs, infos = env.step({a: int(rng.integers(5)) for a in env.agents})
        assert all(isinstance(r, float) for r in rewards.values())
        if not env.agents:
            break
    assert not any(terms.values()) and all(truncs.values()) and env.agents == []
    assert env.state().shape == (19,)


def test_seeded_reset_is_reproducible(env):
    a, _ = env.reset(seed=123)
    b, _ = env.reset(seed=123)
    c, _ = env.reset(seed=124)
    for agent in env.possible_agents:
        np.testing.assert_array_equal(a[agent], b[agent])
    assert not np.array_equal(a["agent_0"], c["agent_0"])


def test_oracle_through_wrapper_terminates_with_success(env):
    env.reset(seed=1)
    for _ in range(64):
        actions = np.asarray(oracle_actions(env.state_, env.config))
        _, rewards, terms, truncs, infos = env.step(
            {a: int(actions[i]) for i, a in enumerate(env.possible_agents)}
        )
        if not env.agents:
            break
    assert all(terms.values()) and not any(truncs.values())
    assert all(r == 1200.0 for r in rewards.values())
    assert all(info["success"] and info["in_radius"] for info in infos.values())
    with pytest.raises(RuntimeError):
        env.step({})


def test_render_rgb_array(env):
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    assert NavigationParallelEnv().render() is None  # no render mode
    with pytest.raises(ValueError, match="render_mode"):
        NavigationParallelEnv(render_mode="human")
