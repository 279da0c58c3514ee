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

import dataclasses
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import optax
from flax import struct

from sparsecomm import budget as bit_budget
from sparsecomm.agents import Team
from sparsecomm.configs import ILConfig
from sparsecomm.envs.navigation import NavigationEnv
from sparsecomm.envs.oracle import oracle_actions
from sparsecomm.rl import make_team
from sparsecomm.rollout import Expert, deliver, episode_metrics, rollout, step_dither, transmit


class ILState(struct.PyTreeNode):
    """Learners' parameters, optimiser, PRNG and counters (the expert is a constant)."""

    params: dict
    opt_state: optax.OptState
    key: jax.Array
    update: jax.Array
    budget: bit_budget.BudgetState  # this run's lambda, bit budget and penalty-weight controller


def oracle_expert(env: NavigationEnv) -> Expert:
    """The centralised scripted controller as an :class:`Expert` (stateless, sends nothing)."""
    cfg = env.config
    return Expert(
        init=lambda batch: jnp.zeros(()),
        step=lambda carry, key, state, obs: (
            carry,
            jax.vmap(oracle_actions, (0, None))(state, cfg),
        ),
    )


def team_expert(team: Team, channel_cfg, actor_params) -> Expert:
    """A trained team as an :class:`Expert`: it talks among itself over its own channel (fresh
    dither keys), and only its actions leave it. Acts greedily."""
    k = team.num_agents
    c = channel_cfg.num_elements

    def init(batch):
        keys = jax.random.split(jax.random.key(12345), batch)
        msgs = jnp.zeros((batch, k, (k - 1) * c), jnp.float32)
        return (team.initial_carry(batch), msgs, keys, jnp.zeros((), jnp.int32))

    def step(carry, key, state, obs):
        h, msgs, keys, t = carry
        h, logits, z = team.act(actor_params, h, obs, msgs)
        z_hat = transmit(channel_cfg, step_dither(channel_cfg, keys, t, k), z)[0]
        msgs = deliver(z_hat)
        return (h, msgs, keys, t + 1), jnp.argmax(logits, -1)

    return Expert(init=init, step=step)


@dataclasses.dataclass(frozen=True)
class Imitator:
    config: ILConfig
    env: NavigationEnv
    team: Team
    expert: Expert
    init: Callable
    update: Callable
    update_chunk: Callable
    train: Callable
    evaluate: Callable


def load_expert(config: ILConfig, env: NavigationEnv) -> Expert:
    if config.expert == "oracle":
        return oracle_expert(env)
    from sparsecomm.experiment import load_run

    rl_config, trainer, runs, actor = load_run(Path(config.expert_checkpoint))
    if rl_config.env != config.env:
        raise ValueError("expert_checkpoint was trained on a different task (env config)")
    if not 0 <= config.expert_index < len(runs):
        raise ValueError(f"expert_index must be in [0, {len(runs) - 1}], got {config.expert_index}")
    params = jax.tree.map(lambda x: x[config.expert_index], actor)
    return team_expert(trainer.team, rl_config.channel, params)


def make_imitate(config: ILConfig, expert: Expert | None = None) -> Imitator:
    env, team = make_team(config)
    expert = expert if expert is not None else load_expert(config, env)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.lr))

    def init(key, lam, budget=jnp.nan) -> ILState:
        """A run's first state; ``budget`` (payload bits per step, NaN: none) overrides lambda."""
        k_params, k_run = jax.random.split(key)
        params = team.init(k_params)
        controller = bit_budget.init(config.budget, budget, lam)
        return ILState(params, tx.init(params), k_run, jnp.zeros((), jnp.int32), controller)

    def beta_at(update):
        if config.beta_decay_updates == 0:
            return jnp.float32(config.beta_end)
        frac = jnp.clip(update / config.beta_decay_updates, 0.0, 1.0)
        return config.beta_start + (config.beta_end - config.beta_start) * frac

    def loss_fn(params, key, lam, beta):
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
            keep_hidden=config.budget.decoupled,
        )
        valid = traj.valid.astype(jnp.float32)
        nll = -jnp.take_along_axis(traj.log_probs, traj.expert_actions[..., None], -1)[..., 0]
        steps = valid.sum()

        def mean(x):
            return (x * valid).sum() / steps

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
        return loss, (metrics, (traj.hidden, traj.valid))

    def update(state: ILState):
        key, k_roll = jax.random.split(state.key)
        beta = beta_at(state.update)
        price = bit_budget.weight(state.budget)
        in_loss = 0.0 if config.budget.decoupled else price  # else a step of its own, below
        grads, (metrics, (hidden, valid)) = jax.grad(loss_fn, has_aux=True)(
            state.params, k_roll, in_loss, beta
        )
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        params = bit_budget.decoupled_update(
            config.budget, params, team.message_penalty, hidden, valid, price, config.channel.levels
        )
        metrics["grad_norm"] = optax.tree.norm(grads)
        # The team's own success counts only once beta has reached beta_end (the learners drive
        # as much as they ever will): before, the expert's actions make the episodes succeed.
        own_success = jnp.where(beta <= config.beta_end, metrics["success_rate"], 0.0)
        controller = bit_budget.update(
            config.budget, state.budget, metrics["bits_per_step"], own_success
        )
        metrics.update(bit_budget.log(state.budget, price))
        return ILState(params, opt_state, key, state.update + 1, controller), metrics

    def update_chunk(state: ILState, num_updates: int):
        return jax.lax.scan(lambda s, _: update(s), state, None, length=num_updates)

    def train(key, lam, budget=jnp.nan):
        return update_chunk(init(key, lam, budget), config.num_updates)

    def evaluate(actor_params, key, num_episodes: int, greedy: bool = False):
        """Learners drive alone (no expert): the team's own success."""
        traj = rollout(team, env, config.channel, actor_params, key, num_episodes, greedy=greedy)
        return episode_metrics(traj)

    return Imitator(config, env, team, expert, init, update, update_chunk, train, evaluate)


__all__ = ["ILState", "Imitator", "make_imitate", "oracle_expert", "team_expert"]
