"""``sparsecomm.stats.bootstrap_ci``: coverage of its 95% interval at 10 seeds, degenerate cases;
a run folder's learning curves (``curves.png``): units, each budget on the bits it counts."""

import numpy as np
import pytest
from scipy import stats

from sparsecomm import learners
from sparsecomm.configs import PRESETS
from sparsecomm.experiment import write_curves
from sparsecomm.stats import bootstrap_ci, curves_figure, expanded_level, student_t_ci

TRIALS = 1000
"""Fixed-seed samples in the coverage test (about 5 s on one core with 1000 resamples each)."""


def test_95_interval_covers_the_mean_of_10_normal_values_about_95_percent():
    se = np.sqrt(0.95 * 0.05 / TRIALS)  # binomial standard error of a 95% coverage estimate
    ours = percentile = 0
    for trial in range(TRIALS):
        x = np.random.default_rng(trial).normal(size=10)  # true mean 0
        _, lo, hi = bootstrap_ci(x, n_resamples=1000)
        ours += lo <= 0.0 <= hi
        ci = stats.bootstrap(
            (x,), np.mean, n_resamples=1000, method="percentile", rng=np.random.default_rng(0)
        ).confidence_interval
        percentile += ci.low <= 0.0 <= ci.high
    # measured: 0.938 here (0.951 over other seeds, docstring); the nominal-level percentile
    # interval (the previous method) covers 0.902: too narrow at 10 values.
    assert abs(ours / TRIALS - 0.95) <= 3 * se, ours / TRIALS
    assert percentile / TRIALS < 0.95 - 3 * se < ours / TRIALS, percentile / TRIALS


def test_expanded_level():
    assert expanded_level(10) == pytest.approx(0.9829, abs=1e-4)
    assert expanded_level(5) == pytest.approx(0.9981, abs=1e-4)
    assert expanded_level(10_000) == pytest.approx(0.95, abs=1e-4)
    assert expanded_level(2) == 1.0  # BCa cannot give this level: Student-t instead


def test_degenerate_values_give_a_point_interval():
    assert bootstrap_ci([0.7]) == (0.7, 0.7, 0.7)
    assert bootstrap_ci([3.0, 3.0, 3.0, 3.0, 3.0]) == (3.0, 3.0, 3.0)
    assert bootstrap_ci(np.zeros((2, 5))) == (0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="non-empty"):
        bootstrap_ci([])


def test_two_values_fall_back_to_student_t():
    half = stats.t.ppf(0.975, 1) * np.sqrt(0.5) / np.sqrt(2)  # 12.706 x sd / sqrt(n)
    assert student_t_ci([0.0, 1.0]) == pytest.approx((0.5, 0.5 - half, 0.5 + half))
    assert bootstrap_ci([0.0, 1.0]) == pytest.approx((0.5, 0.5 - half, 0.5 + half))
    est, lo, hi = bootstrap_ci([0.0, 1.0], statistic=np.median)  # no t interval for a median
    assert est == 0.5 and np.isnan(lo) and np.isnan(hi)


def test_binary_values_with_one_different():
    # success flags of 5 seeds, one failed: a finite interval inside the data's range
    est, lo, hi = bootstrap_ci([1.0, 1.0, 1.0, 1.0, 0.0])
    assert est == 0.8 and 0.0 <= lo < 0.8 and hi == 1.0
    est, lo, hi = bootstrap_ci([0.0] * 9 + [1.0])
    assert est == pytest.approx(0.1) and lo == 0.0 and 0.1 < hi < 1.0


def test_deterministic_for_a_fixed_seed():
    x = np.random.default_rng(7).exponential(size=8)
    assert bootstrap_ci(x, n_resamples=2000) == bootstrap_ci(x, n_resamples=2000)
    assert bootstrap_ci(x, n_resamples=2000, seed=1) != bootstrap_ci(x, n_resamples=2000)


def _metrics(links: bool = False) -> dict[str, np.ndarray]:
    """A ``metrics.csv`` as :func:`sparsecomm.stats.read_csv` reads it: two groups (no budget,
    budget 24) of two seeds, five updates each."""
    rows = [(b, s, u) for b in (np.nan, 24.0) for s in (0, 1) for u in range(5)]
    budget, seed, update = (np.array(c, float) for c in zip(*rows, strict=True))
    data = {
        "seed": seed,
        "lam": np.zeros_like(seed),
        "budget": budget,
        "env_steps": (update + 1) * 1000,
        "episode/success_rate": update / 4,
        "episode/episode_length": 64 - 8 * update,
        "channel/bits_per_step": 10 - update,
        "channel/wire_bits_per_step": 100 - 10 * update,
        "channel/speaking_fraction": 1 - update / 5,
    }
    if links:
        data["channel/links_per_step"] = 2 + update
    return data


def _dashed(ax) -> list[np.ndarray]:
    return [line.get_ydata() for line in ax.get_lines() if line.get_linestyle() == "--"]


def test_the_curves_show_success_speaking_and_the_priced_bits_against_the_budget():
    import matplotlib.pyplot as plt

    metrics = (
        "episode/success_rate",
        "episode/episode_length",
        "channel/wire_bits_per_step",
        "channel/speaking_fraction",
        "loss/imitation_loss",  # not in the data: no panel
    )
    fig, axes = curves_figure(_metrics(), metrics, 1, "channel/wire_bits_per_step", ncols=2)
    assert list(axes) == list(metrics[:4])
    units = {m: (ax.get_title(), ax.get_ylabel(), ax.get_xlabel()) for m, ax in axes.items()}
    assert units == {
        "episode/success_rate": ("success rate", "share of episodes", "env steps"),
        "episode/episode_length": ("episode length", "steps", "env steps"),
        "channel/wire_bits_per_step": (
            "wire bits per step",
            "bits per step, whole team",
            "env steps",
        ),
        "channel/speaking_fraction": ("links speaking", "share of link-steps", "env steps"),
    }
    # one line per group everywhere; the budget's line on the bits it counts, and only there
    wire = axes["channel/wire_bits_per_step"]
    (line,) = _dashed(wire)
    np.testing.assert_array_equal(line, np.full(5, 24.0))
    assert all(_dashed(ax) == [] for m, ax in axes.items() if ax is not wire)
    assert [len(ax.get_lines()) for ax in axes.values()] == [2, 2, 3, 2]
    np.testing.assert_allclose(wire.get_lines()[0].get_ydata(), [100, 90, 80, 70, 60])
    plt.close(fig)
    # a payload budget on the payload bits; no budget, no line
    fig, axes = curves_figure(_metrics(), ["channel/bits_per_step"], 1, "channel/bits_per_step")
    assert len(_dashed(axes["channel/bits_per_step"])) == 1
    plt.close(fig)
    fig, axes = curves_figure(_metrics(), ["channel/bits_per_step"], 1)
    assert _dashed(axes["channel/bits_per_step"]) == []
    plt.close(fig)


def test_a_budget_per_link_is_drawn_times_the_links():
    import matplotlib.pyplot as plt

    bits = "channel/wire_bits_per_step"
    fig, axes = curves_figure(_metrics(), [bits], 1, bits, budget_links=2)
    np.testing.assert_array_equal(_dashed(axes[bits])[0], np.full(5, 48.0))
    plt.close(fig)
    fig, axes = curves_figure(_metrics(links=True), [bits], 1, bits, budget_links=2)
    np.testing.assert_array_equal(_dashed(axes[bits])[0], 24.0 * np.arange(2, 7))
    plt.close(fig)


@pytest.mark.parametrize("preset, bits", [("silent", "wire"), ("small", "bits_per_step")])
def test_a_run_folder_curves_draw_the_bits_its_budget_counts(tmp_path, monkeypatch, preset, bits):
    drawn = {}

    def plot(csv, png, metrics, **kw):
        drawn.update(kw, metrics=metrics, png=png)
        return png

    monkeypatch.setattr("sparsecomm.experiment.plot_curves", plot)
    cfg = PRESETS[preset]["train"]
    write_curves(cfg, learners.of_config(cfg), tmp_path, 2)
    counted = "channel/wire_bits_per_step" if bits == "wire" else "channel/bits_per_step"
    assert drawn["budget_metric"] == counted and drawn["budget_links"] is None
    assert drawn["metrics"] == (
        "episode/success_rate",
        "episode/episode_length",
        counted,
        "channel/speaking_fraction",
    )
    assert drawn["png"] == tmp_path / "curves.png"
