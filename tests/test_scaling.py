"""Many agents (sparsecomm.scaling, docs/scaling.md): routing by position, per-link costs and
gradients of the links that do not exist, a permutation-invariant inbox, who sees whose goal."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm.channel import listed_pairs
from sparsecomm.channel import slots as by_sender
from sparsecomm.configs import AgentConfig, ChannelConfig, ExperimentalConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig, NavigationEnv
from sparsecomm.learner import make_team
from sparsecomm.rollout import episode_metrics, rollout
from sparsecomm.scaling import nearest_senders, routing_mask


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
        mask = np.asarray(routing_mask(traj.aside.env_states.pos, 3, radius))  # (T, B, K, K)
        assert np.isclose(m["links_per_step"], mask.sum() / mask[..., 0, 0].size)
        if radius is None:
            assert m["links_per_step"] == 30.0  # every agent hears its 3 nearest
        bits = np.asarray(traj.link_bits)  # (T, B, K, K) by sender, recipient; 0 diagonal
        assert not bits[~mask].any() and bits[mask].sum() > 0
        null = ~np.asarray(by_sender(mask))
        assert not np.asarray(traj.aside.symbols)[null].any()  # the null symbols
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
    ring = np.asarray(routing_mask(pos, 2, None, hears="ring"))  # j hears j - 1 and j - 2
    want = np.array([[(j - i) % 7 in (1, 2) for j in range(7)] for i in range(7)])
    np.testing.assert_array_equal(ring, np.broadcast_to(want, ring.shape))
    for hears in ("nearest", "ring"):  # the listing is the mask, by recipient
        senders, live = nearest_senders(pos, 2, 0.5, hears)
        np.testing.assert_array_equal(listed_pairs(live, senders), routing_mask(pos, 2, 0.5, hears))


@pytest.mark.parametrize("aggregate", ["concat", "mean"])  # masked, and only the live links
def test_masked_links_pass_zero_gradient(fast_compile, aggregate):
    """Receiver j's log-probabilities at step 1 depend on sender i's message head only through
    the link i -> j at step 0: zero gradient exactly when that link did not exist."""
    env = NavConfig(num_agents=4, max_steps=2)
    agent = AgentConfig(neighbours=1, share_params=False, aggregate=aggregate)
    cfg = RLConfig(env=env, agent=agent)
    env_, team, params, traj = _run(cfg, num_envs=1, keep_states=True)
    mask = np.asarray(routing_mask(traj.aside.env_states.pos[0, 0], 1, None))  # (K, K) at step 0

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


def test_an_agent_parks_only_slow_inside_its_radius_and_then_stays():
    """``success_rule = each``: agent 0 arrives slowly (parks), agent 1 crosses its goal at
    full speed (does not), agent 2 is far; a parked agent ignores its actions, keeps its goal
    (jumps every step here) and its in-radius term; the team succeeds when all have parked."""
    cfg = NavConfig(num_agents=3, success_rule="each", goal_jump_prob=1.0, max_steps=50)
    env = NavigationEnv(cfg)
    goals = jnp.array([[0.0, 0.0], [0.5, 0.5], [-0.8, 0.8]])
    state = env.reset(jax.random.key(0))[1].replace(
        pos=jnp.array([[0.01, 0.0], [0.44, 0.5], [0.9, -0.9]]),
        vel=jnp.array([[0.0, 0.0], [1.2, 0.0], [0.0, 0.0]]),
        goals=goals,
    )
    step = jax.jit(env.step)
    _, state, rewards, _, info = step(jax.random.key(1), state, jnp.array([0, 4, 0]))
    np.testing.assert_array_equal(state.parked, [True, False, False])
    np.testing.assert_array_equal(info["in_radius"], [True, True, False])  # 1 is fast, inside
    assert not info["success"] and not state.done
    np.testing.assert_array_equal(state.goals[0], goals[0])  # a parked goal does not jump
    assert not np.allclose(state.goals[1:], goals[1:])  # the others jumped (probability 1)
    pos0 = state.pos[0]
    _, state, rewards, _, info = step(jax.random.key(2), state, jnp.array([4, 0, 0]))
    np.testing.assert_array_equal(state.pos[0], pos0)  # its action (right) is ignored
    np.testing.assert_array_equal(state.vel[0], [0.0, 0.0])
    assert info["in_radius"][0] and rewards[0] > 0  # still 0.5 * 250 + the group term
    # every agent parked: success, the bonus, the episode ends
    done = state.replace(
        parked=jnp.array([True, True, False]), pos=state.pos.at[2].set(state.goals[2])
    )
    _, done, rewards, dones, info = step(jax.random.key(3), done, jnp.array([0, 0, 0]))
    assert info["success"] and done.success and dones.all()
    np.testing.assert_array_equal(rewards, [cfg.success_bonus] * 3)


@pytest.mark.parametrize("k", [3, 10, 30])
def test_many_agent_task_brackets_oracle_and_centre(k):
    """The many-agent task's brackets (``success_rule = each``, goal jumps on): the oracle that
    sees every goal succeeds in every episode at any K, the best silent scripted policy (drive
    to the centre) in none."""
    from sparsecomm.configs import SMALL_TASK
    from sparsecomm.envs.oracle import center_actions, oracle_actions, run_policy_episodes

    cfg = dataclasses.replace(
        SMALL_TASK, num_agents=k, goal_view="ring", success_rule="each", group_weight=0.5 / k
    )
    oracle = run_policy_episodes(jax.random.key(k), cfg, oracle_actions, 200)
    centre = run_policy_episodes(jax.random.key(k), cfg, center_actions, 200)
    assert float(np.mean(oracle.success)) == 1.0 and np.mean(oracle.length) < 40
    assert float(np.mean(centre.success)) <= 0.01
    # under the paper's rule the oracle loses episodes to goal jumps as K grows
    together = run_policy_episodes(
        jax.random.key(k), dataclasses.replace(cfg, success_rule="together"), oracle_actions, 200
    )
    assert float(np.mean(together.success)) < 1.0 or k == 3


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: NavConfig(goal_view="nearest"), "NavConfig.goal_view"),
        (lambda: NavConfig(num_agents=4, goal_view="ring", goal_view_count=4), "goal_view_count"),
        (lambda: NavConfig(goal_view_count=0), "NavConfig.goal_view_count"),
        (lambda: NavConfig(success_rule="all"), "NavConfig.success_rule"),
        (lambda: NavConfig(park_speed=-0.1), "NavConfig.park_speed"),
        (lambda: AgentConfig(neighbours=0), "AgentConfig.neighbours"),
        (lambda: AgentConfig(neighbours=2.5), "AgentConfig.neighbours"),
        (lambda: AgentConfig(radius=-1.0), "AgentConfig.radius"),
        (lambda: AgentConfig(radius=float("inf")), "AgentConfig.radius"),
        (lambda: AgentConfig(aggregate="sum"), "AgentConfig.aggregate"),
        (lambda: AgentConfig(hears="far"), "AgentConfig.hears"),
        (lambda: AgentConfig(hears="ring"), "AgentConfig.hears 'ring' needs"),
        (lambda: RLConfig(agent=AgentConfig(neighbours=3)), r"neighbours must be in \[1, 2\]"),
    ],
)
def test_bad_configs_are_refused_with_the_field_name(make, field):
    with pytest.raises(ValueError, match=field):
        make()


@pytest.mark.parametrize(
    "channel_cfg",
    [
        ChannelConfig(),
        ChannelConfig(code="fixed", check_bits=16),
        ChannelConfig(link_gate=True),
        ChannelConfig(mode="continuous"),
    ],
    ids=["paper", "fixed", "gated", "continuous"],
)
def test_listed_live_links_are_the_masked_links_bit_for_bit(channel_cfg):
    """The K k live links listed by recipient carry exactly what the masked K (K - 1) links
    carry on those links: symbols, messages, penalty, payload and wire bits, frames, and the
    gradient with respect to each link's signal; a listed link outside the radius costs and
    passes nothing."""
    from sparsecomm import channel

    b, k, nb = 3, 10, 3
    keys = jax.random.split(jax.random.key(0), 4)
    pos = jax.random.uniform(keys[0], (b, k, 2), minval=-1, maxval=1)
    z = jax.random.uniform(keys[1], (b, k, k - 1, channel_cfg.signal_elements))
    z = jnp.where(jax.random.uniform(keys[2], z.shape[:-1] + (1,)) < 0.3, 0.0, z)  # some silent
    chan_keys, t = jax.random.split(keys[3], b), 5
    senders, live = nearest_senders(pos, nb, 0.8)
    assert senders.shape == live.shape == (b, k, nb) and not live.all() and live.any()
    mask = routing_mask(pos, nb, 0.8)
    np.testing.assert_array_equal(channel.listed_pairs(live, senders), mask)

    def masked(z):
        u = channel.step_dither(channel_cfg, chan_keys, t, k)
        return channel.transmit(channel_cfg, z, u, chan_keys, t, live=by_sender(mask)), u

    def listed(z):
        u = channel.listed_dither(channel_cfg, chan_keys, t, senders)
        zl = channel.listed(z, senders, 1)
        return channel.transmit(channel_cfg, zl, u, chan_keys, t, live=live, senders=senders), u

    (full, u_full), (mine, u_mine) = masked(z), listed(z)
    if u_full is not None:
        np.testing.assert_array_equal(channel.listed(u_full, senders, 1), u_mine)
    for name in ("symbols", "z_hat", "penalty", "payload_bits", "wire_bits", "frame_bits"):
        a, g = getattr(full, name), getattr(mine, name)
        if a is None:
            assert g is None
            continue
        np.testing.assert_array_equal(channel.listed(a, senders, a.ndim - 3), g, err_msg=name)
    assert float(mine.wire_bits.sum()) == float(full.wire_bits.sum()) > 0  # every frame counted
    for name in ("payload_bits", "wire_bits", "penalty"):
        assert not np.asarray(getattr(mine, name))[~np.asarray(live)].any()

    def loss(sent):
        w = jnp.linspace(0.5, 1.5, sent.z_hat.shape[-1])
        return (sent.z_hat * w).sum() + sent.penalty.sum()

    g_full = jax.grad(lambda z: loss(masked(z)[0]))(z)
    g_mine = jax.grad(lambda z: loss(listed(z)[0]))(z)
    np.testing.assert_array_equal(g_mine, jnp.where(by_sender(mask)[..., None], g_full, 0.0))
    assert np.abs(np.asarray(g_mine)).sum() > 0


@pytest.mark.parametrize(
    "aggregate, hears", [("mean", "nearest"), ("attention", "nearest"), ("mean", "ring")]
)
def test_a_k10_team_on_live_links_plays_as_on_masked_links(fast_compile, aggregate, hears):
    """A K = 10 team hearing its 2 nearest: the rollout on the live links alone plays the same
    episodes as the masked one (actions, bits of every link; the ``mean`` inbox bit for bit, the
    attention's softmax over 2 senders instead of 9 to float32 rounding) with the same
    gradients (to float32 rounding: sums over other numbers of zeros)."""
    env = NavConfig(num_agents=10, max_steps=6, goal_view="ring")
    agent = AgentConfig(neighbours=2, aggregate=aggregate, hears=hears)
    runs = {}
    for only in (True, False):
        cfg = RLConfig(env=env, agent=agent, experimental=ExperimentalConfig(live_links_only=only))
        env_, team = make_team(cfg)
        params = jax.jit(team.init)(jax.random.key(0))["actor"]

        def play(p, cfg=cfg, env_=env_, team=team):
            return rollout(team, env_, cfg.channel, p, jax.random.key(3), 4)

        def loss(p, play=play):
            tr = play(p)
            return (tr.log_probs.max(-1) * tr.valid[..., None]).sum() + tr.penalty.sum()

        runs[only] = jax.jit(play)(params), jax.jit(jax.grad(loss))(params)
    (mine, g_mine), (full, g_full) = runs[True], runs[False]
    for name in ("actions", "rewards", "link_bits", "payload_bits", "speaking"):
        np.testing.assert_array_equal(getattr(mine, name), getattr(full, name), err_msg=name)
    np.testing.assert_array_equal(mine.aside.links, full.aside.links)
    for name in ("wire_bits", "penalty", "datagram_bits"):  # sums of other lengths
        np.testing.assert_allclose(getattr(mine, name), getattr(full, name), rtol=1e-6)
    if aggregate == "mean":
        np.testing.assert_array_equal(mine.log_probs, full.log_probs)
    np.testing.assert_allclose(mine.log_probs, full.log_probs, rtol=0, atol=1e-5)
    for a, g in zip(jax.tree.leaves(g_mine), jax.tree.leaves(g_full), strict=True):
        np.testing.assert_allclose(a, g, rtol=1e-4, atol=1e-5 * float(np.abs(g).max()))
    assert float(mine.aside.links.mean()) == 20.0 and float(mine.payload_bits.sum()) > 0
