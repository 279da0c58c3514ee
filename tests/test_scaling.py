"""Many agents (sparsecomm.scaling, docs/scaling.md): routing by position, per-link costs and
gradients of the links that do not exist, a permutation-invariant inbox, who sees whose goal."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm.channel import slots as by_sender
from sparsecomm.configs import AgentConfig, ChannelConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig, NavigationEnv
from sparsecomm.learner import make_team
from sparsecomm.rollout import episode_metrics, rollout
from sparsecomm.scaling import routing_mask


def _run(cfg: RLConfig, num_envs=2, key=1, **kw):
    env, team = make_team(cfg)
    params = jax.jit(team.init)(jax.random.key(0))["actor"]
    play = jax.jit(lambda p, k: rollout(team, env, cfg.channel, p, k, num_envs, **kw))
    return env, team, params, play(params, jax.random.key(key))


def test_k10_rollouts_compile_and_run_on_cpu_and_masked_links_carry_zero_bits(fast_compile):
    """Under the fixed-width code even the null symbol costs bits: a missing link costs none."""
    env = NavConfig(num_agents=10, max_steps=4, goal_view="ring")
    for agg, code, radius in (("mean", "fixed", None), ("attention", "paper", 0.6)):
        agent = AgentConfig(neighbours=3, radius=radius, aggregate=agg)
        cfg = RLConfig(env=env, channel=ChannelConfig(code=code), agent=agent)
        _, team, _, traj = _run(cfg, num_envs=3, keep_states=True, keep_symbols=True)
        assert team.in_dim == 4 + 2 + (11 if agg == "mean" else 1) + 10  # obs, inbox, id
        m = jax.device_get(episode_metrics(traj))
        assert all(np.isfinite(v) for v in m.values()) and m["bits_per_step"] > 0
        mask = np.asarray(routing_mask(traj.env_states.pos, 3, radius))  # (T, B, K, K)
        assert np.isclose(m["links_per_step"], mask.sum() / mask[..., 0, 0].size)
        if radius is None:
            assert m["links_per_step"] == 30.0  # every agent hears its 3 nearest
        bits = np.asarray(traj.link_bits)  # (T, B, K, K) by sender, recipient; 0 diagonal
        assert not bits[~mask].any() and bits[mask].sum() > 0
        assert not np.asarray(traj.symbols)[~np.asarray(by_sender(mask))].any()  # null symbols
        np.testing.assert_allclose(bits.sum((-2, -1)), traj.payload_bits)


def test_channel_off_has_no_links(fast_compile):
    env = NavConfig(num_agents=5, max_steps=4)
    off = RLConfig(env=env, channel=ChannelConfig(mode="off"), agent=AgentConfig(radius=0.8))
    m = episode_metrics(_run(off, num_envs=2)[3])
    assert m["links_per_step"] == 0 and m["bits_per_step"] == 0 and m["wire_bits_per_step"] == 0


def test_routing_mask_neighbours_and_radius(fast_compile):
    pos = jax.random.uniform(jax.random.key(0), (5, 7, 2), minval=-1, maxval=1)
    mask = np.asarray(routing_mask(pos, 2, None))
    assert (mask.sum(-2) == 2).all() and not mask[..., np.arange(7), np.arange(7)].any()
    dist = np.linalg.norm(np.asarray(pos)[:, :, None] - np.asarray(pos)[:, None], axis=-1)
    for b in range(5):
        for j in range(7):  # the two senders of j are its two nearest
            d = np.where(np.arange(7) == j, np.inf, dist[b, :, j])
            assert set(np.flatnonzero(mask[b, :, j])) == set(np.argsort(d, kind="stable")[:2])
    near = np.asarray(routing_mask(pos, None, 0.5))
    np.testing.assert_array_equal(near, (dist <= 0.5) & ~np.eye(7, dtype=bool))
    both = np.asarray(routing_mask(pos, 2, 0.5))
    np.testing.assert_array_equal(both, mask & near)


def test_masked_links_pass_zero_gradient(fast_compile, aggregate="concat"):
    """Receiver j's log-probabilities at step 1 depend on sender i's message head only through
    the link i -> j at step 0: zero gradient exactly when that link did not exist."""
    env = NavConfig(num_agents=4, max_steps=2)
    agent = AgentConfig(neighbours=1, share_params=False, aggregate=aggregate)
    cfg = RLConfig(env=env, agent=agent)
    env_, team, params, traj = _run(cfg, num_envs=1, keep_states=True)
    mask = np.asarray(routing_mask(traj.env_states.pos[0, 0], 1, None))  # (K, K) at step 0

    def step1_logp(head):
        p = jax.tree.map(lambda x: x, params)
        p["params"]["message"] = head
        tr = rollout(team, env_, cfg.channel, p, jax.random.key(1), 1)
        return tr.log_probs[1, 0].sum(-1)  # (K,) one per receiver

    jac = jax.jacrev(step1_logp)(params["params"]["message"])
    # (K receivers, K senders): size of d logp_j / d (sender i's head)
    size = sum(np.abs(np.asarray(g)).reshape(4, 4, -1).sum(-1) for g in jax.tree.leaves(jac))
    for i in range(4):
        for j in range(4):
            if i != j:
                assert (size[j, i] > 0) == mask[i, j], (i, j, size[j, i], mask[i, j])


@pytest.mark.parametrize("aggregate", ["mean", "attention"])
def test_aggregate_is_permutation_invariant(fast_compile, aggregate):
    _, team = make_team(
        RLConfig(env=NavConfig(num_agents=6), agent=AgentConfig(aggregate=aggregate))
    )
    params = jax.jit(team.init)(jax.random.key(0))["actor"]
    ks = jax.random.split(jax.random.key(1), 4)
    carry = jax.random.normal(ks[0], (3, 6, team.cfg.gru))
    obs = jax.random.normal(ks[1], (3, 6, 4 + 2 * 5))
    inbox = jax.random.uniform(ks[2], (3, 6, 5, 10))
    heard = jax.random.bernoulli(ks[3], 0.6, (3, 6, 5))
    inbox = jnp.where(heard[..., None], inbox, 0.0)
    perm = np.array([3, 0, 4, 2, 1])
    act = jax.jit(team.act)
    out = act(params, carry, obs, inbox.reshape(3, 6, 50), heard)
    permuted = act(params, carry, obs, inbox[:, :, perm].reshape(3, 6, 50), heard[:, :, perm])
    for a, b in zip(out, permuted, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    other = act(params, carry, obs, (inbox + 0.1).reshape(3, 6, 50), heard)
    assert not np.allclose(out[1], other[1])  # it does read its messages


def test_goal_observation_shows_exactly_the_configured_goals():
    for view, count, seen in [
        ("others", 1, [[j for j in range(5) if j != i] for i in range(5)]),
        ("ring", 1, [[(i + 1) % 5] for i in range(5)]),
        ("ring", 3, [[(i + 1) % 5, (i + 2) % 5, (i + 3) % 5] for i in range(5)]),
    ]:
        env = NavigationEnv(NavConfig(num_agents=5, goal_view=view, goal_view_count=count))
        obs, state = jax.jit(env.reset)(jax.random.key(0))
        assert obs.shape == (5, 4 + 2 * len(seen[0])) == (5, env.obs_dim)
        for i in range(5):
            np.testing.assert_array_equal(obs[i, :2], state.pos[i])
            np.testing.assert_array_equal(obs[i, 4:].reshape(-1, 2), state.goals[np.array(seen[i])])


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: NavConfig(goal_view="nearest"), "NavConfig.goal_view"),
        (lambda: NavConfig(num_agents=4, goal_view="ring", goal_view_count=4), "goal_view_count"),
        (lambda: NavConfig(goal_view_count=0), "NavConfig.goal_view_count"),
        (lambda: AgentConfig(neighbours=0), "AgentConfig.neighbours"),
        (lambda: AgentConfig(neighbours=2.5), "AgentConfig.neighbours"),
        (lambda: AgentConfig(radius=-1.0), "AgentConfig.radius"),
        (lambda: AgentConfig(radius=float("inf")), "AgentConfig.radius"),
        (lambda: AgentConfig(aggregate="sum"), "AgentConfig.aggregate"),
        (lambda: RLConfig(agent=AgentConfig(neighbours=3)), r"neighbours must be in \[1, 2\]"),
    ],
)
def test_bad_configs_are_refused_with_the_field_name(make, field):
    with pytest.raises(ValueError, match=field):
        make()
