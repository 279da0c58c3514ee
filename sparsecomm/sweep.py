"""Seeds x lambdas as one vmapped program, with progress, logs and resumable checkpoints.

Every learner (RL, imitation) exposes ``init(key, lam, budget) -> state`` and
``update_chunk(state, n) -> (state, metrics stacked over n updates)``. :func:`run_sweep` vmaps
them over the flattened grid of (lambda, budget, seed) runs (a budget of NaN is none), advances
all runs together chunk by chunk, and after each chunk appends one CSV row per run and update,
writes TensorBoard scalars (every metric under its written name, ``group/key``:
:mod:`sparsecomm.metric_names`), updates the progress bar, and every ``checkpoint_every``
chunks saves the whole batched state. A run that dies resumes from its last checkpoint and
ends with the same parameters as an uninterrupted one.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from sparsecomm import checkpoint, learners
from sparsecomm.configs import to_dict, upgrade
from sparsecomm.errors import CheckpointError, DivergedError, RunError
from sparsecomm.learner import Learner
from sparsecomm.metric_names import written
from sparsecomm.sharding import (
    RUNS,
    is_primary,
    make_mesh,
    place_runs,
    runs_on_devices,
    to_host,
    use_mesh,
)

FIRST_COLUMNS = ["seed", "lam", "budget", "update", "env_steps", "episodes"]
WALL_CSV = "wall.csv"
"""A run folder's wall-clock log: one row ``update, wall_s`` per compiled chunk, ``wall_s`` the
seconds the whole sweep (every run, one program) has trained when that chunk ended, compiling
and earlier invocations of a resumed sweep included (updates redone after a resume are counted
again: they cost time). Kept apart from ``metrics.csv`` so that the metrics of two identical
runs stay identical byte for byte."""
RECORD = "run.json"
"""A run folder's record of the run it holds, outside its checkpoint (a checkpoint alone cannot
prove which run it belongs to): the :func:`sweep_record` (kind, config, sweep axes, start),
``num_updates``, every parameter's shape (:func:`param_shapes`) and the SHA-256 of the rest
(``record_sha256``). :func:`run_sweep` writes it as a run starts or resumes;
:func:`sparsecomm.runfolder.check_record` compares a checkpoint with it before anything is
evaluated."""
METRIC_ORDER = [
    "group_reward",
    "episode_length",
    "success_rate",
    "bits_per_step",
    "wire_bits_per_step",
    "speaking_fraction",
    "datagrams_per_step",
    "datagram_bits_per_step",
    "penalty",
]


class Run(NamedTuple):
    """One run of a sweep."""

    seed: int
    """Seed offset s (the run uses ``config.seed + s``)."""
    lam: float
    """Bit-penalty weight (with a budget: the weight until the controller engages)."""
    budget: float | None
    """Payload bits per step that the controller meets, or ``None`` (fixed lambda)."""

    @property
    def group(self) -> str:
        """The name of the run's (lambda, budget) group, shared by its seeds."""
        return f"{self.lam:g}" if self.budget is None else f"budget={self.budget:g}/{self.lam:g}"


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """The runs of a sweep: every lambda with every budget and every seed."""

    seeds: int = 1
    """Number of seeds per (lambda, budget) (seed s uses ``config.seed + s``)."""
    lams: tuple[float, ...] = (0.0,)
    """Bit-penalty weights to sweep."""
    budgets: tuple[float | None, ...] = (None,)
    """Bit budgets (payload bits per step) to sweep; ``None``: the fixed lambda."""

    def __post_init__(self):
        if self.seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {self.seeds}")
        if not self.lams or any(not np.isfinite(x) or x < 0 for x in self.lams):
            raise ValueError(f"lams must be non-empty, finite and >= 0, got {self.lams}")
        if not self.budgets or any(
            b is not None and (not math.isfinite(b) or b < 0) for b in self.budgets
        ):
            raise ValueError(f"budgets must be non-empty, finite and >= 0, got {self.budgets}")

    def runs(self) -> list[Run]:
        return [
            Run(s, float(lam), None if b is None else float(b))
            for lam in self.lams
            for b in self.budgets
            for s in range(self.seeds)
        ]


def run_arrays(config, runs: list[Run]):
    """The learners' ``init`` arguments of every run: PRNG keys, lambdas and budgets (NaN for
    none), each with a leading run axis."""
    keys = jnp.stack([jax.random.key(config.seed + r.seed) for r in runs])
    lams = jnp.asarray([r.lam for r in runs], jnp.float32)
    budgets = jnp.asarray([np.nan if r.budget is None else r.budget for r in runs], jnp.float32)
    return keys, lams, budgets


def spec_from_meta(meta: dict) -> SweepSpec:
    """The sweep a checkpoint's metadata describes."""
    return SweepSpec(meta["seeds"], tuple(meta["lams"]), tuple(meta.get("budgets", [None])))


def _row_metrics(metrics: dict) -> list[str]:
    """The metric keys of a CSV row: :data:`METRIC_ORDER` first, then the rest by name."""
    rest = sorted(k for k in metrics if k not in METRIC_ORDER)
    return [k for k in METRIC_ORDER if k in metrics] + rest


def _truncate_csv(path: Path, max_update: int) -> None:
    """Drop rows logged after the checkpoint we resume from (they will be logged again), and a
    last row cut short by a kill."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or "update" not in rows[0]:
        path.unlink()
        return
    col, width = rows[0].index("update"), len(rows[0])

    def kept(row):
        try:
            return len(row) == width and int(row[col]) <= max_update
        except ValueError:
            return False

    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        csv.writer(f).writerows([rows[0]] + [r for r in rows[1:] if kept(r)])
    os.replace(tmp, path)


def tensorboard_run(run: Run) -> str:
    """The TensorBoard run (a folder under ``tensorboard/``) of one run of a sweep:
    ``lam=L/seed=S``, or ``budget=B/lam=L/seed=S`` for a budgeted run."""
    budget = "" if run.budget is None else f"budget={run.budget:g}/"
    return f"{budget}lam={run.lam:g}/seed={run.seed}"


class _Log:
    """A sweep's ``metrics.csv`` (one row per run and update) and TensorBoard scalars.

    Both name each metric as it is written (``group/key``, :func:`metric_names.written`). The
    CSV has one column per metric; TensorBoard has one writer per run of the sweep
    (:func:`tensorboard_run`) and one tag per metric, so each metric's chart shows every run.
    Only the writing process (process 0 under ``jax.distributed``) opens anything.
    """

    def __init__(
        self,
        out: Path,
        runs,
        steps_per_update: int,
        episodes_per_update: int,
        *,
        resume_at: int,
        tensorboard: bool,
        primary: bool,
    ):
        self.runs, self.steps, self.episodes = runs, steps_per_update, episodes_per_update
        self.csv = self.file = self.wall = self.wall_file = None
        self.tb = []
        if not primary:
            return
        path, wall = out / "metrics.csv", out / WALL_CSV
        for p in (path, wall):
            if resume_at > 0:
                _truncate_csv(p, resume_at)
            elif p.exists():
                p.unlink()
        new_wall = not wall.exists()
        self.wall_file = open(wall, "a", newline="")
        self.wall = csv.writer(self.wall_file)
        if new_wall:
            self.wall.writerow(["update", "wall_s"])
        self.header = path.exists() and resume_at > 0
        self.file = open(path, "a", newline="")
        self.csv = csv.writer(self.file)
        self.tb_dir = out / "tensorboard"
        if tensorboard:
            # A resumed run redoes the updates after its checkpoint: purge_step makes TensorBoard
            # drop the earlier events from that step on, so each update shows once.
            purge = (resume_at + 1) * steps_per_update if resume_at > 0 else None
            self._open_tb(purge, resume_at)

    def _open_tb(self, purge_step, update: int) -> None:
        """One TensorBoard writer per run, in its :func:`tensorboard_run` folder."""
        from tensorboardX import SummaryWriter

        self.tb = [
            SummaryWriter(
                str(self.tb_dir / tensorboard_run(run)),
                purge_step=purge_step,
                filename_suffix=f".{update}.{os.getpid()}",
            )
            for run in self.runs
        ]

    def sync(self, update: int) -> None:
        """Everything logged so far on disk, before a checkpoint that covers it. tensorboardX
        writes events from a queue in a thread, and its ``flush`` does not wait for the queue:
        closing the writer does, so the writer is closed and a new one (a new event file) opened.
        Without this a SIGKILL just after a checkpoint lost the TensorBoard points of its last
        updates for good (the resumed run starts after them)."""
        for f in (self.file, self.wall_file):
            if f is not None:
                f.flush()
        if self.tb:
            for writer in self.tb:
                writer.close()
            self._open_tb(None, update)

    def write(self, metrics: dict, first_update: int) -> None:
        """Log ``metrics`` ({name: (runs, n)}) of updates ``first_update`` .. + n - 1."""
        if self.csv is None:
            return
        names = _row_metrics(metrics)
        tags = [written(k) for k in names]
        if not self.header:
            self.csv.writerow(FIRST_COLUMNS + tags)
            self.header = True
        n = next(iter(metrics.values())).shape[1]
        for u in range(n):
            upd = first_update + u
            env_steps = upd * self.steps
            for r, run in enumerate(self.runs):
                values = [metrics[k][r, u] for k in names]
                budget = "" if run.budget is None else f"{run.budget:g}"
                self.csv.writerow(
                    [run.seed, run.lam, budget, upd, env_steps, upd * self.episodes]
                    + [f"{v:.6g}" for v in values]
                )
                if self.tb:
                    self._scalars(self.tb[r], tags, values, env_steps)
        self.file.flush()  # on disk before the checkpoint that covers these updates
        for writer in self.tb:
            writer.flush()

    @staticmethod
    def _scalars(writer, tags, values, env_steps: int) -> None:
        """One run's scalars of one update, at its env steps; a value that is not finite (a
        target not yet set, inf, or none, NaN) is left out."""
        for tag, v in zip(tags, values, strict=True):
            if np.isfinite(v):
                writer.add_scalar(tag, v, env_steps)

    def write_wall(self, update: int, wall_s: float) -> None:
        """Log that the sweep had trained ``wall_s`` seconds when update ``update`` ended."""
        if self.wall is not None:
            self.wall.writerow([update, f"{wall_s:.3f}"])
            self.wall_file.flush()

    def close(self) -> None:
        for f in (self.file, *self.tb, self.wall_file):
            if f is not None:
                f.close()


@functools.lru_cache(maxsize=16)
def compiled(learner, sharded: bool):
    """The learner's vmapped, jitted ``init`` and ``update_chunk`` (compiled once per learner).

    ``sharded``: the run axis is the mesh's ``runs`` axis (for the rollout's episode split).
    """
    spmd = RUNS if sharded else None
    init = jax.jit(jax.vmap(learner.init, spmd_axis_name=spmd))
    steps = jax.jit(
        jax.vmap(learner.update_chunk, (0, None), spmd_axis_name=spmd), static_argnums=1
    )
    return init, steps


def check_start(params: dict, start: dict, where: str, name: str = "init_from") -> None:
    """Refuse starting parameters ``start`` (no run axis) whose parts' shapes differ from
    ``params`` (a run axis first; arrays or ``jax.eval_shape``'s shapes), naming the part and
    the field ``name``: a ``RunError``."""
    for part, values in start.items():
        same = jax.tree.structure(params[part]) == jax.tree.structure(values) and all(
            t.shape[1:] == np.shape(v)
            for t, v in zip(jax.tree.leaves(params[part]), jax.tree.leaves(values), strict=True)
        )
        if not same:
            raise RunError(
                f"{name} {where}: its {part} network has other shapes than this run's "
                "(the agent config must match)"
            )


def _start_from(params: dict, start: dict, where: str) -> dict:
    """``params`` (with a run axis) with each part in ``start`` (no run axis) copied into every
    run; a part whose shapes differ is refused, naming it (:func:`check_start`)."""
    check_start(params, start, where)
    out = dict(params)
    for part, values in start.items():
        out[part] = jax.tree.map(
            lambda t, v: jnp.broadcast_to(jnp.asarray(v, t.dtype), t.shape), params[part], values
        )
    return out


def run_sweep(
    learner: Learner,
    spec: SweepSpec,
    out: str | Path,
    *,
    num_updates: int | None = None,
    chunk: int = 10,
    checkpoint_every: int = 10,
    resume: bool = True,
    tensorboard: bool = True,
    progress: bool = True,
    kind: str | None = None,
    on_chunk: Callable | None = None,
    devices=None,
    start_params=None,
    start_from: str = "",
):
    """Run (or resume) a sweep of ``learner``; returns a :class:`Sweep` (final state, runs,
    elapsed time).

    The learner says the rest: its config (recorded in the checkpoint; ``config.num_envs``
    episodes per update) and its task (``env.max_steps`` steps per episode, for the
    logged env steps). ``num_updates`` stops the sweep there instead of at
    ``config.num_updates`` (a resume continues from the checkpoint either way). ``kind``: what
    the run folder records, a learner kind's name (default: the kind of the learner's config,
    :mod:`sparsecomm.learners`).

    ``start_params`` (one run's parameters, no run axis): every run starts from them, with a
    fresh optimiser state (fine-tuning; ``start_from`` names where they came from, recorded in
    the checkpoint). A resumed sweep continues from its checkpoint instead.

    The runs, and each run's episodes, are split over ``devices`` (default: all local devices;
    :func:`sparsecomm.sharding.make_mesh`); pass ``[jax.devices()[0]]`` to keep everything on
    one device.
    """
    config = learner.config
    kind = learners.of_config(config).name if kind is None else kind
    num_updates = config.num_updates if num_updates is None else num_updates
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = spec.runs()
    mesh, steps, state = _first_state(learner, runs, devices, start_params, start_from)
    meta = {
        **sweep_record(kind, config, spec, start_from),
        "num_updates": num_updates,
        "chunk": chunk,
    }
    ckpt = out / "checkpoint"
    primary = is_primary()  # writes the logs and checkpoints
    start, elapsed = 0, 0.0
    if resume and checkpoint.exists(ckpt):  # a checkpoint that is there is used, or refused
        state, start, elapsed = _resumed(ckpt, meta, state, mesh)
    if primary:  # the run this folder holds from now on, before any checkpoint of it is saved
        write_record(out, sweep_record(kind, config, spec, start_from), state.params, num_updates)

    log, prog = _open_outputs(
        out, learner, runs, kind, num_updates, start, elapsed, tensorboard, progress, primary
    )
    done, chunks = start, 0
    while done < num_updates:
        n = min(chunk, num_updates - done)
        state, metrics = _train_chunk(steps, state, mesh, done, n, runs, ckpt, log, prog)
        done += n
        chunks += 1
        if chunks % checkpoint_every == 0 or done >= num_updates:
            log.sync(done)
            checkpoint.save(ckpt, state, {**meta, "elapsed_s": prog.elapsed()})
        if on_chunk is not None:
            on_chunk(done, state, metrics)
    prog.bar.close()
    log.close()
    return Sweep(state, runs, prog.elapsed())


def _open_outputs(
    out: Path, learner, runs, kind, num_updates, start, elapsed, tensorboard, progress, primary
):
    """The sweep's :class:`_Log` (its CSVs cut back to update ``start`` on a resume) and
    :class:`_Progress` (shown with ``progress``); only the primary process writes either."""
    steps_per_update = learner.config.num_envs * learner.env.max_steps
    log = _Log(
        out,
        runs,
        steps_per_update,
        learner.config.num_envs,
        resume_at=start,
        tensorboard=tensorboard,
        primary=primary,
    )
    prog = _Progress(
        kind, runs, num_updates, start, elapsed, steps_per_update, progress and primary
    )
    return log, prog


def _train_chunk(steps, state, mesh, done: int, n: int, runs, ckpt: Path, log, prog):
    """Advance every run ``n`` updates from update ``done``, returning the new state and the
    chunk's metrics ({name: (runs, n)} on every process), logged with the wall clock, checked
    for divergence (which stops the sweep) and shown on the progress bar."""
    with use_mesh(mesh):
        new_state, metrics = steps(state, n)
    metrics = to_host(metrics)
    log.write(metrics, done + 1)
    _stop_if_diverged(metrics, runs, done + 1, ckpt, prog.bar, log)
    log.write_wall(done + n, prog.elapsed())
    prog.show(done + n, n, metrics)
    return new_state, metrics


def _first_state(learner: Learner, runs: list[Run], devices, start_params, start_from: str):
    """The sweep's device mesh (or None), compiled ``update_chunk`` and first batched state:
    every run's ``init``, placed on the mesh, and with ``start_params`` (one run's parameters,
    no run axis) those parameters in every run with a fresh optimiser state."""
    config = learner.config
    keys, lams, budgets = run_arrays(config, runs)
    mesh = make_mesh(len(runs), config.num_envs, devices)
    init, steps = compiled(learner, mesh is not None)
    with use_mesh(mesh):
        state = init(*place_runs((keys, lams, budgets), mesh))
        if start_params is not None:
            params = _start_from(state.params, start_params, start_from)
            state = state.replace(params=params, opt_state=jax.vmap(learner.tx.init)(params))
    # init leaves some parts replicated: each run on its own device, as a chunk returns them,
    # so that the chunk compiles once (else a second time for the state its first call returns)
    return mesh, steps, runs_on_devices(state, mesh)


def _resumed(ckpt: Path, meta: dict, state, mesh):
    """The checkpoint's batched state (placed on ``mesh``; ``state`` gives its structure), the
    update it ends at and the seconds trained before it, or :class:`CheckpointError` when it
    records another run than ``meta``."""
    old = checkpoint.load_meta(ckpt)
    check_resumable(old, meta, ckpt)
    state = place_runs(checkpoint.load(ckpt, state), mesh)
    start = int(to_host(state.update).max())
    elapsed = float(old.get("elapsed_s", 0.0))
    return state, start, elapsed


class _Progress:
    """A sweep's progress bar (hidden unless ``show``) and clock: the seconds the sweep has
    trained, earlier invocations of a resumed sweep and compiling included."""

    def __init__(self, kind, runs, num_updates, start, elapsed, steps_per_update, show):
        self.bar = tqdm(
            total=num_updates,
            initial=start,
            disable=not show,
            unit="upd",
            desc=f"{kind} {len(runs)} run(s)",
            dynamic_ncols=True,
        )
        if show and start < num_updates:
            tqdm.write(
                f"{kind}: {len(runs)} run(s) from update {start}; compiling the first chunk "
                "(this can take a minute) ..."
            )
        self.runs, self.start, self.before = len(runs), start, elapsed
        self.steps_per_update = steps_per_update
        self.t0 = time.time()

    def elapsed(self) -> float:
        """Seconds trained: those before this invocation plus this one's so far."""
        return self.before + time.time() - self.t0

    def show(self, done: int, n: int, metrics: dict) -> None:
        """Advance the bar by a chunk's ``n`` updates, ending at update ``done``, and show its
        last update's metrics (mean over runs) and the env steps per second of the whole sweep
        (all runs, compilation included) in this invocation."""
        last = {k: float(metrics[k][:, -1].mean()) for k in METRIC_ORDER if k in metrics}
        self.bar.update(n)
        sps = (done - self.start) * self.runs * self.steps_per_update / (time.time() - self.t0)
        self.bar.set_postfix(
            succ=f"{last.get('success_rate', 0):.2f}",
            len=f"{last.get('episode_length', 0):.0f}",
            R=f"{last.get('group_reward', 0):.0f}",
            bits=f"{last.get('bits_per_step', 0):.1f}",
            wire=f"{last.get('wire_bits_per_step', 0):.0f}",
            speak=f"{last.get('speaking_fraction', 0):.0%}",
            sps=f"{sps:.0f}",
        )


RESUME_MAY_CHANGE = ("num_updates",)
"""Config fields a resume may change: no learner's update depends on ``num_updates``, so a run
extended from its checkpoint equals one started with the larger budget. Everything about the
run itself must match; how it is driven (``--chunk``, ``--checkpoint-every``, ``--progress``,
``--tensorboard``, ``--eval-episodes``) is not part of the checkpoint and may change freely."""


def sweep_record(kind: str, config, spec: SweepSpec, start_from: str = "") -> dict:
    """What a checkpoint's metadata records of the run itself (:func:`run_sweep` writes it and
    :func:`check_resumable` compares it): the kind, the config and the sweep's axes, as JSON
    reads them back (lists, not tuples)."""
    record = {
        "kind": kind,
        "config": to_dict(config),
        "seeds": spec.seeds,
        "lams": list(spec.lams),
        "budgets": list(spec.budgets),
        "start_from": start_from,
    }
    return json.loads(json.dumps(record))


def param_shapes(params) -> dict[str, list[int]]:
    """Every parameter array's shape (the run axis first) by its path, e.g.
    ``actor/params/Dense_0/kernel``: what :data:`RECORD` keeps of the networks."""
    return {
        jax.tree_util.keystr(path, simple=True, separator="/"): [int(n) for n in np.shape(leaf)]
        for path, leaf in jax.tree_util.tree_leaves_with_path(params)
    }


def record_digest(record: dict) -> str:
    """SHA-256 of a :data:`RECORD` (every field but ``record_sha256``, keys sorted)."""
    rest = {k: v for k, v in record.items() if k != "record_sha256"}
    return hashlib.sha256(json.dumps(rest, sort_keys=True).encode()).hexdigest()


def write_record(out: Path, record: dict, params, num_updates: int) -> Path:
    """Write a run folder's :data:`RECORD`: ``record`` (a :func:`sweep_record`), ``num_updates``,
    the shapes of ``params`` (a run axis first) and the digest of them all; swapped in whole."""
    data = {**record, "num_updates": num_updates, "params": param_shapes(params)}
    data["record_sha256"] = record_digest(data)
    path, new = Path(out) / RECORD, Path(out) / (RECORD + ".new")
    new.write_text(json.dumps(data, indent=2))
    os.replace(new, path)
    return path


def _differences(old, new, path: str = "", now: str = "now") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            where = f"{path}.{k}" if path else str(k)
            out += _differences(old.get(k, _MISSING), new.get(k, _MISSING), where, now)
        return out
    added = ADDED_FIELDS.get(tuple(path.split(".")[-2:]), _MISSING)
    if old is _MISSING and added is not _MISSING and _same(added, new):
        return []  # written before the field existed: its default is what that run did
    return [] if _same(old, new) else [f"{path} (checkpoint: {old!r}, {now}: {new!r})"]


ADDED_FIELDS = {
    ("config", "task"): "navigation",
    ("agent", "hears"): "nearest",
    ("experimental", "live_links_only"): True,
    ("env", "success_rule"): "together",
    ("env", "park_speed"): 0.3,
    ("agent", "reads_sent"): False,
    ("channel", "news_margin"): None,
}
"""Config fields added after run folders were first written, by (section, field),
with the default that does what runs before them did: a checkpoint without one reads back,
and resumes, as that default."""


def _same(old, new) -> bool:
    """One JSON value: 1 and 1.0 are one number, NaN is none, "4" is not 4, nor true 1."""
    if all(isinstance(x, int | float) and not isinstance(x, bool) for x in (old, new)):
        return old == new
    return type(old) is type(new) and old == new


class _Missing:
    def __repr__(self) -> str:
        return "missing"


_MISSING = _Missing()
_RECORD_DEFAULTS = {"budgets": [None], "start_from": ""}
"""Fields of a :func:`sweep_record` that older checkpoints lack, and what their absence means
(as :func:`spec_from_meta` reads it)."""


def _kind_name(kind):
    """A recorded learner kind by its name (older run folders recorded the command that
    trained it, :func:`sparsecomm.learners.named`); anything else as it is."""
    try:
        return learners.named(kind).name
    except (ValueError, TypeError):
        return kind


def differences(old: dict, new: dict, may_change=RESUME_MAY_CHANGE, now: str = "now") -> list:
    """Every field of the run where the checkpoint's metadata ``old`` differs from ``new`` (a
    :func:`sweep_record`), ``config`` fields in ``may_change`` aside, each with both values."""
    config = old.get("config", {})
    if not isinstance(config, dict):
        return [f"config (checkpoint: {config!r}, {now}: an object of the config's fields)"]
    config = upgrade(config)  # fields since moved, in today's places
    if "experimental" in new["config"]:  # written before the section: its fields one by one
        config = {"experimental": {}} | config
    old = {**old, "kind": _kind_name(old.get("kind", _MISSING))}
    new = {**new, "kind": _kind_name(new["kind"])}
    old_cfg = {k: v for k, v in config.items() if k not in may_change}
    new_cfg = {k: v for k, v in new["config"].items() if k not in may_change}
    diffs = _differences(old_cfg, new_cfg, "config", now)
    for field in ("kind", "seeds", "lams", "budgets", "start_from"):
        default = _RECORD_DEFAULTS.get(field, _MISSING)
        diffs += _differences(old.get(field, default), new[field], field, now)
    return diffs


def check_resumable(old: dict, meta: dict, ckpt: Path) -> None:
    """Refuse to resume a checkpoint of another run, naming every field that differs."""
    diffs = differences(old, meta)
    if diffs:
        raise CheckpointError(
            f"cannot resume from {ckpt}: this run differs in "
            + "; ".join(diffs)
            + " (use a new --out folder, or --no-resume to start over)"
        )


def _stop_if_diverged(metrics: dict, runs, first_update: int, ckpt: Path, bar, log) -> None:
    """Stop the sweep when an update of the chunk had a non-finite loss, gradient or parameter
    (``nonfinite`` > 0, flagged inside the compiled update): the checkpoint on disk, from before
    the chunk, stays the last good one."""
    bad = np.asarray(metrics.get("nonfinite", 0.0)) > 0
    if not np.any(bad):
        return
    bar.close()
    log.close()
    u = int(np.argmax(bad.any(axis=0)))  # the chunk's first update with a diverged run
    r = int(np.argmax(bad[:, u]))
    run = runs[r]
    where = f"lambda {run.lam:g}" + ("" if run.budget is None else f", budget {run.budget:g}")
    count = int(np.any(bad, axis=1).sum())
    kept = (
        f"the last good checkpoint {ckpt} is kept"
        if checkpoint.exists(ckpt)
        else ("no checkpoint had been saved yet")
    )
    raise DivergedError(
        f"training diverged: run {r} (seed {run.seed}, {where}) had a non-finite loss, gradient "
        f"or parameter at update {first_update + u} ({count} of {len(runs)} runs diverged "
        f"in this chunk); {kept}. Lower --config.lr or check the config."
    )


class Sweep(NamedTuple):
    """What :func:`run_sweep` returns."""

    state: object
    """The final batched state (a leading run axis)."""
    runs: list
    """The sweep's runs, in the order of the run axis."""
    elapsed_s: float
    """Wall-clock seconds of training, summed over every resume (compilation included)."""
