"""The bit-budget frontier: success against bits, per budget and per lambda (docs/budget.md).

Reads the ``results.json`` of trained sweeps (``sparsecomm train|imitate --budgets ...``, or the
``rl_budget`` / ``il_budget`` parts of ``sparsecomm reproduce``) and writes

- ``summary.json``: a list of rows ``{"learner": "rl"|"imitation", "budget": float|null,
  "lam": float, "seeds": int, "success": [mean, lo, hi], "payload_bits": [...],
  "wire_bits": [...], "episode_length": [...]}``, one per (learner, budget, lambda) group, over
  its seeds (95% CIs of :func:`sparsecomm.stats.bootstrap_ci`), and a ``"series"`` field where
  the sweep was given a name (say ``"small task, oracle"``: runs of one learner on different
  tasks or experts are separate series, each compared with its own lambda-0 row);
- ``frontier.png``: success against payload bits and against wire bits per step, budgets joined
  by a line, fixed-lambda points beside them;
- the budget-matched verdicts of the paper's claims 4 and 5 (:func:`budget_claims`) and the
  budget targets (:func:`targets`), for the report.

Command line (the numbers of docs/budget.md)::

    python -m sparsecomm.frontier --rl RUN/results.json --il RUN/results.json --out FOLDER
    python -m sparsecomm.frontier --il "small task, oracle=RUN/results.json" ...  # a named series
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sparsecomm import learners
from sparsecomm.claims import BITS_FACTOR, IL_MIN_SUCCESS, IL_SUCCESS_TOL, keeps_performance
from sparsecomm.jsonfile import write_json
from sparsecomm.metric_names import aliased_results
from sparsecomm.stats import bootstrap_ci

COLUMNS = {
    "success": "episode/success_rate",
    "payload_bits": "channel/bits_per_step",
    "wire_bits": "channel/wire_bits_per_step",
    "episode_length": "episode/episode_length",
}
"""Row field -> the evaluation metric it summarises."""
TARGET_BUDGET, STRETCH_BUDGET = 16.0, 8.0
"""The default target (docs/budget.md): budget 16 at >= ``TARGET_SUCCESS`` of lambda 0's success
with final bits within ``TARGET_BITS_TOL`` of the budget; stretch: budget 8 at the same success."""
TARGET_SUCCESS, TARGET_BITS_TOL = 0.95, 0.10


def rows(results: dict, learner: str, series: str | None = None) -> list[dict]:
    """The frontier rows of one sweep's ``results.json`` (its ``runs`` list), in ``series`` if
    given."""
    groups: dict[tuple, list[dict]] = {}
    for run in aliased_results(results)["runs"]:
        groups.setdefault((run.get("budget"), float(run["lam"])), []).append(run)
    out = []
    for (budget, lam), runs in groups.items():
        row = {"learner": learner, "budget": budget, "lam": lam, "seeds": len(runs)}
        if series is not None:
            row["series"] = series
        for name, metric in COLUMNS.items():
            row[name] = list(bootstrap_ci([r[metric] for r in runs]))
        out.append(row)
    return out


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
    """A row in the ``{metric: {mean, ci_low, ci_high}}`` form of :mod:`sparsecomm.claims`."""
    return {
        COLUMNS[name]: dict(zip(("mean", "ci_low", "ci_high"), row[name], strict=True))
        for name in ("success", "episode_length")
    }


def budget_claims(table: list[dict]) -> list[dict]:
    """Claims 4 (RL) and 5 (imitation) judged at budget-matched points, labelled as such.

    Claim 4 at budgets: some budget sends <= 1/``BITS_FACTOR`` of lambda 0's payload bits while
    keeping its success rate and episode length (:func:`sparsecomm.claims.keeps_performance`).
    Claim 5 at budgets (its sparse half; the collapse half is a property of a fixed lambda): the
    imitation reference reaches ``IL_MIN_SUCCESS`` and some budget sends <= 1/``BITS_FACTOR`` of
    its bits losing at most ``IL_SUCCESS_TOL`` success.
    """
    out = []
    for learner, series in series_of(table):
        number = 4 if learner == learners.RL.name else 5
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


def write_rows(table: list[dict], path: str | Path) -> Path:
    """The rows as JSON (non-finite numbers as null)."""
    path = Path(path)
    write_json(path, table)
    return path


def write(out: str | Path, sources: dict[str, list]) -> list[dict]:
    """``summary.json`` and ``frontier.png`` in ``out`` from ``{learner: [results, ...]}``; an
    entry may be a ``(series, results)`` pair to name its series."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = []
    for learner, docs in sources.items():
        for doc in docs:
            series, doc = doc if isinstance(doc, tuple) else (None, doc)
            table += rows(doc, learner, series)
    write_rows(table, out / "summary.json")
    plot(table, out / "frontier.png")
    return table


def _read(arg: str) -> tuple[str | None, dict]:
    """``PATH`` or ``SERIES=PATH`` as ``(series, results)``."""
    series, _, path = arg.rpartition("=")
    return series or None, json.loads(Path(path).read_text())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rl", nargs="*", default=[], help="results.json of RL sweeps (SERIES=PATH names a series)"
    )
    parser.add_argument("--il", nargs="*", default=[], help="... of imitation sweeps")
    parser.add_argument("--out", required=True, help="folder for summary.json and frontier.png")
    args = parser.parse_args(argv)
    sources = {
        learners.RL.name: [_read(p) for p in args.rl],
        learners.IMITATION.name: [_read(p) for p in args.il],
    }
    table = write(args.out, sources)
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


if __name__ == "__main__":
    main()
