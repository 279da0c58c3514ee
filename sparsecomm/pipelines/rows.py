"""The one row schema of the frontier: what every summary of trained sweeps is made of.

A row summarises one (budget, lambda) group of a sweep's evaluation (a run folder's
``results.json``, or the ``eval.json`` ``sparsecomm eval`` writes beside it) over its seeds; its
figures are ``[mean, lo, hi]`` with 95% CIs of :func:`sparsecomm.stats.bootstrap_ci`.
:class:`Row` names every field. A row comes in two forms:

- the *plain* form, from an evaluation alone: ``learner``, ``series`` (where the sweep was
  given a name), ``budget``, ``lam``, ``seeds`` and the figures of :data:`COLUMNS`. Written by
  ``sparsecomm reproduce`` (``budget_summary.json``) and by ``--rl``/``--il`` without ``--task``
  of :mod:`sparsecomm.pipelines.frontier` (docs/budget.md);
- the *wire* form, from an evaluation and its run folder (its config, ``metrics.csv`` and
  ``wall.csv``): the plain fields, ``speaking_fraction`` (:data:`WIRE_COLUMNS`), the bits on a
  network of unicast links, what the channel and the learner were, how soon the group's
  training success passed 0.95, and each seed's figures. Written by ``sparsecomm paper-task``
  (``summary.json``, with ``part`` and ``greedy``) and by the frontier's ``--task``
  (docs/wire.md, with ``deployed``).

Files written before some fields existed are read through :func:`from_json`, the one place
where an older row becomes a row of this schema.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TypedDict

import numpy as np

from sparsecomm import runfolder
from sparsecomm.deploy.wire import HEADER_BYTES, UDP_IP_BYTES
from sparsecomm.jsonfile import write_json
from sparsecomm.metric_names import aliased_results
from sparsecomm.stats import bootstrap_ci, curves, first_pass, read_csv
from sparsecomm.sweep import WALL_CSV

TASKS = ("small", "paper")
LEARNERS = ("rl", "imitation")
COLUMNS = {
    "success": "episode/success_rate",
    "episode_length": "episode/episode_length",
    "payload_bits": "channel/bits_per_step",
    "wire_bits": "channel/wire_bits_per_step",
}
"""Row field -> the evaluation metric it summarises, in every row."""
WIRE_COLUMNS = COLUMNS | {"speaking_fraction": "channel/speaking_fraction"}
"""Row field -> the evaluation metric it summarises, in a row of the wire form."""
DATAGRAM_HEADER_BITS = 8 * (HEADER_BYTES + UDP_IP_BYTES)
"""376: the runtime's datagram header and MAC (19 bytes) and the IPv4 and UDP headers (28
bytes)."""
TARGET, WINDOW = 0.95, 10
"""The success a team must pass, and the updates of the moving average: 0.95, the speed target's
(docs/paper-task.md), and ``benchmarks/learner_race.py``'s default window, so a row and a race
count alike."""

CI = list[float]
"""``[mean, lo, hi]``: a mean over seeds and its 95% CI."""


class Row(TypedDict, total=False):
    """One (budget, lambda) group of a sweep over its seeds (a JSON object in ``summary.json``)."""

    learner: str
    """``"rl"`` or ``"imitation"``."""
    series: str | None
    """The sweep's name where it has one (say ``"RL team"``: imitation of a trained team);
    each series is compared with its own lambda-0 row. Absent or None: the learner's own."""
    budget: float | None
    """The payload budget (bits per step for the team); None: a fixed lambda."""
    lam: float
    """The penalty weight."""
    seeds: int
    """The runs the figures are over."""
    success: CI
    episode_length: CI
    payload_bits: CI
    """Payload bits per step of the team."""
    wire_bits: CI
    """Bits per step on the wire, frames included."""
    # The wire form:
    task: str
    """``"small"`` or ``"paper"``."""
    algo: str
    """RL: ``RLConfig.algo``; imitation: ``"dagger"`` while the expert's share of the driving
    falls, else ``"bc"``."""
    expert: str | None
    """Imitation: ``"oracle"`` or ``"rl"`` (a trained team); RL: None."""
    episodes_per_update: int
    counts: str | None
    """What the budget counts (``ChannelConfig.prices``: ``"payload"`` or ``"wire"``); None
    without a budget."""
    speaking_fraction: CI
    """The share of link-steps that speak."""
    network_bits: CI | None
    """Bits per step on a network of unicast UDP links: each speaking link's datagram, its
    sender's frame and the datagram's header and the IPv4 and UDP headers
    (:data:`DATAGRAM_HEADER_BITS` each). None for an evaluation without datagram counts."""
    check_bits: int
    link_gate: bool
    on_silence: str
    news_margin: float | None
    """The news that opens a silent link; None: the learned gate alone."""
    env_steps_to_095: float | None
    """Env steps per run at which the group's mean training success over its seeds, a moving
    average over :data:`WINDOW` updates, first exceeds 0.95 (None: never, or no logs)."""
    wall_s_to_095: float | None
    """Seconds of training of the whole sweep (compiling included: ``wall.csv``) at that point."""
    per_seed: dict[str, list]
    """Each run's ``seed`` and figures (:data:`WIRE_COLUMNS`, one value per seed): the row can
    be judged again after its run folder is gone (:func:`seed_runs`)."""
    # Added by the commands that write the rows:
    part: str
    """``sparsecomm paper-task``: the part the row comes from."""
    greedy: dict
    """``sparsecomm paper-task``: the :data:`WIRE_COLUMNS` figures and ``per_seed`` of the same
    runs taking their most probable actions."""
    deployed: dict
    """The frontier's ``--deployed``: what a deployment measured (:func:`deployed`)."""


def time_to_target(folder: str | Path) -> dict[tuple, tuple[float | None, float | None]]:
    """Per group ``(budget, lam)`` of a run folder: ``(env_steps, wall_s)`` per run at which
    the group's mean training success first passes :data:`TARGET` (see ``env_steps_to_095``);
    ``{}`` without ``metrics.csv``, ``wall_s`` None without ``wall.csv``."""
    folder = Path(folder)
    if not (folder / "metrics.csv").exists():
        return {}
    wall = read_csv(folder / WALL_CSV) if (folder / WALL_CSV).exists() else None
    success = curves(read_csv(folder / "metrics.csv"), "episode/success_rate")
    out = {}
    for (budget, lam), (steps, vals) in success.items():
        key = (None if np.isnan(budget) else float(budget), float(lam))
        u = first_pass(np.nanmean(vals, 0), TARGET, WINDOW)
        if u is None:
            out[key] = (None, None)
            continue
        update = round(steps[u] / steps[0])  # the log starts at update 1
        wall_s = None
        if wall is not None:  # the chunk that holds that update ended at this wall-clock
            ended = np.nonzero(wall["update"] >= update)[0]
            wall_s = float(wall["wall_s"][ended[0]]) if len(ended) else None
        out[key] = (float(steps[u]), wall_s)
    return out


def learner_of(config, learner: str) -> dict:
    """The row fields that say which learner made a group: ``algo``, ``expert``,
    ``episodes_per_update``."""
    if learner == "rl":
        return {"algo": config.algo, "expert": None, "episodes_per_update": config.num_envs}
    algo = "dagger" if config.beta_end < config.beta_start else "bc"
    expert = "oracle" if config.expert == "oracle" else "rl"
    return {"algo": algo, "expert": expert, "episodes_per_update": config.num_envs}


def network_bits(run: dict) -> float | None:
    """Bits per step on a network of unicast links for one evaluated run (``None`` when the
    evaluation has no datagram counts)."""
    datagrams, bits = "channel/datagrams_per_step", "channel/datagram_bits_per_step"
    if datagrams not in run or bits not in run:
        return None
    return run[bits] + DATAGRAM_HEADER_BITS * run[datagrams]


def _wire_row(runs: list[dict], budget, lam: float, config, task: str, learner: str, times):
    """A group's row of the wire form (fields in the order ``summary.json`` files hold them)."""
    counts = None if budget is None else config.channel.prices
    row = {"task": task, "learner": learner, **learner_of(config, learner)}
    row |= {"counts": counts, "budget": budget, "lam": lam, "seeds": len(runs)}
    for name, metric in WIRE_COLUMNS.items():
        row[name] = list(bootstrap_ci([r[metric] for r in runs]))
    network = [network_bits(r) for r in runs]
    row["network_bits"] = None if None in network else list(bootstrap_ci(network))
    row["check_bits"] = config.channel.check_bits
    row |= config.channel.link_rules
    steps, wall_s = (times or {}).get((budget, lam), (None, None))
    row["env_steps_to_095"], row["wall_s_to_095"] = steps, wall_s
    row["per_seed"] = {"seed": [r.get("seed") for r in runs]}
    row["per_seed"] |= {name: [float(r[m]) for r in runs] for name, m in WIRE_COLUMNS.items()}
    return row


def rows(
    results: dict,
    learner: str,
    series: str | None = None,
    *,
    config=None,
    task: str | None = None,
    times: dict | None = None,
) -> list[Row]:
    """The rows of one sweep's evaluation (its ``runs`` list), one per (budget, lambda) group,
    in ``series`` if given: the plain form, or with ``config`` and ``task`` the wire form
    (``times``: :func:`time_to_target` of the sweep's folder)."""
    if (config is None) != (task is None):
        raise ValueError("rows: config and task come together (the wire form), got one of them")
    if task is not None and task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    if learner not in LEARNERS:
        raise ValueError(f"learner must be one of {LEARNERS}, got {learner!r}")
    groups: dict[tuple, list[dict]] = {}
    for run in aliased_results(results)["runs"]:
        groups.setdefault((run.get("budget"), float(run["lam"])), []).append(run)
    out = []
    for (budget, lam), runs in groups.items():
        if config is None:
            row = {"learner": learner, "budget": budget, "lam": lam, "seeds": len(runs)}
            row |= {name: list(bootstrap_ci([r[m] for r in runs])) for name, m in COLUMNS.items()}
        else:
            row = _wire_row(runs, budget, lam, config, task, learner, times)
        if series is not None:
            row["series"] = series
        out.append(row)
    return out


def read_rows(
    path: str | Path, learner: str, series: str | None = None, task: str | None = None
) -> list[Row]:
    """The rows of an evaluation file; with ``task``, of the wire form, the config and the
    training logs read from the run folder that holds the file."""
    path = Path(path)
    results = json.loads(path.read_text())
    if task is None:
        return rows(results, learner, series)
    config = runfolder.read_config(path.parent)
    times = time_to_target(path.parent)
    return rows(results, learner, series, config=config, task=task, times=times)


def seed_runs(row: Row) -> list[dict]:
    """A row's runs back as evaluation runs (``results.json``'s fields: ``seed``, ``lam``,
    ``budget`` and the metrics of :data:`WIRE_COLUMNS`), one per seed, from its ``per_seed``;
    ``[]`` for a row written without them."""
    per = row.get("per_seed")
    if not per:
        return []
    runs = [{"seed": seed, "lam": row["lam"], "budget": row["budget"]} for seed in per["seed"]]
    for name, metric in WIRE_COLUMNS.items():
        for run, value in zip(runs, per[name], strict=True):
            run[metric] = value
    return runs


def row_key(row: Row) -> tuple:
    """What a row of the wire form stands for: a newer row of the same key replaces it."""
    fields = ("task", "learner", "counts", "budget", "lam")
    return (*(row[f] for f in fields), from_json(row).get("news_margin"))


def from_json(row: dict) -> Row:
    """A row as read from a ``summary.json``, in this schema: a row written before a field
    existed gets the value that field's absence meant. A wire-form row without ``news_margin``:
    the learned gate alone (None); without ``network_bits``: no datagram counts (None). (A row
    without ``series``, ``per_seed``, ``greedy`` or ``deployed`` has none: they stay absent.)"""
    if "task" in row:
        row = {"news_margin": None, "network_bits": None} | row
    return row


def load_rows(path: str | Path) -> list[Row]:
    """The rows of a ``summary.json`` (any written so far), through :func:`from_json`."""
    return [from_json(r) for r in json.loads(Path(path).read_text())]


def write_rows(table: list[Row], path: str | Path) -> Path:
    """The rows as JSON (non-finite numbers as null)."""
    path = Path(path)
    write_json(path, table)
    return path


def deployed(report: dict) -> dict:
    """What a deployment (``sparsecomm deploy``'s ``deploy.json``) measured, over its runs:
    ``{"runs", "episodes", "success", "network_bits", "identical_episodes"}``, the figures as
    ``[mean, lo, hi]`` (95% CIs over runs)."""
    runs = report["runs"]
    out = {"runs": len(runs), "episodes": report["episodes_per_run"]}
    for name, metric in (("success", "success_rate"), ("network_bits", "network_bits_per_step")):
        values = [r[metric] for r in runs]
        out[name] = list(bootstrap_ci(values)) if len(values) > 1 else [values[0]] * 3
    same = [r["simulation"].get("identical_episodes") for r in runs]
    out["identical_episodes"] = None if None in same else int(sum(same))
    return out
