"""Command line: ``sparsecomm train | imitate | eval | render | reproduce`` (typed configs, tyro).

Every flag is a documented config field: ``sparsecomm train --help`` lists them all.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm import checkpoint
from sparsecomm.configs import ILConfig, RLConfig, from_dict
from sparsecomm.imitation import make_imitate
from sparsecomm.report import bootstrap_ci, plot_curves
from sparsecomm.rl import make_train
from sparsecomm.sharding import (
    RUNS,
    Distributed,
    is_primary,
    make_mesh,
    place_runs,
    to_host,
    use_mesh,
)
from sparsecomm.sweep import SweepSpec, run_sweep

EVAL_SEED_OFFSET = 1_000_003
"""Evaluation episodes use seed ``config.seed + EVAL_SEED_OFFSET + run``: disjoint from training."""


@dataclasses.dataclass
class Train:
    """Train teams by actor-critic RL through the channel; a sweep of lambdas x seeds."""

    config: RLConfig = RLConfig()
    """The learner."""
    seeds: int = 1
    """Seeds per lambda."""
    lams: tuple[float, ...] = (0.0,)
    """Bit-penalty weights to sweep (one vmapped program)."""
    out: Path = Path("runs/train")
    """Output folder: metrics.csv, tensorboard/, checkpoint/, results.json, curves.png, team.gif."""
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

    run: Path
    """Folder of a ``sparsecomm train`` run."""
    episodes: int = 1000
    """Episodes per run."""
    greedy: bool = False
    """Take the most probable action instead of sampling."""
    out: Path | None = None
    """JSON file to write (default: ``<run>/eval.json``)."""


@dataclasses.dataclass
class Render:
    """Write a GIF of one episode of a trained team (links drawn with the bits they carry)."""

    run: Path
    """Folder of a ``sparsecomm train`` run."""
    index: int = 0
    """Which run of the sweep (lambda-major, then seed)."""
    seed: int = 0
    """Episode seed."""
    out: Path | None = None
    """GIF path (default: ``<run>/team.gif``)."""
    fps: int = 12
    """Frames per second."""


def load_run(folder: Path):
    meta = checkpoint.load_meta(folder / "checkpoint")
    kinds = {"train": (RLConfig, make_train), "imitate": (ILConfig, make_imitate)}
    if meta.get("kind") not in kinds:
        raise ValueError(f"{folder} holds a {meta.get('kind')!r} run, not one of {list(kinds)}")
    config_cls, make = kinds[meta["kind"]]
    config = from_dict(config_cls, meta["config"])
    trainer = make(config)
    spec = SweepSpec(meta["seeds"], tuple(meta["lams"]))
    runs = spec.runs()
    keys = jnp.stack([jax.random.key(0)] * len(runs))
    template = jax.vmap(trainer.init)(keys, jnp.zeros(len(runs)))
    state = checkpoint.load(folder / "checkpoint", template)
    return config, trainer, runs, state


def evaluate_runs(trainer, runs, state, episodes: int, greedy: bool = False, devices=None) -> dict:
    """Evaluate every run of a sweep over ``episodes`` fresh episodes, with bootstrap CIs.

    The runs and episodes are split over ``devices`` (default: the local ones) as in training;
    with several processes every process must call this (pass ``jax.devices()``).
    """
    config = trainer.config
    keys = jnp.stack([jax.random.key(config.seed + EVAL_SEED_OFFSET + r) for r in range(len(runs))])
    mesh = make_mesh(len(runs), episodes, devices)
    params = place_runs(to_host(state.params["actor"]), mesh)
    spmd = RUNS if mesh is not None else None
    ev = jax.jit(
        jax.vmap(lambda p, k: trainer.evaluate(p, k, episodes, greedy), spmd_axis_name=spmd)
    )
    with use_mesh(mesh):
        metrics = to_host(ev(params, place_runs(keys, mesh)))
    per_run = [
        {"seed": s, "lam": lam, **{k: float(v[i]) for k, v in metrics.items()}}
        for i, (s, lam) in enumerate(runs)
    ]
    summary = {}
    for lam in sorted({lam for _, lam in runs}):
        idx = [i for i, (_, lm) in enumerate(runs) if lm == lam]
        summary[f"{lam:g}"] = {
            k: dict(zip(("mean", "ci_low", "ci_high"), bootstrap_ci(v[idx]), strict=True))
            for k, v in metrics.items()
        }
    return {"episodes_per_run": episodes, "greedy": greedy, "runs": per_run, "by_lambda": summary}


def render_run(trainer, actor_params, seed: int, out: Path, fps: int = 12) -> Path:
    from sparsecomm.envs.render import render_frames, write_gif
    from sparsecomm.rollout import rollout

    traj = jax.jit(
        lambda p, k: rollout(
            trainer.team, trainer.env, trainer.config.channel, p, k, 1, keep_states=True
        )
    )(actor_params, jax.random.key(seed))
    length = int(np.asarray(traj.valid).sum())
    states = jax.tree.map(lambda x: np.asarray(x)[:length, 0], traj.env_states)
    link_bits = np.asarray(traj.link_bits)[:length, 0]
    frames = render_frames(states, trainer.env.config, link_bits=link_bits)
    write_gif(out, frames, fps=fps)
    return out


def train(args: Train) -> dict:
    """Run ``sparsecomm train`` or ``sparsecomm imitate`` (by the type of ``args``)."""
    args.distributed.initialize()
    cfg = args.config
    kind = "imitate" if isinstance(args, Imitate) else "train"
    trainer = make_imitate(cfg) if kind == "imitate" else make_train(cfg)
    spec = SweepSpec(args.seeds, args.lams)
    t0 = time.time()
    state, runs = run_sweep(
        trainer,
        cfg,
        spec,
        args.out,
        num_updates=cfg.num_updates,
        episodes_per_update=cfg.num_envs,
        steps_per_episode=cfg.env.max_steps,
        chunk=args.chunk,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        tensorboard=args.tensorboard,
        progress=args.progress,
        kind=kind,
        devices=jax.devices(),
    )
    wall = time.time() - t0
    results = evaluate_runs(trainer, runs, state, args.eval_episodes, devices=jax.devices())
    results.update(
        env_steps=cfg.num_updates * cfg.num_envs * cfg.env.max_steps,
        wall_clock_s=wall,
        device=str(jax.devices()[0]),
        devices=jax.device_count(),
        processes=jax.process_count(),
    )
    if args.gif:  # gathered on every process (a collective under jax.distributed)
        actor0 = jax.tree.map(lambda x: x[0], to_host(state.params["actor"]))
    if not is_primary():
        return results
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"results -> {args.out / 'results.json'}")
    for lam, m in results["by_lambda"].items():
        print(
            f"  lambda={lam}: success {m['success_rate']['mean']:.3f} "
            f"[{m['success_rate']['ci_low']:.3f}, {m['success_rate']['ci_high']:.3f}], "
            f"length {m['episode_length']['mean']:.1f}, "
            f"group reward {m['group_reward']['mean']:.0f}, "
            f"bits/step {m['bits_per_step']['mean']:.1f}"
        )
    if cfg.num_updates > 0:
        metrics = ("group_reward", "episode_length", "success_rate", "bits_per_step")
        if kind == "imitate":
            metrics = ("imitation_loss", *metrics)
        curves = plot_curves(args.out / "metrics.csv", args.out / "curves.png", metrics)
        print(f"curves  -> {curves}")
    if args.gif:
        print(f"gif     -> {render_run(trainer, actor0, 0, args.out / 'team.gif')}")
    return results


def evaluate(args: Eval) -> dict:
    _, trainer, runs, state = load_run(args.run)
    results = evaluate_runs(trainer, runs, state, args.episodes, args.greedy)
    out = args.out or args.run / "eval.json"
    out.write_text(json.dumps(results, indent=2))
    print(json.dumps(results["by_lambda"], indent=2))
    print(f"-> {out}")
    return results


def render(args: Render) -> Path:
    _, trainer, runs, state = load_run(args.run)
    if not 0 <= args.index < len(runs):
        raise ValueError(f"index must be in [0, {len(runs) - 1}], got {args.index}")
    params = jax.tree.map(lambda x: x[args.index], state.params["actor"])
    out = render_run(trainer, params, args.seed, args.out or args.run / "team.gif", args.fps)
    print(f"-> {out}")
    return out


def main(argv: list[str] | None = None) -> None:
    import tyro

    from sparsecomm.reproduce import Reproduce, reproduce

    commands = {"train": Train, "imitate": Imitate, "eval": Eval, "render": Render}
    cmd = tyro.extras.subcommand_cli_from_dict({**commands, "reproduce": Reproduce}, args=argv)
    handler = {Train: train, Imitate: train, Eval: evaluate, Render: render, Reproduce: reproduce}
    handler[type(cmd)](cmd)


if __name__ == "__main__":
    main()
