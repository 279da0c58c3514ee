"""The bit budget: the controller on a problem with a known answer, and in tiny training runs."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm import budget, channel
from sparsecomm.budget import BudgetConfig
from sparsecomm.configs import AgentConfig, ChannelConfig, ExperimentalConfig, ILConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.imitation import make_imitate
from sparsecomm.rl import make_train
from sparsecomm.rollout import rollout


def _track(cfg, bits_of_weight, budget_bits, updates, success=1.0, lam=0.0):
    state = budget.init(cfg, budget_bits, lam)
    step = jax.jit(lambda s, b: budget.update(cfg, s, b, success))
    history = []
    for _ in range(updates):
        w = float(budget.weight(state))
        bits = bits_of_weight(w)
        history.append((w, bits, float(state.target)))
        state = step(state, bits)
    return state, np.array(history)


def test_controller_finds_the_price_that_meets_the_budget():
    # A team whose bits fall with the price as 160 / (1 + w / 0.05): the budget of 16 bits is met
    # at w* = 0.05 * (160 / 16 - 1) = 0.45, which the controller must find from the bits alone.
    cfg = BudgetConfig(halving_updates=20.0, engage_success=0.5, success_ema=1.0)
    state, hist = _track(cfg, lambda w: 160.0 / (1.0 + w / 0.05), 16.0, 600)
    assert float(state.target) == pytest.approx(16.0)
    w, bits, _ = hist[-50:].T
    assert np.all(np.abs(bits - 16.0) / 16.0 < 0.02)
    assert np.all(np.abs(w - 0.45) / 0.45 < 0.03)
    # The target fell gradually: never more than one halving per halving_updates.
    targets = hist[1:, 2][np.isfinite(hist[1:, 2])]
    ratio = targets[1:] / targets[:-1]
    assert np.all(ratio >= 0.5 ** (1 / 20) - 1e-6) and np.all(ratio <= 1.0)


def test_controller_waits_for_success_and_keeps_fixed_lambda_without_budget():
    cfg = BudgetConfig(success_ema=1.0)
    # No success yet: the weight stays the run's lambda and the target is not set.
    state, hist = _track(cfg, lambda w: 100.0, 8.0, 30, success=0.0, lam=0.002)
    assert np.all(hist[:, 0] == pytest.approx(0.002)) and math.isinf(float(state.target))
    # No budget (NaN): a fixed lambda, whatever the bits and the success.
    state, hist = _track(cfg, lambda w: 100.0, float("nan"), 30, success=1.0, lam=0.003)
    assert np.all(hist[:, 0] == pytest.approx(0.003))
    assert math.isnan(float(budget.log(state, 0.003)["bit_target"]))


def test_a_silent_team_stops_paying_for_bits():
    # After engaging, a team that falls silent (0 bits < target) sees the price fall
    # geometrically to the floor: the penalty cannot hold the channel shut.
    cfg = BudgetConfig(success_ema=1.0, dual_lr=0.1, weight_min=1e-5)
    state, hist = _track(cfg, lambda w: 0.0 if w > 0.05 else 200.0, 20.0, 300)
    w = hist[:, 0]
    silent = np.nonzero(w > 0.05)[0]
    assert silent.size > 0  # the price did reach the level that silences this team
    after = w[silent[0] :]
    assert after.min() < 0.05 and np.all(after < 0.06)  # never held above the silencing price
    assert hist[-100:, 1].mean() > 0  # the team talks again part of the time


@pytest.mark.parametrize(
    "bits, message",
    [
        (-1.0, "BudgetConfig.bits must be finite and >= 0"),
        (float("nan"), "BudgetConfig.bits must be finite and >= 0"),
        (241.0, "RLConfig.budget.bits must be <= 240"),
    ],
)
def test_bad_budgets_are_refused_with_the_field_name(bits, message):
    with pytest.raises(ValueError, match=message):
        RLConfig(budget=BudgetConfig(bits=bits))


def test_budget_needs_the_discrete_channel_and_sane_controller_settings():
    with pytest.raises(ValueError, match="ILConfig.budget.bits needs channel.mode 'discrete'"):
        ILConfig(channel=ChannelConfig(mode="continuous"), budget=BudgetConfig(bits=8.0))
    with pytest.raises(ValueError, match="BudgetConfig.dual_lr must be finite and > 0"):
        BudgetConfig(dual_lr=0.0)
    with pytest.raises(ValueError, match="BudgetConfig.hold_success must be in"):
        BudgetConfig(hold_success=1.5)


FAST = BudgetConfig(engage_success=0.0, halving_updates=1.0, dual_lr=0.5, weight_init=0.1)
TINY_RL = RLConfig(env=NavConfig(max_steps=16), num_envs=8, num_updates=40, budget=FAST)


@pytest.mark.slow
def test_tiny_rl_run_moves_its_bits_toward_the_budget(fast_compile):
    tr = make_train(TINY_RL)
    keys = jnp.stack([jax.random.key(0)] * 2)
    train = jax.jit(jax.vmap(tr.train, (0, None, 0)))
    _, m = train(keys, 0.0, jnp.array([jnp.nan, 8.0]))
    bits = np.asarray(m["bits_per_step"])
    free, budgeted = bits[0, -5:].mean(), bits[1, -5:].mean()
    assert bits[1, :3].mean() > 100  # both start near the untrained team's ~170 bits
    assert budgeted < 0.5 * free, (free, budgeted)
    target = np.asarray(m["bit_target"])
    assert np.isnan(target[0]).all() and target[1, -1] == pytest.approx(8.0)


@pytest.mark.slow
def test_a_wire_budget_on_gated_links_makes_them_fall_silent(fast_compile):
    # The gate's price (its sender's expected frame, smooth in g) has a gradient wherever the
    # link speaks, so a wire budget closes links instead of only shortening their codewords.
    gated = ChannelConfig(link_gate=True, on_silence="hold", prices="wire")
    tr = make_train(dataclasses.replace(TINY_RL, channel=gated))
    keys = jnp.stack([jax.random.key(0)] * 2)
    train = jax.jit(jax.vmap(tr.train, (0, None, 0)))
    _, m = train(keys, 0.0, jnp.array([jnp.nan, 24.0]))
    speaking, wire = np.asarray(m["speaking_fraction"]), np.asarray(m["wire_bits_per_step"])
    assert 0.3 < speaking[:, :3].mean() < 0.7  # the gates start half open
    assert speaking[1, -5:].mean() < 0.5 * speaking[0, -5:].mean(), speaking[:, -5:]
    assert wire[1, -5:].mean() < 0.5 * wire[0, -5:].mean()
    np.testing.assert_allclose(m["bit_target"][1, -1], 24.0)


@pytest.mark.slow
@pytest.mark.parametrize("gate, recovers", [("hard", True), ("sigmoid", False)])
def test_silenced_channel_recovers_when_the_budget_is_raised(gate, recovers, fast_compile):
    # Imitation of the oracle: the learners need each other's messages to predict its actions.
    cfg = ILConfig(
        env=NavConfig(max_steps=16),
        agent=AgentConfig(message_gate=gate),
        num_envs=16,
        num_updates=0,
        lr=1e-2,
        beta_decay_updates=0,
        budget=FAST,
    )
    im = make_imitate(cfg)
    chunk = jax.jit(im.update_chunk, static_argnums=1)
    state = jax.jit(im.init)(jax.random.key(0), 0.0, 0.0)  # budget 0: silence
    state, m = chunk(state, 40)
    silent = np.asarray(m["bits_per_step"])[-10:]
    assert silent.max() < 0.5, silent
    raised = state.replace(budget=state.budget.replace(budget=jnp.float32(100.0)))
    state, m = chunk(raised, 50)
    bits, price = np.asarray(m["bits_per_step"]), np.asarray(m["price"])
    assert price.min() < 1e-3  # the price fell: bits were (nearly) free again
    if recovers:  # the hard gate's silence is reversible: the team talks again
        assert bits[-10:].mean() > 50, bits[::5]
    else:  # the sigmoid's silence is the trap the hard gate removes (sigmoid saturated)
        assert bits.max() < 0.5, bits[::5]


def test_hard_gate_is_exactly_silent_and_passes_only_gradients_that_reopen():
    a = jnp.array([-9.0, -2.0, 0.0, 2.0, 9.0])
    z = channel.hard_gate(a)
    np.testing.assert_allclose(z, [0.0, 0.0, 0.5, 1.0, 1.0])
    _, vjp = jax.vjp(channel.hard_gate, a)
    # Cotangent -1 (the loss falls as z grows): passes at the lower edge, not at the upper.
    np.testing.assert_allclose(vjp(-jnp.ones(5))[0], [-0.25, -0.25, -0.25, 0.0, 0.0])
    # Cotangent +1 (e.g. the bit penalty): stopped where z is already 0, passes at z = 1.
    np.testing.assert_allclose(vjp(jnp.ones(5))[0], [0.0, 0.0, 0.25, 0.25, 0.25])
    # A silent element sends the null message: 0 payload bits, whatever the dither.
    m, _ = channel.quantize(jax.random.key(0), channel.hard_gate(jnp.full((1000,), -3.0)), 15)
    assert int(channel.payload_bits(m, "paper").sum()) == 0


def test_target_rises_again_while_the_team_loses_its_success():
    cfg = BudgetConfig(success_ema=1.0, halving_updates=10.0, hold_success=0.8)
    state = budget.init(cfg, 10.0, 0.0)
    step = jax.jit(lambda s, b, ok: budget.update(cfg, s, b, ok))
    for _ in range(15):  # engaged at 100 bits, then 14 updates of success
        state = step(state, 100.0, 1.0)
    low = float(state.target)
    assert low == pytest.approx(100 * 0.5 ** (14 / 10), rel=1e-4)
    for _ in range(5):  # success falls below 0.8 of its best: the target climbs back
        state = step(state, 100.0, 0.5)
    assert float(state.target) == pytest.approx(low * 2 ** (5 / 10), rel=1e-4)
    for _ in range(200):  # ... but never above where it started
        state = step(state, 100.0, 0.5)
    assert float(state.target) == pytest.approx(100.0)
    for _ in range(200):  # and down to the budget, not below, once the team keeps up again
        state = step(state, 5.0, 1.0)
    assert float(state.target) == pytest.approx(10.0)


@pytest.mark.parametrize(
    "share, channel_cfg",
    [
        (True, ChannelConfig()),
        (False, ChannelConfig()),
        (True, ChannelConfig(link_gate=True, prices="wire")),  # g times the expected packet
        (False, ChannelConfig(link_gate=True, prices="wire")),
    ],
)
def test_message_penalty_of_the_head_matches_the_rollout(share, channel_cfg, fast_compile):
    agent = AgentConfig(share_params=share)
    cfg = RLConfig(env=NavConfig(max_steps=6), num_envs=3, agent=agent, channel=channel_cfg)
    tr = make_train(cfg)
    actor = tr.team.init(jax.random.key(0))["actor"]
    traj = rollout(tr.team, tr.env, cfg.channel, actor, jax.random.key(1), 3, keep_hidden=True)
    head = actor["params"]["message"]
    again = tr.team.message_penalty(head, traj.aside.hidden, cfg.channel.link_penalty).sum(-1)
    np.testing.assert_allclose(again, traj.penalty, rtol=1e-5)


@pytest.mark.slow
def test_decoupled_penalty_moves_only_the_message_head_by_its_own_gradient(fast_compile):
    cfg = dataclasses.replace(TINY_RL, budget=FAST, experimental=ExperimentalConfig(decoupled=True))
    tr = make_train(cfg)
    state = tr.init(jax.random.key(0), 0.3)  # a fixed price 0.3, no budget
    new, m = jax.jit(tr.update)(state)
    # Same update without any price: the penalty is then all that differs.
    free, _ = jax.jit(tr.update)(state.replace(budget=state.budget.replace(lam=jnp.float32(0))))
    moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), new.params, free.params)
    head = moved["actor"]["params"].pop("message")
    assert max(head.values()) > 0 and max(jax.tree.leaves(moved)) == 0.0
    # ... and it lowers the penalty of the messages the head would send from the same states.
    np.testing.assert_array_less(0.0, float(m["penalty"]))
    trb = make_train(dataclasses.replace(cfg, experimental=ExperimentalConfig()))  # in the loss
    coupled, _ = jax.jit(trb.update)(state)
    moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), coupled.params, free.params)
    assert max(jax.tree.leaves(moved["actor"]["params"]["Dense_0"])) > 0  # reaches the trunk


@pytest.mark.slow
def test_tiny_rl_run_with_decoupled_penalty_meets_its_budget(fast_compile):
    fast = dataclasses.replace(FAST, dual_lr=0.5)
    decoupled = ExperimentalConfig(decoupled=True)
    tr = make_train(dataclasses.replace(TINY_RL, budget=fast, experimental=decoupled))
    _, m = jax.jit(jax.vmap(tr.train, (0, None, 0)))(
        jnp.stack([jax.random.key(0)] * 2), 0.0, jnp.array([jnp.nan, 8.0])
    )
    bits = np.asarray(m["bits_per_step"])
    assert bits[1, -5:].mean() < 0.5 * bits[0, -5:].mean(), bits[:, ::5]


def test_relief_rate_lets_the_price_fall_fast_below_the_target_and_while_success_is_down():
    cfg = BudgetConfig(success_ema=1.0, dual_lr=0.03, relief_lr=0.3, weight_init=0.01)
    state = budget.init(cfg, 10.0, 0.0)
    step = jax.jit(lambda s, b, ok: budget.update(cfg, s, b, ok))
    state = step(state, 100.0, 1.0)  # engages at 100 bits
    w0 = float(budget.weight(state))
    state = step(state, 150.0, 1.0)  # above target: the slow rise
    target = 100 * 0.5 ** (1 / 50)  # halving every 50 updates
    expected = w0 * math.exp(0.03 * (150 - target) / target)
    assert float(budget.weight(state)) == pytest.approx(expected, rel=1e-4)
    w1 = float(budget.weight(state))
    state = step(state, 0.0, 1.0)  # bits fell off the cliff: relief at the full rate
    assert float(budget.weight(state)) == pytest.approx(w1 * math.exp(-0.3), rel=1e-4)
    w2 = float(budget.weight(state))
    state = step(state, 500.0, 0.1)  # success down: the price falls whatever the bits
    assert float(budget.weight(state)) == pytest.approx(w2 * math.exp(-0.3), rel=1e-4)


def test_relief_floor_bounds_the_fall_to_a_fraction_of_the_last_good_price_then_decays():
    cfg = BudgetConfig(success_ema=1.0, dual_lr=0.03, relief_lr=0.3, relief_floor=0.1)
    state = budget.init(cfg, 10.0, 0.0)
    step = jax.jit(lambda s, b, ok: budget.update(cfg, s, b, ok))
    for _ in range(20):  # engaged, success held, bits above target: the price rises
        state = step(state, 100.0, 1.0)
    good = float(jnp.exp(state.held))  # the price in use at the last update that held success
    assert good == pytest.approx(float(budget.weight(state)), rel=0.02)
    for _ in range(10):  # success down: the price falls fast, but not below 0.1 x good
        state = step(state, 100.0, 0.1)
    # the bound itself falls at dual_lr per update while success stays down (10 updates)
    floor = 0.1 * good * math.exp(-0.03 * 10)
    assert float(budget.weight(state)) == pytest.approx(floor, rel=1e-3)
    unbounded = dataclasses.replace(cfg, relief_floor=None)
    free = budget.init(unbounded, 10.0, 0.0)
    free_step = jax.jit(lambda s, b, ok: budget.update(unbounded, s, b, ok))
    for _ in range(20):
        free = free_step(free, 100.0, 1.0)
    for _ in range(10):
        free = free_step(free, 100.0, 0.1)
    assert float(budget.weight(free)) == pytest.approx(good * math.exp(-3.0), rel=0.02)  # < floor
    for _ in range(300):  # a long failure: the bound decays away to weight_min
        state = step(state, 100.0, 0.1)
    assert float(budget.weight(state)) == pytest.approx(cfg.weight_min, rel=1e-3)


def test_checkpoint_from_before_the_relief_floor_loads_with_held_at_the_current_price(tmp_path):
    from sparsecomm import checkpoint

    state = {"budget": budget.init(BudgetConfig(), 16.0, 0.0).replace(log_weight=jnp.float32(-2.0))}
    old = {"budget": {k: v for k, v in state["budget"].__dict__.items() if k != "held"}}
    checkpoint.save(tmp_path / "ckpt", old, {"what": "a checkpoint written before `held`"})
    back = checkpoint.load(tmp_path / "ckpt", state)
    assert float(back["budget"].held) == -2.0
    assert float(back["budget"].log_weight) == -2.0


@pytest.mark.parametrize("routed", [False, True])
def test_a_per_link_budget_counts_the_bits_of_each_link_that_exists(routed, fast_compile):
    """With ``per_link`` the controller engages from the team's bits per step divided by its
    links per step (K (K - 1) for a full team, the live links of a routed one), and the most a
    budget can ask is one link's most."""
    k = 4
    agent = AgentConfig(hidden=8, gru=8, critic_hidden=8, neighbours=1 if routed else None)
    per_link = dataclasses.replace(FAST, per_link=True)
    links = k if routed else k * (k - 1)
    starts = {}
    for cfg in (FAST, per_link):
        rl = RLConfig(
            env=NavConfig(num_agents=k, max_steps=8),
            agent=agent,
            num_envs=4,
            num_updates=1,
            budget=cfg,
        )
        state, m = jax.jit(make_train(rl).train)(jax.random.key(0), 0.0, 0.5)
        bits = float(m["bits_per_step"][0])
        if routed:
            assert float(m["links_per_step"][0]) == links  # one heard sender per agent
        starts[cfg.per_link] = float(state.budget.start)
        assert bits > links  # both engage above the budget, from what the team sent
    np.testing.assert_allclose(starts[True], starts[False] / links, rtol=1e-6)
    with pytest.raises(ValueError, match="RLConfig.budget.bits must be <= 40"):
        RLConfig(env=NavConfig(num_agents=k), budget=BudgetConfig(bits=41.0, per_link=True))
