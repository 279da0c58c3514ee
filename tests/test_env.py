"""Tests of the hidden-goal navigation environment (SPEC section 4)."""

from __future__ import annotations

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from sparsecomm.envs import NavConfig, NavigationEnv, NavState

CFG = NavConfig()
ENV = NavigationEnv(CFG)
STEP = jax.jit(ENV.step)
RESET = jax.jit(ENV.reset)


def make_state(
    pos, vel=None, goals=None, time=0, done=False, success=False, parked=None
) -> NavState:
    pos = jnp.asarray(pos, jnp.float32)
    return NavState(
        pos=pos,
        vel=jnp.zeros_like(pos) if vel is None else jnp.asarray(vel, jnp.float32),
        goals=jnp.full_like(pos, -0.9) if goals is None else jnp.asarray(goals, jnp.float32),
        time=jnp.asarray(time, jnp.int32),
        done=jnp.asarray(done),
        success=jnp.asarray(success),
        parked=jnp.zeros(pos.shape[0], bool) if parked is None else jnp.asarray(parked),
    )


def reference_step(pos, vel, actions, cfg: NavConfig):
    """float64 NumPy reference of the documented dynamics."""
    directions = {0: (0, 0), 1: (0, 1), 2: (0, -1), 3: (-1, 0), 4: (1, 0)}
    force = np.array([directions[int(a)] for a in actions], np.float64)
    vel = (1 - cfg.damping) * vel + cfg.accel * cfg.dt * force
    pos = np.clip(pos + cfg.dt * vel, -cfg.position_limit, cfg.position_limit)
    return pos, vel


def test_interface_sizes():
    obs, state = RESET(jax.random.PRNGKey(0))
    assert ENV.num_agents == 3 and ENV.num_actions == 5
    assert ENV.obs_dim == 8 and obs.shape == (3, 8) and obs.dtype == jnp.float32
    assert state.pos.shape == state.vel.shape == state.goals.shape == (3, 2)
    assert state.time.dtype == jnp.int32 and state.done.dtype == jnp.bool_
    assert np.all(np.abs(np.asarray(state.pos)) <= 1.0)
    assert np.all(np.abs(np.asarray(state.goals)) <= 1.0)
    assert np.all(np.asarray(state.vel) == 0)
    gs = ENV.global_state(state)
    assert ENV.state_dim == 19 and gs.shape == (19,) and gs.dtype == jnp.float32
    np.testing.assert_array_equal(gs[:6], np.asarray(state.pos).reshape(-1))
    np.testing.assert_array_equal(gs[6:12], np.asarray(state.vel).reshape(-1))
    np.testing.assert_array_equal(gs[12:18], np.asarray(state.goals).reshape(-1))
    assert gs[18] == 0.0
    _, s1, *_ = STEP(jax.random.PRNGKey(1), state, jnp.zeros(3, jnp.int32))
    assert ENV.global_state(s1)[18] == pytest.approx(1 / 256)


def test_dynamics_exact_values():
    state = make_state(
        pos=[[0.0, 0.0], [0.5, -0.5], [1.4, 0.0]],
        vel=[[0.0, 0.0], [1.0, 0.0], [0.5, 0.0]],
    )
    _, s1, *_ = STEP(jax.random.PRNGKey(0), state, jnp.array([1, 3, 4], jnp.int32))
    # vel' = 0.75 vel + 3.0 * 0.1 * dir; pos' = pos + 0.1 vel'
    np.testing.assert_allclose(s1.vel, [[0.0, 0.3], [0.45, 0.0], [0.675, 0.0]], atol=1e-6)
    np.testing.assert_allclose(s1.pos, [[0.0, 0.03], [0.545, -0.5], [1.4675, 0.0]], atol=1e-6)
    # Down and no force.
    _, s2, *_ = STEP(jax.random.PRNGKey(0), s1, jnp.array([2, 0, 0], jnp.int32))
    np.testing.assert_allclose(s2.vel, [[0.0, -0.075], [0.3375, 0.0], [0.50625, 0.0]], atol=1e-6)
    # The last agent would reach x = 1.518125 and is clipped at position_limit = 1.5 (its
    # velocity is not changed by the clipping).
    np.testing.assert_allclose(s2.pos, [[0.0, 0.0225], [0.57875, -0.5], [1.5, 0.0]], atol=1e-6)
    assert float(s2.pos[2, 0]) == 1.5


def test_clipping_at_position_limit():
    state = make_state(
        pos=[[1.49, -1.49], [-1.49, 1.49], [0.0, 0.0]], vel=[[2, -2], [-2, 2], [0, 0]]
    )
    for _ in range(5):
        _, state, *_ = STEP(jax.random.PRNGKey(0), state, jnp.array([4, 3, 0], jnp.int32))
    np.testing.assert_array_equal(np.asarray(state.pos[:2]), [[1.5, -1.5], [-1.5, 1.5]])


def test_dynamics_match_reference_over_random_actions():
    _, state = RESET(jax.random.PRNGKey(3))
    pos, vel = np.asarray(state.pos, np.float64), np.asarray(state.vel, np.float64)
    actions = np.random.default_rng(0).integers(0, 5, size=(200, 3))
    for t in range(200):
        _, state, *_ = STEP(jax.random.PRNGKey(t), state, jnp.asarray(actions[t], jnp.int32))
        pos, vel = reference_step(pos, vel, actions[t], CFG)
    np.testing.assert_allclose(state.vel, vel, atol=1e-4)
    np.testing.assert_allclose(state.pos, pos, atol=1e-4)
    # Terminal speed: accel * dt / damping = 1.2.
    assert CFG.max_speed == pytest.approx(1.2)
    assert np.all(np.abs(np.asarray(state.vel)) <= 1.2 + 1e-5)


def _run_noop(cfg: NavConfig, key, state_fn=None, num_steps=None):
    env = NavigationEnv(cfg)
    num_steps = cfg.max_steps if num_steps is None else num_steps

    def episode(k):
        k0, k1 = jax.random.split(k)
        _, s = env.reset(k0)
        if state_fn is not None:
            s = state_fn(s)

        def body(s, sk):
            _, s2, r, d, info = env.step(sk, s, jnp.zeros(cfg.num_agents, jnp.int32))
            return s2, (d, info, s2.goals, s.goals)

        return jax.lax.scan(body, s, jax.random.split(k1, num_steps))

    return episode


def test_noop_policy_ends_at_exactly_max_steps():
    # Agents parked outside the arena can never reach a goal, so only the time limit ends.
    park = lambda s: s.replace(pos=jnp.full_like(s.pos, 1.5))
    episode = _run_noop(CFG, None, park)
    final, (dones, info, _, _) = jax.jit(jax.vmap(episode))(
        jax.random.split(jax.random.PRNGKey(0), 8)
    )
    dones = np.asarray(dones)  # (E, T, K)
    assert dones.shape == (8, 256, 3)
    assert not dones[:, :255].any()
    assert dones[:, 255].all()
    assert np.all(np.asarray(final.time) == 256) and np.all(np.asarray(final.done))
    assert not np.asarray(final.success).any() and not np.asarray(info["success"]).any()


def test_success_ends_episode_early_with_bonus():
    goals = [[0.0, 0.0], [0.5, 0.5], [-0.5, 0.2]]
    state = make_state(pos=np.array(goals) + [[0.05, 0.0], [0.0, -0.05], [0.03, 0.03]], goals=goals)
    _, s1, rewards, dones, info = STEP(jax.random.PRNGKey(0), state, jnp.zeros(3, jnp.int32))
    assert bool(info["success"]) and np.all(np.asarray(info["in_radius"]))
    assert np.all(np.asarray(dones)) and bool(s1.done) and bool(s1.success)
    assert int(s1.time) == 1
    np.testing.assert_array_equal(rewards, [1200.0, 1200.0, 1200.0])
    # Goals are frozen once the episode is over (whatever the jump draws say).
    np.testing.assert_array_equal(s1.goals, state.goals)
    # Stepping a finished state is allowed: done and success stay set, goals stay frozen.
    cfg1 = NavConfig(goal_jump_prob=1.0)
    env1 = NavigationEnv(cfg1)
    _, s2, _, d2, info2 = env1.step(jax.random.PRNGKey(1), s1, jnp.array([1, 2, 3], jnp.int32))
    assert bool(s2.done) and bool(s2.success) and np.all(np.asarray(d2))
    assert not np.asarray(info2["goal_jumped"]).any()
    np.testing.assert_array_equal(s2.goals, state.goals)


def test_reward_values():
    w_ind, w_grp = 0.5, 0.5 / 3
    goals = np.array([[0.0, 0.0], [0.2, 0.2], [-0.4, 0.6]], np.float32)
    # Distances 0.05 (in radius), 0.5 and 1.0 (along x), zero velocity and no force.
    pos = goals + np.array([[0.05, 0.0], [0.5, 0.0], [0.0, -1.0]], np.float32)
    _, _, rewards, dones, info = STEP(
        jax.random.PRNGKey(0), make_state(pos, goals=goals), jnp.zeros(3, jnp.int32)
    )
    individual = np.array([250.0, -0.25, -1.0])
    expected = w_ind * individual + w_grp * individual.sum()
    np.testing.assert_allclose(rewards, expected, rtol=1e-5)
    np.testing.assert_allclose(info["dist"], [0.05, 0.5, 1.0], rtol=1e-5)
    np.testing.assert_array_equal(info["in_radius"], [True, False, False])
    assert not bool(info["success"]) and not np.asarray(dones).any()
    # For K = 3 the calibration is r_i = 0.5 individual_i + 0.5 mean(individual).
    np.testing.assert_allclose(rewards, 0.5 * individual + 0.5 * individual.mean(), rtol=1e-5)

    # Nobody in the radius: pure negative squared distances. Radius is strict (< 0.1).
    pos = goals + np.array([[0.3, 0.0], [0.0, 0.4], [0.1, 0.0]], np.float32)
    _, _, rewards, _, info = STEP(
        jax.random.PRNGKey(0), make_state(pos, goals=goals), jnp.zeros(3, jnp.int32)
    )
    d = np.asarray(info["dist"], np.float64)
    individual = np.where(d < 0.1, 250.0, -(d**2))
    assert individual[0] == pytest.approx(-0.09, rel=1e-5)
    np.testing.assert_allclose(rewards, w_ind * individual + w_grp * individual.sum(), rtol=1e-5)

    # The weights are config fields.
    env = NavigationEnv(NavConfig(individual_weight=1.0, group_weight=0.0, in_radius_bonus=7.0))
    pos = goals + np.array([[0.05, 0.0], [0.0, 0.4], [0.3, 0.0]], np.float32)
    _, _, rewards, _, _ = env.step(
        jax.random.PRNGKey(0), make_state(pos, goals=goals), jnp.zeros(3, jnp.int32)
    )
    np.testing.assert_allclose(rewards, [7.0, -0.16, -0.09], rtol=1e-5)


def test_observation_layout_and_hidden_own_goal():
    goals = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]], np.float32)
    state = make_state(
        pos=[[1, 2], [3, 4], [5, 6]], vel=[[-1, -2], [-3, -4], [-5, -6]], goals=goals
    )
    obs = np.asarray(ENV.get_obs(state))
    np.testing.assert_allclose(obs[0], [1, 2, -1, -2, 0.3, 0.4, 0.5, 0.6], rtol=1e-6)
    np.testing.assert_allclose(obs[1], [3, 4, -3, -4, 0.1, 0.2, 0.5, 0.6], rtol=1e-6)
    np.testing.assert_allclose(obs[2], [5, 6, -5, -6, 0.1, 0.2, 0.3, 0.4], rtol=1e-6)
    for i in range(3):
        moved = goals.copy()
        moved[i] = [-0.7, -0.8]
        obs2 = np.asarray(ENV.get_obs(state.replace(goals=jnp.asarray(moved))))
        np.testing.assert_array_equal(obs2[i], obs[i])  # own goal invisible
        for j in range(3):
            if j != i:
                assert not np.array_equal(obs2[j], obs[j])  # others see it


def test_observation_for_other_team_sizes():
    env = NavigationEnv(NavConfig(num_agents=4, group_weight=0.125))
    obs, state = env.reset(jax.random.PRNGKey(0))
    assert env.obs_dim == 10 and obs.shape == (4, 10) and env.state_dim == 25
    g = np.asarray(state.goals)
    np.testing.assert_array_equal(obs[2, 4:], g[[0, 1, 3]].reshape(-1))


def test_goal_jump_frequency_and_uniformity():
    num_envs, num_steps, p = 1000, 200, CFG.goal_jump_prob
    cfg = NavConfig(max_steps=10_000)  # no time limit inside the window
    park = lambda s: s.replace(pos=jnp.full_like(s.pos, 1.5))  # success impossible
    episode = _run_noop(cfg, None, park, num_steps=num_steps)
    _, (_, info, new_goals, old_goals) = jax.jit(jax.vmap(episode))(
        jax.random.split(jax.random.PRNGKey(42), num_envs)
    )
    jumped = np.asarray(info["goal_jumped"])  # (E, T, K)
    new_goals, old_goals = np.asarray(new_goals), np.asarray(old_goals)
    n = jumped.size
    rate = jumped.mean()
    sigma = np.sqrt(p * (1 - p) / n)
    assert abs(rate - p) < 4 * sigma, (rate, p, sigma)
    for k in range(3):  # per goal
        sigma_k = np.sqrt(p * (1 - p) / jumped[..., k].size)
        assert abs(jumped[..., k].mean() - p) < 4 * sigma_k
    # Independence between goals: both jump together at rate p^2.
    both = (jumped[..., 0] & jumped[..., 1]).mean()
    assert abs(both - p * p) < 4 * np.sqrt(p * p * (1 - p * p) / jumped[..., 0].size)
    # Goals that did not jump are unchanged; jumped ones moved.
    stay = ~jumped
    np.testing.assert_array_equal(new_goals[stay], old_goals[stay])
    assert np.all(np.any(new_goals[jumped] != old_goals[jumped], axis=-1))
    # New locations are uniform in [-1, 1]^2.
    landed = new_goals[jumped]
    assert len(landed) > 20_000
    assert np.all(np.abs(landed) <= 1.0)
    for axis in range(2):
        ks = stats.kstest(landed[:, axis], stats.uniform(loc=-1, scale=2).cdf)
        assert ks.pvalue > 1e-3, ks
    assert abs(np.corrcoef(landed[:, 0], landed[:, 1])[0, 1]) < 4 / np.sqrt(len(landed))


def test_determinism_same_key_bitwise_identical():
    def rollout(key):
        k0, k1, k2 = jax.random.split(key, 3)
        obs, s = ENV.reset(k0)
        acts = jax.random.randint(k2, (256, 3), 0, 5)

        def body(s, x):
            sk, a = x
            obs, s2, r, d, info = ENV.step(sk, s, a)
            return s2, (obs, r, s2.pos, s2.goals)

        return jax.lax.scan(body, s, (jax.random.split(k1, 256), acts))[1]

    f = jax.jit(rollout)
    a = jax.tree.leaves(f(jax.random.PRNGKey(7)))
    b = jax.tree.leaves(f(jax.random.PRNGKey(7)))
    c = jax.tree.leaves(f(jax.random.PRNGKey(8)))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not np.array_equal(np.asarray(a[2]), np.asarray(c[2]))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("num_agents", 1),
        ("num_agents", 2.5),
        ("max_steps", 0),
        ("goal_jump_prob", -0.1),
        ("goal_jump_prob", 1.5),
        ("success_radius", 0.0),
        ("arena_half_width", -1.0),
        ("position_limit", 0.5),
        ("dt", 0.0),
        ("damping", 1.0),
        ("damping", -0.1),
        ("accel", 0.0),
        ("success_bonus", float("nan")),
        ("group_weight", float("inf")),
    ],
)
def test_config_validation_names_field(field, value):
    with pytest.raises(ValueError, match=rf"NavConfig\.{field}"):
        NavConfig(**{field: value})


def test_config_is_hashable_static_and_documented():
    assert hash(NavConfig()) == hash(NavConfig())
    assert NavConfig(num_agents=4) != NavConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        NavConfig().num_agents = 4  # type: ignore[misc]
    f = jax.jit(lambda cfg, x: x * cfg.accel, static_argnums=0)
    assert float(f(NavConfig(), 2.0)) == 6.0
    # Every field has a docstring right under it (tyro shows them as --help text).
    source = inspect.getsource(NavConfig)
    for field in dataclasses.fields(NavConfig):
        after = source.split(f"    {field.name}:", 1)[1].split("\n", 2)[1]
        assert after.strip().startswith('"""'), field.name
