"""The learner scaffold that RL and imitation share: state, init, update, chunked scan, evaluate.

A learner is its loss. ``make_learner(config, loss_fn, tx)`` wraps
``loss_fn(params, key, price, update) -> (loss, LossAux)`` (``price``: the bit-penalty weight of
this update, in lambda's units; ``update``: the 0-based update counter) in pure functions,
PureJaxRL-style:

- ``init(key, lam, budget=nan) -> LearnerState``: a run's first state; ``budget`` (payload bits
  per step; NaN: none) hands the price to the controller of :mod:`sparsecomm.budget`;
- ``update(state) -> (state, metrics)``: one rollout and gradient step, then the controller's
  step from the bits and the success the update's episodes really had; ``metrics["nonfinite"]``
  is 1 when the loss, a gradient or a parameter stopped being finite (the sweep then stops);
- ``update_chunk(state, n)``: ``n`` updates in one ``lax.scan`` (metrics stacked);
- ``train(key, lam, budget=nan)``: the whole run as one program, so ``vmap`` over seeds,
  lambdas and budgets is a sweep;
- ``evaluate(actor_params, key, num_episodes, greedy=False)``: the team alone, no expert.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
import optax
from flax import struct

from sparsecomm import budget as bit_budget
from sparsecomm import channel
from sparsecomm.agents import Team
from sparsecomm.configs import LearnerConfig
from sparsecomm.envs import registry
from sparsecomm.envs.task import Task
from sparsecomm.rollout import Expert, episode_metrics, rollout
from sparsecomm.scaling import check_fits


class LearnerState(struct.PyTreeNode):
    """Everything a run needs to continue exactly: parameters, optimiser, PRNG, counters."""

    params: dict
    opt_state: optax.OptState
    key: jax.Array
    update: jax.Array  # () int32, updates done
    budget: bit_budget.BudgetState  # this run's lambda, bit budget and penalty-weight controller


class LossAux(NamedTuple):
    """What a learner's loss returns beside the loss itself: ``loss_fn(...) -> (loss, LossAux)``."""

    metrics: dict
    """The update's scalars: ``rollout.episode_metrics`` of its episodes and the loss's terms."""
    hidden: jax.Array | None
    """(T, B, K, H) GRU states the messages came from (``rollout(keep_hidden=True)``, for the
    decoupled penalty step), else None."""
    valid: jax.Array
    """(T, B) bool: the step belongs to the episode (``Trajectory.valid``)."""


class Loss(Protocol):
    """A learner's loss on a batch it plays itself: ``loss(params, key, price, update) ->
    (loss, LossAux)`` (``price``: the bit-penalty weight of this update, in lambda's units;
    ``update``: the 0-based update counter)."""

    def __call__(
        self, params: dict, key: jax.Array, price: jax.Array, update: jax.Array
    ) -> tuple[jax.Array, LossAux]: ...


class ReplayLoss(Protocol):
    """A learner's loss on the (b,) episodes ``episodes`` of a batch collected once
    (:class:`Replay`): ``loss(params, batch, episodes, price, update) -> (loss, LossAux)``."""

    def __call__(
        self, params: dict, batch, episodes: jax.Array, price: jax.Array, update: jax.Array
    ) -> tuple[jax.Array, LossAux]: ...


@dataclasses.dataclass(frozen=True)
class Replay:
    """How a learner that plays each batch once and then takes several gradient steps on it
    (``RLConfig.algo = "ppo"``) gets its batches. Its loss is then
    ``loss_fn(params, batch, episodes, price, update) -> (loss, LossAux)`` on the (b,) episodes
    ``episodes`` of the batch."""

    collect: Callable
    """``collect(params, key, update) -> (batch, LossAux)``: the batch of ``num_envs`` episodes
    of ``key`` played without gradients, and the metrics, GRU states and valid steps of its
    episodes (those the controller and the decoupled penalty step read)."""
    epochs: int
    """Passes over each batch (>= 1)."""
    minibatches: int
    """Gradient steps per pass, each on ``num_envs / minibatches`` episodes drawn without
    replacement (>= 1)."""


@dataclasses.dataclass(frozen=True)
class Learner:
    """The pure functions of one configuration (see the module docstring)."""

    config: LearnerConfig
    env: Task
    team: Team
    tx: optax.GradientTransformation
    init: Callable
    update: Callable
    update_chunk: Callable
    train: Callable
    evaluate: Callable
    loss: Loss
    """The learner's loss on the batch of a key (a replaying learner's: the loss of the first
    minibatch of that batch, the shape of every step it takes; ``memory.estimate`` sizes an
    update by it)."""
    expert: Expert | None = None


def make_team(config: LearnerConfig) -> tuple[Task, Team]:
    """The task and the team of a learner's config (``env``, ``agent``, ``channel``): the task
    is the registered one ``config.env`` configures (``sparsecomm.envs.registry.make``)."""
    env = registry.make(config.env)
    check_fits(config.agent, env.num_agents)
    links = channel.build(config.channel, env.num_agents, reads_sent=config.agent.reads_sent)
    team = Team(
        config.agent,
        env.num_agents,
        env.obs_dim,
        env.num_actions,
        links,
        env.state_dim,
        config.experimental,
    )
    return env, team


def make_learner(
    config: LearnerConfig,
    loss_fn: Loss | ReplayLoss,
    tx: optax.GradientTransformation,
    *,
    env: Task,
    team: Team,
    success_of: Callable | None = None,
    expert: Expert | None = None,
    replay: Replay | None = None,
) -> Learner:
    """Wrap a loss into a learner. ``success_of(metrics, update)`` is the success rate the budget
    controller sees (default: the batch's ``success_rate``). ``replay``: the loss is a
    :class:`ReplayLoss`, taken on minibatches of a batch played once (:class:`Replay`); by
    default it is a :class:`Loss` that plays its own batch."""
    success_of = success_of or _batch_success

    def init(key: jax.Array, lam, budget=jnp.nan) -> LearnerState:
        """A run's first state; ``budget`` (payload bits per step, NaN: none) overrides lambda."""
        k_params, k_run = jax.random.split(key)
        params = team.init(k_params)
        controller = bit_budget.init(config.budget, budget, lam)
        return LearnerState(params, tx.init(params), k_run, jnp.zeros((), jnp.int32), controller)

    def gradient_step(params, opt_state, *loss_args):
        """One step of the optimiser on the loss's gradient: the new parameters and optimiser
        state, the loss's aux and each part's gradient norm."""
        grads, aux = jax.grad(loss_fn, has_aux=True)(params, *loss_args)
        updates, opt_state = tx.update(grads, opt_state, params)
        norms = {f"{part}_grad_norm": optax.tree.norm(g) for part, g in grads.items()}
        return optax.apply_updates(params, updates), opt_state, aux, norms

    def update(state: LearnerState):
        key, k_roll = jax.random.split(state.key)
        price = bit_budget.weight(state.budget)
        in_loss = 0.0 if config.experimental.decoupled else price  # else its own step, below
        if replay is None:
            params, opt_state, aux, norms = gradient_step(
                state.params, state.opt_state, k_roll, in_loss, state.update
            )
            metrics = {**aux.metrics, **norms}
            finite = jnp.isfinite(metrics["loss"])
        else:
            params, opt_state, aux, metrics, finite = _replayed_steps(
                config.num_envs, replay, gradient_step, state, k_roll, in_loss
            )
        params = bit_budget.decoupled_update(
            config.experimental.decoupled_step,
            params,
            team.message_penalty,
            aux.hidden,
            aux.valid,
            price,
            config.channel.link_penalty,
        )
        metrics["nonfinite"] = _nonfinite(params, metrics, finite)
        controller = bit_budget.update(
            config.budget,
            state.budget,
            bit_budget.measured_bits(config.budget, metrics, env.num_agents, config.channel),
            success_of(metrics, state.update),
        )
        metrics.update(bit_budget.log(state.budget, price))
        return LearnerState(params, opt_state, key, state.update + 1, controller), metrics

    def update_chunk(state: LearnerState, num_updates: int):
        """``num_updates`` updates in one ``lax.scan``; metrics stacked on a leading axis."""
        return jax.lax.scan(lambda s, _: update(s), state, None, length=num_updates)

    def train(key: jax.Array, lam, budget=jnp.nan) -> tuple[LearnerState, dict]:
        """The whole run, pure: vmap it over keys, lambdas and budgets for a sweep."""
        return update_chunk(init(key, lam, budget), config.num_updates)

    def evaluate(actor_params, key: jax.Array, num_episodes: int, greedy: bool = False):
        """The team drives alone (no expert): its own success, length and bits."""
        traj = rollout(team, env, config.channel, actor_params, key, num_episodes, greedy=greedy)
        return episode_metrics(traj)

    loss = loss_fn if replay is None else _first_minibatch_loss(config.num_envs, replay, loss_fn)
    return Learner(config, env, team, tx, init, update, update_chunk, train, evaluate, loss, expert)


def _batch_success(metrics: dict, update) -> jax.Array:
    """The success rate the budget controller sees by default: the batch's."""
    return metrics["success_rate"]


def _replayed_steps(num_envs: int, replay: Replay, gradient_step, state: LearnerState, key, price):
    """Play the batch once, then ``epochs`` passes of ``minibatches`` gradient steps over it;
    the batch's episodes' metrics, and each loss term and gradient norm averaged over the
    steps."""
    k_roll, k_order = jax.random.split(key)
    batch, aux = replay.collect(state.params, k_roll, state.update)
    orders = jax.vmap(lambda k: jax.random.permutation(k, num_envs))(
        jax.random.split(k_order, replay.epochs)
    )
    minibatches = orders.reshape(replay.epochs * replay.minibatches, num_envs // replay.minibatches)

    def step(carry, episodes):
        params, opt_state, aux_mb, norms = gradient_step(
            *carry, batch, episodes, price, state.update
        )
        return (params, opt_state), (aux_mb.metrics, norms)

    (params, opt_state), (steps, norms) = jax.lax.scan(
        step, (state.params, state.opt_state), minibatches
    )
    metrics = {**jax.tree.map(jnp.mean, steps), **aux.metrics, **jax.tree.map(jnp.mean, norms)}
    return params, opt_state, aux, metrics, jnp.isfinite(steps["loss"]).all()


def _first_minibatch_loss(num_envs: int, replay: Replay, loss_fn: ReplayLoss) -> Loss:
    """A replaying learner's :class:`Loss`: the loss of the first minibatch of the batch of
    ``key`` (the shape every replayed step has)."""

    def loss(params, key, price, update):
        batch, _ = replay.collect(params, key, update)
        return loss_fn(params, batch, jnp.arange(num_envs // replay.minibatches), price, update)

    return loss


def _nonfinite(params, metrics: dict, finite) -> jax.Array:
    """1.0 when the loss (``finite`` False), a gradient or a parameter stopped being finite,
    else 0.0. Divergence is flagged inside the compiled update (no host sync per step); the
    sweep stops at the end of the chunk and keeps its last good checkpoint. A gradient that
    stopped being finite shows in its norm."""
    for x in jax.tree.leaves(params) + [v for n, v in metrics.items() if "grad_norm" in n]:
        finite &= jnp.isfinite(x).all()
    return 1.0 - finite.astype(jnp.float32)


def masked_mean(valid: jax.Array) -> Callable:
    """``mean(x)``: the mean of a (T, B) per-step quantity over the valid steps."""
    valid = valid.astype(jnp.float32)
    steps = valid.sum()
    return lambda x: (x * valid).sum() / steps
