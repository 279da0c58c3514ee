"""The frontier in packets (docs/wire.md): success against the bits a network carries.

Reads the evaluations of trained sweeps (a run folder's ``results.json``, or the ``eval.json``
``sparsecomm eval`` writes beside it) and writes to ``--out``

- ``summary.json``: a list of rows ``{"task": "small"|"paper", "learner": "rl"|"imitation",
  "counts": "payload"|"wire"|null, "budget": float|null, "lam": float, "seeds": int,
  "success": [mean, lo, hi], "episode_length": [...], "payload_bits": [...], "wire_bits":
  [...], "speaking_fraction": [...], "network_bits": [...]}``, one per (sweep, budget,
  lambda) group over its seeds, 95% CIs of :func:`sparsecomm.stats.bootstrap_ci`. ``counts``
  is what the group's budget counts (``ChannelConfig.prices``; ``null`` without a budget).
  ``network_bits`` are the bits per step the team puts on a network of unicast UDP links:
  each speaking link's datagram, its sender's frame (``datagram_bits_per_step``) and the
  datagram's header and the IPv4 and UDP headers (:data:`DATAGRAM_HEADER_BITS` each,
  ``datagrams_per_step``). A deployed team plays ``eval``'s episodes exactly, so this is what
  ``sparsecomm deploy`` measures; ``--deployed`` adds a deployment's measured figures to its
  row (``"deployed"``). ``null`` for an evaluation made before these counts existed.
  Each row also says which learner made it, and how soon: ``algo`` (RL: ``RLConfig.algo``;
  imitation: ``"dagger"`` while the expert's share of the driving falls, else ``"bc"``),
  ``expert`` (imitation: ``"oracle"`` or ``"rl"``, a trained team; RL: ``null``),
  ``episodes_per_update``, and ``env_steps_to_095`` / ``wall_s_to_095``: the env steps per run
  and the seconds of training of the whole sweep (one program for every group, compiling
  included: the folder's ``wall.csv``) at which the group's mean training success over its
  seeds, a moving average over :data:`WINDOW` updates, first exceeds 0.95 (``null``: never, or
  a folder without the logs). ``check_bits``, ``link_gate``, ``on_silence`` and
  ``news_margin`` say the channel; ``per_seed`` holds each run's ``seed`` and figures (the
  columns above, one value per seed), so that a row can be judged again after its run folder
  is gone (:func:`seed_runs`). A row replaces an earlier one of the same task, learner,
  counts, budget, lambda and ``news_margin`` (:func:`row_key`).
- ``frontier.png``: success against wire bits per step, and the share of link-steps that speak.

Command line (the numbers of docs/wire.md)::

    python -m sparsecomm.wire_frontier --task small --learner rl \\
        --runs RUN/eval.json OTHER/eval.json --out docs/results/wire
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sparsecomm import learners, runfolder
from sparsecomm.deploy.wire import HEADER_BYTES, UDP_IP_BYTES
from sparsecomm.jsonfile import write_json
from sparsecomm.metric_names import aliased_results
from sparsecomm.stats import bootstrap_ci, curves, first_pass, read_csv
from sparsecomm.sweep import WALL_CSV

TASKS = ("small", "paper")
LEARNERS = tuple(learners.KINDS)
COLUMNS = {
    "success": "episode/success_rate",
    "episode_length": "episode/episode_length",
    "payload_bits": "channel/bits_per_step",
    "wire_bits": "channel/wire_bits_per_step",
    "speaking_fraction": "channel/speaking_fraction",
}
"""Row field -> the evaluation metric it summarises."""
DATAGRAM_HEADER_BITS = 8 * (HEADER_BYTES + UDP_IP_BYTES)
"""376: the runtime's datagram header and MAC (19 bytes) and the IPv4 and UDP headers (28
bytes)."""
TARGET, WINDOW = 0.95, 10
"""The success a team must pass, and the updates of the moving average: 0.95, the speed target's
(docs/paper-task.md), and ``benchmarks/learner_race.py``'s default window, so a row and a race
count alike."""


def time_to_target(folder: str | Path) -> dict[tuple, tuple[float | None, float | None]]:
    """Per group ``(budget, lam)`` of a run folder: ``(env_steps, wall_s)`` per run at which
    the group's mean training success first passes :data:`TARGET` (see the module's doc);
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
    kind = learners.named(learner)
    algo = kind.algo_of(config)
    if kind is learners.RL:
        return {"algo": algo, "expert": None, "episodes_per_update": config.num_envs}
    expert = "oracle" if config.expert == "oracle" else learners.RL.name
    return {"algo": algo, "expert": expert, "episodes_per_update": config.num_envs}


def network_bits(run: dict) -> float | None:
    """Bits per step on a network of unicast links for one evaluated run, its metrics by
    written name (``None`` when the evaluation has no datagram counts)."""
    datagrams, bits = "channel/datagrams_per_step", "channel/datagram_bits_per_step"
    if datagrams not in run or bits not in run:
        return None
    return run[bits] + DATAGRAM_HEADER_BITS * run[datagrams]


def rows(results: dict, config, task: str, learner: str, times: dict | None = None) -> list[dict]:
    """The summary rows of one sweep's evaluation (its ``runs`` list) and config; ``times``:
    :func:`time_to_target` of its folder."""
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    if learner not in LEARNERS:
        raise ValueError(f"learner must be one of {LEARNERS}, got {learner!r}")
    groups: dict[tuple, list[dict]] = {}
    for run in aliased_results(results)["runs"]:
        groups.setdefault((run.get("budget"), float(run["lam"])), []).append(run)
    out = []
    for (budget, lam), runs in groups.items():
        counts = None if budget is None else config.channel.prices
        row = {"task": task, "learner": learner, **learner_of(config, learner)}
        row |= {"counts": counts, "budget": budget, "lam": lam, "seeds": len(runs)}
        for name, metric in COLUMNS.items():
            row[name] = list(bootstrap_ci([r[metric] for r in runs]))
        network = [network_bits(r) for r in runs]
        row["network_bits"] = None if None in network else list(bootstrap_ci(network))
        row["check_bits"] = config.channel.check_bits
        row["link_gate"] = config.channel.link_gate
        row["on_silence"] = config.channel.on_silence
        row["news_margin"] = config.channel.news_margin
        steps, wall_s = (times or {}).get((budget, lam), (None, None))
        row["env_steps_to_095"], row["wall_s_to_095"] = steps, wall_s
        row["per_seed"] = {"seed": [r.get("seed") for r in runs]}
        row["per_seed"] |= {name: [float(r[m]) for r in runs] for name, m in COLUMNS.items()}
        out.append(row)
    return out


def seed_runs(row: dict) -> list[dict]:
    """A summary row's runs back as evaluation runs (``results.json``'s fields: ``seed``,
    ``lam``, ``budget`` and the metrics of :data:`COLUMNS`), one per seed, from its
    ``per_seed``; ``[]`` for a row written without them."""
    per = row.get("per_seed")
    if not per:
        return []
    runs = [{"seed": seed, "lam": row["lam"], "budget": row["budget"]} for seed in per["seed"]]
    for name, metric in COLUMNS.items():
        for run, value in zip(runs, per[name], strict=True):
            run[metric] = value
    return runs


def row_key(row: dict) -> tuple:
    """What a row of ``summary.json`` stands for: a newer row of the same key replaces it. A
    row written before ``news_margin`` existed has none (the learned gate alone)."""
    fields = ("task", "learner", "counts", "budget", "lam")
    return (*(row[f] for f in fields), row.get("news_margin"))


def read_rows(path: str | Path, task: str, learner: str) -> list[dict]:
    """The rows of an evaluation file inside a run folder (its config read from the folder)."""
    path = Path(path)
    results = json.loads(path.read_text())
    config = runfolder.read_config(path.parent)
    return rows(results, config, task, learner, time_to_target(path.parent))


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


def plot(table: list[dict], out_png: str | Path) -> Path:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for r in table:
        name = "λ 0" if r["budget"] is None else f"{r['counts']} {r['budget']:g}"
        name = f"{r['task']}, {r['learner']}: {name}"
        if r.get("news_margin") is not None:
            name += " (news)"
        x, y, s = r["wire_bits"], r["success"], r["speaking_fraction"]
        axes[0].errorbar(
            x[0], y[0], xerr=[[x[0] - x[1]], [x[2] - x[0]]], yerr=[[y[0] - y[1]], [y[2] - y[0]]],
            fmt="o", capsize=3, label=name,
        )  # fmt: skip
        axes[1].errorbar(
            x[0], s[0], xerr=[[x[0] - x[1]], [x[2] - x[0]]], yerr=[[s[0] - s[1]], [s[2] - s[0]]],
            fmt="o", capsize=3, label=name,
        )  # fmt: skip
    axes[0].set(xlabel="wire bits per step", ylabel="success rate", xscale="log")
    axes[1].set(xlabel="wire bits per step", ylabel="link-steps that speak", xscale="log")
    for ax in axes:  # plain numbers on the log axis, at round values
        ax.set_xticks([16, 24, 32, 48, 64, 128, 256])
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    return out_png


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=TASKS, required=True)
    parser.add_argument("--learner", choices=LEARNERS, required=True)
    parser.add_argument(
        "--runs", nargs="+", required=True, help="results.json or eval.json inside run folders"
    )
    parser.add_argument(
        "--deployed",
        nargs="*",
        default=[],
        help="BUDGET=DEPLOY_JSON: a deployment (sparsecomm deploy's deploy.json) of the runs of "
        "the group with this budget (none: the lambda-0 group)",
    )
    parser.add_argument("--out", required=True, help="folder of summary.json (rows appended)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = out / "summary.json"
    table = json.loads(summary.read_text()) if summary.exists() else []
    new = [r for path in args.runs for r in read_rows(path, args.task, args.learner)]
    for spec in args.deployed:
        budget, _, report = spec.partition("=")
        want = None if budget == "none" else float(budget)
        for r in new:
            if r["budget"] == want:
                r["deployed"] = deployed(json.loads(Path(report).read_text()))
    keys = {row_key(r) for r in new}
    table = [r for r in table if row_key(r) not in keys] + new
    write_json(summary, table)
    plot(table, out / "frontier.png")
    for r in new:
        name = "λ 0" if r["budget"] is None else f"{r['counts']} budget {r['budget']:g}"
        net = "-" if r["network_bits"] is None else f"{r['network_bits'][0]:.0f}"
        print(
            f"{r['task']} {r['learner']} {name}: success {r['success'][0]:.3f} "
            f"[{r['success'][1]:.3f}, {r['success'][2]:.3f}], length {r['episode_length'][0]:.1f}, "
            f"payload {r['payload_bits'][0]:.1f}, wire {r['wire_bits'][0]:.1f}, speaking "
            f"{r['speaking_fraction'][0]:.0%}, network {net} ({r['seeds']} seeds)"
        )


if __name__ == "__main__":
    main()
