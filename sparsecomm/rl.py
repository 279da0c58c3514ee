"""Actor-critic reinforcement learning through the channel (paper eq. 5, SPEC section 5).

Each update plays ``num_envs`` whole episodes with :func:`sparsecomm.rollout.rollout` and takes
one gradient step on

    loss = mean over valid steps of  sum_i [ -log pi_i(a_t | o_<=t) * A_i,t
                                             + vf_coef * (V_i(S_t) - G_i,t)^2
                                             - ent_coef * H(pi_i) ]
                                     + w * sum_{i, j != i, c} log2(|M| z_t^{i->j}[c] + 1)

with ``G`` the Monte-Carlo returns of the scaled rewards (``gae_lambda = 1``, paper eq. 5) or GAE
targets, and ``A = G - V(S_t)`` held constant (standardised per agent by default). The penalty
weight ``w = lam * reward_scale / std(A)`` (``/ std(A)`` only when advantages are standardised)
makes this the gradient of the paper's objective ``E[sum_t gamma^t r_t] - lam E[sum_t penalty_t]``
up to one positive factor: ``lam`` is the price of one bit in the paper's reward units
(optionally switched on late, ``ExperimentalConfig.penalty_delay``, ``penalty_ramp``). With a bit
budget (``RLConfig.budget``, ``sparsecomm.budget``) the price is set each update by the
controller from the bits the update's episodes really sent, inside the compiled update. The
gradient of the whole expression is taken through the episode: through every agent's GRU and
through the channel from every receiver's log-probabilities into every sender's parameters.

``make_train(config)`` returns the pure functions of :mod:`sparsecomm.learner` around this loss:
``train(key, lam, budget)`` runs the whole loop as one compiled program, so ``vmap`` over seeds,
lambdas and budgets gives a sweep for free; ``init`` and ``update_chunk`` split it into
resumable pieces (checkpoints, progress, logs).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax
from flax import struct

from sparsecomm.configs import RLConfig
from sparsecomm.learner import Learner, LossAux, Replay, make_learner, make_team, masked_mean
from sparsecomm.rollout import Trajectory, episode_metrics, rollout


def discounted_targets(rewards, values, dones, valid, gamma, gae_lambda):
    """Advantages and value targets, (T, B, K), by a backward scan over time.

    ``rewards`` are zero on invalid steps; ``dones`` marks the last step of an episode, where
    nothing is bootstrapped (the 256-step limit is part of the state the critic sees).
    With ``gae_lambda = 1`` the targets are Monte-Carlo returns.
    """
    not_done = 1.0 - dones.astype(jnp.float32)[..., None]
    valid = valid.astype(jnp.float32)[..., None]
    next_values = jnp.concatenate([values[1:], jnp.zeros_like(values[:1])], 0)

    def back(adv_next, x):
        r, v, v_next, nd, ok = x
        delta = r + gamma * nd * v_next - v
        adv = (delta + gamma * gae_lambda * nd * adv_next) * ok
        return adv, adv

    _, adv = jax.lax.scan(
        back,
        jnp.zeros_like(values[0]),
        (rewards, values, next_values, not_done, valid),
        reverse=True,
    )
    return adv, adv + values


def penalty_schedule(update, delay: int, ramp: int):
    """Factor on the penalty weight at 0-based ``update``: 0 before ``delay``, then a linear
    ramp to 1 over ``ramp`` updates (1 at once if ``ramp`` is 0)."""
    if ramp == 0:
        return (update >= delay).astype(jnp.float32)
    return jnp.clip((update - delay + 1) / ramp, 0.0, 1.0)


def normalize_per_agent(adv, valid, eps: float = 1e-8):
    """Advantages (T, B, K) standardised per agent over the valid steps (invalid ones -> 0).

    Returns the standardised advantages and the per-agent standard deviations (K,).
    """
    w = valid.astype(adv.dtype)[..., None]
    n = jnp.maximum(w.sum((0, 1)), 1.0)
    mean = (adv * w).sum((0, 1)) / n
    std = jnp.sqrt((jnp.square(adv - mean) * w).sum((0, 1)) / n + eps)
    return (adv - mean) / std * w, std


def clip_each_part(max_norm: float) -> optax.GradientTransformation:
    """Clip the actors' and the critic's gradients by their global norms separately: the
    critic's squared errors on returns of a few hundred (scaled) units would otherwise dominate
    one global norm and starve the actors."""
    clip = optax.clip_by_global_norm(max_norm)
    return optax.stateless(
        lambda grads, _: {k: clip.update(g, clip.init(g))[0] for k, g in grads.items()}
    )


def make_train(config: RLConfig) -> Learner:
    """The learner of ``config``, on the task ``config.env`` names (``make_team``)."""
    env, team = make_team(config)
    tx = optax.chain(clip_each_part(config.max_grad_norm), optax.adam(config.learning_rate()))
    if config.algo == "ppo":
        return _make_ppo(config, env, team, tx)

    def loss_fn(params, key, lam, update):
        traj: Trajectory = rollout(
            team,
            env,
            config.channel,
            params["actor"],
            key,
            config.num_envs,
            remat=config.remat,
            keep_hidden=config.experimental.decoupled,
        )
        values = jax.lax.map(lambda s: team.value(params["critic"], s), traj.states)
        adv, targets, adv_std = advantages(config, traj, values)
        logp = action_log_probs(traj)
        if config.channel.samples_symbols:  # the symbols sent are actions too (RCL)
            logp = logp + traj.msg_log_probs
        pg = -(logp * jax.lax.stop_gradient(adv)).sum(-1)
        return _objective(config, traj, pg, values, targets, lam, update, adv_std)

    return make_learner(config, loss_fn, tx, env=env, team=team)


def advantages(config: RLConfig, traj: Trajectory, values):
    """The advantages, the critic's targets (both (T, B, K)) and, when they are standardised,
    the advantages' per-agent standard deviations (K,) (else None), from the scaled rewards
    (minus ``bit_cost`` per payload bit sent, RCL) and the critic's ``values`` (T, B, K)."""
    valid = traj.valid.astype(jnp.float32)
    rewards = traj.rewards * config.reward_scale * valid[..., None]
    if config.channel.samples_symbols:  # RCL: each agent pays bit_cost per payload bit it sends
        sent = traj.link_bits.sum(-1) * valid[..., None]  # (T, B, K) bits by sender
        rewards = rewards - config.channel.bit_cost * config.reward_scale * sent
    adv, targets = discounted_targets(
        rewards,
        jax.lax.stop_gradient(values),
        traj.dones,
        traj.valid,
        config.gamma,
        config.gae_lambda,
    )
    adv_std = None
    if config.normalize_advantages:
        adv, adv_std = normalize_per_agent(adv, traj.valid)
    return adv, targets, adv_std


def action_log_probs(traj: Trajectory):
    """(T, B, K) log-probabilities of the actions the trajectory executed."""
    return jnp.take_along_axis(traj.log_probs, traj.actions[..., None], -1)[..., 0]


def _objective(config: RLConfig, traj: Trajectory, pg, values, targets, lam, update, adv_std):
    """The loss of eq. 5 around a policy-gradient term: ``pg`` (T, B) summed over agents, the
    critic's squared error on ``targets`` (T, B, K), the entropy bonus and the bit penalty.

    ``lam`` prices a bit in the paper's reward units (SPEC 3: J = E[sum_t gamma^t r_t] - lam
    E[sum_t penalty_t]), so the penalty is scaled exactly as the policy-gradient term: by
    ``reward_scale``, and by 1 / std of the advantages (``adv_std`` (K,), None when they are
    not standardised)."""
    penalty_weight = lam * config.reward_scale
    ex = config.experimental
    penalty_weight *= penalty_schedule(update, ex.penalty_delay, ex.penalty_ramp)
    if adv_std is not None:
        penalty_weight = penalty_weight / jax.lax.stop_gradient(adv_std.mean())
    entropy = -(jnp.exp(traj.log_probs) * traj.log_probs).sum(-1)
    value_loss = jnp.square(values - jax.lax.stop_gradient(targets)).sum(-1)
    mean = masked_mean(traj.valid)
    loss = (
        mean(pg)
        + config.vf_coef * mean(value_loss)
        - config.ent_coef * mean(entropy.sum(-1))
        + penalty_weight * mean(traj.penalty)
    )
    metrics = episode_metrics(traj)
    metrics.update(
        loss=loss,
        policy_loss=mean(pg),
        value_loss=mean(value_loss),
        entropy=mean(entropy.mean(-1)),
        penalty_weight=penalty_weight,
    )
    return loss, LossAux(metrics, traj.aside.hidden, traj.valid)


class Batch(struct.PyTreeNode):
    """A batch played once for ``algo = "ppo"``: what its replays need, leading axes (T, B)."""

    key: jax.Array  # the batch's key: a replay draws the same episodes, dither and all
    actions: jax.Array  # (T, B, K) int32 actions executed
    log_probs: jax.Array  # (T, B, K) their log-probabilities under the collecting parameters
    advantages: jax.Array  # (T, B, K) advantages (standardised per agent when configured)
    targets: jax.Array  # (T, B, K) the critic's targets
    states: jax.Array  # (T, B, state_dim) global states (the critic's input)
    adv_std: jax.Array | None  # (K,) the advantages' standard deviations, or None


def clipped_policy_loss(log_probs, old_log_probs, advantages, clip: float):
    """PPO's clipped surrogate, ``-min(r A, clip(r, 1 - clip, 1 + clip) A)`` with the ratio
    ``r = exp(log_probs - old_log_probs)``; all (T, B, K). At ``r = 1`` its gradient is the
    plain policy gradient's, ``-A grad log pi``. Returns the loss (T, B, K) and the ratio."""
    ratio = jnp.exp(log_probs - old_log_probs)
    clipped = jnp.clip(ratio, 1.0 - clip, 1.0 + clip)
    return -jnp.minimum(ratio * advantages, clipped * advantages), ratio


def _make_ppo(config: RLConfig, env, team, tx) -> Learner:
    """``algo = "ppo"``: each batch is played once without gradients (``collect``), then each
    minibatch of its episodes is replayed with the current parameters, the batch's actions and
    its dither: the messages, the log-probabilities and the bit penalty are recomputed and
    differentiable through the episode, as in ``a2c``, and the policy term is PPO's clipped
    surrogate on the advantages of the collecting parameters."""

    def critic(params, states):
        return jax.lax.map(lambda s: team.value(params["critic"], s), states)

    def collect(params, key, update):
        params = jax.lax.stop_gradient(params)
        traj = rollout(
            team,
            env,
            config.channel,
            params["actor"],
            key,
            config.num_envs,
            keep_hidden=config.experimental.decoupled,
        )
        adv, targets, adv_std = advantages(config, traj, critic(params, traj.states))
        logp = action_log_probs(traj)
        batch = Batch(key, traj.actions, logp, adv, targets, traj.states, adv_std)
        return batch, LossAux(episode_metrics(traj), traj.aside.hidden, traj.valid)

    def loss_fn(params, batch: Batch, episodes, lam, update):
        def pick(x):
            return x[:, episodes]

        traj: Trajectory = rollout(
            team,
            env,
            config.channel,
            params["actor"],
            batch.key,
            config.num_envs,
            remat=config.remat,
            episodes=episodes,
            actions=pick(batch.actions),
        )
        logp = action_log_probs(traj)
        pg, ratio = clipped_policy_loss(
            logp, pick(batch.log_probs), pick(batch.advantages), config.ppo_clip
        )
        values = critic(params, pick(batch.states))
        loss, aux = _objective(
            config, traj, pg.sum(-1), values, pick(batch.targets), lam, update, batch.adv_std
        )
        mean = masked_mean(traj.valid)
        ratio = jax.lax.stop_gradient(ratio)
        aux.metrics.update(
            clip_fraction=mean((jnp.abs(ratio - 1.0) > config.ppo_clip).mean(-1)),
            approx_kl=mean((ratio - 1.0 - jnp.log(ratio)).mean(-1)),
        )
        return loss, aux

    replay = Replay(collect, config.ppo_epochs, config.ppo_minibatches)
    return make_learner(config, loss_fn, tx, env=env, team=team, replay=replay)
