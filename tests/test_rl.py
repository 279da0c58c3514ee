"""RL through the channel: gradient flow across agents, determinism, resume, learning."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm import checkpoint
from sparsecomm.channel import link_tables
from sparsecomm.configs import AgentConfig, ChannelConfig, ExperimentalConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.errors import CheckpointError
from sparsecomm.rl import discounted_targets, make_train, penalty_schedule
from sparsecomm.rollout import rollout
from sparsecomm.sweep import SweepSpec, run_sweep

TINY = RLConfig(env=NavConfig(max_steps=8), num_envs=4, num_updates=3)


def _receiver_grads(mode: str, receiver: int):
    """Gradients of one receiver's log-probabilities with respect to every agent's own actor
    parameters (separate parameters, so each agent's share can be read off)."""
    separate = AgentConfig(share_params=False)
    cfg = dataclasses.replace(TINY, channel=ChannelConfig(mode=mode), agent=separate)
    tr = make_train(cfg)
    params = tr.team.init(jax.random.key(0))["actor"]

    def receiver_loss(p):
        traj = rollout(tr.team, tr.env, cfg.channel, p, jax.random.key(1), cfg.num_envs)
        return (traj.log_probs[..., receiver, :] * traj.valid[..., None]).sum()

    return jax.grad(receiver_loss)(params)


def _agent_norm(grads, agent):
    return sum(float(jnp.abs(g[agent]).sum()) for g in jax.tree.leaves(grads))


@pytest.mark.parametrize("mode", ["discrete", "continuous"])
def test_gradient_flows_from_receiver_into_every_sender(mode, fast_compile):
    grads = _receiver_grads(mode, receiver=2)
    for sender in (0, 1):
        assert _agent_norm(grads, sender) > 0.0
    # Specifically into the sender's message head.
    assert float(jnp.abs(grads["params"]["message"]["kernel"][0]).sum()) > 0.0


def test_no_gradient_between_agents_without_communication(fast_compile):
    grads = _receiver_grads("off", receiver=2)
    assert _agent_norm(grads, 2) > 0.0
    for sender in (0, 1):
        assert _agent_norm(grads, sender) == 0.0


def test_link_tables_route_each_link_to_its_recipient():
    sender, slot = link_tables(4)
    recipients = np.array([[j for j in range(4) if j != i] for i in range(4)])
    for j in range(4):
        assert list(sender[j]) == [i for i in range(4) if i != j]
        for s in range(3):
            assert recipients[sender[j, s], slot[j, s]] == j


def test_returns_are_monte_carlo_and_stop_at_episode_end():
    r = jnp.array([1.0, 2.0, 3.0, 5.0])[:, None, None]
    valid = jnp.array([True, True, True, False])[:, None]
    dones = jnp.array([False, False, True, False])[:, None]
    v = jnp.zeros_like(r)
    adv, target = discounted_targets(r * valid[..., None], v, dones, valid, 0.5, 1.0)
    np.testing.assert_allclose(target[:, 0, 0], [1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3, 3, 0])


def test_training_is_deterministic(fast_compile):
    tr = make_train(TINY)
    a = jax.jit(tr.train)(jax.random.key(3), 0.0)
    b = jax.jit(tr.train)(jax.random.key(3), 0.0)
    for x, y in zip(jax.tree.leaves(a[0].params), jax.tree.leaves(b[0].params), strict=True):
        np.testing.assert_array_equal(x, y)


def test_pricing_after_the_time_loop_equals_pricing_each_step(monkeypatch, fast_compile):
    """``ChannelConfig.prices_later``: the rollout prices the wire after its scan; the same
    penalty, step by step, and the same gradients as the price each step's ``transmit`` makes."""
    channel_cfg = ChannelConfig(
        prices="wire", link_gate=True, on_silence="hold", check_bits=16, news_margin=0.1
    )
    cfg = dataclasses.replace(TINY, channel=channel_cfg)
    tr = make_train(cfg)
    params = tr.team.init(jax.random.key(0))["actor"]

    def penalty(p):
        traj = rollout(tr.team, tr.env, cfg.channel, p, jax.random.key(1), cfg.num_envs)
        return traj.penalty

    def total(p):
        return (penalty(p) * jnp.arange(1.0, 9.0)[:, None]).sum()  # each step weighed apart

    assert channel_cfg.prices_later
    later, later_grad = penalty(params), jax.grad(total)(params)
    monkeypatch.setattr(ChannelConfig, "prices_later", property(lambda self: False))
    each, each_grad = penalty(params), jax.grad(total)(params)
    assert float(later.min()) > 0 and later.shape == (8, cfg.num_envs)
    np.testing.assert_allclose(later, each, rtol=1e-6)
    for a, b in zip(jax.tree.leaves(later_grad), jax.tree.leaves(each_grad), strict=True):
        # float32 sums in another order: each element to 1e-4 of itself, or to 1e-6 of the
        # leaf's largest (an element near 0 among ones near 1e3 keeps only the absolute error;
        # a fixed atol of 1e-6 failed by 4.6e-6 on an Intel Xeon, passed on an AMD EPYC)
        atol = 1e-6 * float(np.abs(b).max())
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=atol)
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(later_grad)) > 0


def test_bits_and_penalty_logged_from_real_symbols(fast_compile):
    def metrics(mode):
        cfg = dataclasses.replace(TINY, channel=ChannelConfig(mode=mode))
        tr = make_train(cfg)
        params = tr.team.init(jax.random.key(0))["actor"]
        return jax.jit(lambda p: tr.evaluate(p, jax.random.key(1), 16))(params)

    m = metrics("discrete")
    # 3 agents x 2 recipients x 10 elements; payload bits at most 4 each. On the wire, each
    # sender with a speaking link sends one frame: a 2-bit recipient map, each speaking link's
    # 10-bit bitmap and codewords (2 P bits for P payload bits), padding to a byte (at most 6
    # bits: the body is even) and a 32-bit CRC; a silent sender sends nothing.
    bits, wire = m["bits_per_step"], m["wire_bits_per_step"]
    assert 0 < bits <= 60 * 4
    assert 2 * bits < wire <= 2 * bits + 3 * (2 + 2 * 10 + 6 + 32)
    assert m["penalty"] >= m["bits_per_step"]  # the bound holds on average here too
    off = metrics("off")
    assert off["bits_per_step"] == 0 and off["wire_bits_per_step"] == 0 and off["penalty"] == 0
    cont = metrics("continuous")
    assert cont["bits_per_step"] == 60 * 32 and cont["penalty"] == 0
    # 3 frames of 2 links of 10 non-zero floats: a 2-bit map, two 10-bit bitmaps and 640 bits
    # of floats (662 bits, padded to 83 bytes), then 4 bytes of CRC.
    assert cont["wire_bits_per_step"] == 3 * 8 * (83 + 4)


@pytest.mark.slow
def test_lambda_lowers_bits(fast_compile):
    cfg = dataclasses.replace(TINY, num_updates=30, lr=3e-3)
    tr = make_train(cfg)
    _, m = jax.jit(jax.vmap(tr.train, (None, 0)))(jax.random.key(0), jnp.array([0.0, 1.0]))
    bits = np.asarray(m["bits_per_step"])[:, -5:].mean(1)
    assert bits[1] < 0.5 * bits[0]


def test_penalty_schedule_delays_and_ramps_the_weight(fast_compile):
    def f(u, delay, ramp):
        return float(penalty_schedule(jnp.asarray(u), delay, ramp))

    assert f(0, 0, 0) == 1.0 and f(4, 5, 0) == 0.0 and f(5, 5, 0) == 1.0
    assert [f(u, 2, 4) for u in range(8)] == [0, 0, 0.25, 0.5, 0.75, 1, 1, 1]
    cfg = dataclasses.replace(TINY, experimental=ExperimentalConfig(penalty_delay=2))
    _, m = jax.jit(make_train(cfg).train)(jax.random.key(0), 1.0)
    w = np.asarray(m["penalty_weight"])
    assert w[0] == w[1] == 0.0 and w[2] > 0.0


def test_resume_gives_same_parameters_as_uninterrupted_run(tmp_path, fast_compile):
    tr = make_train(TINY)
    spec = SweepSpec(seeds=2, lams=(0.0, 0.01))
    kw = dict(
        chunk=1,
        checkpoint_every=1,
        tensorboard=False,
        progress=False,
    )
    full = run_sweep(tr, spec, tmp_path / "a", num_updates=4, **kw).state
    run_sweep(tr, spec, tmp_path / "b", num_updates=2, **kw)  # "dies" after 2 updates
    resumed = run_sweep(tr, spec, tmp_path / "b", num_updates=4, **kw).state
    for x, y in zip(jax.tree.leaves(full.params), jax.tree.leaves(resumed.params), strict=True):
        np.testing.assert_array_equal(x, y)
    rows_a = (tmp_path / "a" / "metrics.csv").read_text()
    assert rows_a == (tmp_path / "b" / "metrics.csv").read_text()
    # A longer budget extends a finished run: the same parameters as one started with it.
    longer = dataclasses.replace(TINY, num_updates=TINY.num_updates + 2)
    run_sweep(tr, spec, tmp_path / "c", num_updates=2, **kw)
    extended = run_sweep(make_train(longer), spec, tmp_path / "c", num_updates=4, **kw).state
    for x, y in zip(jax.tree.leaves(full.params), jax.tree.leaves(extended.params), strict=True):
        np.testing.assert_array_equal(x, y)
    # The checkpoint is msgpack + JSON (no pickle) and a different config refuses to resume.
    assert checkpoint.load_meta(tmp_path / "b" / "checkpoint")["lams"] == [0.0, 0.01]
    other = dataclasses.replace(TINY, lr=0.5)
    with pytest.raises(CheckpointError, match=r"config.lr \(checkpoint: 0.001, now: 0.5\)"):
        run_sweep(make_train(other), spec, tmp_path / "b", num_updates=4, **kw)
    # How a run is driven may change on resume: another chunk size is fine.
    again = run_sweep(tr, spec, tmp_path / "b", num_updates=4, **{**kw, "chunk": 3})
    for x, y in zip(jax.tree.leaves(full.params), jax.tree.leaves(again.state.params), strict=True):
        np.testing.assert_array_equal(x, y)


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="RLConfig.lr must be > 0"):
        RLConfig(lr=0.0)
    with pytest.raises(ValueError, match="ChannelConfig.mode must be one of"):
        ChannelConfig(mode="analog")
    with pytest.raises(ValueError, match="lams"):
        SweepSpec(lams=(-1.0,))


@pytest.mark.slow
def test_short_training_improves_the_team():
    """CI learning smoke test: 40 updates of 32 episodes raise the group reward clearly."""
    cfg = RLConfig(num_envs=32, lr=1e-3)
    tr = make_train(cfg)
    state = tr.init(jax.random.key(0), 0.0)
    ev = jax.jit(lambda p: tr.evaluate(p, jax.random.key(99), 256))
    before = float(ev(state.params["actor"])["group_reward"])
    state, _ = jax.jit(tr.update_chunk, static_argnums=1)(state, 40)
    after = float(ev(state.params["actor"])["group_reward"])
    assert after > before + 500, (before, after)


@pytest.mark.parametrize("shape", [(64, 64), (64, 192), (192, 64)])
def test_orthogonal_init_is_orthogonal_and_random(shape):
    from sparsecomm.agents import orthogonal

    q = np.asarray(orthogonal()(jax.random.key(0), shape), np.float64)
    gram = q.T @ q if shape[0] >= shape[1] else q @ q.T
    np.testing.assert_allclose(gram, np.eye(gram.shape[0]), atol=1e-5)
    assert not np.allclose(q, np.asarray(orthogonal()(jax.random.key(1), shape)))


def test_learning_rate_decays_linearly_then_stays():
    cfg = dataclasses.replace(TINY, lr=1e-3, lr_final=1e-4, lr_decay_steps=10)
    lr = cfg.learning_rate()
    np.testing.assert_allclose(
        [lr(0), lr(5), lr(10), lr(50)], [1e-3, 5.5e-4, 1e-4, 1e-4], rtol=1e-6
    )
    assert TINY.learning_rate() == TINY.lr  # the default: constant, no schedule state
    with pytest.raises(ValueError, match="RLConfig.lr_decay_steps must be >= 1 when lr_final"):
        dataclasses.replace(TINY, lr_final=1e-4)
    with pytest.raises(ValueError, match="RLConfig.lr_final must be None or > 0, got 0.0"):
        dataclasses.replace(TINY, lr_final=0.0, lr_decay_steps=3)

    # Two updates each: the first at 1e-3 on both sides, the second at 1e-5 with the decay.
    def deltas(config):
        tr = make_train(config)
        first, _ = tr.update(tr.init(jax.random.key(0), 0.0))
        second, _ = tr.update(first)
        leaves = zip(jax.tree.leaves(second.params), jax.tree.leaves(first.params), strict=True)
        return first.params, sum(float(jnp.abs(a - b).sum()) for a, b in leaves)

    (p_decay, d_decay), (p_const, d_const) = (
        deltas(dataclasses.replace(TINY, lr_final=1e-5, lr_decay_steps=1)),
        deltas(TINY),
    )
    for x, y in zip(jax.tree.leaves(p_decay), jax.tree.leaves(p_const), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-7)
    assert 0.003 < d_decay / d_const < 0.03, (d_decay, d_const)
