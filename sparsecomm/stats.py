"""Statistics and figures: BCa bootstrap confidence intervals, interquartile means, curves."""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np
from scipy import stats

from sparsecomm.metric_names import alias


def expanded_level(n: int, confidence: float = 0.95) -> float:
    """Hesterberg's small-sample expansion of a bootstrap interval's nominal level.

    A bootstrap distribution of the mean has the plug-in variance (divisor n, not n - 1) and
    normal, not Student-t, tails, so any bootstrap interval of the mean is too narrow at small n:
    at nominal 95%, percentile and plain BCa intervals cover the mean of 5 normal values about
    85% of the time and of 10 values about 91%. The expansion asks the bootstrap for the level
    whose normal quantile is ``sqrt(n / (n - 1)) * t_{n-1}`` (the Student-t quantile with the
    n - 1 variance): 0.998 at n = 5, 0.983 at n = 10, tending to ``confidence``. T. Hesterberg,
    "What teachers should know about the bootstrap", The American Statistician 69(4), 2015
    (the "expanded percentile interval"; here the expanded level is given to BCa).
    """
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n}")
    tail = (1 - confidence) / 2
    z = np.sqrt(n / (n - 1)) * stats.t.ppf(1 - tail, n - 1)
    return float(1 - 2 * stats.norm.sf(z))


def student_t_ci(values, confidence: float = 0.95) -> tuple[float, float, float]:
    """``(mean, low, high)``: the Student-t interval for the mean (exact for normal values)."""
    x = np.asarray(values, np.float64).reshape(-1)
    mean = float(x.mean())
    half = stats.t.ppf(0.5 + confidence / 2, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size)
    return mean, float(mean - half), float(mean + half)


def bootstrap_ci(
    values,
    confidence: float = 0.95,
    statistic=np.mean,
    seed: int = 0,
    n_resamples: int = 10_000,
):
    """``(estimate, low, high)`` of ``statistic`` with a BCa bootstrap CI at an expanded level.

    The interval is scipy's bias-corrected and accelerated (BCa) bootstrap, asked for the level
    :func:`expanded_level` gives instead of ``confidence``, because at the sample sizes of a
    seed sweep (5-10 runs) every bootstrap interval at the nominal level is too narrow. Measured
    coverage (%) of the 95% interval for the mean over 1000 samples, 10,000 resamples each
    (bimodal: 60% of values uniform in [0.85, 1], the rest in [0, 0.3]; tests/test_stats.py
    checks the normal, n = 10 case):

    ===================================  ======  ===========  =====================
    values                               n       BCa          BCa at expanded level
    ===================================  ======  ===========  =====================
    normal                               5 / 10  85.4 / 90.9  92.3 / 95.1
    exponential (skewed)                 5 / 10  79.2 / 88.4  87.2 / 92.5
    bimodal (seeds that solve or stall)  5 / 10  91.6 / 96.6  91.7 / 98.6
    ===================================  ======  ===========  =====================

    No bootstrap interval leaves the range of the values, which misses the mean of a symmetric
    continuous distribution with probability 2^(1-n): at n <= 5 the coverage cannot reach 95%
    (at most 94% at n = 5, 75% at n = 3); use at least 6 values where coverage matters.

    Degenerate cases: one value, or all values equal, give ``(v, v, v)`` (no spread can be
    estimated). Where BCa has no answer (at n = 2 the expanded level is 1; BCa also returns NaN
    when the bootstrap distribution is degenerate) the Student-t interval for the mean is used
    instead (:func:`student_t_ci`, at ``confidence``); for another ``statistic`` the bounds
    are then NaN. Deterministic: the resamples come from ``seed``.
    """
    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("values must be non-empty")
    est = float(statistic(x))
    if x.size == 1 or np.all(x == x[0]):
        return est, est, est
    level = expanded_level(x.size, confidence)
    low = high = np.nan
    if level < 1:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", stats.DegenerateDataWarning)
            warnings.simplefilter("ignore", RuntimeWarning)
            res = stats.bootstrap(
                (x,),
                statistic,
                confidence_level=level,
                n_resamples=n_resamples,
                method="BCa",
                rng=np.random.default_rng(seed),
            )
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if np.isfinite(low) and np.isfinite(high):
        return est, low, high
    if statistic is np.mean:
        return student_t_ci(x, confidence)
    return est, float("nan"), float("nan")


def iqm(values) -> float:
    """Interquartile mean: the mean of the middle 50% of the values."""
    return float(stats.trim_mean(np.asarray(values, np.float64).reshape(-1), 0.25))


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Every column of a CSV file (``metrics.csv``, ``wall.csv``) as floats, by name; metric
    columns by their written names (``group/key``), those of files written before the groups
    read through :func:`sparsecomm.metric_names.alias`."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    # Blank cells (the budget of a fixed-lambda run) read as NaN.
    return {alias(k): np.asarray([float(r[k] or "nan") for r in rows]) for k in rows[0]}


def group_label(lam: float, budget: float) -> str:
    """A run group's legend label: its lambda, or its budget (NaN: none)."""
    return f"λ={lam:g}" if np.isnan(budget) else f"budget {budget:g} bits"


def curves(data: dict[str, np.ndarray], metric: str):
    """Per run group: env steps and (seeds, updates) values of ``metric`` (a written name, or a
    flat key read through :func:`~sparsecomm.metric_names.alias`). Groups are keyed
    ``(budget, lam)`` (budget NaN for fixed-lambda runs), fixed lambdas first, then budgets
    from the largest."""
    out, metric = {}, alias(metric)
    budget = data.get("budget", np.full(data["lam"].shape, np.nan))
    # NaN != NaN, so the fixed-lambda runs' budget joins a group as None, not as NaN.
    groups = {
        (None if np.isnan(b) else float(b), float(lam))
        for b, lam in zip(budget, data["lam"], strict=True)
    }
    order = sorted(groups, key=lambda g: (g[0] is not None, -(g[0] or 0.0), g[1]))
    for b, lam in order:
        b = np.nan if b is None else b
        sel = (data["lam"] == lam) & ((budget == b) | (np.isnan(budget) & np.isnan(b)))
        seeds = np.unique(data["seed"][sel])
        steps = np.unique(data["env_steps"][sel])
        vals = np.full((seeds.size, steps.size), np.nan)
        for i, s in enumerate(seeds):
            m = sel & (data["seed"] == s)
            vals[i, np.searchsorted(steps, data["env_steps"][m])] = data[metric][m]
        out[(b, lam)] = (steps, vals)
    return out


def smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along the last axis (window clipped to the length)."""
    window = max(1, min(window, x.shape[-1]))
    c = np.cumsum(np.pad(x, [(0, 0)] * (x.ndim - 1) + [(1, 0)]), axis=-1)
    out = np.empty_like(x)
    n = x.shape[-1]
    idx = np.arange(n)
    lo = np.maximum(idx + 1 - window, 0)
    out[...] = (c[..., idx + 1] - c[..., lo]) / (idx + 1 - lo)
    return out


def first_pass(curve, target: float, window: int) -> int | None:
    """0-based index at which the trailing moving average of ``curve`` (a 1-D series, e.g. the
    mean training success over seeds, one value per update) over ``window`` values first
    exceeds ``target``; None if it never does (or the series is shorter than ``window``)."""
    curve = np.asarray(curve, np.float64)
    if len(curve) < window:
        return None
    avg = np.convolve(curve, np.ones(window) / window, mode="valid")
    hits = np.nonzero(avg > target)[0]
    return None if len(hits) == 0 else int(hits[0] + window - 1)


def _save(fig, legend_ax, title: str | None, out_png: str | Path, below: bool = False) -> Path:
    """The legend of ``legend_ax``'s lines on it (or ``below`` the panels, where it hides no
    curve), optional title, tight layout; write the PNG and close."""
    import matplotlib.pyplot as plt

    bottom = 0.0
    if below:
        handles, labels = legend_ax.get_legend_handles_labels()
        cols = max(1, min(len(labels), round(fig.get_figwidth() / 2.1)))  # ~2 a panel
        fig.legend(handles, labels, loc="lower center", ncol=cols, fontsize=8, frameon=False)
        bottom = (0.1 + 0.2 * -(-len(labels) // cols)) / fig.get_figheight()
    else:
        legend_ax.legend(fontsize=8, loc="upper right")  # "best" takes minutes on long curves
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, bottom, 1, 1))
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


PANELS: dict[str, tuple[str, str]] = {
    "episode/group_reward": ("group reward", "reward per episode"),
    "episode/episode_length": ("episode length", "steps"),
    "episode/success_rate": ("success rate", "share of episodes"),
    "channel/bits_per_step": ("payload bits per step", "bits per step, whole team"),
    "channel/wire_bits_per_step": ("wire bits per step", "bits per step, whole team"),
    "channel/speaking_fraction": ("links speaking", "share of link-steps"),
    "loss/imitation_loss": ("imitation loss", "nats per step, summed over agents"),
}
"""A curve panel's title and its y axis (the unit) by metric; other metrics get their name."""


def curves_figure(
    data: dict[str, np.ndarray],
    metrics,
    window: int = 10,
    budget_metric: str | None = None,
    budget_links: float | None = None,
    ncols: int | None = None,
):
    """The figure of :func:`plot_curves` from ``data`` (:func:`read_csv`): one panel per metric
    of ``metrics`` that ``data`` has, its y axis in the metric's unit (:data:`PANELS`), x in env
    steps; one colour per run group. On the panel of ``budget_metric`` (the bits the budget
    counts, ``ChannelConfig.counted_metric``), each group with a budget gets a dashed line at
    it: the budget times the links per step for a budget per link (``budget_links``, or the
    logged ``channel/links_per_step`` where there is one). Returns the figure and its panels by
    metric, in ``metrics``' order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [alias(m) for m in metrics if alias(m) in data]
    cols = min(ncols or len(metrics), len(metrics))
    rows = -(-len(metrics) // cols)
    fig, grid = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    axes = list(grid.flat)
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    for ax, metric in zip(axes, metrics, strict=False):
        for i, ((budget, lam), (steps, vals)) in enumerate(curves(data, metric).items()):
            v, colour = smooth(vals, window), f"C{i % 10}"
            seeds = vals.shape[0]
            label = f"{group_label(lam, budget)} ({seeds} seed{'s' * (seeds > 1)})"
            ax.plot(steps, np.nanmean(v, 0), color=colour, label=label)
            if vals.shape[0] > 1:
                ax.fill_between(steps, np.nanmin(v, 0), np.nanmax(v, 0), color=colour, alpha=0.2)
            if budget_metric and metric == alias(budget_metric) and not np.isnan(budget):
                _budget_line(ax, data, budget, lam, steps, budget_links, colour)
        title, unit = PANELS.get(metric, (metric.split("/")[-1].replace("_", " "), ""))
        ax.set(title=title, xlabel="env steps", ylabel=unit)
        ax.grid(alpha=0.3)
    return fig, dict(zip(metrics, axes, strict=False))


def _budget_line(ax, data, budget: float, lam: float, steps, links, colour) -> None:
    """A group's budget on the panel of the bits it counts: flat for the team's count; for a
    budget per link (``links`` given), the budget times the links per step (the logged ones
    where the run logs them)."""
    label = f"budget {budget:g}"
    if links is not None:
        label = f"budget {budget:g} per link x links"
        if "channel/links_per_step" in data:
            logged = curves(data, "channel/links_per_step")[(budget, lam)][1]
            links = np.nanmean(logged, 0)
        budget = budget * np.broadcast_to(links, steps.shape)
    ax.plot(steps, np.broadcast_to(budget, steps.shape), "--", color=colour, label=label)


def plot_curves(
    csv_path: str | Path,
    out_png: str | Path,
    metrics=(
        "episode/group_reward",
        "episode/episode_length",
        "episode/success_rate",
        "channel/bits_per_step",
    ),
    window: int = 10,
    title: str | None = None,
    budget_metric: str | None = None,
    budget_links: float | None = None,
    ncols: int | None = None,
) -> Path:
    """Learning curves (mean over seeds, shaded min-max band) per lambda or budget, one panel
    per metric (written names; flat keys are read through
    :func:`~sparsecomm.metric_names.alias`), each budget drawn on the panel of the bits it
    counts (:func:`curves_figure`), ``ncols`` panels a row (default: one row)."""
    fig, axes = curves_figure(
        read_csv(csv_path), metrics, window, budget_metric, budget_links, ncols
    )
    # the groups' legend, with the budgets' lines, below the panels
    legend_ax = axes.get(alias(budget_metric or ""), next(iter(axes.values())))
    return _save(fig, legend_ax, title, out_png, below=True)


def plot_pareto(points, out_png: str | Path, title: str | None = None) -> Path:
    """Success rate and group reward against payload bits per step, one marker per method.

    ``points``: sequence of dicts with ``label``, ``group`` (methods of one group share a colour
    and are joined by a line, e.g. the lambdas of a sweep) and the metrics by written name,
    ``channel/bits_per_step``, ``episode/success_rate``, ``episode/group_reward``, each a
    ``(mean, ci_low, ci_high)`` tuple. The bit axis is
    symmetric-log so that 0 bits (no communication, the oracle) stays on the plot.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = list(points)
    if not points:
        raise ValueError("points must be non-empty")
    groups = list(dict.fromkeys(p["group"] for p in points))
    colours = {g: f"C{i % 10}" for i, g in enumerate(groups)}
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.2))
    bits = "channel/bits_per_step"
    for ax, metric in zip(axes, ("episode/success_rate", "episode/group_reward"), strict=True):
        for g in groups:
            pts = sorted((p for p in points if p["group"] == g), key=lambda p: p[bits][0])
            x = np.array([p[bits] for p in pts])
            y = np.array([p[metric] for p in pts])
            ax.errorbar(
                x[:, 0],
                y[:, 0],
                xerr=np.abs(x[:, 1:].T - x[:, 0]),
                yerr=np.abs(y[:, 1:].T - y[:, 0]),
                fmt="o-" if len(pts) > 1 else "o",
                color=colours[g],
                capsize=3,
                label=g,
            )
            for p, xi, yi in zip(pts, x[:, 0], y[:, 0], strict=True):
                if p["label"] != g:
                    ax.annotate(
                        p["label"], (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points"
                    )
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel("payload bits per step (team)")
        ax.set_title(metric.split("/")[-1].replace("_", " "))
        ax.grid(alpha=0.3)
    return _save(fig, axes[0], title, out_png)
