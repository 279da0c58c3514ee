"""The memory a sweep needs, known before anything is allocated or compiled.

:func:`estimate` traces (``jax.eval_shape``, no allocation) one run's state, the residuals that
its update's backward pass keeps (``jax.vjp`` of the learner's loss: every activation of every
step of every episode), its gradients, and the rollout of the final evaluation, and multiplies
by the number of runs. :func:`check_fits` compares that with the memory of the devices present
and refuses, with the estimate and the flags that lower it, what cannot fit. XLA reuses buffers,
so the estimate is not exact: on the CPU it came within 10% below XLA's own memory analysis of
the compiled update (docs/reliability.md), and :data:`MARGIN` covers that.
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp

from sparsecomm.errors import TooLargeError
from sparsecomm.rollout import episode_metrics, rollout

GIB = 2.0**30
MARGIN = 1.25
"""Headroom on the estimate when checking it: on the CPU the estimate came within 10% below
XLA's own memory analysis of the compiled update (docs/reliability.md)."""


def _bytes(tree) -> int:
    def size(x):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            return 8  # a threefry key: two uint32
        return jnp.dtype(x.dtype).itemsize

    return sum(math.prod(x.shape) * size(x) for x in jax.tree.leaves(tree))


def estimate(learner, num_runs: int, eval_episodes: int) -> dict:
    """Bytes a sweep of ``num_runs`` runs of ``learner`` needs: per run and in all."""
    key = jax.random.key(0)
    state = jax.eval_shape(learner.init, key, 0.0)

    def residuals(params):
        return jax.vjp(
            lambda p: learner.loss(p, key, 0.0, jnp.zeros((), jnp.int32)), params, has_aux=True
        )[1]

    saved = jax.eval_shape(residuals, state.params)
    cfg = learner.config

    def evaluation(params):
        traj = rollout(learner.team, learner.env, cfg.channel, params, key, eval_episodes)
        return traj, episode_metrics(traj)

    final = jax.eval_shape(evaluation, state.params["actor"])
    train = _bytes(state) + _bytes(saved) + _bytes(state.params)  # + gradients
    per_run = max(train, _bytes(final) + _bytes(state))
    return {"per_run": per_run, "total": per_run * num_runs, "num_runs": num_runs}


def available(devices=None) -> tuple[int, str]:
    """Bytes the devices can hold, and their name: the accelerators' memory limit, or the
    host's available memory for the CPU."""
    devices = devices or jax.devices()
    dev = devices[0]
    if dev.platform != "cpu":
        stats = dev.memory_stats() or {}
        limit = stats.get("bytes_limit")
        if limit:
            return int(limit) * len(devices), f"{len(devices)} x {dev.device_kind}"
    try:
        with open("/proc/meminfo") as f:
            info = dict(line.split(":", 1) for line in f)
        return int(info["MemAvailable"].split()[0]) * 1024, "the host (MemAvailable)"
    except (OSError, KeyError, ValueError):
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        return int(pages), "the host (physical memory)"


def check_fits(learner, num_runs: int, eval_episodes: int, devices=None) -> dict:
    """Refuse (:class:`TooLargeError`) a sweep whose estimate exceeds what the devices hold."""
    need = estimate(learner, num_runs, eval_episodes)
    have, where = available(devices)
    if MARGIN * need["total"] > have:
        cfg = learner.config
        raise TooLargeError(
            f"this sweep needs about {need['total'] / GIB:.1f} GiB ({num_runs} run(s) x "
            f"{need['per_run'] / GIB:.2f} GiB: state, and {cfg.num_envs} episodes x "
            f"{learner.env.max_steps} steps kept for the backward pass), more than the "
            f"{have / GIB:.1f} GiB of {where}; lower --seeds, --lams or --budgets (runs), "
            "--config.num-envs, --config.env.max-steps, --config.agent.hidden/--config.agent.gru "
            "or --config.channel.num-elements, or set --config.remat"
        )
    return need
