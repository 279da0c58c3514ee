"""PPO through the channel (``RLConfig.algo = "ppo"``): the clipped objective, the replay of a
batch, resume, bad fields, and a short run that learns."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm.channel import ChannelConfig
from sparsecomm.configs import SMALL_TASK, AgentConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.rl import clipped_policy_loss, make_train
from sparsecomm.rollout import rollout
from sparsecomm.sweep import SweepSpec, run_sweep

TINY = RLConfig(
    env=NavConfig(max_steps=8),
    num_envs=4,
    num_updates=3,
    algo="ppo",
    ppo_epochs=2,
    ppo_minibatches=2,
)


def _log_probs(theta, actions):
    """Log-probabilities (T, B, K) of ``actions`` under logits linear in ``theta``."""
    logits = jnp.tanh(jnp.arange(2 * 3 * 2 * 5).reshape(2, 3, 2, 5) * 0.1 + theta)
    return jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)[..., 0]


def test_clipped_objective_at_ratio_one_is_the_plain_policy_gradient():
    actions = jax.random.randint(jax.random.key(0), (2, 3, 2), 0, 5)
    adv = jax.random.normal(jax.random.key(1), (2, 3, 2))
    theta = jax.random.normal(jax.random.key(2), (2, 3, 2, 5))
    old = _log_probs(theta, actions)

    def clipped(t):
        return clipped_policy_loss(_log_probs(t, actions), old, adv, 0.2)[0].sum()

    def plain(t):
        return -(_log_probs(t, actions) * adv).sum()

    np.testing.assert_allclose(jax.grad(clipped)(theta), jax.grad(plain)(theta), atol=1e-6)
    assert float(clipped(theta)) == pytest.approx(-float(adv.sum()), abs=1e-5)  # -r A at r = 1


def test_clipped_objective_stops_the_gradient_beyond_the_clip():
    lp = jnp.log(jnp.array([1.5, 1.5, 0.5, 0.5]))  # ratios to old log-probs of 0
    adv = jnp.array([1.0, -1.0, 1.0, -1.0])

    def loss(x):
        return clipped_policy_loss(x, jnp.zeros(4), adv, 0.2)[0].sum()

    g = jax.grad(loss)(lp)
    # ratio 1.5 > 1.2 with A > 0, and 0.5 < 0.8 with A < 0: clipped, no gradient; the others
    # keep the unclipped term (the pessimistic one), gradient -r A.
    np.testing.assert_allclose(g, [0.0, 1.5, -0.5, 0.0], atol=1e-6)
    _, ratio = clipped_policy_loss(lp, jnp.zeros(4), adv, 0.2)
    np.testing.assert_allclose(ratio, [1.5, 1.5, 0.5, 0.5], rtol=1e-6)


@pytest.mark.parametrize(
    "channel",
    [ChannelConfig(), ChannelConfig(link_gate=True, on_silence="hold", prices="wire")],
    ids=["paper", "gated-hold"],
)
def test_a_replay_plays_its_episodes_again(channel):
    """A minibatch replayed with the batch's actions and key is the same episodes: the same
    rewards and bits, bit for bit, and the same log-probabilities and penalty at the same
    parameters, to float32 rounding (a matmul over 3 episodes instead of 8 may round otherwise:
    bit for bit on an AVX-512 CPU, 1 ulp apart on an AVX2 one)."""
    cfg = dataclasses.replace(TINY, env=SMALL_TASK, num_envs=8, channel=channel)
    tr = make_train(cfg)
    actor = tr.team.init(jax.random.key(0))["actor"]
    key = jax.random.key(5)
    full = rollout(tr.team, tr.env, cfg.channel, actor, key, 8)
    idx = jnp.array([6, 1, 3])
    again = rollout(
        tr.team, tr.env, cfg.channel, actor, key, 8, episodes=idx, actions=full.actions[:, idx]
    )
    for field in ("actions", "rewards", "payload_bits", "wire_bits", "valid"):
        np.testing.assert_array_equal(getattr(full, field)[:, idx], getattr(again, field))
    for field in ("log_probs", "penalty"):
        got, want = getattr(again, field), getattr(full, field)[:, idx]
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6, err_msg=field)
    # New parameters: the same actions and world, but the messages and log-probs move.
    moved = jax.tree.map(lambda x: x * 1.5, actor)
    other = rollout(
        tr.team, tr.env, cfg.channel, moved, key, 8, episodes=idx, actions=full.actions[:, idx]
    )
    np.testing.assert_array_equal(full.actions[:, idx], other.actions)
    assert not np.allclose(full.log_probs[:, idx], other.log_probs)


def test_the_first_replayed_step_starts_at_ratio_one():
    tr = make_train(dataclasses.replace(TINY, env=SMALL_TASK, num_envs=8))
    params = tr.team.init(jax.random.key(0))
    _, aux = tr.loss(params, jax.random.key(3), 0.0, jnp.zeros((), jnp.int32))
    assert float(aux.metrics["clip_fraction"]) == 0.0
    assert abs(float(aux.metrics["approx_kl"])) < 1e-7


def test_gradients_reach_every_sender_through_the_replay():
    """The replayed messages are differentiable: a receiver's loss moves each sender's
    parameters (separate actors, so each agent's share can be read off)."""
    cfg = dataclasses.replace(TINY, agent=AgentConfig(share_params=False))
    tr = make_train(cfg)
    params = tr.team.init(jax.random.key(0))
    grads = jax.grad(lambda p: tr.loss(p, jax.random.key(1), 0.0, jnp.zeros((), jnp.int32))[0])(
        params
    )
    message_head = grads["actor"]["params"]["message"]["kernel"]
    assert all(float(jnp.abs(message_head[i]).sum()) > 0 for i in range(cfg.env.num_agents))


def test_update_is_deterministic_and_resumes_bit_identically(tmp_path, fast_compile):
    tr = make_train(TINY)
    spec = SweepSpec(seeds=2)
    kw = dict(chunk=1, checkpoint_every=1, tensorboard=False, progress=False)
    full = run_sweep(tr, spec, tmp_path / "a", num_updates=3, **kw).state
    run_sweep(tr, spec, tmp_path / "b", num_updates=1, **kw)  # "dies" after one update
    resumed = run_sweep(tr, spec, tmp_path / "b", num_updates=3, **kw).state
    for x, y in zip(jax.tree.leaves(full.params), jax.tree.leaves(resumed.params), strict=True):
        np.testing.assert_array_equal(x, y)
    rows = (tmp_path / "a" / "metrics.csv").read_text()
    assert rows == (tmp_path / "b" / "metrics.csv").read_text()
    assert "clip_fraction" in rows.splitlines()[0]


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (dict(algo="sac"), "RLConfig.algo must be one of ('a2c', 'ppo'), got 'sac'"),
        (dict(ppo_epochs=0), "RLConfig.ppo_epochs must be >= 1, got 0"),
        (
            dict(ppo_minibatches=3),
            "RLConfig.ppo_minibatches must be >= 1 and, with algo 'ppo', divide num_envs (4)",
        ),
        (dict(ppo_clip=0.0), "RLConfig.ppo_clip must be > 0, got 0.0"),
        (
            dict(channel=ChannelConfig(mode="reinforced")),
            "RLConfig.channel.mode must be a mode whose symbols are not sampled",
        ),
    ],
)
def test_bad_ppo_fields_are_refused_by_name(fields, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        dataclasses.replace(TINY, **fields)
    # the PPO fields do not bind the default learner: 4 minibatches of 3 episodes is no error
    assert RLConfig(num_envs=3).ppo_minibatches == 4


@pytest.mark.slow
def test_a_short_ppo_run_learns_the_small_task():
    """80 updates of 32 episodes (4 epochs of 2 minibatches) on the CPU-sized task take the
    team from ~2% success to ~50% (measured: 0.016 -> 0.500 over 256 evaluation episodes)."""
    cfg = dataclasses.replace(
        TINY, env=SMALL_TASK, num_envs=32, ppo_epochs=4, ppo_minibatches=2, gae_lambda=0.95
    )
    tr = make_train(cfg)
    state = tr.init(jax.random.key(0), 0.0)
    ev = jax.jit(lambda p: tr.evaluate(p, jax.random.key(99), 256))
    before = float(ev(state.params["actor"])["success_rate"])
    state, _ = jax.jit(tr.update_chunk, static_argnums=1)(state, 80)
    after = float(ev(state.params["actor"])["success_rate"])
    assert before < 0.05 and after > 0.25, (before, after)
