"""Run folders and exported teams: the one module that reads them, and writes exported teams.

A **run folder** is the ``--out`` of ``sparsecomm train`` or ``imitate``. Its ``checkpoint/``
(:data:`CHECKPOINT`, :mod:`sparsecomm.checkpoint`) holds the batched state of every run of the
sweep and the metadata: the learner kind (:mod:`sparsecomm.learners`), the config and the
sweep's axes, from which :func:`runs_of` rebuilds the list of runs.
:func:`sparsecomm.sweep.run_sweep` writes it, beside ``metrics.csv``, ``wall.csv``
(:data:`sparsecomm.sweep.WALL_CSV`), ``tensorboard/`` and ``run.json``
(:data:`sparsecomm.sweep.RECORD`: the run the folder holds, which every reader compares its
checkpoint with, :func:`check_record`);
:func:`sparsecomm.experiment.train` then writes :data:`RESULTS`, ``curves.png`` and
``team.gif``.

An **exported team** (``sparsecomm export``; every run ``sparsecomm deploy`` plays) is one run's
actor, weights only: :data:`TEAM` (JSON: the kind, the config, the run, a note) and
:data:`ACTOR` (the actor's parameters as msgpack, no run axis). :func:`write_team` alone writes
it; :func:`read_team` reads it without building a learner.

Everything that takes a folder takes either. Nothing here unpickles: msgpack and JSON only.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from sparsecomm import checkpoint, learners
from sparsecomm.configs import ILConfig, RLConfig, from_dict, to_dict
from sparsecomm.envs import registry
from sparsecomm.envs.task import Task
from sparsecomm.errors import CheckpointError, RunError
from sparsecomm.imitation import oracle_expert, team_expert
from sparsecomm.jsonfile import write_json
from sparsecomm.learner import Learner, make_team
from sparsecomm.rollout import Expert
from sparsecomm.sharding import to_host
from sparsecomm.sweep import (
    RECORD,
    Run,
    SweepSpec,
    differences,
    param_shapes,
    record_digest,
    run_arrays,
    spec_from_meta,
    sweep_record,
)

CHECKPOINT = "checkpoint"
"""A run folder's checkpoint folder."""
RESULTS = "results.json"
"""A run folder's final evaluation (``sparsecomm.experiment.evaluate_runs``)."""
TEAM, ACTOR = "team.json", "actor.msgpack"
"""An exported team's two files: its metadata and its actor's parameters."""

PRETRAINED = Path(__file__).parent / "pretrained" / "sparse_team"
"""The trained sparse team shipped with the package, an exported team (docs/budget.md says how
it was trained)."""

EVAL_SEED_OFFSET = 1_000_003
"""Evaluation episodes of run ``r`` use seed ``config.seed + EVAL_SEED_OFFSET + r``: disjoint
from training (``sparsecomm eval`` and ``sparsecomm deploy`` play the same ones)."""


def kind_of(config: RLConfig | ILConfig) -> str:
    """The learner kind's name (:data:`sparsecomm.learners.KINDS`) a run of ``config`` is
    recorded as."""
    return learners.of_config(config).name


def at_least(args, **lowest) -> None:
    """Refuse an integer field of ``args`` below its lowest allowed value, naming the field."""
    for name, low in lowest.items():
        value = getattr(args, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(
                f"{type(args).__name__}.{name} must be an integer >= {low}, got {value!r}"
            )


def at_most(args, why: str = "", **highest) -> None:
    """Refuse an integer field of ``args`` above its highest allowed value, naming the field
    (``why``: where the bound comes from, e.g. the constant that documents it)."""
    for name, high in highest.items():
        value = getattr(args, name)
        if isinstance(value, bool) or not isinstance(value, int) or value > high:
            because = f" ({why})" if why else ""
            raise ValueError(
                f"{type(args).__name__}.{name} must be an integer <= {high}{because}, got {value!r}"
            )


def output_problem(path: Path, folder: bool) -> str | None:
    """Why ``path`` cannot be written as an output folder (``folder``) or file, or None: it is
    a file where a folder is wanted or the other way round, it is not writable, or it cannot be
    created (its nearest existing parent is a file, or not writable). Looks only; writes
    nothing."""
    path = Path(path)
    want = "a folder" if folder else "a file"
    if path.exists():
        if path.is_dir() != folder:
            return f"must be {want} to write, and {path} is {'a file' if folder else 'a folder'}"
        if not os.access(path, os.W_OK | (os.X_OK if folder else 0)):
            return f"must be {want} this user can write, and {path} is not writable"
        return None
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot be created: {parent} is a file, not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot be created: the folder {parent} is not writable"
    return None


def check_output(args, name: str = "out", *, folder: bool, error=ValueError) -> None:
    """Refuse the output path ``args.<name>`` (None: the default, checked where it is made)
    unless :func:`output_problem` finds none, naming the field: a ``ValueError`` from a
    ``__post_init__``, so the command line refuses it while parsing, or ``error=RunError`` as
    the first step of a command."""
    path = getattr(args, name)
    if path is None:
        return
    problem = output_problem(Path(path), folder)
    if problem:
        raise error(f"{type(args).__name__}.{name} {problem}, got {str(path)!r}")


def default_output(args, path: Path, name: str = "out") -> Path:
    """``args.<name>``, or the default ``path`` (a file) checked as :func:`check_output` checks
    the field, refused with a ``RunError`` naming the field."""
    given = getattr(args, name)
    if given is not None:
        return Path(given)
    problem = output_problem(path, folder=False)
    if problem:
        raise RunError(f"{type(args).__name__}.{name} (default: {path}) {problem}")
    return path


def check_index(args, runs: list) -> None:
    """Refuse ``args.index`` outside the runs of the folder ``args.run``, naming the field."""
    if not 0 <= args.index < len(runs):
        raise RunError(
            f"{type(args).__name__}.index must be in [0, {len(runs) - 1}] (the runs of "
            f"{args.run}), got {args.index}"
        )


def load_expert(config: ILConfig) -> Expert:
    """The expert ``config`` names: the oracle, or run ``expert_index`` of the RL run folder (or
    exported team) ``expert_checkpoint``, acting greedily over its own channel."""
    if config.expert == "oracle":
        return oracle_expert(registry.make(config.env))
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


def learner_for(config: RLConfig | ILConfig) -> Learner:
    """The learner of a config, by its kind's ``make``: RL, or imitation of the expert the
    config names."""
    kind = learners.of_config(config)
    if kind is learners.IMITATION:
        return kind.make(config, load_expert(config))
    return kind.make(config)


def _config(meta: dict, where: Path) -> RLConfig | ILConfig:
    """The config recorded in a run folder's or exported team's metadata, read as its learner
    kind's config class (a kind recorded by its command, as older folders did, reads too)."""
    try:
        kind = learners.named(meta.get("kind"))
    except ValueError as e:
        raise ValueError(f"{where} holds a {meta.get('kind')!r} run: {e}") from None
    return from_dict(kind.config, meta["config"])


def is_team(folder: str | Path) -> bool:
    """``folder`` is an exported team (else a run folder, or nothing)."""
    return (Path(folder) / TEAM).exists()


def _team_meta(folder: Path) -> dict:
    if not is_team(folder):
        raise ValueError(f"team must be an exported team folder ({TEAM}), got {folder}")
    return json.loads((folder / TEAM).read_text())


def _team_config(folder: Path) -> RLConfig | ILConfig:
    """The config an exported team's metadata records; one it cannot be read back as (a task
    not registered, a field refused) is a ``CheckpointError`` naming the file."""
    try:
        return _config(_team_meta(folder), folder / TEAM)
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"{folder / TEAM} does not hold a valid team: {e}") from None


def read_meta(folder: str | Path) -> tuple[RLConfig | ILConfig, SweepSpec]:
    """The config and the sweep a run folder's checkpoint records, checked as a resume checks
    them (:func:`sparsecomm.sweep.differences`): the kind, config and axes it records must be
    the ones rebuilt from them, so a value of the wrong type, a missing field, a NaN or any other
    value the config refuses is a ``CheckpointError`` naming the field and ``config.json``,
    before anything is built from it. Reading the file's bytes is :func:`checkpoint.load_meta`'s
    (a digest mismatch, an unreadable file)."""
    config, spec, _ = _read_meta(folder)
    return config, spec


def _read_meta(folder: str | Path) -> tuple[RLConfig | ILConfig, SweepSpec, dict]:
    """:func:`read_meta`, and the checkpoint's metadata itself."""
    ckpt = Path(folder) / CHECKPOINT
    meta = checkpoint.load_meta(ckpt)
    where = checkpoint.meta_file(ckpt)
    try:
        config = _config(meta, where)
        spec = spec_from_meta(meta)
        record = sweep_record(meta["kind"], config, spec, meta.get("start_from", ""))
    except KeyError as e:
        raise CheckpointError(f"checkpoint file {where} has no field {e}") from None
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"checkpoint file {where} does not hold a valid run: {e}") from None
    diffs = differences(meta, record, may_change=(), now="read back")
    if diffs:
        raise CheckpointError(
            f"checkpoint file {where} does not hold a valid run (a field missing or not the "
            "one its config reads back): " + "; ".join(diffs)
        )
    return config, spec, meta


def _read_record(path: Path) -> dict:
    """A run folder's :data:`~sparsecomm.sweep.RECORD` as a :func:`sweep_record` read back
    through its config class (so one written before a field existed reads as that field's
    default), plus ``params``; unreadable, damaged (its SHA-256) or not a valid run is a
    ``CheckpointError`` naming the file."""
    try:
        data = json.loads(path.read_bytes().decode())
    except OSError as e:
        reason = e.strerror or type(e).__name__
        raise CheckpointError(f"run record {path} cannot be read ({reason})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"run record {path} is damaged (not valid JSON: {e})") from None
    if not isinstance(data, dict) or data.get("record_sha256") != record_digest(data):
        raise CheckpointError(
            f"run record {path} is damaged: its record_sha256 is not the SHA-256 of its other "
            "fields (edited, or not written by sparsecomm)"
        )
    try:
        config = _config(data, path)
        spec = spec_from_meta(data)
        record = sweep_record(data["kind"], config, spec, data.get("start_from", ""))
        shapes = data["params"]
        if not isinstance(shapes, dict) or not all(
            isinstance(v, list) and all(isinstance(n, int) for n in v) for v in shapes.values()
        ):
            raise ValueError(f"params must map each parameter to its shape, got {shapes!r}")
    except KeyError as e:
        raise CheckpointError(f"run record {path} has no field {e}") from None
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"run record {path} does not hold a valid run: {e}") from None
    return {**record, "params": shapes}


def _shape_differences(got: dict, want: dict) -> list[str]:
    """The first parameter whose shape in the checkpoint (``got``) is not the record's
    (``want``), both values, and how many more differ."""
    missing = "missing"
    diffs = [
        f"params {name} (checkpoint: {got.get(name, missing)}, {RECORD}: {want.get(name, missing)})"
        for name in sorted(set(got) | set(want))
        if got.get(name) != want.get(name)
    ]
    if len(diffs) > 1:
        return [f"{diffs[0]} and {len(diffs) - 1} more parameter(s)"]
    return diffs


def check_record(folder: Path, meta: dict, params) -> None:
    """Refuse a run folder whose checkpoint (its metadata ``meta``, its parameters ``params``
    with the run axis) is not the run its :data:`~sparsecomm.sweep.RECORD` records: a checkpoint
    swapped in from another run folder, or one edited consistently. The comparison is a
    resume's (:func:`sparsecomm.sweep.differences`: the kind, every config field but
    ``num_updates``, the sweep's axes, where it started from), then every parameter's shape; a
    ``CheckpointError`` names each field that differs with both values. A folder written before
    the record existed has none: one warning line, and its checkpoint is read as it is."""
    path = Path(folder) / RECORD
    if not path.exists():
        print(
            f"sparsecomm: warning: {folder} has no {RECORD} (written by an older sparsecomm): "
            "its checkpoint is read without checking it against the run that trained it",
            file=sys.stderr,
        )
        return
    record = _read_record(path)
    diffs = differences(meta, record, now=RECORD)
    diffs += _shape_differences(param_shapes(params), record["params"])
    if diffs:
        raise CheckpointError(
            f"run folder {folder} does not hold the run its {RECORD} records: its checkpoint "
            "differs in " + "; ".join(diffs) + " (a checkpoint from another run folder, or "
            "edited: put back this run's own checkpoint, or read the folder that trained it)"
        )


def runs_of(folder: str | Path) -> list[Run]:
    """The runs of a run folder or exported team, in the order of the run axis, read from its
    metadata alone."""
    folder = Path(folder)
    if is_team(folder):
        return [Run(**_team_meta(folder)["run"])]
    return read_meta(folder)[1].runs()


def read_config(folder: str | Path) -> RLConfig | ILConfig:
    """The config of a run folder or exported team, read from its metadata alone."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RunError(f"no run folder at {folder}")
    if is_team(folder):
        return _team_config(folder)
    return read_meta(folder)[0]


class ExportedTeam(NamedTuple):
    """An exported team loaded without building a learner: what an agent or world process
    needs, in a second."""

    config: RLConfig | ILConfig
    env: Task
    team: object  # sparsecomm.agents.Team
    actor: dict | None  # the actor's parameters (numpy), no run axis; None: not read
    run: Run


def write_team(folder: str | Path, config, runs: list[Run], actor, index: int, note: str = ""):
    """Write run ``index`` of a sweep (``actor``: its actors' parameters, leading run axis) as
    an exported team in ``folder``; returns the folder."""
    folder = Path(folder)
    one = jax.tree.map(lambda x: np.asarray(x[index]), to_host(actor))
    folder.mkdir(parents=True, exist_ok=True)
    meta = {"kind": kind_of(config), "config": to_dict(config), "run": runs[index]._asdict()}
    write_json(folder / TEAM, {**meta, "note": note})
    (folder / ACTOR).write_bytes(serialization.to_bytes(one))
    return folder


def read_team(folder: str | Path, weights: bool = True) -> ExportedTeam:
    """The exported team in ``folder``. ``weights=False``: its config only (``actor`` None)."""
    folder = Path(folder)
    meta = _team_meta(folder)
    config = _team_config(folder)
    env, team = make_team(config)
    actor = None
    if weights:
        actor = serialization.msgpack_restore((folder / ACTOR).read_bytes())
    return ExportedTeam(config, env, team, actor, Run(**meta["run"]))


class Actors(NamedTuple):
    """The teams of a folder, ready to play: what :func:`load_actors` returns."""

    config: RLConfig | ILConfig
    env: Task
    team: object  # sparsecomm.agents.Team
    runs: list[Run]
    actor: dict  # the actors' parameters, leading run axis


def load_actors(folder: str | Path) -> Actors:
    """The teams of a run folder or exported team, the actors' parameters with a leading run
    axis; an exported team is read without building a learner (a second instead of several)."""
    folder = Path(folder)
    if is_team(folder):
        loaded = read_team(folder)
        actor = jax.tree.map(lambda x: jnp.asarray(x)[None], loaded.actor)
        return Actors(loaded.config, loaded.env, loaded.team, [loaded.run], actor)
    config, trainer, runs, actor = load_run(folder)
    return Actors(config, trainer.env, trainer.team, runs, actor)


def load_run(folder: str | Path):
    """A run folder (or an exported team) as ``(config, learner, runs, actor_params)``, the
    actors' parameters with a leading run axis."""
    config, trainer, runs, params = _load(folder)
    return config, trainer, runs, params["actor"]


def load_params(folder: str | Path, index: int = 0) -> dict:
    """The parameters of run ``index`` of a run folder (``{"actor", "critic"}``; an exported
    team has its actor only), without the run axis."""
    _, _, runs, params = _load(folder)
    if not 0 <= index < len(runs):
        raise RunError(
            f"init_index must be in [0, {len(runs) - 1}] (the runs of {folder}), got {index}"
        )
    return jax.tree.map(lambda x: np.asarray(x[index]), to_host(params))


def _team_actor(folder: Path, template, raw: dict):
    """An exported team's actor parameters ``raw`` in the structure of ``template`` (the actor
    its config builds); another structure or shape (an ``actor.msgpack`` of another team) is a
    ``CheckpointError`` naming the file, the first parameter that differs and both shapes."""
    where = f"team file {folder / ACTOR} does not hold the actor its {TEAM} describes"
    try:
        actor = serialization.from_state_dict(template, raw)
    except (ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{where} ({type(e).__name__}: {e})") from None
    got, want = param_shapes(actor), param_shapes(template)
    for name in sorted(set(got) | set(want)):
        if got.get(name) != want.get(name):
            raise CheckpointError(
                f"{where}: {name} has shape {got.get(name, 'missing')} in {ACTOR}, "
                f"{want.get(name, 'missing')} in the actor its config builds"
            )
    return actor


def _load(folder: str | Path):
    """``(config, learner, runs, params)`` of a run folder or an exported team (its params: the
    actor only), every parameter with a leading run axis."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RunError(f"no run folder at {folder}")
    if is_team(folder):  # one run, weights only
        loaded = read_team(folder)
        trainer = learner_for(loaded.config)
        template = trainer.team.init(jax.random.key(0))["actor"]
        actor = _team_actor(folder, template, loaded.actor)
        actor = jax.tree.map(lambda x: jnp.asarray(x)[None], actor)
        return loaded.config, trainer, [loaded.run], {"actor": actor}
    config, spec, meta = _read_meta(folder)
    trainer = learner_for(config)
    runs = spec.runs()
    template = jax.vmap(trainer.init)(*run_arrays(config, runs))
    state = checkpoint.load(folder / CHECKPOINT, template)
    check_record(folder, meta, state.params)
    return config, trainer, runs, state.params
