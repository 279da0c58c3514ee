"""Rollout and training throughput (env steps/s) and peak memory, by hand.

One "env step" is one step of the whole team in one episode. ``rollout`` plays episodes with the
actors and the channel, no gradient; ``train`` is a full update: rollout, loss, backpropagation
through the episode and through the channel, Adam step. Compile time excluded; the median of
``--repeats`` timed calls is reported.

    python benchmarks/train_throughput.py --mode train --num-envs 256 --seeds 1
    python benchmarks/train_throughput.py --mode train --budget 16     # with the budget controller
    python benchmarks/train_throughput.py --mode rollout --num-envs 256 --agents 5 --max-steps 128
    python benchmarks/train_throughput.py --agents 10 --num-envs 64 --max-steps 64 \
        --goal-view ring --neighbours 3 --aggregate mean     # many agents (docs/scaling.md)
    python benchmarks/train_throughput.py --agents 30 --num-envs 64 --max-steps 64 \
        --goal-view ring --neighbours 2 --aggregate mean --no-live-links-only  # masked links
    XLA_FLAGS=--xla_force_host_platform_device_count=2 \
        python benchmarks/train_throughput.py --mode train --sharded   # the sweep's device mesh
"""

from __future__ import annotations

import dataclasses
import resource
import statistics
import time
from typing import Literal

import jax
import tyro

from sparsecomm.budget import BudgetConfig
from sparsecomm.configs import AgentConfig, ExperimentalConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.rl import make_train
from sparsecomm.rollout import rollout
from sparsecomm.sharding import RUNS, make_mesh, place_runs, use_mesh


@dataclasses.dataclass
class Args:
    mode: Literal["rollout", "train"] = "train"
    """What to time."""
    num_envs: int = 256
    """Parallel episodes per seed."""
    agents: int = 3
    """K."""
    max_steps: int = 256
    """Episode length T."""
    seeds: int = 1
    """Vmapped seeds (independent runs)."""
    remat: bool = False
    """jax.checkpoint each step (train mode)."""
    updates: int = 2
    """Updates per timed call (train mode)."""
    repeats: int = 3
    """Timed calls."""
    budget: float | None = None
    """Train mode: a bit budget (payload bits per step), so the update runs the budget controller
    (``sparsecomm.budget``); None: the fixed lambda 0."""
    share_params: bool = True
    """One set of actor parameters for all agents (the default learner); ``--no-share-params``
    for separate ones (the paper's)."""
    goal_view: str = "others"
    """Who sees whose goal (``NavConfig.goal_view``): ``others`` (paper) or ``ring``."""
    neighbours: int | None = None
    """Each agent hears at most this many nearest agents (``AgentConfig.neighbours``)."""
    radius: float | None = None
    """Links only within this distance (``AgentConfig.radius``)."""
    aggregate: str = "concat"
    """The actors' inbox: ``concat``, ``mean`` or ``attention`` (``AgentConfig.aggregate``)."""
    live_links_only: bool = True
    """With ``neighbours`` and a ``mean`` / ``attention`` inbox, compute only the live links
    (``ExperimentalConfig.live_links_only``); ``--no-live-links-only``: all K (K - 1), masked (the
    former computation)."""
    sharded: bool = False
    """Train mode: split the seeds and episodes over all local devices as ``run_sweep`` does
    (``sparsecomm.sharding``); otherwise everything runs on the default device."""


def main(a: Args) -> None:
    env = NavConfig(num_agents=a.agents, max_steps=a.max_steps, goal_view=a.goal_view)
    agent = AgentConfig(
        share_params=a.share_params,
        neighbours=a.neighbours,
        radius=a.radius,
        aggregate=a.aggregate,
    )
    cfg = RLConfig(
        env=env,
        num_envs=a.num_envs,
        remat=a.remat,
        agent=agent,
        experimental=ExperimentalConfig(live_links_only=a.live_links_only),
        budget=BudgetConfig(bits=a.budget),
    )
    tr = make_train(cfg)
    keys = jax.random.split(jax.random.key(0), a.seeds)
    mesh = make_mesh(a.seeds, a.num_envs) if a.sharded and a.mode == "train" else None
    spmd = RUNS if mesh is not None else None
    with use_mesh(mesh):
        budget = float("nan") if a.budget is None else a.budget
        state = jax.jit(jax.vmap(tr.init, (0, None, None), spmd_axis_name=spmd))(
            place_runs(keys, mesh), 0.0, budget
        )
    if a.mode == "train":
        update = jax.jit(jax.vmap(lambda s: tr.update_chunk(s, a.updates)[0], spmd_axis_name=spmd))

        def fn(s):
            with use_mesh(mesh):
                return update(s)

        steps_per_call = a.seeds * a.updates * a.num_envs * a.max_steps
        arg = state
    else:

        def play(params, key):
            traj = rollout(tr.team, tr.env, cfg.channel, params, key, a.num_envs)
            return traj.payload_bits.sum()

        fn = jax.jit(jax.vmap(play))
        steps_per_call = a.seeds * a.num_envs * a.max_steps
        arg = (state.params["actor"], keys)
    call = (lambda: fn(arg)) if a.mode == "train" else (lambda: fn(*arg))
    t0 = time.perf_counter()
    jax.block_until_ready(call())
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    dev = jax.devices()[0]
    mem = dev.memory_stats() or {}
    peak_dev = mem.get("peak_bytes_in_use", 0) / 2**30
    layout = dict(mesh.shape) if mesh is not None else "one device"
    print(
        f"{a.mode} K={a.agents} T={a.max_steps} envs={a.num_envs} seeds={a.seeds} "
        f"remat={a.remat} shared={a.share_params} budget={a.budget} goal_view={a.goal_view} "
        f"neighbours={a.neighbours} radius={a.radius} aggregate={a.aggregate} "
        f"live_links_only={a.live_links_only} ({layout}): "
        f"{steps_per_call / med:,.0f} env steps/s ({a.agents * steps_per_call / med:,.0f} agent "
        f"steps/s) "
        f"(median of {a.repeats}, "
        f"{med:.2f} s/call; compile+first {compile_s:.1f} s) peak RSS {peak_rss:.2f} GiB"
        + (f", device peak {peak_dev:.2f} GiB" if peak_dev else "")
        + f" on {dev.platform} jax {jax.__version__}"
    )


if __name__ == "__main__":
    main(tyro.cli(Args))
