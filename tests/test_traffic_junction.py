"""The JAX port of IC3Net's Traffic Junction (:mod:`sparsecomm.envs.traffic_junction`) against
the original: episodes recorded with ic3net-envs (``tests/data/ic3net_traffic_junction.npz``,
written by ``scripts/record_ic3net_parity.py --tj-out``) are replayed through the port with the
recorded actions and arrivals, and every observation, reward, activity flag and success must be
equal; the routes must be the original's; plus the levels, refusals and conformance check."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from sparsecomm.envs import registry
from sparsecomm.envs.task import check_task
from sparsecomm.envs.traffic_junction import TrafficJunction, TrafficJunctionConfig

FIXTURE = Path(__file__).parent / "data" / "ic3net_traffic_junction.npz"


def _episodes():
    with np.load(FIXTURE) as f:
        data = {k: f[k] for k in f.files}
    meta = json.loads(str(data.pop("meta")))
    return [
        (m, {k.split("/")[1]: v for k, v in data.items() if k.split("/")[0] == str(e)})
        for e, m in enumerate(meta)
    ]


EPISODES = _episodes()
ENVS = {}


def _env(level: str) -> TrafficJunction:
    if level not in ENVS:
        ENVS[level] = TrafficJunction(TrafficJunctionConfig(level=level))
    return ENVS[level]


def compare(meta: dict, rec: dict) -> list[str]:
    """Where the port and the original differ, one line each (empty: equal)."""
    env = _env(meta["level"])
    advance = jax.jit(env.advance)
    obs, state = env.reset(jax.random.key(0))
    got = {"obs": [obs], "rewards": [], "alive": [], "crash_free": [], "done": []}
    for actions, arrivals in zip(rec["actions"], rec["arrivals"], strict=True):
        obs, state, rewards, _, info = advance(state, actions, arrivals)
        for name, value in (
            ("obs", obs),
            ("rewards", rewards),
            ("alive", env.active(state)),
            ("crash_free", info["crash_free"]),
            ("done", state.done),
        ):
            got[name].append(value)
    got = {k: np.stack([np.asarray(x) for x in v]) for k, v in got.items()}
    t = len(rec["actions"])
    want_obs = np.zeros((t + 1, env.num_agents, env.obs_dim), np.float32)
    want_obs[tuple(rec["obs_idx"].T)] = rec["obs_val"]
    diffs = []
    if not np.array_equal(got["obs"], want_obs):
        bad = np.argwhere(got["obs"] != want_obs)[0]
        diffs.append(f"observations differ first at (time, car, index) {tuple(bad)}")
    if not np.array_equal(got["rewards"], rec["rewards"].astype(np.float32)):
        diffs.append(f"rewards differ at {np.argwhere(got['rewards'] != rec['rewards'])[:3]}")
    if not np.array_equal(got["alive"], rec["alive"]):
        diffs.append("active cars differ")
    if not np.array_equal(got["crash_free"], rec["success"] == 1):
        diffs.append("successes differ")
    if not np.array_equal(got["done"], np.arange(1, t + 1) >= env.max_steps):
        diffs.append("dones differ")
    return diffs


@pytest.mark.parametrize(
    "meta,rec", EPISODES, ids=[f"{m['level']}-{m['seed']}-{m['p_gas']}" for m, _ in EPISODES]
)
def test_the_port_replays_the_originals_episodes_exactly(meta, rec):
    assert compare(meta, rec) == []


@pytest.mark.parametrize("level", ["easy", "medium", "hard"])
def test_the_routes_are_the_originals(level):
    rec = next(r for m, r in EPISODES if m["level"] == level)
    env = _env(level)
    assert [len(g) for g in env.routes] == rec["group_sizes"].tolist()
    mine = [p for g in env.routes for p in g]
    assert [len(p) for p in mine] == rec["route_lengths"].tolist()
    assert np.array_equal(np.concatenate(mine), rec["routes"])


def test_the_fixture_has_arrivals_departures_and_crashes():
    for level in ("easy", "medium", "hard"):
        recs = [r for m, r in EPISODES if m["level"] == level]
        assert sum(int((r["arrivals"][..., 0] >= 0).sum()) for r in recs) >= 10
        assert any((r["alive"][:-1] & ~r["alive"][1:]).any() for r in recs)  # cars leave
        assert any((r["rewards"] <= -10).any() for r in recs)
        assert any(r["success"][-1] == 1 for r in recs) or level == "hard"


def test_the_parity_check_sees_a_difference():
    meta, rec = EPISODES[1]
    assert compare(meta, rec) == []
    assert compare(meta, dict(rec, actions=1 - rec["actions"]))
    late = np.concatenate([np.full_like(rec["arrivals"][:1], -1), rec["arrivals"][:-1]])
    assert compare(meta, dict(rec, arrivals=late))


def test_levels_refusals_and_the_conformance_check():
    assert (_env("easy").num_agents, _env("easy").obs_dim) == (5, 17)
    assert (_env("medium").num_agents, _env("medium").obs_dim) == (10, 61)
    assert (_env("hard").num_agents, _env("hard").obs_dim) == (20, 149)
    with pytest.raises(ValueError, match=r"TrafficJunctionConfig.level must be one of"):
        TrafficJunctionConfig(level="rush")
    with pytest.raises(ValueError, match="TrafficJunctionConfig.arrival_rate"):
        TrafficJunctionConfig(arrival_rate=1.5)
    assert registry.task_of(TrafficJunctionConfig()) == "traffic_junction"
    env = _env("medium")
    check_task(env, jax.random.key(2), episodes=2)
    obs, state = env.reset(jax.random.key(0))
    assert not np.asarray(env.active(state)).any() and not np.asarray(obs).any()


def test_drawn_arrivals_follow_the_rate_and_take_inactive_cars():
    env = TrafficJunction(TrafficJunctionConfig(level="easy", arrival_rate=0.3))
    episodes = 64

    def play(key):
        _, state = env.reset(key)

        def body(state, key):
            _, new, *_ = env.step(key, state, jax.numpy.ones(env.num_agents, int))  # all brake
            return new, (state.alive, new.alive)

        return jax.lax.scan(body, state, jax.random.split(key, env.max_steps))[1]

    before, after = jax.jit(jax.vmap(play))(jax.random.split(jax.random.key(5), episodes))
    before, after = np.asarray(before), np.asarray(after)
    assert not (before & ~after).any()  # braking cars never leave; arrivals only add
    added = (after & ~before).sum(-1)  # (episodes, steps): 0, 1 or 2 (two entry points)
    free = (~before).sum(-1) >= 2  # room for both entry points' cars
    rate = added[free].mean() / env.num_entries
    assert abs(rate - 0.3) < 0.05, rate
