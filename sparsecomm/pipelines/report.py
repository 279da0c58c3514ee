"""The report of ``sparsecomm reproduce``: every part found under ``out`` read back, the figures,
``table1.md``, ``summary.json``, ``budget_summary.json`` and ``report.md``.

:func:`write_report` reads every part found under ``out`` (also parts run earlier) and writes
``fig1.png``, ``fig2.png``, ``fig3.png``, ``pareto.png``, ``table1.md``, ``report.md`` and
``summary.json``, and with the budget parts ``frontier.png`` and ``budget_summary.json``
(rows of :mod:`sparsecomm.pipelines.rows`, :mod:`sparsecomm.pipelines.frontier`). All numbers in
them come from the runs' ``results.json`` and ``metrics.csv``; the verdicts from the rules of
:mod:`sparsecomm.pipelines.claims`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sparsecomm.jsonfile import read_json
from sparsecomm.pipelines import claims, frontier
from sparsecomm.pipelines.plan import Part
from sparsecomm.pipelines.rows import write_rows
from sparsecomm.pipelines.runner import part_rows
from sparsecomm.provenance import git_commit
from sparsecomm.stats import plot_curves, plot_pareto

BASELINE_LABELS = {
    "no_comm": "no communication (RL)",
    "continuous": "real-valued messages, float32 (RL)",
    "fixed": "fixed-width code (RL, λ=0 teams)",
    "rcl": "reinforced comm. learning (RCL)",
    "oracle": "oracle (centralised, upper bound)",
    "centre": "scripted, no communication (centre)",
}
"""Each baseline's label in the figures and the report (``centre`` comes with ``oracle``)."""
BUDGET_PARTS = ("rl_budget", "il_budget", "il_budget_rl")
"""The parts whose presence in ``out`` puts the bit-budget frontier in the report."""


def collect(out: Path, plan: Sequence[Part]) -> dict:
    """The summary (see :mod:`sparsecomm.pipelines.claims`) of every part of ``plan`` found
    under ``out``, with the frontier's rows when a budget part is there."""
    summary: dict = {}
    for part in ("rl", "imitation"):
        res = read_json(out / part / "results.json")
        if res is not None:
            summary[part] = claims.summarize_runs(res["runs"])
    baselines = {}
    files = {
        "no_comm": "no_comm/results.json",
        "continuous": "continuous/results.json",
        "fixed": "fixed/results.json",
        "rcl": "rcl/results.json",
        "oracle": "oracle/results.json",
        "centre": "oracle/centre.json",
    }
    for name, rel in files.items():
        res = read_json(out / rel)
        if res is not None:
            baselines[name] = next(iter(claims.summarize_runs(res["runs"]).values()))
    if baselines:
        summary["baselines"] = baselines
    auc = {}
    if (out / "rl" / "metrics.csv").exists():
        auc["rl"] = claims.training_mean(out / "rl" / "metrics.csv")
    if (out / "rcl" / "metrics.csv").exists():
        auc["rcl"] = next(iter(claims.training_mean(out / "rcl" / "metrics.csv").values()))
    if auc:
        summary["training_success"] = auc
    if any((out / part).exists() for part in BUDGET_PARTS):
        found = part_rows(plan, out)  # RL's parts first, then imitation's, each in plan order
        learner = {p.name: p.learner for p in plan}
        order = sorted(found, key=lambda name: learner[name] != "rl")
        summary["frontier"] = [row for name in order for row in found[name]]
    return summary


POINT_METRICS = ("channel/bits_per_step", "episode/success_rate", "episode/group_reward")
"""The metrics of each method's point on the Pareto plot (``stats.plot_pareto``)."""


def _points(summary: dict) -> list[dict]:
    def tup(st, m):
        return (st[m]["mean"], st[m]["ci_low"], st[m]["ci_high"])

    pts = []
    for part, group in (("rl", "RL through the channel"), ("imitation", "imitation (oracle)")):
        for lam, st in summary.get(part, {}).items():
            pts.append(
                {"label": f"λ={lam:g}", "group": group} | {m: tup(st, m) for m in POINT_METRICS}
            )
    for name, st in summary.get("baselines", {}).items():
        label = BASELINE_LABELS[name]
        pts.append({"label": label, "group": label} | {m: tup(st, m) for m in POINT_METRICS})
    return pts


def write_figures(out: Path, summary: dict) -> list[Path]:
    """fig1.png, fig2.png, fig3.png and pareto.png from the parts found in ``out``."""
    made = []
    rl_csv, il_csv = out / "rl" / "metrics.csv", out / "imitation" / "metrics.csv"
    if rl_csv.exists():
        made.append(
            plot_curves(
                rl_csv,
                out / "fig1.png",
                ("episode/group_reward", "episode/episode_length"),
                title="Fig. 1: RL through the channel, group reward and episode length",
            )
        )
        made.append(
            plot_curves(
                rl_csv,
                out / "fig2.png",
                ("channel/bits_per_step",),
                title="Fig. 2: RL, bits per step",
            )
        )
    if il_csv.exists():
        made.append(
            plot_curves(
                il_csv,
                out / "fig3.png",
                ("loss/imitation_loss", "channel/bits_per_step"),
                title="Fig. 3: imitation of the oracle, loss and bits per step",
            )
        )
    if summary.get("frontier"):
        made.append(frontier.plot(summary["frontier"], out / "frontier.png"))
    pts = _points(summary)
    if pts:
        made.append(
            plot_pareto(
                pts, out / "pareto.png", title="Final evaluation: mean and 95% CI over seeds"
            )
        )
    return made


def _hardware_lines(timings: dict, parts: Sequence[str]) -> list[str]:
    lines = [
        "| part | wall-clock | CPU | cores (usable) | device | jax | commit | finished |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    for part in parts:
        t = timings.get(part)
        if t is None:
            continue
        h = t["hardware"]
        lines.append(
            f"| {part} | {t['wall_clock_s']:.0f} s | {h['cpu']} | {h['cpu_cores']} "
            f"({h['usable_cores']}) | {h['device_kind']} x{h['devices']} | {h['jax']} | "
            f"{t.get('commit') or '?'} | {t['finished']} |"
        )
    return lines


def _budget_lines(timings: dict, parts: Sequence[str]) -> list[str]:
    lines = ["| part | budget |", "|---|---|"]
    for part in parts:
        if part in timings:
            b = timings[part]["budget"]
            lines.append(f"| {part} | " + ", ".join(f"{k} {v}" for k, v in b.items()) + " |")
    return lines


def _frontier_lines(table: list[dict]) -> list[str]:
    """The bit-budget section: the frontier table, the budget-matched verdicts of claims 4 and
    5 (labelled as such), and the budget targets (``frontier.targets``)."""
    md = ["## Bit budgets: the frontier (not in the paper)", ""]
    md += [
        "| learner | budget | λ | seeds | success | episode length | payload bits/step | "
        "wire bits/step |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table:
        cells = [
            f"{r[k][0]:.4g} [{r[k][1]:.4g}, {r[k][2]:.4g}]"
            for k in ("success", "episode_length", "payload_bits", "wire_bits")
        ]
        budget = "-" if r["budget"] is None else f"{r['budget']:g}"
        md.append(
            f"| {frontier.label(r['learner'], r.get('series'))} | {budget} | {r['lam']:g} | "
            f"{r['seeds']} | " + " | ".join(cells) + " |"
        )
    md.append("")
    for c in frontier.budget_claims(table):
        verdict = "held" if c["held"] else "not held"
        md.append(
            f"- **{c['label']}: {verdict}** (budgets that hold: {c['budgets_held'] or 'none'})."
        )
    for t in frontier.targets(table):
        met = "met" if t["met"] else "not met"
        md.append(
            f"- Target, {frontier.label(t['learner'], t['series'])} budget {t['budget']:g}: "
            f"**{met}** (success "
            f"{t['success_ratio']:.1%} of λ=0's, payload bits {t['bits']:.3g})."
        )
    return md + [""]


def _seeds_text(summary: dict) -> str:
    """How many runs (seeds) each method's statistics are over, e.g. "10 seeds per method"."""
    counts = set()
    for key in ("rl", "imitation", "baselines"):
        for st in summary.get(key, {}).values():
            counts.add(next(iter(st.values()))["n"])
    if len(counts) == 1:
        return f"{counts.pop()} seeds per method"
    return f"{min(counts)}-{max(counts)} seeds per method, the runs column" if counts else "seeds"


def _intro_lines(summary: dict, command: str, timings: dict) -> list[str]:
    """The report's title and opening: where its numbers come from and how their statistics
    are taken, the command that ran it, the commit it was written at (when git knows it) and a
    warning when the parts ran with ``--quick``'s tiny budgets."""
    md = ["# Reproduction of Freed et al. (IROS 2020): report", ""]
    md += [
        "Generated by `sparsecomm reproduce` from the runs in this folder; every number below was "
        "measured by those runs (final evaluation of each trained run over fresh episodes, "
        f"sampled actions). Statistics over runs ({_seeds_text(summary)}): mean with a 95% "
        "BCa bootstrap CI at Hesterberg's expanded level (Student-t where BCa has no answer; "
        "`sparsecomm.stats.bootstrap_ci`), and the interquartile mean (IQM). Env steps count "
        "episodes x max_steps (the scan length), masked steps after an episode ended included.",
        "",
    ]
    if command:
        md += [f"Invoked as: `{command}`", ""]
    commit = git_commit()
    if commit:
        md += [f"Report written at commit `{commit}` (each part's: hardware table).", ""]
    quick = timings.get("_meta", {}).get("quick")
    if quick:
        md += [
            "**Quick run (`--quick`): tiny budgets. The verdicts below test the pipeline, "
            "not the paper.**",
            "",
        ]
    return md


def _claim_lines(verdicts: list) -> list[str]:
    """The table of the paper's claims: each one's number ("extra" for none), text, verdict,
    the numbers it rests on and its rule (:func:`sparsecomm.pipelines.claims.decide_claims`)."""
    md = ["## The paper's claims (SPEC section 7)", ""]
    md += ["| # | claim | verdict | numbers | rule |", "|---|---|---|---|---|"]
    for c in verdicts:
        num = str(c.number) if c.number else "extra"
        md.append(f"| {num} | {c.text} | **{c.verdict}** | {c.evidence} | {c.rule} |")
    md.append("")
    return md


def _result_lines(summary: dict) -> list[str]:
    """The sections of the parts found: RL and imitation per lambda (largest first), the
    baselines, the bit-budget frontier and the mean success over training."""
    md = []
    if "rl" in summary:
        md += ["## RL through the channel (Fig. 1, Fig. 2)", ""]
        md.append(
            claims.metrics_table(
                {f"{k:g}": v for k, v in sorted(summary["rl"].items(), reverse=True)}, "λ"
            )
        )
    if "imitation" in summary:
        md += ["## Imitation of the oracle (Fig. 3, Table I)", ""]
        md.append(
            claims.metrics_table(
                {f"{k:g}": v for k, v in sorted(summary["imitation"].items(), reverse=True)}, "λ"
            )
        )
    if "baselines" in summary:
        md += ["## Baselines", ""]
        rows = {BASELINE_LABELS[k]: v for k, v in summary["baselines"].items()}
        md.append(claims.metrics_table(rows, "method"))
    if summary.get("frontier"):
        md += _frontier_lines(summary["frontier"])
    if "training_success" in summary:
        md += _training_lines(summary["training_success"])
    return md


def _training_lines(auc: dict) -> list[str]:
    """The table of mean success over training (the area under the learning curve): RL per
    lambda (largest first), then RCL when it ran."""
    md = ["## Mean success over training (area under the learning curve)", ""]
    md += ["| run | mean success over training |", "|---|---|"]
    for lam, st in sorted(auc.get("rl", {}).items(), reverse=True):
        md.append(f"| RL λ={lam:g} | {claims.fmt(st)} |")
    if "rcl" in auc:
        md.append(f"| RCL | {claims.fmt(auc['rcl'])} |")
    md.append("")
    return md


def _appendix_lines(figures: list[Path], timings: dict, parts: Sequence[str]) -> list[str]:
    """The report's closing sections: the figures written (linked by file name), and from
    ``timings.json`` each part's hardware, wall-clock time and budget."""
    md = []
    if figures:
        md += ["## Figures", ""]
        md += [f"![{p.stem}]({p.name})" for p in figures]
        md.append("")
    if timings:
        md += ["## Hardware and wall-clock", ""]
        md += _hardware_lines(timings, parts) + [""]
        md += ["## Budgets", ""]
        md += _budget_lines(timings, parts) + [""]
    return md


def write_report(out: Path, plan: Sequence[Part], command: str = "") -> dict:
    """Figures, table1.md, summary.json and report.md from every part of ``plan`` found in
    ``out``."""
    summary = collect(out, plan)
    if not summary:
        raise ValueError(f"no part results found in {out}")
    claims.write_summary(
        {k: v for k, v in summary.items() if k != "frontier"}, out / "summary.json"
    )
    if summary.get("frontier"):
        write_rows(summary["frontier"], out / "budget_summary.json")
    figures = write_figures(out, summary)
    if "imitation" in summary:
        (out / "table1.md").write_text(claims.table1(summary["imitation"]))
    timings = read_json(out / "timings.json") or {}
    verdicts = claims.decide_claims(summary)
    md = _intro_lines(summary, command, timings)
    md += _claim_lines(verdicts)
    md += _result_lines(summary)
    md += _appendix_lines(figures, timings, [p.name for p in plan])
    (out / "report.md").write_text("\n".join(md))
    return summary
