"""JaxMARL's MPE simple_reference as a sparsecomm task (``sparsecomm.envs.jaxmarl_reference``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("jaxmarl")

from sparsecomm.channel import ChannelConfig  # noqa: E402
from sparsecomm.configs import RLConfig  # noqa: E402
from sparsecomm.envs.jaxmarl_reference import (  # noqa: E402
    ReferenceConfig,
    ReferenceState,
    SimpleReference,
)
from sparsecomm.rl import make_train  # noqa: E402


def test_sizes_and_observations_follow_the_comm_choice():
    key = jax.random.PRNGKey(0)
    for comm, obs_dim, actions in (("channel", 11, 5), ("none", 11, 5), ("env", 21, 50)):
        env = SimpleReference(ReferenceConfig(comm=comm))
        assert (env.obs_dim, env.num_actions, env.num_agents) == (obs_dim, actions, 2)
        obs, state = jax.jit(env.reset)(key)
        assert obs.shape == (2, obs_dim)
        assert env.global_state(state).shape == (env.state_dim,)
        # the observation is JaxMARL's, cut before the word unless the words are the env's
        theirs = env.mpe.get_obs(state.mpe)
        np.testing.assert_array_equal(obs[1], theirs["agent_1"][:obs_dim])


def test_moves_are_jaxmarls_and_words_reach_the_other_agent():
    key = jax.random.PRNGKey(1)
    env = SimpleReference(ReferenceConfig(comm="env"))
    quiet = SimpleReference(ReferenceConfig(comm="channel"))
    _, state = env.reset(key)
    # agent 0 moves +x (move 2) and says word 7; agent 1 moves -y (move 3) and says word 4
    obs, after, _, _, _ = env.step(key, state, jnp.array([2 + 5 * 7, 3 + 5 * 4]))
    np.testing.assert_array_equal(obs[1, 11:], jax.nn.one_hot(7, 10))
    np.testing.assert_array_equal(obs[0, 11:], jax.nn.one_hot(4, 10))
    # the same moves without words move the agents the same way
    _, moved, _, _, _ = quiet.step(key, state, jnp.array([2, 3]))
    np.testing.assert_allclose(moved.mpe.p_pos, after.mpe.p_pos)
    assert moved.mpe.p_vel[0, 0] > 0 and moved.mpe.p_vel[0, 1] == 0  # +x
    assert moved.mpe.p_vel[1, 1] < 0 and moved.mpe.p_vel[1, 0] == 0  # -y


def test_rewards_time_and_success():
    cfg = ReferenceConfig(comm="none", max_steps=3)
    env = SimpleReference(cfg)
    _, state = env.reset(jax.random.PRNGKey(2))
    # put both agents on their goal landmarks (success, at the last step only), or agent 1 on
    # a landmark that is not its goal (no success)
    goal = state.mpe.goal
    goals = state.mpe.p_pos[2 + goal]
    wrong = goals.at[1].set(state.mpe.p_pos[2 + (goal[1] + 1) % 3])
    on_goal = state.replace(mpe=state.mpe.replace(p_pos=state.mpe.p_pos.at[:2].set(goals)))
    far = state.replace(mpe=state.mpe.replace(p_pos=state.mpe.p_pos.at[:2].set(wrong)))
    for start, succeeds in ((on_goal, True), (far, False)):
        s = start
        for t in range(3):
            _, s, rewards, dones, info = env.step(jax.random.PRNGKey(t), s, jnp.zeros(2, int))
            assert bool(dones.all()) == (t == 2) == bool(s.done)
            assert bool(info["success"]) == (succeeds and t == 2)
            # the two rewards sum to minus the two distances (local_ratio 0.5 or not)
            np.testing.assert_allclose(rewards.sum(), -env.goal_distances(s).sum(), rtol=1e-5)
        assert int(s.time) == 3
    assert isinstance(s, ReferenceState)


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="ReferenceConfig.comm"):
        ReferenceConfig(comm="radio")
    with pytest.raises(ValueError, match="ReferenceConfig.max_steps"):
        ReferenceConfig(max_steps=0)


@pytest.mark.parametrize("comm", ["channel", "env"])
def test_sparsecomms_learner_trains_on_it(comm):
    mode = "discrete" if comm == "channel" else "off"
    cfg = RLConfig(
        env=ReferenceConfig(comm=comm),
        channel=ChannelConfig(mode=mode),
        num_envs=8,
        num_updates=2,
        reward_scale=1.0,
    )
    learner = make_train(cfg)
    state, metrics = jax.jit(learner.train)(jax.random.PRNGKey(3), 0.0)
    assert metrics["episode_length"].tolist() == [25.0, 25.0]
    assert np.isfinite(np.asarray(metrics["loss"])).all()
    assert float(metrics["actor_grad_norm"][0]) > 0
    if comm == "channel":  # the agents talk through the channel: real bits, on every link
        assert float(metrics["bits_per_step"][0]) > 0
        assert float(metrics["wire_bits_per_step"][0]) > float(metrics["bits_per_step"][0])
    else:
        assert float(metrics["bits_per_step"][0]) == 0.0
