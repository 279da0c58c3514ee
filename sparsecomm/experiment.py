"""The commands behind the command line: train, imitate, evaluate, render, export.

Each command's arguments are a typed dataclass (``Train``, ``Imitate``, ``Eval``, ``Render``,
``Export``) whose every field is documented; :mod:`sparsecomm.cli` only parses them. Tests,
benchmarks and ``sparsecomm reproduce`` call these functions directly. Run folders and exported
teams are read and written by :mod:`sparsecomm.runfolder`; ``sparsecomm deploy`` lives in
:mod:`sparsecomm.deploy` (``deploy.args``, ``deploy.launcher``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm import learners
from sparsecomm.channel import NoiseConfig
from sparsecomm.configs import MAX_SEED, ILConfig, RLConfig, check_budget_fits
from sparsecomm.envs.render import write_gif
from sparsecomm.errors import RunError
from sparsecomm.jsonfile import write_json
from sparsecomm.memory import check_fits
from sparsecomm.metric_names import written_row
from sparsecomm.rollout import rollout
from sparsecomm.runfolder import (
    EVAL_SEED_OFFSET,
    PRETRAINED,
    RESULTS,
    at_least,
    at_most,
    check_index,
    check_output,
    default_output,
    learner_for,
    load_params,
    load_run,
    write_team,
)
from sparsecomm.sharding import (
    RUNS,
    Distributed,
    is_primary,
    make_mesh,
    place_runs,
    sweep_devices,
    to_host,
    use_mesh,
)
from sparsecomm.stats import bootstrap_ci, plot_curves
from sparsecomm.sweep import SweepSpec, check_start, run_arrays, run_sweep

MAX_FPS = 50
"""Most frames per second of a GIF (``sparsecomm render --fps``). A GIF stores each frame's
delay in whole centiseconds, and browsers show a delay under 2 cs (0 or 1: more than 50 fps) as
10 cs, so a faster GIF would play slower, and one over 100 fps would store a delay of 0."""


@dataclasses.dataclass
class Train:
    """Train teams by actor-critic RL through the channel; a sweep of lambdas x budgets x seeds.
    ``sparsecomm train --preset small`` starts from a named preset (``configs.PRESETS``),
    ``--task NAME`` from a registered task's defaults (``envs.registry``: ``navigation``,
    ``simple_reference`` and the tasks of the modules in ``SPARSECOMM_TASKS``)."""

    config: RLConfig = RLConfig()
    """The learner."""
    seeds: int = 1
    """Seeds per lambda."""
    lams: tuple[float, ...] = (0.0,)
    """Bit-penalty weights to sweep (one vmapped program). With ``--budgets``: the weight each
    run starts from (the controller sets it from then on)."""
    budgets: tuple[float | None, ...] = ()
    """Bit budgets to sweep (payload bits per step for the team, the paper's count), one vmapped
    program with the lambdas and seeds (``None``: fixed-lambda runs beside them); empty (the
    default): ``config.budget.bits`` alone."""
    out: Path = Path("runs/train")
    """Output folder: metrics.csv, tensorboard/, checkpoint/, results.json, curves.png, team.gif
    (a folder this user can write, or a path where one can be created: checked as the command
    starts)."""
    chunk: int = 10
    """Updates per compiled call: the logging and progress granularity."""
    checkpoint_every: int = 5
    """Save a checkpoint every this many chunks (and at the end)."""
    resume: bool = True
    """Continue from ``out/checkpoint`` when it exists."""
    tensorboard: bool = True
    """Write TensorBoard scalars to ``out/tensorboard``."""
    eval_episodes: int = 500
    """Episodes per run for the final evaluation written to results.json."""
    gif: bool = True
    """Render one episode of the first run's team to ``out/team.gif``."""
    progress: bool = True
    """Show a progress bar."""
    distributed: Distributed = dataclasses.field(default_factory=Distributed)
    """Multi-host: every process runs this command; the runs and episodes are split over all
    processes' devices, process 0 writes the files."""
    init_from: Path | None = None
    """Fine-tune: every run starts from the parameters of run ``init_index`` of this run folder
    (actor and critic; an exported team gives the actor only) with a fresh optimiser, e.g. to
    retrain a team under another code or budget. The networks must have the same shapes."""
    init_index: int = 0
    """Which run of ``init_from`` (lambda-major, then budget, then seed)."""

    def __post_init__(self):
        at_least(self, seeds=1, chunk=1, checkpoint_every=1, eval_episodes=1, init_index=0)
        SweepSpec(self.seeds, tuple(self.lams), tuple(self.budgets or ()) or (None,))
        check_budget_fits(self.config, self.budgets or None, "budgets")


@dataclasses.dataclass
class Imitate(Train):
    """Imitate an expert's actions through the channel; a sweep of lambdas x seeds."""

    config: ILConfig = ILConfig()
    """The learner."""
    out: Path = Path("runs/imitate")
    """Output folder: metrics.csv, tensorboard/, checkpoint/, results.json, curves.png, team.gif."""


@dataclasses.dataclass
class Eval:
    """Evaluate every run of a trained sweep over fresh episodes; print and write JSON."""

    run: Path | None = None
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team; default: the
    sparse team shipped with the package (:data:`PRETRAINED`)."""
    episodes: int = 1000
    """Episodes per run."""
    greedy: bool = False
    """Take the most probable action instead of sampling."""
    out: Path | None = None
    """JSON file to write, a writable file path, not a folder (default: ``<run>/eval.json``;
    ``runs/pretrained/eval.json`` for the shipped team)."""
    own_noise: bool = True
    """Evaluate under the channel noise the run was trained with; ``--no-own-noise``: under
    ``--noise.*`` instead (clean unless given)."""
    noise: NoiseConfig = NoiseConfig()
    """With ``--no-own-noise``: the channel noise to evaluate under (``--noise.erasure 0.2``,
    ``--noise.flip 0.01``, ...; ``sparsecomm.channel.noise``)."""

    def __post_init__(self):
        at_least(self, episodes=1)
        check_output(self, folder=False)


@dataclasses.dataclass
class Render:
    """Write a GIF of one episode of a trained team (links drawn with the bits they carry)."""

    run: Path | None = None
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team; default: the
    sparse team shipped with the package (:data:`PRETRAINED`)."""
    index: int = 0
    """Which run of the sweep (lambda-major, then seed)."""
    seed: int = 0
    """Episode seed, in [0, :data:`~sparsecomm.configs.MAX_SEED`] (the PRNG's 32 bits)."""
    out: Path | None = None
    """GIF path, a writable file path, not a folder (default: ``<run>/team.gif``;
    ``runs/pretrained/team.gif`` for the shipped team)."""
    fps: int = 12
    """Frames per second, in [1, :data:`MAX_FPS`] (the GIF's centisecond delays, its docstring
    says why). ours: 12."""

    def __post_init__(self):
        at_least(self, index=0, fps=1, seed=0)
        at_most(self, "experiment.MAX_FPS: a GIF's delay is >= 2 centiseconds", fps=MAX_FPS)
        at_most(self, "configs.MAX_SEED: the PRNG keeps 32 bits", seed=MAX_SEED)
        check_output(self, folder=False)


@dataclasses.dataclass
class Export:
    """Export one trained team of a run as weights only (msgpack) and its config (JSON)."""

    run: Path
    """Folder of a ``sparsecomm train``/``imitate`` run."""
    out: Path
    """Folder to write ``team.json`` and ``actor.msgpack`` to (a folder this user can write, or a
    path where one can be created)."""
    index: int = 0
    """Which run of the sweep (lambda-major, then budget, then seed)."""
    note: str = ""
    """Free text stored in ``team.json`` (e.g. the command that trained it)."""

    def __post_init__(self):
        at_least(self, index=0)
        check_output(self, folder=True)


def export_team(args: Export) -> Path:
    """Write run ``args.index`` of a run folder as an exported team (see :class:`Export`)."""
    config, _, runs, actor = load_run(args.run)
    check_index(args, runs)
    write_team(args.out, config, runs, actor, args.index, args.note)
    print(f"-> {args.out}")
    return args.out


def evaluate_runs(
    trainer, runs, actor_params, episodes: int, greedy: bool = False, devices=None
) -> dict:
    """Evaluate every run of a sweep over ``episodes`` fresh episodes, with bootstrap CIs;
    each metric under its written name (``group/key``, :mod:`sparsecomm.metric_names`).

    The runs and episodes are split over ``devices`` (default: all of them), or over as many
    as :func:`sparsecomm.sharding.sweep_devices` gives the runs, as in training; with several
    processes every process must call this.
    """
    devices = sweep_devices(len(runs), devices)
    config = trainer.config
    keys = jnp.stack([jax.random.key(config.seed + EVAL_SEED_OFFSET + r) for r in range(len(runs))])
    mesh = make_mesh(len(runs), episodes, devices)
    params = place_runs(to_host(actor_params), mesh)
    spmd = RUNS if mesh is not None else None
    ev = jax.jit(
        jax.vmap(lambda p, k: trainer.evaluate(p, k, episodes, greedy), spmd_axis_name=spmd)
    )
    with use_mesh(mesh):
        metrics = written_row(to_host(ev(params, place_runs(keys, mesh))))
    per_run = [
        {**run._asdict(), **{k: float(v[i]) for k, v in metrics.items()}}
        for i, run in enumerate(runs)
    ]
    summary = {}
    for group in dict.fromkeys(run.group for run in runs):  # in sweep order
        idx = [i for i, run in enumerate(runs) if run.group == group]
        summary[group] = {
            k: dict(zip(("mean", "ci_low", "ci_high"), bootstrap_ci(v[idx]), strict=True))
            for k, v in metrics.items()
        }
    return {"episodes_per_run": episodes, "greedy": greedy, "runs": per_run, "by_group": summary}


def render_run(trainer, actor_params, seed: int, out: Path, fps: int = 12) -> Path:
    """A GIF of one episode of the team (seed ``seed``) drawn by the task's ``render``; a
    ``RunError`` if the task draws nothing."""
    if not hasattr(trainer.env, "render"):
        raise RunError(f"task {trainer.config.task!r} has no render (envs/task.py)")
    traj = jax.jit(
        lambda p, k: rollout(
            trainer.team, trainer.env, trainer.config.channel, p, k, 1, keep_states=True
        )
    )(actor_params, jax.random.key(seed))
    length = int(np.asarray(traj.valid).sum())
    states = jax.tree.map(lambda x: np.asarray(x)[:length, 0], traj.aside.env_states)
    link_bits = np.asarray(traj.link_bits)[:length, 0]
    frames = trainer.env.render(states, link_bits)
    write_gif(out, frames, fps=fps)
    return out


def train(args: Train) -> dict:
    """Run ``sparsecomm train`` or ``sparsecomm imitate`` (by the learner kind of
    ``args.config``, :mod:`sparsecomm.learners`)."""
    # Here, not in __post_init__: a preset's default --out is built before the flags replace it.
    check_output(args, folder=True, error=RunError)
    args.distributed.initialize()
    cfg = args.config
    kind = learners.of_config(cfg)
    trainer = learner_for(cfg)
    budgets = args.budgets or (cfg.budget.bits,)
    spec = SweepSpec(args.seeds, args.lams, tuple(budgets))
    devices = sweep_devices(len(spec.runs()))
    check_fits(trainer, len(spec.runs()), args.eval_episodes, devices)
    start = None if args.init_from is None else load_params(args.init_from, args.init_index)
    where = "" if args.init_from is None else f"{args.init_from}:{args.init_index}"
    if start is not None:  # refused here, before run_sweep makes the output folder
        shapes = jax.eval_shape(jax.vmap(trainer.init), *run_arrays(cfg, spec.runs()[:1]))
        check_start(shapes.params, start, where, f"{type(args).__name__}.init_from")
    state, runs, wall = run_sweep(
        trainer,
        spec,
        args.out,
        chunk=args.chunk,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        tensorboard=args.tensorboard,
        progress=args.progress,
        kind=kind.name,
        devices=devices,
        start_params=start,
        start_from=where,
    )
    actor = state.params["actor"]
    results = evaluate_runs(trainer, runs, actor, args.eval_episodes, devices=devices)
    results.update(
        env_steps=cfg.num_updates * cfg.num_envs * trainer.env.max_steps,
        wall_clock_s=wall,
        device=str(devices[0]),
        devices=len(devices),
        processes=jax.process_count(),
    )
    if args.gif:  # gathered on every process (a collective under jax.distributed)
        actor0 = jax.tree.map(lambda x: x[0], to_host(actor))
    if not is_primary():
        return results
    print(f"results -> {write_json(args.out / RESULTS, results)}")
    _print_groups(results["by_group"])
    if cfg.num_updates > 0:
        print(f"curves  -> {write_curves(cfg, kind, args.out, trainer.env.num_agents)}")
    if args.gif and hasattr(trainer.env, "render"):
        print(f"gif     -> {render_run(trainer, actor0, 0, args.out / 'team.gif')}")
    elif args.gif:
        print(f"gif     -> none: task {cfg.task!r} has no render")
    return results


def write_curves(cfg, kind, out: Path, num_agents: int) -> Path:
    """A run folder's ``curves.png`` from its ``metrics.csv``: success, episode length, the
    bits per step the channel prices (``ChannelConfig.counted_metric``: wire or payload bits)
    with each budget's line, and the share of link-steps that speak; imitation first adds its
    loss."""
    bits = f"channel/{cfg.channel.counted_metric}"
    metrics = ("episode/success_rate", "episode/episode_length", bits, "channel/speaking_fraction")
    if kind is learners.IMITATION:
        metrics = ("loss/imitation_loss", *metrics)
    links = num_agents * (num_agents - 1) if cfg.budget.per_link else None
    return plot_curves(
        out / "metrics.csv",
        out / "curves.png",
        metrics,
        budget_metric=bits,
        budget_links=links,
        ncols=-(-len(metrics) // 2),
    )


def _print_groups(by_group: dict) -> None:
    """One line per run group of a ``results.json``: success with its CI, length, reward,
    payload and wire bits per step, the share of link-steps that speak."""
    for group, m in by_group.items():
        name = group if group.startswith("budget") else f"lambda={group}"
        success = m["episode/success_rate"]
        print(
            f"  {name}: success {success['mean']:.3f} "
            f"[{success['ci_low']:.3f}, {success['ci_high']:.3f}], "
            f"length {m['episode/episode_length']['mean']:.1f}, "
            f"group reward {m['episode/group_reward']['mean']:.0f}, "
            f"bits/step {m['channel/bits_per_step']['mean']:.1f} payload, "
            f"{m['channel/wire_bits_per_step']['mean']:.1f} wire, "
            f"{m['channel/speaking_fraction']['mean']:.0%} of link-steps speak"
        )


def _run_and_outputs(run: Path | None) -> tuple[Path, Path]:
    """The run folder to read (default: the shipped team) and the folder to write beside it."""
    if run is None:
        return PRETRAINED, Path("runs/pretrained")
    return run, run


def evaluate(args: Eval) -> dict:
    run, outputs = _run_and_outputs(args.run)
    out = default_output(args, outputs / "eval.json")
    config, trainer, runs, actor = load_run(run)
    if not args.own_noise:
        channel = dataclasses.replace(config.channel, noise=args.noise)
        trainer = learner_for(dataclasses.replace(config, channel=channel))
    results = evaluate_runs(trainer, runs, actor, args.episodes, args.greedy)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, results)
    print(json.dumps(results["by_group"], indent=2))
    print(f"-> {out}")
    return results


def render(args: Render) -> Path:
    run, outputs = _run_and_outputs(args.run)
    out = default_output(args, outputs / "team.gif")
    _, trainer, runs, actor = load_run(run)
    check_index(args, runs)
    params = jax.tree.map(lambda x: x[args.index], actor)
    out.parent.mkdir(parents=True, exist_ok=True)
    out = render_run(trainer, params, args.seed, out, args.fps)
    print(f"-> {out}")
    return out
