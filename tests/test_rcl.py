"""Reinforced communication learning (``ChannelConfig.mode = "reinforced"``), the RCL baseline:
binomial symbols, exact log-probabilities, no gradient through the channel, and a bit cost that
lowers the bits sent."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from sparsecomm.channel import transmit
from sparsecomm.configs import AgentConfig, ChannelConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.rl import make_train
from sparsecomm.rollout import rollout
from sparsecomm.sharding import fast_compile as set_fast_compile

RCL = ChannelConfig(mode="reinforced", levels=15, num_elements=4)


@pytest.fixture(autouse=True, scope="module")
def fast_compile():
    """Compile with most XLA optimisations off: these tiny programs then compile several times
    faster (compilation, not running, dominates this module's time)."""
    previous = set_fast_compile(True)
    yield
    set_fast_compile(previous)


def _send(z, seed=0, cfg=RCL):
    keys = jax.random.split(jax.random.key(seed), z.shape[0])
    return transmit(cfg, z, keys=keys, t=jnp.asarray(3))


def test_symbols_are_binomial_with_mean_levels_z():
    levels = RCL.levels
    grid = jnp.asarray([0.0, 0.05, 0.3, 0.5, 0.77, 1.0])
    b = 4000  # batch of episodes; each z value sits in every batch element
    z = jnp.broadcast_to(grid.reshape(1, 1, 1, 6), (b, 3, 2, 6))
    z_hat = _send(z).z_hat
    m = np.asarray(z_hat) * levels
    assert np.allclose(m, np.round(m), atol=1e-4) and m.min() >= 0 and m.max() <= levels
    m = np.round(m).reshape(-1, 6)
    p = np.asarray(grid)
    se = np.sqrt(levels * p * (1 - p) / m.shape[0])
    assert np.all(np.abs(m.mean(0) - levels * p) <= 4 * se + 1e-9)
    assert np.allclose(m.var(0), levels * p * (1 - p), rtol=0.1, atol=1e-9)
    # wide support at z = 0.5 (P(m = 1) = 15 / 2^15: about 11 of the 24000 draws)
    assert set(range(1, levels)) <= set(np.unique(m[:, 3]))
    assert m[:, 0].max() == 0 and m[:, 5].min() == levels


def test_log_prob_matches_scipy_binomial():
    z = jax.random.uniform(jax.random.key(5), (8, 3, 2, 4), minval=0.02, maxval=0.98)
    sent = _send(z, seed=1)
    z_hat, link, log_prob = sent.z_hat, sent.payload_bits, sent.log_prob
    m = np.round(np.asarray(z_hat) * RCL.levels).astype(int)
    expect = stats.binom.logpmf(m, RCL.levels, np.asarray(z, np.float64)).sum((-2, -1))
    assert log_prob.shape == (8, 3)
    np.testing.assert_allclose(np.asarray(log_prob), expect, rtol=1e-4, atol=1e-3)
    # bits: the paper code's payload bits of the symbols sent
    bits = np.floor(np.log2(m + 1)).sum(-1)
    np.testing.assert_array_equal(np.asarray(link), bits)
    np.testing.assert_array_equal(np.asarray(link).sum((-2, -1)), bits.sum((-2, -1)))


def test_no_gradient_through_the_channel():
    """A receiver's loss has zero gradient w.r.t. a sender's parameters (its only path to them
    is the channel); the sender's own message log-probability does carry gradient. Separate
    actor parameters, so that each agent's share of the gradient can be read off."""
    separate = AgentConfig(share_params=False)
    cfg = RLConfig(env=NavConfig(max_steps=6), num_envs=4, channel=RCL, agent=separate)
    tr = make_train(cfg)
    params = tr.team.init(jax.random.key(0))["actor"]

    def traj(p):
        return rollout(tr.team, tr.env, cfg.channel, p, jax.random.key(1), cfg.num_envs)

    def receivers_loss(p):
        t = traj(p)
        return (t.log_probs[..., 1:, :] * t.valid[..., None, None]).sum()

    def sender_msg_loss(p):
        return traj(p).msg_log_probs[..., 0].sum()

    def norm(g, agent):
        return sum(float(jnp.abs(x[agent]).sum()) for x in jax.tree.leaves(g))

    g = jax.grad(receivers_loss)(params)
    assert norm(g, 0) == 0.0 and norm(g, 1) > 0.0  # agent 1's own policy: nonzero
    g = jax.grad(sender_msg_loss)(params)
    assert norm(g, 0) > 0.0 and norm(g, 1) == 0.0 and norm(g, 2) == 0.0


def test_other_modes_record_zero_message_log_probs():
    cfg = RLConfig(env=NavConfig(max_steps=4), num_envs=2, channel=ChannelConfig(num_elements=2))
    tr = make_train(cfg)
    params = tr.team.init(jax.random.key(0))["actor"]
    t = rollout(tr.team, tr.env, cfg.channel, params, jax.random.key(1), 2)
    assert t.msg_log_probs.shape == (4, 2, 3) and float(jnp.abs(t.msg_log_probs).sum()) == 0.0


@pytest.mark.slow
def test_bit_cost_lowers_bits():
    """Same seed and budget; a per-bit cost makes the senders send fewer bits. gamma = 0 credits
    each step's symbols with that step's cost only (the cleanest signal for a short test)."""

    def bits(cost):
        cfg = RLConfig(
            env=NavConfig(max_steps=16),
            num_envs=16,
            num_updates=20,
            lr=1e-2,
            gamma=0.0,
            channel=dataclasses.replace(RCL, bit_cost=cost),
        )
        _, metrics = jax.jit(make_train(cfg).train)(jax.random.key(0), 0.0)
        return np.asarray(metrics["bits_per_step"])

    free, costly = bits(0.0), bits(50.0)
    assert free[0] == pytest.approx(costly[0])  # same start
    assert costly[-3:].mean() < 0.5 * costly[0]
    assert costly[-3:].mean() < 0.6 * free[-3:].mean()


def test_bit_cost_must_be_non_negative():
    with pytest.raises(ValueError, match="ChannelConfig.bit_cost"):
        ChannelConfig(mode="reinforced", bit_cost=-1.0)
