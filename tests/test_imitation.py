"""Imitation through the channel: loss, experts, DAgger mixing, and a short learning run."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm.configs import AgentConfig, ChannelConfig, ILConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.envs.oracle import oracle_actions
from sparsecomm.imitation import make_imitate
from sparsecomm.rollout import rollout
from sparsecomm.runfolder import load_expert, load_run

TINY = ILConfig(env=NavConfig(max_steps=16), num_envs=4, num_updates=2)


def test_oracle_labels_every_step_and_drives_when_beta_is_one(fast_compile):
    im = make_imitate(TINY)
    params = im.team.init(jax.random.key(0))["actor"]
    traj = rollout(
        im.team,
        im.env,
        TINY.channel,
        params,
        jax.random.key(1),
        4,
        expert=im.expert,
        beta=1.0,
        keep_states=True,
    )
    expect = jax.vmap(jax.vmap(oracle_actions, (0, None)), (0, None))(
        traj.aside.env_states, im.env.config
    )
    np.testing.assert_array_equal(traj.expert_actions, expect)
    np.testing.assert_array_equal(traj.actions, traj.expert_actions)
    learner = rollout(
        im.team, im.env, TINY.channel, params, jax.random.key(1), 4, expert=im.expert, beta=0.0
    )
    assert np.mean(np.asarray(learner.actions) != np.asarray(learner.expert_actions)) > 0.3


def test_beta_schedule_and_lambda_in_loss(fast_compile):
    cfg = dataclasses.replace(TINY, num_updates=4, beta_decay_updates=2)
    im = make_imitate(cfg)
    _, m = jax.jit(jax.vmap(im.train, (None, 0)))(jax.random.key(0), jnp.array([0.0, 1.0]))
    np.testing.assert_allclose(m["beta"][0], [1.0, 0.5, 0.0, 0.0])
    np.testing.assert_allclose(m["loss"][0], m["imitation_loss"][0], rtol=1e-6)
    np.testing.assert_allclose(m["loss"][1], m["imitation_loss"][1] + m["penalty"][1], rtol=1e-5)


def test_learners_get_gradient_only_through_messages_from_others(fast_compile):
    separate = dataclasses.replace(TINY, agent=AgentConfig(share_params=False))
    im = make_imitate(separate)
    params = im.team.init(jax.random.key(0))["actor"]

    def loss_of_agent0(p):
        traj = rollout(
            im.team, im.env, TINY.channel, p, jax.random.key(1), 4, expert=im.expert, beta=1.0
        )
        nll = -jnp.take_along_axis(traj.log_probs, traj.expert_actions[..., None], -1)[..., 0]
        return (nll[..., 0] * traj.valid).sum()

    g = jax.grad(loss_of_agent0)(params)
    assert sum(float(jnp.abs(x[1]).sum()) for x in jax.tree.leaves(g)) > 0
    off = make_imitate(dataclasses.replace(separate, channel=ChannelConfig(mode="off")))
    g = jax.grad(
        lambda p: jnp.sum(
            rollout(
                off.team,
                off.env,
                off.config.channel,
                p,
                jax.random.key(1),
                4,
                expert=off.expert,
                beta=1.0,
            ).log_probs[..., 0, :]
        )
    )(params)
    assert sum(float(jnp.abs(x[1]).sum()) for x in jax.tree.leaves(g)) == 0


@pytest.mark.slow
def test_trained_team_can_be_the_expert(tmp_path, fast_compile):
    from sparsecomm.configs import RLConfig
    from sparsecomm.experiment import Train, train

    rl = RLConfig(env=TINY.env, num_envs=4, num_updates=2)
    train(
        Train(
            config=rl,
            out=tmp_path / "rl",
            chunk=1,
            tensorboard=False,
            eval_episodes=4,
            gif=False,
            progress=False,
        )
    )
    cfg = dataclasses.replace(TINY, expert="checkpoint", expert_checkpoint=str(tmp_path / "rl"))
    with pytest.raises(ValueError, match="needs the expert itself"):
        make_imitate(cfg)  # imitation does not load run folders: runfolder.load_expert does
    im = make_imitate(cfg, load_expert(cfg))
    state, m = jax.jit(im.train)(jax.random.key(0), 0.0)
    assert np.all(np.isfinite(m["imitation_loss"]))
    # The expert's labels are the trained team's greedy actions (checked on the first step,
    # where the team's memory and messages are zeros).
    _, tr, _, rl_actor = load_run(tmp_path / "rl")
    params = jax.tree.map(lambda x: x[0], rl_actor)
    obs, env_state = jax.vmap(im.env.reset)(jax.random.split(jax.random.key(3), 16))
    _, labels = im.expert.step(im.expert.init(16), None, env_state, obs)
    msgs = jnp.zeros((16, 3, 2 * cfg.channel.num_elements))
    _, logits, _ = tr.team.act(params, tr.team.initial_carry(16), obs, msgs)
    np.testing.assert_array_equal(np.asarray(labels), np.asarray(jnp.argmax(logits, -1)))
    with pytest.raises(ValueError, match="expert_checkpoint"):
        ILConfig(expert="checkpoint")


@pytest.mark.parametrize(
    "chan",
    [
        ChannelConfig(),
        ChannelConfig(link_gate=True, on_silence="hold", news_margin=0.1),
    ],
    ids=["paper", "silent_on_news"],
)
def test_team_expert_plays_the_rollouts_greedy_episode(chan, fast_compile):
    """Given the rollout's channel keys, a team expert's actions are the rollout's greedy
    actions at every step: its links (gates, held messages, news) behave as the rollout's."""
    from sparsecomm.configs import RLConfig
    from sparsecomm.imitation import team_expert
    from sparsecomm.learner import make_team
    from sparsecomm.rollout import agent_draws, world_draws

    cfg = RLConfig(
        env=NavConfig(max_steps=24), channel=chan, agent=AgentConfig(message_gate="hard")
    )
    env, team = make_team(cfg)
    actor = team.init(jax.random.key(1))["actor"]
    key, n, t_max = jax.random.key(2), 8, cfg.env.max_steps
    traj = rollout(team, env, chan, actor, key, n, greedy=True)
    expert = team_expert(team, chan, actor)
    reset_keys, env_keys = world_draws(key, n, t_max)
    carry = expert.init(n)
    carry["keys"] = agent_draws(key, n, t_max, env.num_agents, team.num_actions)[0]
    obs, state = jax.vmap(env.reset)(reset_keys)
    speaking = 0.0
    for t in range(t_max):
        carry, actions = expert.step(carry, None, state, obs)
        valid = np.asarray(traj.valid[t])
        np.testing.assert_array_equal(
            np.asarray(actions)[valid], np.asarray(traj.actions[t])[valid]
        )
        obs, state, *_ = jax.vmap(env.step)(env_keys[t], state, actions)
        speaking += float(traj.speaking[t].sum())
    links = t_max * n * env.num_agents * (env.num_agents - 1)
    assert 0 < speaking < links if chan.link_gate else speaking == links


@pytest.mark.slow
def test_short_imitation_lowers_loss_and_raises_success():
    """CI learning test: 140 DAgger updates of 32 episodes from the oracle, on CPU."""
    cfg = ILConfig(num_envs=32, beta_decay_updates=60)
    im = make_imitate(cfg)
    state = im.init(jax.random.key(0), 0.0)
    ev = jax.jit(lambda p: im.evaluate(p, jax.random.key(99), 256))
    before = ev(state.params["actor"])
    state, m = jax.jit(im.update_chunk, static_argnums=1)(state, 140)
    after = ev(state.params["actor"])
    loss = np.asarray(m["imitation_loss"])
    assert loss[-10:].mean() < loss[:10].mean() - 1.0, (loss[:10].mean(), loss[-10:].mean())
    assert float(before["success_rate"]) == 0.0
    assert float(after["success_rate"]) >= 0.2, after
