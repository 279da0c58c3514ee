"""A bit budget that training meets: the penalty weight as a dual variable (docs/budget.md).

A fixed bit-penalty weight lambda is right at one moment of training only: the ratio of the
penalty's gradient to the task gradient's noise falls by orders of magnitude as a team learns
(docs/budget.md), so a lambda that prunes a trained team silences an untrained one, and one that
an untrained team survives barely moves a trained one. Instead of a price, the user gives a
*budget*: payload bits per step for the whole team (the paper's count, summed over every link),
and training sets the price itself, inside the compiled update, from the real bits of each
update's episodes:

1. **Wait for the team.** Until the team first succeeds (the moving average of its success rate
   reaches ``engage_success``) the weight is the run's lambda (0 by default): nothing is priced
   while the team has yet to learn that talking pays.
2. **Lower the target gradually, and only while the team keeps up.** Once engaged, the target
   starts at the bits the team sends then and halves every ``halving_updates`` updates until it
   reaches the budget, as long as the team's success (a moving average) stays at or above
   ``hold_success`` of its best so far. When success falls below that, the target rises again
   at the same rate (up to where it started), so the team gets bits back to re-learn before it
   is asked for less.
3. **Dual ascent in log space, slow up and fast down.** ``log w += dual_lr * clip((bits -
   target) / target, -1, 1)`` while the team sends more than its target; while it sends less, or
   while its success is down, the weight falls at ``relief_lr`` instead: the bits answer the
   price with a cliff, and a price that gives way fast keeps a team that falls off it from
   learning to ignore its messages. In log space one step size serves weights that differ by
   1000x, and a silent team (bits 0 < target) quickly stops paying for bits, so the penalty
   cannot hold a link silent that reward needs; the weight stays within ``[weight_min,
   weight_max]``.

The same controller serves RL and imitation (``sparsecomm.rl``, ``sparsecomm.imitation``): each
learner prices a bit with ``weight(state)`` exactly as it would with lambda, and calls
:func:`update` once per gradient update with the batch's measured payload bits per step and
success rate. Runs without a budget carry ``budget = NaN`` and keep their fixed lambda, so fixed
and budgeted runs share one vmapped program.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

__all__ = [
    "BudgetConfig",
    "BudgetState",
    "check_budget",
    "decoupled_update",
    "init",
    "log",
    "penalty_step",
    "update",
    "weight",
]


@dataclasses.dataclass(frozen=True)
class BudgetConfig:
    """The bit budget and its controller. ``bits = None`` keeps the paper's fixed lambda."""

    bits: float | None = None
    """Payload bits per step (>= 0) that training must meet, for the whole team (the paper's
    count, summed over all links) or per link with ``per_link``; ``None``: no budget, the penalty
    weight is the fixed lambda. ``sparsecomm train --budgets`` sweeps it. ours: ``None`` (the
    paper's behaviour)."""
    weight_init: float = 0.01
    """Penalty weight (lambda units: the price of one bit; > 0) when the controller engages,
    unless the run's lambda is larger. ours: 0.01, the largest paper lambda (docs/budget.md, "How
    the defaults were chosen")."""
    weight_min: float = 1e-5
    """Lower bound of the weight (lambda units, > 0). ours: small enough to be no pressure at all
    (docs/budget.md, "How the defaults were chosen")."""
    weight_max: float = 1e3
    """Upper bound of the weight (lambda units, >= ``weight_min``). ours: far above any weight a
    team needs (docs/budget.md, "How the defaults were chosen")."""
    dual_lr: float = 0.03
    """Step of ``log(weight)`` per update at a relative excess of 100% (> 0; the excess
    ``(bits - target) / target`` is clipped to [-1, 1]), so the weight can change 10x in 77
    updates. ours (docs/budget.md, "The budget, RL")."""
    relief_lr: float | None = 0.3
    """Step of ``log(weight)`` per update (> 0) while the team sends less than its target or its
    success is below ``hold_success`` of its best (then the price falls at this rate whatever
    the bits): how fast the price gives way once bits fall off the cliff; 0.3 is 10x in 8
    updates. ``None``: ``dual_lr`` (a symmetric step). ours: 0.3 (docs/budget.md, "The budget,
    RL")."""
    relief_floor: float | None = None
    """Bound of the relief, in (0, 1): while the team's success is down, the price falls no lower
    than this fraction of the last price at which its success held, and that bound itself falls
    at ``dual_lr`` per update while success stays down (so no link is held silent for good).
    ``None``: unbounded. ours: ``None`` for RL; imitation's default is set in ``ILConfig.budget``
    (docs/budget.md, the relief bounded)."""
    engage_success: float = 0.5
    """The target starts to fall when the moving average of the batch success rate (in [0, 1])
    first reaches this. ours."""
    halving_updates: float = 50.0
    """Once engaged, the target halves every this many updates (> 0) until it reaches ``bits``.
    ours (docs/budget.md, "How the defaults were chosen")."""
    hold_success: float = 0.8
    """The target falls while the moving average of success is at least this fraction (in
    [0, 1]) of its best so far, and rises (at the same rate, up to where it started) while it is
    below. ours."""
    success_ema: float = 0.1
    """Weight, in (0, 1], of the newest update in the moving average of the success rate. ours."""
    per_link: bool = False
    """Count ``bits`` (and the target, and the bits the controller measures) per link that
    exists, per step, instead of for the whole team: the controller sees the team's payload bits
    per step divided by its links per step (``links_per_step`` of a routed team,
    ``sparsecomm.scaling``; K (K - 1) for a full team). A budget of b bits per link then holds
    whatever the team's size and routing. ours: False (the team's count, as the paper's bits)."""

    def __post_init__(self):
        if self.bits is not None:
            check_budget(self.bits, "BudgetConfig.bits")
        checks = {
            "weight_init": self.weight_init > 0 and math.isfinite(self.weight_init),
            "weight_min": self.weight_min > 0 and math.isfinite(self.weight_min),
            "weight_max": self.weight_max >= self.weight_min and math.isfinite(self.weight_max),
            "dual_lr": self.dual_lr > 0 and math.isfinite(self.dual_lr),
            "relief_lr": self.relief_lr is None
            or (self.relief_lr > 0 and math.isfinite(self.relief_lr)),
            "relief_floor": self.relief_floor is None or 0 < self.relief_floor < 1,
            "engage_success": 0 <= self.engage_success <= 1,
            "halving_updates": self.halving_updates > 0 and math.isfinite(self.halving_updates),
            "hold_success": 0 <= self.hold_success <= 1,
            "success_ema": 0 < self.success_ema <= 1,
        }
        allowed = {
            "relief_lr": "None or finite and > 0",
            "relief_floor": "None or in (0, 1)",
            "weight_max": f"finite and >= weight_min ({self.weight_min})",
            "engage_success": "in [0, 1]",
            "hold_success": "in [0, 1]",
            "success_ema": "in (0, 1]",
        }
        for name, ok in checks.items():
            if not ok:
                value = getattr(self, name)
                raise ValueError(
                    f"BudgetConfig.{name} must be {allowed.get(name, 'finite and > 0')}, "
                    f"got {value!r}"
                )


def check_budget(bits, name: str = "budget", max_bits: float | None = None) -> float:
    """Validate one budget (payload bits per step): finite, >= 0 and at most ``max_bits`` (the
    most the team's code can send per step), with the field's name in the message."""
    try:
        b = float(bits)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number of bits per step >= 0, got {bits!r}") from None
    if not math.isfinite(b) or b < 0:
        raise ValueError(f"{name} must be finite and >= 0 (payload bits per step), got {bits!r}")
    if max_bits is not None and b > max_bits:
        raise ValueError(
            f"{name} must be <= {max_bits:g}, the most the team's code can send per step, got {b:g}"
        )
    return b


class BudgetState(struct.PyTreeNode):
    """The controller's state, one per run (scalars, so runs vmap)."""

    budget: jax.Array  # () float32, payload bits per step to reach; NaN: no budget (fixed lambda)
    lam: jax.Array  # () float32, the run's lambda (the weight until engaged, or for good)
    log_weight: jax.Array  # () float32, log of the penalty weight once engaged
    target: jax.Array  # () float32, the current target (inf until engaged)
    start: jax.Array  # () float32, the target when the controller engaged (inf until then)
    engaged: jax.Array  # () bool, the team has succeeded once: the target has started to fall
    success: jax.Array  # () float32, moving average of the batch success rate
    best: jax.Array  # () float32, the best moving average so far
    held: jax.Array  # () float32, log weight when success last held (decays while it does not)


def init(cfg: BudgetConfig, budget, lam) -> BudgetState:
    """The state of a run with ``budget`` (NaN: none) and lambda ``lam``."""
    f32 = jnp.float32
    return BudgetState(
        budget=jnp.asarray(budget, f32),
        lam=jnp.asarray(lam, f32),
        log_weight=jnp.log(jnp.maximum(jnp.asarray(lam, f32), cfg.weight_init)),
        target=jnp.asarray(jnp.inf, f32),
        start=jnp.asarray(jnp.inf, f32),
        engaged=jnp.zeros((), bool),
        success=jnp.zeros((), f32),
        best=jnp.zeros((), f32),
        held=jnp.log(jnp.maximum(jnp.asarray(lam, f32), cfg.weight_init)),
    )


def has_budget(state: BudgetState) -> jax.Array:
    return ~jnp.isnan(state.budget)


def weight(state: BudgetState) -> jax.Array:
    """The penalty weight (the price of one bit, in lambda's units) for this update."""
    return jnp.where(has_budget(state) & state.engaged, jnp.exp(state.log_weight), state.lam)


def log(state: BudgetState, price) -> dict[str, jax.Array]:
    """What a learner logs per update: the price of a bit it used and the bit target (NaN when
    the run has no budget; inf until the controller engages)."""
    return {"price": price, "bit_target": jnp.where(has_budget(state), state.target, jnp.nan)}


def measured_bits(cfg: BudgetConfig, metrics: dict, num_agents: int, channel=None) -> jax.Array:
    """The bits an update's episodes sent, in the budget's units: the team's bits per step in
    the count the channel prices (``ChannelConfig.prices``: payload, default, or wire), or per
    link that existed (``BudgetConfig.per_link``)."""
    bits = metrics["bits_per_step" if channel is None else channel.counted_metric]
    if not cfg.per_link:
        return bits
    links = metrics.get("links_per_step", num_agents * (num_agents - 1))
    return bits / jnp.maximum(links, 1e-6)


def update(cfg: BudgetConfig, state: BudgetState, bits, success) -> BudgetState:
    """One controller step after a gradient update whose episodes sent ``bits`` payload bits per
    step (:func:`measured_bits`) at batch success rate ``success`` (both measured, not
    surrogates)."""
    bits = jnp.asarray(bits, jnp.float32)
    ema = (1 - cfg.success_ema) * state.success + cfg.success_ema * success
    best = jnp.maximum(state.best, ema)
    engaging = has_budget(state) & ~state.engaged & (ema >= cfg.engage_success)
    # The target starts from what the team sends when it first succeeds, then falls gradually
    # while the team keeps its success, and rises again while it does not.
    start = jnp.where(engaging, jnp.maximum(bits, state.budget), state.start)
    target = jnp.where(engaging, start, state.target)
    rate = 0.5 ** (1.0 / cfg.halving_updates)
    keeping_up = ema >= cfg.hold_success * best
    moved = jnp.where(
        keeping_up,
        jnp.maximum(target * rate, state.budget),
        jnp.minimum(target / rate, start),
    )
    target = jnp.where(state.engaged, moved, target)
    engaged = state.engaged | engaging
    excess = jnp.clip((bits - target) / jnp.maximum(target, 1.0), -1.0, 1.0)
    if cfg.relief_lr is None:
        step = cfg.dual_lr * excess
    else:  # the price gives way fast below the target, and whenever success is down
        relief = jnp.where(keeping_up, jnp.minimum(excess, 0.0), -1.0)
        step = jnp.where(keeping_up & (excess > 0), cfg.dual_lr * excess, cfg.relief_lr * relief)
    lo, hi = math.log(cfg.weight_min), math.log(cfg.weight_max)
    stepped = jnp.clip(state.log_weight + step, lo, hi)
    held = jnp.where(keeping_up, state.log_weight, state.held - cfg.dual_lr)
    if cfg.relief_floor is not None:  # fall no lower than a fraction of the last good price
        floor = jnp.minimum(held + math.log(cfg.relief_floor), state.log_weight)
        stepped = jnp.maximum(stepped, floor)
    log_weight = jnp.where(state.engaged, stepped, state.log_weight)
    held = jnp.where(state.engaged, held, state.log_weight)
    return state.replace(
        log_weight=log_weight,
        target=target,
        start=start,
        engaged=engaged,
        success=ema,
        best=best,
        held=held,
    )


def decoupled_update(
    lr: float | None, params: dict, message_penalty, hidden, valid, price, penalty
):
    """A learner's parameters after the decoupled penalty step of size ``lr`` (unchanged when
    ``lr`` is None: the penalty is in the loss; ``ExperimentalConfig.decoupled``).
    ``message_penalty(head, hidden, penalty)`` is ``Team.message_penalty`` and ``penalty`` the
    channel's cost of each link (``ChannelConfig.link_penalty``); ``hidden`` (T, B, K, H) and
    ``valid`` (T, B) come from the update's rollout."""
    if lr is None:
        return params
    actor = penalty_step(
        lr, params["actor"], lambda head: message_penalty(head, hidden, penalty), valid, price
    )
    return {**params, "actor": actor}


def penalty_step(lr: float, actor_params: dict, penalty_of_head, valid, price) -> dict:
    """The decoupled penalty step (``ExperimentalConfig.decoupled``) on the actors' ``message``
    head.

    ``penalty_of_head(head) -> (T, B, K)`` is the bit penalty of each step's messages as a
    function of the head alone (the GRU states held fixed, ``Team.message_penalty``); its mean
    over the valid steps is what the head descends, by ``lr * price``.
    """
    params = actor_params["params"]
    valid = valid.astype(jnp.float32)

    def mean_penalty(head):
        per_step = penalty_of_head(head).sum(-1)
        return (per_step * valid).sum() / jnp.maximum(valid.sum(), 1.0)

    grads = jax.grad(mean_penalty)(params["message"])
    size = lr * price
    head = jax.tree.map(lambda p, g: p - size * g, params["message"], grads)
    return {**actor_params, "params": {**params, "message": head}}
