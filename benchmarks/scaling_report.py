"""Tables and figures of docs/scaling.md from the throughput logs and the training runs.

    python benchmarks/scaling_report.py --throughput docs/results/scaling/throughput.txt \
        --runs runs/scaling/k10_mean runs/scaling/k10_mean_nb2 runs/scaling/k10_off \
        --out docs/results/scaling

    python benchmarks/scaling_report.py --each-runs runs/k10_each runs/k10_each_off ... \
        --out docs/results/scaling

Throughput: the lines ``benchmarks/train_throughput.py`` prints (one per run). Runs: folders of
``sparsecomm train`` (``results.json``, ``metrics.csv``, ``checkpoint/config.json``); per arm
the mean over seeds of the final evaluation with a BCa 95% CI over seeds
(``sparsecomm.stats.bootstrap_ci``), and learning curves. Writes ``throughput.png``,
``learning.png`` and ``tables.md``. Each-runs: the many-agent task's arms (``success_rule
each``), talking and silent at several K; writes ``learning.json`` (one row per arm),
``each.png`` (success against K; success and payload bits per link over training) and
``each.md``.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import tyro  # noqa: E402

from sparsecomm.metric_names import alias, aliased_results  # noqa: E402
from sparsecomm.stats import bootstrap_ci, read_csv, smooth  # noqa: E402

LINE = re.compile(
    r"train K=(?P<k>\d+) .*goal_view=(?P<view>\w+) neighbours=(?P<nb>\w+) radius=(?P<r>[\w.]+) "
    r"aggregate=(?P<agg>\w+) .*?: (?P<env>[\d,]+) env steps/s \((?P<agent>[\d,]+) agent steps/s\)"
    r".*?compile\+first (?P<compile>[\d.]+) s\) peak RSS (?P<rss>[\d.]+) GiB"
)


@dataclasses.dataclass
class Args:
    throughput: Path | None = None
    """Log of benchmarks/train_throughput.py lines."""
    runs: tuple[Path, ...] = ()
    """``sparsecomm train`` run folders, one per arm."""
    each_runs: tuple[Path, ...] = ()
    """``sparsecomm train`` run folders of the many-agent task, one per arm (K, talking or not)."""
    previous: Path | None = None
    """Each-runs: an earlier ``learning.json`` whose rows are kept beside the folders' (arms
    whose run folders are gone: their curves are not drawn). A folder's row replaces a previous
    row of the same K, talking, budget, lambda and number of updates."""
    seeds: tuple[int, ...] = ()
    """Each-runs: keep only the runs of these seeds (run s of a folder is seed ``config.seed +
    s``), e.g. the report seeds of a folder that also trained tuning seeds. Empty: every run."""
    out: Path = Path("docs/results/scaling")
    """Where the figures and tables go."""


def throughput_rows(path: Path) -> list[dict]:
    rows = []
    for line in path.read_text().splitlines():
        m = LINE.match(line)
        if m:
            d = m.groupdict()
            rows.append(
                {
                    "K": int(d["k"]),
                    "layout": f"{d['view']}, neighbours {d['nb']}, {d['agg']}",
                    "env": float(d["env"].replace(",", "")),
                    "agent": float(d["agent"].replace(",", "")),
                    "compile": float(d["compile"]),
                    "rss": float(d["rss"]),
                }
            )
    return rows


def _ci(vals: np.ndarray) -> list[float]:
    """Mean and BCa 95% interval over seeds (the value thrice when every seed agrees)."""
    est, lo, hi = bootstrap_ci(vals) if np.ptp(vals) > 0 else (vals.mean(),) * 3
    return [float(est), float(lo), float(hi)]


def arm(folder: Path) -> dict:
    cfg = json.loads((folder / "checkpoint" / "config.json").read_text())
    cfg = cfg.get("config", cfg)
    k = cfg["env"]["num_agents"]
    runs = aliased_results(json.loads((folder / "results.json").read_text()))["runs"]
    out = {"name": folder.name, "K": k, "seeds": len(runs), "updates": cfg["num_updates"]}
    for metric in ("success_rate", "group_reward", "bits_per_step", "links_per_step"):
        vals = np.array([r.get(alias(metric), np.nan) for r in runs], float)
        if metric == "bits_per_step":
            metric, vals = "bits_per_agent_step", vals / k
        if np.isnan(vals).all():
            continue
        out[metric] = _ci(vals)
    out["curves"] = read_csv(folder / "metrics.csv")
    return out


def _kept(folder: Path, seeds: tuple[int, ...]) -> tuple[dict, list[int]]:
    """The folder's saved run metadata and the indices of its runs to keep (all when ``seeds``
    is empty)."""
    meta = json.loads((folder / "checkpoint" / "config.json").read_text())
    n = len(json.loads((folder / "results.json").read_text())["runs"])
    base = meta["config"]["seed"]
    keep = [s for s in range(n) if not seeds or base + s in seeds]
    if not keep:
        raise ValueError(f"seeds: none of {seeds} was trained in {folder} (seeds {base}..)")
    return meta, keep


def learning_row(folder: Path, seeds: tuple[int, ...] = ()) -> dict:
    """One arm of the many-agent task as a row of ``learning.json``: the mean over its seeds of
    the final evaluation, with a BCa 95% CI over seeds; ``env_steps`` per seed. Beyond
    success, length and bits: ``lam``, ``budget`` (payload bits per step, ``null`` for none),
    ``budget_per_link`` (whether ``budget`` counts per link rather than for the team) and
    ``speaking`` (the fraction of existing links that sent, per step), ``engage_success`` (the
    batch success at which the budget's controller engages, ``null`` without one),
    ``seed_list`` (the seeds kept), ``updates`` and ``device`` (where it trained)."""
    meta, keep = _kept(folder, seeds)
    cfg = meta["config"]
    results = aliased_results(json.loads((folder / "results.json").read_text()))
    runs = [results["runs"][s] for s in keep]

    def metric(name):
        return _ci(np.array([r[alias(name)] for r in runs], float))

    return {
        "K": cfg["env"]["num_agents"],
        "comm": cfg["channel"]["mode"] != "off",
        "neighbours": cfg["agent"]["neighbours"],
        "seeds": len(runs),
        "success": metric("success_rate"),
        "episode_length": metric("episode_length"),
        "payload_bits": metric("bits_per_step"),
        "wire_bits": metric("wire_bits_per_step"),
        "links_per_step": metric("links_per_step"),
        "env_steps": int(results["env_steps"]),
        "lam": float(runs[0]["lam"]),
        "budget": cfg["budget"]["bits"],
        "budget_per_link": bool(cfg["budget"]["per_link"]),
        "speaking": metric("speaking_fraction"),
        "engage_success": cfg["budget"]["engage_success"] if cfg["budget"]["bits"] else None,
        "seed_list": [cfg["seed"] + s for s in keep],
        "updates": int(meta["num_updates"]),
        "device": results["device"],
    }


def _arm_key(r: dict) -> tuple:
    return r["K"], r["comm"], r["budget"], r["budget_per_link"], r["lam"], r["updates"]


def each_report(
    folders: tuple[Path, ...],
    out: Path,
    seeds: tuple[int, ...] = (),
    previous: Path | None = None,
) -> list[str]:
    """``learning.json``, ``each.png`` and the lines of ``each.md`` for the many-agent task."""
    new = [learning_row(f, seeds) for f in folders]
    old = json.loads(previous.read_text()) if previous is not None else []
    replaced = {_arm_key(r) for r in new}
    rows = [r for r in old if _arm_key(r) not in replaced] + new
    rows.sort(key=lambda r: (r["K"], r["budget"] is not None, not r["comm"]))
    (out / "learning.json").write_text(json.dumps(rows, indent=1) + "\n")
    lines = [
        "| K | talking | budget | neighbours | seeds | success | episode length | "
        "payload bits / step | wire bits / step | links / step | env steps per seed | updates | "
        "trained on |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def fmt(x, digits):
        return f"{x[0]:.{digits}f} [{x[1]:.{digits}f}, {x[2]:.{digits}f}]"

    def budget(r):
        if r["budget"] is None:
            return f"λ {r['lam']:g}" if r["comm"] else "-"
        return (
            f"{r['budget']:g} bits / {'link' if r['budget_per_link'] else 'team'} / step, "
            f"engaged at success {r['engage_success']:g}"
        )

    for r in rows:
        lines.append(
            f"| {r['K']} | {'yes' if r['comm'] else 'no'} | {budget(r)} | {r['neighbours']} | "
            f"{r['seeds']} | "
            f"{fmt(r['success'], 3)} | {fmt(r['episode_length'], 1)} | "
            f"{fmt(r['payload_bits'], 1)} | {fmt(r['wire_bits'], 1)} | "
            f"{fmt(r['links_per_step'], 1)} | {r['env_steps']:,} | {r['updates']} | {r['device']} |"
        )
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.4))
    arms = (
        (lambda r: r["comm"] and r["budget"] is None, "talking, λ 0", "o-"),
        (lambda r: not r["comm"], "silent", "o-"),
        (lambda r: r["budget"] is not None, "talking, payload budget", "s"),
    )
    for (keep, label, fmt_), shift in zip(arms, (0.0, 0.0, 0.6), strict=True):
        sel = sorted((r for r in rows if keep(r)), key=lambda r: r["K"])
        if not sel:
            continue
        # the budget's points beside λ 0's, and beside each other at the same K
        ks = [
            r["K"] + shift * (1 + [o["K"] for o in sel[:i]].count(r["K"]))
            for i, r in enumerate(sel)
        ]
        mean = np.array([r["success"][0] for r in sel])
        err = np.array(
            [[m - r["success"][1], r["success"][2] - m] for m, r in zip(mean, sel, strict=True)]
        ).T
        ax[0].errorbar(ks, mean, yerr=err, fmt=fmt_, capsize=3, label=label)
    ax[0].set(xlabel="agents K", ylabel="success (all parked), eval", ylim=(-0.03, 1.03))
    ax[0].set(xlim=(0, 32), xticks=(3, 10, 20, 30))  # the Ks of docs/scaling.md, whichever were run
    ax[0].legend(fontsize=7)
    for f, r in zip(folders, new, strict=True):
        c = read_csv(f / "metrics.csv")
        kept = _kept(f, seeds)[1]
        per_seed = [c["episode/success_rate"][c["seed"] == s] for s in kept]
        n = min(len(v) for v in per_seed)
        mean = np.mean([v[:n] for v in per_seed], 0)
        label = f"K = {r['K']}, {'talking' if r['comm'] else 'silent'} ({r['seeds']} seeds)"
        if r["budget"] is not None:
            label = f"K = {r['K']}, {budget(r)} ({r['seeds']} seeds, {r['device'].split(':')[0]})"
        line = ax[1].plot(np.arange(1, n + 1), smooth(mean, 25), label=label)[0]
        if r["comm"]:
            per_link = [
                (c["channel/bits_per_step"] / c["channel/links_per_step"])[c["seed"] == s][:n]
                for s in kept
            ]
            ax[2].plot(
                np.arange(1, n + 1), smooth(np.mean(per_link, 0), 25), color=line.get_color()
            )
            if r["budget"] is not None and r["budget_per_link"]:
                ax[2].axhline(r["budget"], color=line.get_color(), ls=":", lw=1)  # the budget
    ax[1].set(xlabel="update (32 episodes)", ylabel="success, training batches")
    ax[1].legend(fontsize=7)
    ax[2].set(xlabel="update (32 episodes)", ylabel="payload bits per link per step, training")
    ax[2].set_ylim(bottom=0)
    fig.tight_layout()
    fig.savefig(out / "each.png", dpi=120)
    return lines


def main(a: Args) -> None:
    a.out.mkdir(parents=True, exist_ok=True)
    if a.each_runs:
        each = each_report(a.each_runs, a.out, a.seeds, a.previous)
        (a.out / "each.md").write_text("\n".join(each) + "\n")
        print("\n".join(each))
        if a.throughput is None and not a.runs:
            return
    lines = []
    if a.throughput is not None:
        rows = throughput_rows(a.throughput)
        lines += [
            "| K | layout | env steps/s | agent steps/s | compile (s) | peak RSS (GiB) |",
            "|---|---|---|---|---|---|",
        ]
        for r in rows:
            lines.append(
                f"| {r['K']} | {r['layout']} | {r['env']:,.0f} | {r['agent']:,.0f} | "
                f"{r['compile']:.0f} | {r['rss']:.2f} |"
            )
        fig, ax = plt.subplots(1, 3, figsize=(13, 3.4))
        for layout in sorted({r["layout"] for r in rows}):
            sel = sorted((r for r in rows if r["layout"] == layout), key=lambda r: r["K"])
            ks = [r["K"] for r in sel]
            ax[0].plot(ks, [r["agent"] for r in sel], "o-", label=layout)
            ax[1].plot(ks, [r["rss"] for r in sel], "o-", label=layout)
        ax[0].set(xlabel="agents K", ylabel="agent steps/s (training update)", yscale="log")
        ax[1].set(xlabel="agents K", ylabel="peak RSS (GiB)")
        ax[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(a.out / "throughput.png", dpi=120)
        lines.append("")
    if a.runs:
        arms = [arm(f) for f in a.runs]
        lines += [
            "| arm | K | updates | seeds | success | group reward | bits/agent/step | links/step |",
            "|---|---|---|---|---|---|---|---|",
        ]

        def fmt(x, digits):
            if x is None:
                return "-"
            return f"{x[0]:.{digits}f} [{x[1]:.{digits}f}, {x[2]:.{digits}f}]"

        for r in arms:
            lines.append(
                f"| {r['name']} | {r['K']} | {r['updates']} | {r['seeds']} | "
                f"{fmt(r.get('success_rate'), 3)} | "
                f"{fmt(r.get('group_reward'), 0)} | {fmt(r.get('bits_per_agent_step'), 1)} | "
                f"{fmt(r.get('links_per_step'), 1)} |"
            )
        fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
        for r in arms:
            if any(
                o is not r
                and o["name"].startswith(r["name"].rsplit("_", 1)[0])
                and o["updates"] > r["updates"]
                and o["K"] == r["K"]
                for o in arms
            ):
                continue  # a prefix of a longer run of the same arm: its curve is drawn there
            c = r["curves"]
            for i, metric in enumerate(("group_reward", "success_rate", "bits_per_step")):
                per_seed = [c[alias(metric)][c["seed"] == s] for s in np.unique(c["seed"])]
                n = min(len(v) for v in per_seed)
                mean = np.mean([v[:n] for v in per_seed], 0)
                if metric != "success_rate":
                    mean = mean / r["K"]
                label = f"{r['name']} ({r['seeds']} seeds)"
                ax[i].plot(np.arange(1, n + 1), smooth(mean, 10), label=label)
        names = ("group reward / agent", "success rate", "bits / agent / step")
        for i, name in enumerate(names):
            ax[i].set(xlabel="update (32 episodes of 64 steps)", ylabel=name)
        ax[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(a.out / "learning.png", dpi=120)
    (a.out / "tables.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(Args))
