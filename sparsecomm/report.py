"""Statistics and figures: bootstrap confidence intervals, interquartile means, learning curves."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy import stats


def bootstrap_ci(values, confidence: float = 0.95, statistic=np.mean, seed: int = 0):
    """``(estimate, low, high)`` of ``statistic`` with a percentile bootstrap CI.

    With one value the interval is that value (no spread can be estimated).
    """
    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("values must be non-empty")
    est = float(statistic(x))
    if x.size == 1 or np.all(x == x[0]):
        return est, est, est
    res = stats.bootstrap(
        (x,),
        statistic,
        confidence_level=confidence,
        n_resamples=10_000,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    return est, float(res.confidence_interval.low), float(res.confidence_interval.high)


def iqm(values) -> float:
    """Interquartile mean: the mean of the middle 50% of the values."""
    return float(stats.trim_mean(np.asarray(values, np.float64).reshape(-1), 0.25))


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    return {k: np.asarray([float(r[k]) for r in rows]) for k in rows[0]}


def curves(data: dict[str, np.ndarray], metric: str):
    """Per lambda: env steps and (seeds, updates) values of ``metric``."""
    out = {}
    for lam in np.unique(data["lam"]):
        sel = data["lam"] == lam
        seeds = np.unique(data["seed"][sel])
        steps = np.unique(data["env_steps"][sel])
        vals = np.full((seeds.size, steps.size), np.nan)
        for i, s in enumerate(seeds):
            m = sel & (data["seed"] == s)
            vals[i, np.searchsorted(steps, data["env_steps"][m])] = data[metric][m]
        out[float(lam)] = (steps, vals)
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


def _save(fig, legend_ax, title: str | None, out_png: str | Path) -> Path:
    """Legend on ``legend_ax``, optional title, tight layout; write the PNG and close."""
    import matplotlib.pyplot as plt

    legend_ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


def plot_curves(
    csv_path: str | Path,
    out_png: str | Path,
    metrics=("group_reward", "episode_length", "success_rate", "bits_per_step"),
    window: int = 10,
    title: str | None = None,
) -> Path:
    """Learning curves (mean over seeds, shaded min-max band) per lambda, one panel per metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = read_csv(csv_path)
    metrics = [m for m in metrics if m in data]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.4), squeeze=False)
    for ax, metric in zip(axes[0], metrics, strict=True):
        for lam, (steps, vals) in sorted(curves(data, metric).items()):
            v = smooth(vals, window)
            mean = np.nanmean(v, 0)
            ax.plot(steps, mean, label=f"λ={lam:g} ({vals.shape[0]} seeds)")
            if vals.shape[0] > 1:
                ax.fill_between(steps, np.nanmin(v, 0), np.nanmax(v, 0), alpha=0.2)
        ax.set_xlabel("env steps")
        ax.set_title(metric.replace("_", " "))
        ax.grid(alpha=0.3)
    return _save(fig, axes[0][0], title, out_png)


def plot_pareto(points, out_png: str | Path, title: str | None = None) -> Path:
    """Success rate and group reward against payload bits per step, one marker per method.

    ``points``: sequence of dicts with ``label``, ``group`` (methods of one group share a colour
    and are joined by a line, e.g. the lambdas of a sweep) and ``bits_per_step``,
    ``success_rate``, ``group_reward``, each a ``(mean, ci_low, ci_high)`` tuple. The bit axis is
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
    for ax, metric in zip(axes, ("success_rate", "group_reward"), strict=True):
        for g in groups:
            pts = sorted(
                (p for p in points if p["group"] == g), key=lambda p: p["bits_per_step"][0]
            )
            x = np.array([p["bits_per_step"] for p in pts])
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
        ax.set_title(metric.replace("_", " "))
        ax.grid(alpha=0.3)
    return _save(fig, axes[0], title, out_png)
