"""The bit-budget frontier: success against bits, per budget and per lambda (docs/budget.md,
docs/wire.md), from rows of :mod:`sparsecomm.pipelines.rows`.

- :func:`plot`: success against payload and wire bits per step, budgets joined by a line,
  fixed-lambda points beside them; :func:`plot_wire`: success and the share of link-steps that
  speak against wire bits, one point per row;
- the budget-matched verdicts of the paper's claims 4 and 5 (:func:`budget_claims`) and the
  budget targets (:func:`targets`), for the reports.

Command line (the numbers of docs/budget.md and docs/wire.md)::

    python -m sparsecomm.pipelines.frontier --rl RUN/results.json --il RUN/results.json --out F
    python -m sparsecomm.pipelines.frontier --il "small task, oracle=RUN/results.json" ...
    python -m sparsecomm.pipelines.frontier --task small --rl RUN/eval.json --out F

Without ``--task`` it writes ``summary.json`` (rows of the plain form, each sweep in the series
``SERIES=`` names) and ``frontier.png`` (:func:`plot`). With ``--task`` the rows are of the wire
form (each file read inside its run folder), replace the rows of the same
:func:`~sparsecomm.pipelines.rows.row_key` in ``--out``'s ``summary.json`` and the others stay;
``--deployed BUDGET=DEPLOY_JSON`` adds a deployment's measured figures to the new rows of that
budget (``none``: the lambda-0 rows), and ``frontier.png`` is :func:`plot_wire`'s.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sparsecomm.pipelines import rows as rowlib
from sparsecomm.pipelines.claims import (
    BITS_FACTOR,
    IL_MIN_SUCCESS,
    IL_SUCCESS_TOL,
    keeps_performance,
)

TARGET_BUDGET, STRETCH_BUDGET = 16.0, 8.0
"""The default target (docs/budget.md): budget 16 at >= ``TARGET_SUCCESS`` of lambda 0's success
with final bits within ``TARGET_BITS_TOL`` of the budget; stretch: budget 8 at the same success."""
TARGET_SUCCESS, TARGET_BITS_TOL = 0.95, 0.10


def series_of(table: list[dict]) -> list[tuple[str, str | None]]:
    """The ``(learner, series)`` pairs of a table, in order of first appearance."""
    return list(dict.fromkeys((r["learner"], r.get("series")) for r in table))


def _in(table: list[dict], learner: str, series: str | None) -> list[dict]:
    return [r for r in table if r["learner"] == learner and r.get("series") == series]


def reference(table: list[dict], learner: str, series: str | None = None) -> dict | None:
    """The series' lambda-0 row without a budget (what its budgets are compared with)."""
    return next(
        (r for r in _in(table, learner, series) if r["budget"] is None and r["lam"] == 0), None
    )


def label(learner: str, series: str | None) -> str:
    return learner if series is None else f"{learner}, {series}"


def _stats(row: dict) -> dict:
    """A row in the ``{metric: {mean, ci_low, ci_high}}`` form of
    :mod:`sparsecomm.pipelines.claims`."""
    return {
        rowlib.COLUMNS[name]: dict(zip(("mean", "ci_low", "ci_high"), row[name], strict=True))
        for name in ("success", "episode_length")
    }


def budget_claims(table: list[dict]) -> list[dict]:
    """Claims 4 (RL) and 5 (imitation) judged at budget-matched points, labelled as such.

    Claim 4 at budgets: some budget sends <= 1/``BITS_FACTOR`` of lambda 0's payload bits while
    keeping its success rate and episode length
    (:func:`sparsecomm.pipelines.claims.keeps_performance`).
    Claim 5 at budgets (its sparse half; the collapse half is a property of a fixed lambda): the
    imitation reference reaches ``IL_MIN_SUCCESS`` and some budget sends <= 1/``BITS_FACTOR`` of
    its bits losing at most ``IL_SUCCESS_TOL`` success.
    """
    out = []
    for learner, series in series_of(table):
        number = 4 if learner == "rl" else 5
        ref = reference(table, learner, series)
        budgets = [r for r in _in(table, learner, series) if r["budget"] is not None]
        if ref is None or not budgets:
            continue
        good = []
        for r in sorted(budgets, key=lambda r: -r["budget"]):
            sparse = r["payload_bits"][0] <= ref["payload_bits"][0] / BITS_FACTOR
            if number == 4:
                kept = keeps_performance(_stats(r), _stats(ref))
            else:
                kept = r["success"][0] >= ref["success"][0] - IL_SUCCESS_TOL
            if sparse and kept:
                good.append(r["budget"])
        learned = number == 4 or ref["success"][0] >= IL_MIN_SUCCESS
        out.append(
            {
                "claim": number,
                "label": f"claim {number} at budget-matched points ({label(learner, series)})",
                "series": series,
                "held": bool(learned and good),
                "budgets_held": good,
                "evidence": "; ".join(_describe(r) for r in [ref, *budgets]),
            }
        )
    return out


def targets(
    table: list[dict],
    goals: tuple[float, ...] = (TARGET_BUDGET, STRETCH_BUDGET),
    max_length_ratio: float | None = None,
) -> list[dict]:
    """Targets per series: each budget of ``goals`` (by default 16, then the stretch, 8) at >=
    ``TARGET_SUCCESS`` of lambda 0's success, with final payload bits within
    ``TARGET_BITS_TOL`` of the budget and, if ``max_length_ratio`` is given, episodes at most
    that many times lambda 0's length."""
    out = []
    for learner, series in series_of(table):
        ref = reference(table, learner, series)
        for goal in goals:
            row = next((r for r in _in(table, learner, series) if r["budget"] == goal), None)
            if ref is None or row is None:
                continue
            success = row["success"][0] / max(ref["success"][0], 1e-9)
            length = row["episode_length"][0] / max(ref["episode_length"][0], 1e-9)
            met = (
                success >= TARGET_SUCCESS
                and abs(row["payload_bits"][0] - goal) <= TARGET_BITS_TOL * goal
                and (max_length_ratio is None or length <= max_length_ratio)
            )
            out.append(
                {
                    "learner": learner,
                    "series": series,
                    "budget": goal,
                    "met": bool(met),
                    "success_ratio": success,
                    "length_ratio": length,
                    "bits": row["payload_bits"][0],
                }
            )
    return out


def _describe(r: dict) -> str:
    name = f"λ={r['lam']:g}" if r["budget"] is None else f"budget {r['budget']:g}"
    s, b, n = r["success"], r["payload_bits"], r["episode_length"]
    return (
        f"{name}: success {s[0]:.3f} [{s[1]:.3f}, {s[2]:.3f}], bits {b[0]:.3g} "
        f"[{b[1]:.3g}, {b[2]:.3g}], length {n[0]:.1f}"
    )


def plot(table: list[dict], out_png: str | Path, title: str | None = None) -> Path:
    """Success against payload and wire bits per step (symlog axis), 95% CIs as error bars.

    The top row shows every point; the bottom row zooms on the teams that work (success >= 0.5),
    where the budgets and the gentle lambdas sit, and is left out when there are none.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    palette = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
    colours = {key: palette[i % len(palette)] for i, key in enumerate(series_of(table))}
    working = [r for r in table if r["success"][0] >= 0.5]
    rows = 2 if working else 1
    fig, axes = plt.subplots(rows, 2, figsize=(11, 4 * rows), squeeze=False)
    for row in range(rows):
        # With a zoom below, the top row tags only what the zoom leaves out.
        tagged = (lambda r: r["success"][0] < 0.5) if row == 0 and rows == 2 else None
        for ax, bits in zip(axes[row], ("payload_bits", "wire_bits"), strict=True):
            for i, ((learner, series), colour) in enumerate(colours.items()):
                _plot_series(ax, _in(table, learner, series), bits, colour, i, tagged)
                if row == 0:
                    ax.plot([], [], "o-", color=colour, label=label(learner, series))
            ax.set_xscale("symlog", linthresh=1.0)
            ax.set_xlabel(f"{bits.replace('_', ' ')} per step (team)")
            ax.grid(alpha=0.3)
            if row == 1:
                ax.set_ylim(np.floor(min(r["success"][1] for r in working) * 20) / 20, 1.005)
                ax.set_xlim(
                    0.8 * min(r[bits][1] for r in working), 1.25 * max(r[bits][2] for r in working)
                )
        axes[row, 0].set_ylabel("success rate" + (" (zoom)" if row else " (final evaluation)"))
    axes[0, 0].legend(
        fontsize=8, loc="lower right", title="filled: budgets, open: fixed λ", title_fontsize=8
    )
    fig.suptitle(title or "Bit-budget frontier: mean and 95% CI over seeds")
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


def _plot_series(ax, rows: list[dict], bits: str, colour: str, index: int, tagged=None) -> None:
    """One series' budget points (filled, joined) and fixed-lambda points (open), tagged with
    their budget or lambda (only those for which ``tagged(row)`` holds, when given); series
    ``index`` places its tags apart from the others' so that series at the same bits do not
    write over each other."""
    for kind, marker in (("budget", "o"), ("lam", "s")):
        sel = sorted(
            (r for r in rows if (r["budget"] is not None) == (kind == "budget")),
            key=lambda r: r[bits][0],
        )
        if not sel:
            continue
        x = np.array([r[bits] for r in sel])
        y = np.array([r["success"] for r in sel])
        ax.errorbar(
            x[:, 0],
            y[:, 0],
            xerr=np.abs(x[:, 1:].T - x[:, 0]),
            yerr=np.abs(y[:, 1:].T - y[:, 0]),
            fmt=marker + ("-" if kind == "budget" else ""),
            color=colour,
            mfc=colour if kind == "budget" else "white",
            capsize=3,
        )
        for r, xi, yi in zip(sel, x[:, 0], y[:, 0], strict=True):
            if tagged is not None and not tagged(r):
                continue
            tag = f"{r['budget']:g}" if kind == "budget" else f"λ{r['lam']:g}"
            ax.annotate(
                tag,
                (xi, yi),
                textcoords="offset points",
                xytext=(4 if index % 2 == 0 else -16, -10 - 6 * (index // 2)),
                fontsize=7,
                color=colour,
                annotation_clip=True,
            )


def plot_wire(table: list[dict], out_png: str | Path) -> Path:
    """Success and the share of link-steps that speak against wire bits per step (log axis),
    one point per row of the wire form, 95% CIs as error bars."""
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


def write(out: str | Path, sources: dict[str, list]) -> list[dict]:
    """``summary.json`` and ``frontier.png`` in ``out`` from ``{learner: [results, ...]}``; an
    entry may be a ``(series, results)`` pair to name its series."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = []
    for learner, docs in sources.items():
        for doc in docs:
            series, doc = doc if isinstance(doc, tuple) else (None, doc)
            table += rowlib.rows(doc, learner, series)
    rowlib.write_rows(table, out / "summary.json")
    plot(table, out / "frontier.png")
    return table


def write_wire(out: str | Path, new: list[dict]) -> list[dict]:
    """``summary.json`` in ``out`` with the rows ``new`` in place of the rows of the same key
    (the others kept), and ``frontier.png`` (:func:`plot_wire`) of the whole table."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = out / "summary.json"
    table = rowlib.load_rows(summary) if summary.exists() else []
    keys = {rowlib.row_key(r) for r in new}
    table = [r for r in table if rowlib.row_key(r) not in keys] + new
    rowlib.write_rows(table, summary)
    plot_wire(table, out / "frontier.png")
    return table


def _split(arg: str) -> tuple[str | None, str]:
    """``PATH`` or ``SERIES=PATH`` as ``(series, path)``."""
    series, _, path = arg.rpartition("=")
    return series or None, path


def _print_wire(new: list[dict]) -> None:
    for r in new:
        name = "λ 0" if r["budget"] is None else f"{r['counts']} budget {r['budget']:g}"
        net = "-" if r["network_bits"] is None else f"{r['network_bits'][0]:.0f}"
        print(
            f"{r['task']} {r['learner']} {name}: success {r['success'][0]:.3f} "
            f"[{r['success'][1]:.3f}, {r['success'][2]:.3f}], length {r['episode_length'][0]:.1f}, "
            f"payload {r['payload_bits'][0]:.1f}, wire {r['wire_bits'][0]:.1f}, speaking "
            f"{r['speaking_fraction'][0]:.0%}, network {net} ({r['seeds']} seeds)"
        )


def _print_plain(table: list[dict]) -> None:
    for r in table:
        print(
            f"{label(r['learner'], r.get('series')):9s} {_describe(r)}, "
            f"wire {r['wire_bits'][0]:.3g} ({r['seeds']} seeds)"
        )
    for c in budget_claims(table):
        print(f"{c['label']}: {'held' if c['held'] else 'not held'} {c['budgets_held']}")
    for t in targets(table):
        print(
            f"target {label(t['learner'], t['series'])} budget {t['budget']:g}: "
            f"{'met' if t['met'] else 'not met'}"
            f" (success {t['success_ratio']:.1%} of λ=0, bits {t['bits']:.3g})"
        )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rl", nargs="*", default=[], help="results.json (or eval.json) of RL sweeps; "
        "SERIES=PATH names a series",
    )  # fmt: skip
    parser.add_argument("--il", nargs="*", default=[], help="... of imitation sweeps")
    parser.add_argument(
        "--task", choices=rowlib.TASKS, help="rows of the wire form, each file read inside its run "
        "folder, merged into --out's summary.json",
    )  # fmt: skip
    parser.add_argument(
        "--deployed", nargs="*", default=[], help="with --task, BUDGET=DEPLOY_JSON: a deployment "
        "(sparsecomm deploy's deploy.json) of the runs of the group with this budget (none: the "
        "lambda-0 group)",
    )  # fmt: skip
    parser.add_argument("--out", required=True, help="folder for summary.json and frontier.png")
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = _parser()
    args = parser.parse_args(argv)
    sources = {"rl": args.rl, "imitation": args.il}
    if args.deployed and args.task is None:
        parser.error("--deployed needs --task")
    if args.task is None:
        docs = {
            learner: [(s, json.loads(Path(p).read_text())) for s, p in map(_split, paths)]
            for learner, paths in sources.items()
        }
        _print_plain(write(args.out, docs))
        return
    new = [
        row
        for learner, paths in sources.items()
        for series, path in map(_split, paths)
        for row in rowlib.read_rows(path, learner, series, task=args.task)
    ]
    for spec in args.deployed:
        budget, _, report = spec.partition("=")
        want = None if budget == "none" else float(budget)
        for r in new:
            if r["budget"] == want:
                r["deployed"] = rowlib.deployed(json.loads(Path(report).read_text()))
    write_wire(args.out, new)
    _print_wire(new)


if __name__ == "__main__":
    main()
