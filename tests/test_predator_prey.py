"""The JAX port of IC3Net's Predator-Prey (:mod:`sparsecomm.envs.predator_prey`) against the
original: episodes recorded with ic3net-envs (``tests/data/ic3net_predator_prey.npz``, written by
``scripts/record_ic3net_parity.py``, whose docstring gives the command) are replayed through the
port from their recorded initial positions and actions, and every observation, reward, done and
success must be equal; plus the config's levels and refusals and the conformance check."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from sparsecomm.envs import registry
from sparsecomm.envs.predator_prey import PredatorPrey, PredatorPreyConfig
from sparsecomm.envs.task import check_task

FIXTURE = Path(__file__).parent / "data" / "ic3net_predator_prey.npz"


def _episodes():
    with np.load(FIXTURE) as f:
        data = {k: f[k] for k in f.files}
    meta = json.loads(str(data.pop("meta")))
    return [
        (m, {k.split("/")[1]: v for k, v in data.items() if k.split("/")[0] == str(e)})
        for e, m in enumerate(meta)
    ]


def replay(env: PredatorPrey, rec: dict) -> dict:
    """The port's episode from the recorded start and actions: observations (T + 1, K,
    obs_dim), rewards (T, K), dones (T,), successes (T,)."""
    step = jax.jit(env.step)
    obs, state = env.state_from(rec["predators"], rec["prey"])
    out = {"obs": [obs], "rewards": [], "dones": [], "success": []}
    for t, actions in enumerate(rec["actions"]):
        obs, state, rewards, dones, info = step(jax.random.key(t), state, actions)
        assert bool(np.all(np.asarray(dones) == bool(state.done)))
        out["obs"].append(obs)
        out["rewards"].append(rewards)
        out["dones"].append(state.done)
        out["success"].append(info["success"])
    return {k: np.stack([np.asarray(x) for x in v]) for k, v in out.items()}


def dense_obs(rec: dict, shape: tuple) -> np.ndarray:
    obs = np.zeros(shape, np.float32)
    obs[tuple(rec["obs_idx"].T)] = rec["obs_val"]
    return obs


def compare(meta: dict, rec: dict) -> list[str]:
    """Where the port and the original differ, one line each (empty: equal)."""
    env = PredatorPrey(PredatorPreyConfig(level=meta["level"], reward_mode=meta["mode"]))
    got = replay(env, rec)
    t = len(rec["actions"])
    want_obs = dense_obs(rec, (t + 1, env.num_agents, env.obs_dim))
    diffs = []
    if not np.array_equal(got["obs"], want_obs):
        bad = np.argwhere(got["obs"] != want_obs)[0]
        diffs.append(f"observations differ first at (time, agent, index) {tuple(bad)}")
    # The original's rewards are float64 sums of float constants; the port's float32.
    if not np.array_equal(got["rewards"], rec["rewards"].astype(np.float32)):
        diffs.append(f"rewards differ at steps {np.argwhere(got['rewards'] != rec['rewards'])}")
    # The original's done is its episode_over; IC3Net's trainer ends the episode at max_steps.
    want_dones = rec["dones"] | (np.arange(t) == env.max_steps - 1)
    if not np.array_equal(got["dones"], want_dones):
        diffs.append(f"dones differ: {got['dones'].tolist()} vs {want_dones.tolist()}")
    # The original sets no stat["success"] under "competitive" (-1 in the fixture).
    want_success, known = rec["success"] == 1, rec["success"] >= 0
    if not np.array_equal(got["success"][known], want_success[known]):
        diffs.append(f"successes differ: {got['success'].tolist()} vs {want_success.tolist()}")
    return diffs


EPISODES = _episodes()


@pytest.mark.parametrize(
    "meta,rec",
    EPISODES,
    ids=[f"{m['level']}-{m['mode']}-{m['kind']}-{m['seed']}" for m, _ in EPISODES],
)
def test_the_port_replays_the_originals_episodes_exactly(meta, rec):
    assert compare(meta, rec) == []


def test_the_fixture_covers_every_level_the_prey_and_the_end():
    levels = {m["level"] for m, r in EPISODES if m["mode"] == "mixed"}
    assert levels == {"easy", "medium", "hard"}
    assert {m["mode"] for m, _ in EPISODES} == {"mixed", "cooperative", "competitive"}
    for level in levels:  # each level has an episode that the original ended (all on the prey)
        assert any(r["dones"][-1] and m["level"] == level for m, r in EPISODES)
    assert sum(len(r["actions"]) for _, r in EPISODES) > 300


def test_the_parity_check_sees_a_difference():
    meta, rec = next((m, r) for m, r in EPISODES if m["kind"] == "chase" and m["level"] == "easy")
    assert compare(meta, rec) == []
    swapped = dict(rec, actions=np.where(rec["actions"] == 1, 3, rec["actions"]))
    assert compare(meta, swapped)  # right and left swapped
    other = dict(rec, rewards=rec["rewards"] + 1e-3)
    assert any("rewards" in d for d in compare(meta, other))
    later = dict(rec, prey=(rec["prey"] + 1) % 5)
    assert compare(meta, later)


def test_levels_and_refusals():
    sizes = {lv: PredatorPrey(PredatorPreyConfig(level=lv)) for lv in ("easy", "medium", "hard")}
    assert [(e.config.dim, e.num_agents, e.config.vision, e.max_steps) for e in sizes.values()] == [
        (5, 3, 0, 20),
        (10, 5, 1, 40),
        (20, 10, 1, 80),
    ]
    assert sizes["easy"].obs_dim == 29 and sizes["hard"].obs_dim == 9 * 404
    with pytest.raises(ValueError, match=r"PredatorPreyConfig.level must be one of .*'medium'"):
        PredatorPreyConfig(level="extreme")
    with pytest.raises(ValueError, match="PredatorPreyConfig.reward_mode"):
        PredatorPreyConfig(reward_mode="selfish")
    assert registry.task_of(PredatorPreyConfig(level="hard")) == "predator_prey"


def test_the_chaser_ends_the_episode_with_success():
    env = PredatorPrey(PredatorPreyConfig(level="medium"))
    _, state = env.reset(jax.random.key(3))
    step = jax.jit(env.step)
    for t in range(env.max_steps):
        _, state, _, _, info = step(jax.random.key(t), state, env.expert_actions(state))
        if bool(state.done):
            break
    assert bool(info["success"]) and t < 2 * env.config.dim
    check_task(env, jax.random.key(2), episodes=2)
