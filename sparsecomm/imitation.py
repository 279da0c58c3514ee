"""Imitation of an expert's actions through the channel (paper eq. 4, SPEC section 5).

Each update plays ``num_envs`` episodes with the same :func:`sparsecomm.rollout.rollout` as RL.
The expert labels every step; with probability ``beta`` its action is executed, otherwise the
learners' own sampled action (``beta = 1``: behaviour cloning; ``beta -> 0``: DAgger). The loss

    L = mean over valid steps of  sum_i -log pi_i(a_expert_i,t | o_<=t)
                                  + lam * sum_{i, j != i, c} log2(|M| z_t^{i->j}[c] + 1)

(with a bit budget, ``ILConfig.budget``, the controller of :mod:`sparsecomm.budget` sets the
weight in place of ``lam`` every update) is backpropagated through the episode and through the
channel: no learner ever sees its own goal
or an expert message, so the only way to predict the expert's action is to learn what to tell the
others and how to read what they say.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from sparsecomm import channel
from sparsecomm.agents import Team
from sparsecomm.configs import ILConfig
from sparsecomm.envs.task import Task
from sparsecomm.learner import Learner, LossAux, make_learner, make_team, masked_mean
from sparsecomm.rollout import Expert, episode_metrics, rollout


def oracle_expert(env: Task) -> Expert:
    """The task's centralised scripted expert (``env.expert_actions``, e.g. navigation's
    oracle) as an :class:`Expert` (stateless, sends nothing)."""
    if not hasattr(env, "expert_actions"):
        raise ValueError(f"ILConfig.expert 'oracle' needs a task with expert_actions, not {env!r}")
    return Expert(
        init=lambda batch: jnp.zeros(()),
        step=lambda carry, key, state, obs: (carry, jax.vmap(env.expert_actions)(state)),
    )


def team_expert(team: Team, channel_cfg, actor_params) -> Expert:
    """A trained team as an :class:`Expert`: it talks among itself over its own channel (fresh
    dither keys, no noise on the wire), and only its actions leave it. Acts greedily. Its links
    are the rollout's, step for step: the same link rules and state
    (``channel.build``, ``TeamChannel.exchange``). A team whose links follow positions or
    whose inbox is aggregated (``sparsecomm.scaling``) is refused."""
    if team.routed or team.cfg.aggregate != "concat":
        raise ValueError(
            "a team expert must use AgentConfig.neighbours = radius = None and aggregate "
            "'concat' (its own all-to-all channel)"
        )
    k = team.num_agents
    links = channel.build(channel_cfg, k, reads_sent=team.reads_sent, lossy=False)

    def init(batch):
        return dict(
            h=team.initial_carry(batch),
            msgs=jnp.zeros((batch, k, links.inbox_width()), jnp.float32),
            keys=jax.random.split(jax.random.key(12345), batch),
            t=jnp.zeros((), jnp.int32),
            links=links.init((batch,)),
        )

    def step(carry, key, state, obs):
        keys, t = carry["keys"], carry["t"]
        h, logits, z = team.act(actor_params, carry["h"], obs, carry["msgs"])
        u = channel.step_dither(channel_cfg, keys, t, k)
        ex = links.exchange(carry["links"], z, u, keys, t)
        carry = dict(h=h, msgs=ex.msgs, keys=keys, t=t + 1, links=ex.state)
        return carry, jnp.argmax(logits, -1)

    return Expert(init=init, step=step)


def make_imitate(config: ILConfig, expert: Expert | None = None) -> Learner:
    """The imitation learner of ``config`` imitating ``expert`` (default: the oracle, which
    ``config.expert = "oracle"`` names; a team expert is loaded by
    ``sparsecomm.runfolder.load_expert``)."""
    env, team = make_team(config)
    if expert is None:
        if config.expert != "oracle":
            raise ValueError(
                f"ILConfig.expert {config.expert!r} needs the expert itself: "
                "make_imitate(config, sparsecomm.runfolder.load_expert(config))"
            )
        expert = oracle_expert(env)
    tx = optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate())
    )

    def beta_at(update):
        if config.beta_decay_updates == 0:
            return jnp.float32(config.beta_end)
        frac = jnp.clip(update / config.beta_decay_updates, 0.0, 1.0)
        return config.beta_start + (config.beta_end - config.beta_start) * frac

    def loss_fn(params, key, lam, update):
        beta = beta_at(update)
        traj = rollout(
            team,
            env,
            config.channel,
            params["actor"],
            key,
            config.num_envs,
            expert=expert,
            beta=beta,
            remat=config.remat,
            keep_hidden=config.experimental.decoupled,
        )
        nll = -jnp.take_along_axis(traj.log_probs, traj.expert_actions[..., None], -1)[..., 0]
        mean = masked_mean(traj.valid)
        imitation_loss = mean(nll.sum(-1))
        loss = imitation_loss + lam * mean(traj.penalty)
        metrics = episode_metrics(traj)
        agree = (traj.actions == traj.expert_actions).all(-1)
        metrics.update(
            loss=loss,
            imitation_loss=imitation_loss,
            beta=beta,
            expert_agreement=mean(agree.astype(jnp.float32)),
        )
        return loss, LossAux(metrics, traj.aside.hidden, traj.valid)

    def own_success(metrics, update):
        """The team's own success counts only once beta has reached beta_end (the learners drive
        as much as they ever will): before, the expert's actions make the episodes succeed."""
        return jnp.where(beta_at(update) <= config.beta_end, metrics["success_rate"], 0.0)

    return make_learner(
        config, loss_fn, tx, env=env, team=team, success_of=own_success, expert=expert
    )


__all__ = ["make_imitate", "oracle_expert", "team_expert"]
