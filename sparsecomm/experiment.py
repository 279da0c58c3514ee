"""Library runs behind the command line: train, imitate, evaluate, render, load a run.

Each command's arguments are a typed dataclass (``Train``, ``Imitate``, ``Eval``, ``Render``) whose
every field is documented; :mod:`sparsecomm.cli` only parses them. Tests, benchmarks and
``sparsecomm reproduce`` call these functions directly.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from sparsecomm import checkpoint
from sparsecomm.channel import NoiseConfig
from sparsecomm.configs import ILConfig, RLConfig, check_budget_fits, from_dict, to_dict
from sparsecomm.envs.navigation import NavigationEnv
from sparsecomm.envs.render import render_frames, write_gif
from sparsecomm.errors import RunError
from sparsecomm.imitation import make_imitate, oracle_expert, team_expert
from sparsecomm.jsonfile import write_json
from sparsecomm.memory import check_fits
from sparsecomm.rl import make_train
from sparsecomm.rollout import Expert, rollout
from sparsecomm.sharding import (
    RUNS,
    Distributed,
    is_primary,
    make_mesh,
    place_runs,
    to_host,
    use_mesh,
)
from sparsecomm.stats import bootstrap_ci, plot_curves
from sparsecomm.sweep import Run, SweepSpec, run_arrays, run_sweep, spec_from_meta

EVAL_SEED_OFFSET = 1_000_003
"""Evaluation episodes use seed ``config.seed + EVAL_SEED_OFFSET + run``: disjoint from training."""


@dataclasses.dataclass
class Train:
    """Train teams by actor-critic RL through the channel; a sweep of lambdas x budgets x seeds.
    ``sparsecomm train --preset small`` starts from a named preset (``configs.PRESETS``)."""

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
    init_from: Path | None = None
    """Fine-tune: every run starts from the parameters of run ``init_index`` of this run folder
    (actor and critic; an exported team gives the actor only) with a fresh optimiser, e.g. to
    retrain a team under another code or budget. The networks must have the same shapes."""
    init_index: int = 0
    """Which run of ``init_from`` (lambda-major, then budget, then seed)."""

    def __post_init__(self):
        _at_least(self, seeds=1, chunk=1, checkpoint_every=1, eval_episodes=1, init_index=0)
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
    """JSON file to write (default: ``<run>/eval.json``; ``runs/pretrained/eval.json`` for the
    shipped team)."""
    own_noise: bool = True
    """Evaluate under the channel noise the run was trained with; ``--no-own-noise``: under
    ``--noise.*`` instead (clean unless given)."""
    noise: NoiseConfig = NoiseConfig()
    """With ``--no-own-noise``: the channel noise to evaluate under (``--noise.erasure 0.2``,
    ``--noise.flip 0.01``, ...; ``sparsecomm.channel.noise``)."""

    def __post_init__(self):
        _at_least(self, episodes=1)


@dataclasses.dataclass
class Render:
    """Write a GIF of one episode of a trained team (links drawn with the bits they carry)."""

    run: Path | None = None
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team; default: the
    sparse team shipped with the package (:data:`PRETRAINED`)."""
    index: int = 0
    """Which run of the sweep (lambda-major, then seed)."""
    seed: int = 0
    """Episode seed."""
    out: Path | None = None
    """GIF path (default: ``<run>/team.gif``; ``runs/pretrained/team.gif`` for the shipped team)."""
    fps: int = 12
    """Frames per second."""

    def __post_init__(self):
        _at_least(self, index=0, fps=1)


@dataclasses.dataclass
class Export:
    """Export one trained team of a run as weights only (msgpack) and its config (JSON)."""

    run: Path
    """Folder of a ``sparsecomm train``/``imitate`` run."""
    out: Path
    """Folder to write ``team.json`` and ``actor.msgpack`` to."""
    index: int = 0
    """Which run of the sweep (lambda-major, then budget, then seed)."""
    note: str = ""
    """Free text stored in ``team.json`` (e.g. the command that trained it)."""

    def __post_init__(self):
        _at_least(self, index=0)


def _check_index(args, runs) -> None:
    if not 0 <= args.index < len(runs):
        raise RunError(
            f"{type(args).__name__}.index must be in [0, {len(runs) - 1}] (the runs of "
            f"{args.run}), got {args.index}"
        )


def _at_least(args, **lowest) -> None:
    """Refuse an integer field below its lowest allowed value, naming the field."""
    for name, low in lowest.items():
        value = getattr(args, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(
                f"{type(args).__name__}.{name} must be an integer >= {low}, got {value!r}"
            )


PRETRAINED = Path(__file__).parent / "pretrained" / "sparse_team"
"""The trained sparse team shipped with the package (docs/budget.md says how it was trained)."""


def load_expert(config: ILConfig) -> Expert:
    """The expert ``config`` names: the oracle, or run ``expert_index`` of the RL run folder (or
    exported team) ``expert_checkpoint``, acting greedily over its own channel."""
    if config.expert == "oracle":
        return oracle_expert(NavigationEnv(config.env))
    rl_config, trainer, runs, actor = load_run(Path(config.expert_checkpoint))
    if rl_config.env != config.env:
        raise RunError(
            "ILConfig.expert_checkpoint was trained on a different task (env config): "
            f"{rl_config.env} vs {config.env}"
        )
    if not 0 <= config.expert_index < len(runs):
        raise RunError(
            f"ILConfig.expert_index must be in [0, {len(runs) - 1}], got {config.expert_index}"
        )
    params = jax.tree.map(lambda x: x[config.expert_index], actor)
    return team_expert(trainer.team, rl_config.channel, params)


def learner_for(config: RLConfig | ILConfig):
    """The learner of a config: RL, or imitation of the expert the config names."""
    if isinstance(config, ILConfig):
        return make_imitate(config, load_expert(config))
    return make_train(config)


KINDS = {"train": RLConfig, "imitate": ILConfig}


def _learner(kind: str, config_dict: dict, where: Path):
    if kind not in KINDS:
        raise ValueError(f"{where} holds a {kind!r} run, not one of {list(KINDS)}")
    config = from_dict(KINDS[kind], config_dict)
    return config, learner_for(config)


def load_run(folder: Path):
    """A run folder (or an exported team's) as ``(config, learner, runs, actor_params)``, the
    actors' parameters with a leading run axis. Reads msgpack and JSON only (no pickle)."""
    config, trainer, runs, params = _load(folder)
    return config, trainer, runs, params["actor"]


def load_params(folder: Path, index: int = 0) -> dict:
    """The parameters of run ``index`` of a run folder (``{"actor", "critic"}``; an exported
    team has its actor only), without the run axis."""
    _, _, runs, params = _load(folder)
    if not 0 <= index < len(runs):
        raise RunError(
            f"init_index must be in [0, {len(runs) - 1}] (the runs of {folder}), got {index}"
        )
    return jax.tree.map(lambda x: np.asarray(x[index]), to_host(params))


def _load(folder: Path):
    """``(config, learner, runs, params)`` of a run folder or an exported team (its params: the
    actor only), every parameter with a leading run axis."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RunError(f"no run folder at {folder}")
    if (folder / "team.json").exists():  # an exported team: one run, weights only
        meta = json.loads((folder / "team.json").read_text())
        config, trainer = _learner(meta["kind"], meta["config"], folder)
        template = trainer.team.init(jax.random.key(0))["actor"]
        actor = serialization.from_bytes(template, (folder / "actor.msgpack").read_bytes())
        actor = jax.tree.map(lambda x: jnp.asarray(x)[None], actor)
        return config, trainer, [Run(**meta["run"])], {"actor": actor}
    meta = checkpoint.load_meta(folder / "checkpoint")
    config, trainer = _learner(meta.get("kind"), meta["config"], folder)
    runs = spec_from_meta(meta).runs()
    template = jax.vmap(trainer.init)(*run_arrays(config, runs))
    state = checkpoint.load(folder / "checkpoint", template)
    return config, trainer, runs, state.params


def export_team(args: Export) -> Path:
    """Write run ``args.index`` of a run folder as an exported team (see :class:`Export`)."""
    config, trainer, runs, actor = load_run(args.run)
    _check_index(args, runs)
    kind = "imitate" if isinstance(config, ILConfig) else "train"
    one = jax.tree.map(lambda x: np.asarray(x[args.index]), to_host(actor))
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {
        "kind": kind,
        "config": to_dict(config),
        "run": runs[args.index]._asdict(),
        "note": args.note,
    }
    write_json(args.out / "team.json", meta)
    (args.out / "actor.msgpack").write_bytes(serialization.to_bytes(one))
    print(f"-> {args.out}")
    return args.out


def evaluate_runs(
    trainer, runs, actor_params, episodes: int, greedy: bool = False, devices=None
) -> dict:
    """Evaluate every run of a sweep over ``episodes`` fresh episodes, with bootstrap CIs.

    The runs and episodes are split over ``devices`` (default: the local ones) as in training;
    with several processes every process must call this (pass ``jax.devices()``).
    """
    config = trainer.config
    keys = jnp.stack([jax.random.key(config.seed + EVAL_SEED_OFFSET + r) for r in range(len(runs))])
    mesh = make_mesh(len(runs), episodes, devices)
    params = place_runs(to_host(actor_params), mesh)
    spmd = RUNS if mesh is not None else None
    ev = jax.jit(
        jax.vmap(lambda p, k: trainer.evaluate(p, k, episodes, greedy), spmd_axis_name=spmd)
    )
    with use_mesh(mesh):
        metrics = to_host(ev(params, place_runs(keys, mesh)))
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
    trainer = learner_for(cfg)
    budgets = args.budgets or (cfg.budget.bits,)
    spec = SweepSpec(args.seeds, args.lams, tuple(budgets))
    check_fits(trainer, len(spec.runs()), args.eval_episodes, jax.devices())
    start = None if args.init_from is None else load_params(args.init_from, args.init_index)
    state, runs, wall = run_sweep(
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
        start_params=start,
        start_from="" if args.init_from is None else f"{args.init_from}:{args.init_index}",
    )
    actor = state.params["actor"]
    results = evaluate_runs(trainer, runs, actor, args.eval_episodes, devices=jax.devices())
    results.update(
        env_steps=cfg.num_updates * cfg.num_envs * cfg.env.max_steps,
        wall_clock_s=wall,
        device=str(jax.devices()[0]),
        devices=jax.device_count(),
        processes=jax.process_count(),
    )
    if args.gif:  # gathered on every process (a collective under jax.distributed)
        actor0 = jax.tree.map(lambda x: x[0], to_host(actor))
    if not is_primary():
        return results
    write_json(args.out / "results.json", results)
    print(f"results -> {args.out / 'results.json'}")
    for group, m in results["by_group"].items():
        name = group if group.startswith("budget") else f"lambda={group}"
        print(
            f"  {name}: success {m['success_rate']['mean']:.3f} "
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


def _run_and_outputs(run: Path | None) -> tuple[Path, Path]:
    """The run folder to read (default: the shipped team) and the folder to write beside it."""
    if run is None:
        return PRETRAINED, Path("runs/pretrained")
    return run, run


def evaluate(args: Eval) -> dict:
    run, outputs = _run_and_outputs(args.run)
    config, trainer, runs, actor = load_run(run)
    if not args.own_noise:
        channel = dataclasses.replace(config.channel, noise=args.noise)
        trainer = learner_for(dataclasses.replace(config, channel=channel))
    results = evaluate_runs(trainer, runs, actor, args.episodes, args.greedy)
    out = args.out or outputs / "eval.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, results)
    print(json.dumps(results["by_group"], indent=2))
    print(f"-> {out}")
    return results


def render(args: Render) -> Path:
    run, outputs = _run_and_outputs(args.run)
    _, trainer, runs, actor = load_run(run)
    _check_index(args, runs)
    params = jax.tree.map(lambda x: x[args.index], actor)
    out = args.out or outputs / "team.gif"
    out.parent.mkdir(parents=True, exist_ok=True)
    out = render_run(trainer, params, args.seed, out, args.fps)
    print(f"-> {out}")
    return out


@dataclasses.dataclass
class Deploy:
    """Run a trained team decentralised: one OS process per agent and one for the world, the
    channel's real packets as UDP datagrams between them, faults injected and survived
    (docs/deploy.md). Writes ``<out>/deploy.json`` (eval's metrics, CIs over episodes, and the
    simulation of the same episodes beside them)."""

    run: Path | None = None
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team; default: the
    sparse team shipped with the package (:data:`PRETRAINED`), as ``sparsecomm eval``."""
    index: tuple[int, ...] = (0,)
    """Which runs of the sweep to deploy, one after another (lambda-major, then budget, then
    seed); run r plays the episodes ``sparsecomm eval`` plays for it (key ``config.seed +
    EVAL_SEED_OFFSET + r``). Default: the first, as ``sparsecomm render``."""
    episodes: int = 100
    """Episodes per run. With the same number, deploy plays the very episodes of ``sparsecomm
    eval --episodes N`` (the draws depend on N). ours: 100 (eval: 1000; a deployed step is a
    round of datagrams, ~1 ms on loopback)."""
    greedy: bool = False
    """Take the most probable action instead of sampling (as ``sparsecomm eval --greedy``)."""
    out: Path | None = None
    """Output folder: deploy.json, and per run the exported team, the world's episodes.jsonl
    and links.csv (bytes per link and step), the processes' logs. Default: ``<run>/deploy``
    (``runs/pretrained/deploy`` for the shipped team)."""
    loss: float = 0.0
    """Probability that a datagram between agents is lost. ours: 0 (the issue's fault test:
    0.2). A packet missing at the step's deadline is the null message (``on_drop``)."""
    duplicate: float = 0.0
    """Probability that a datagram between agents arrives twice. ours: 0."""
    reorder: float = 0.0
    """Probability that a datagram between agents is held back up to ``reorder_delay`` seconds
    and overtaken by later ones. ours: 0."""
    reorder_delay: float = 0.02
    """Longest hold of a reordered datagram, seconds. ours: 0.02 (a tenth of the message
    deadline)."""
    garbage: float = 0.0
    """Probability that a garbage datagram (random bytes, or the datagram with bits flipped)
    is sent beside a datagram between agents. ours: 0 (the issue's fault test: 0.01)."""
    kills_per_episode: int = 0
    """Agent processes SIGKILLed per episode (a seeded agent at a seeded step in [1,
    ``kill_window``]); each is restarted and rejoins with its recurrent state reset. ours: 0
    (the issue's fault test: 1)."""
    kill_window: int = 8
    """Kills happen at a step in [1, kill_window]. ours: 8 (well inside a trained team's
    ~20-step episodes, so the kill and the rejoin happen mid-episode)."""
    fault_seed: int = 0
    """Seed of every fault draw (losses, duplicates, reordering, garbage, kills). ours: 0."""
    on_drop: str = "null"
    """What a receiver uses for a packet missing at the deadline: ``null`` (the null message,
    the issue's rule) or ``last`` (the link's last good message, as ``NoiseConfig.on_drop``
    for teams trained with it)."""
    message_deadline: float = 0.2
    """Seconds an agent waits, from its observation's arrival, for its peers' packets of the
    previous step (``Deadlines.message``). ours: 0.2."""
    action_deadline: float = 2.0
    """Seconds the world waits for each action; a missing action is 0, no force
    (``Deadlines.action``). ours: 2."""
    startup_deadline: float = 120.0
    """Seconds the world waits for every agent's first hello (``Deadlines.startup``). ours:
    120 (several processes import JAX and compile at once)."""
    host: str = "127.0.0.1"
    """Interface the processes listen on (free UDP ports are picked on it). ours: loopback.
    For agents on separate hosts start the processes by hand (docs/deploy.md)."""
    reference: bool = True
    """Also play the same episodes in simulation (the run's ``sparsecomm eval`` draws, with
    ``loss`` as the simulator's packet erasure) and report them side by side, with the count of
    identical episodes."""

    def __post_init__(self):
        _at_least(self, episodes=1, kills_per_episode=0, kill_window=1, fault_seed=0)
        if isinstance(self.index, int):
            self.index = (self.index,)
        if not self.index:
            raise ValueError("Deploy.index must name at least one run, got ()")
        for i in self.index:
            if isinstance(i, bool) or not isinstance(i, int) or i < 0:
                raise ValueError(f"Deploy.index must hold integers >= 0, got {self.index!r}")
        if self.on_drop not in ("null", "last"):
            raise ValueError(
                f"Deploy.on_drop must be one of ('null', 'last'), got {self.on_drop!r}"
            )
        if self.run is not None and not Path(self.run).is_dir():
            raise ValueError(f"Deploy.run must be a run folder, got {str(self.run)!r} (missing)")
        if not isinstance(self.host, str) or not self.host:
            raise ValueError(f"Deploy.host must be a host name or address, got {self.host!r}")
        try:
            self.faults()
            self.deadlines()
        except ValueError as e:  # name the flag, not the inner dataclass
            raise ValueError(_deploy_field(str(e))) from None

    def faults(self):
        from sparsecomm.deploy.faults import Faults

        return Faults(
            self.loss,
            self.duplicate,
            self.reorder,
            self.reorder_delay,
            self.garbage,
            self.fault_seed,
        )

    def deadlines(self):
        from sparsecomm.deploy.faults import Deadlines

        return Deadlines(
            self.message_deadline,
            self.action_deadline,
            self.startup_deadline,
            max(30.0, 2 * (self.action_deadline + self.message_deadline)),
        )


_DEPLOY_NAMES = {
    "Faults.seed": "Deploy.fault_seed",
    "Faults.": "Deploy.",
    "Deadlines.message": "Deploy.message_deadline",
    "Deadlines.action": "Deploy.action_deadline",
    "Deadlines.startup": "Deploy.startup_deadline",
}


def _deploy_field(message: str) -> str:
    for inner, outer in _DEPLOY_NAMES.items():
        message = message.replace(inner, outer)
    return message


def deploy(args: Deploy) -> dict:
    """Run ``sparsecomm deploy`` (:class:`Deploy`; ``sparsecomm.deploy.launcher``)."""
    from sparsecomm.deploy.launcher import deploy as run_deploy

    return run_deploy(args, load_run=load_run, pretrained=PRETRAINED, seed_offset=EVAL_SEED_OFFSET)
