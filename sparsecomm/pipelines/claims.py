"""The paper's claims: per-method statistics, the five claims' rules, Table I, summary.json.

Everything here reads numbers measured by ``sparsecomm reproduce`` (``results.json`` and
``metrics.csv`` of each part); nothing is hard-coded. A *summary* maps each method to its
statistics::

    {"rl": {lam: stats}, "imitation": {lam: stats}, "baselines": {name: stats}}

where ``stats[metric] = {"mean", "ci_low", "ci_high", "iqm", "n"}`` is computed over the runs
(seeds) of that method: the mean with a 95% BCa bootstrap interval at Hesterberg's expanded level
(:func:`sparsecomm.stats.bootstrap_ci`) and the interquartile mean. Lambdas are floats.

The claims (SPEC section 7) are decided by the explicit rules of :func:`decide_claims`, whose
thresholds are the module constants below. Read by the report of
:mod:`sparsecomm.pipelines.report`, by the budget-matched verdicts of
:mod:`sparsecomm.pipelines.frontier` and by ``sparsecomm paper-task``'s claims at the paper's
lambdas.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from sparsecomm import learners
from sparsecomm.jsonfile import write_json
from sparsecomm.metric_names import aliased
from sparsecomm.stats import bootstrap_ci, iqm, read_csv

METRICS = (
    "episode/success_rate",
    "episode/episode_length",
    "episode/group_reward",
    "channel/bits_per_step",
    "channel/wire_bits_per_step",
    "loss/penalty",
)
"""Final-evaluation metrics summarised per method (SPEC section 6)."""

NO_COMM_MAX_SUCCESS = 0.05
"""Claim 1 ("without communication agents virtually never find their goals"): held when the
no-communication baseline's mean success rate is below this."""
COMM_MIN_GAIN = 0.25
"""Claim 2 ("with communication they do"): held when, for every RL lambda, the mean success
rate exceeds the no-communication baseline's by at least this (absolute) and the two 95% CIs do
not overlap."""
BITS_MONOTONE_TOL = 0.05
"""Claim 3 ("bits fall as lambda rises"): the mean bits per step, lambdas in increasing order,
may rise by at most this fraction (plus ``BITS_ABS_TOL``) from one lambda to the next, and the
largest lambda's CI must lie entirely below the smallest lambda's."""
BITS_ABS_TOL = 0.1
"""Absolute slack (bits per step) of the claim-3 monotonicity test, for near-zero bit counts."""
BITS_FACTOR = 2.0
"""Claims 4 and 5: "over 2-fold fewer bits" means mean bits per step at most 1/this of the
smallest lambda's."""
KEEP_MEAN_TOL = 0.1
"""Claim 4 ("reward not substantially hurt") is judged on task performance, success rate and
episode length, not on group reward: group reward pays +250 per step inside the goal radius, so
a team that hovers there instead of finishing can score more while succeeding less. A lambda
keeps the smallest lambda's performance when, for each of the two metrics, its mean is at most
this fraction worse than the smallest lambda's mean (success >= 90% of it, episode length <= 110%
of it), and its 95% CI reaches within ``KEEP_CI_TOL`` of that mean."""
KEEP_CI_TOL = 0.05
"""Claim 4: the success CI's upper bound must reach >= (1 - this) x the smallest lambda's mean
success and the episode-length CI's lower bound <= (1 + this) x its mean length; otherwise the
runs show a loss larger than this fraction (beyond the CI), whatever the mean."""
IL_MIN_SUCCESS = 0.5
"""Claim 5 ("imitation learns"): the smallest imitation lambda must reach this mean success."""
IL_SUCCESS_TOL = 0.1
"""Claim 5: a sparse imitation lambda may lose at most this much (absolute) mean success against
the smallest lambda."""
COLLAPSE_FRACTION = 0.25
"""Claim 5 ("collapses at lambda = 0.001", the largest imitation lambda): its mean success is
below this fraction of the smallest lambda's."""

CLAIMS = (
    "Without communication, agents virtually never find their goals.",
    "With communication, agents find their goals (for every RL lambda).",
    "Bits per step fall as lambda rises (RL).",
    "Over 2-fold fewer bits with reward not substantially hurt (judged on success rate and "
    "episode length), except at the largest lambda (RL).",
    "Imitation learns sparse communication from expert actions alone, and collapses at the "
    "largest lambda (0.001).",
)
"""The paper's claims, SPEC section 7."""


def stats(values) -> dict:
    """Mean with 95% bootstrap CI, interquartile mean and count of a set of per-run values."""
    x = np.asarray(values, np.float64).reshape(-1)
    mean, lo, hi = bootstrap_ci(x)
    return {"mean": mean, "ci_low": lo, "ci_high": hi, "iqm": iqm(x), "n": int(x.size)}


def summarize_runs(runs: list[dict], metrics=METRICS) -> dict[float, dict]:
    """Per lambda, :func:`stats` of each metric over the runs (``results.json["runs"]``),
    by written name (a run's flat names read through :func:`metric_names.alias`)."""
    out, runs = {}, [aliased(r) for r in runs]
    for lam in sorted({float(r["lam"]) for r in runs}):
        sel = [r for r in runs if float(r["lam"]) == lam]
        out[lam] = {m: stats([r[m] for r in sel]) for m in metrics if m in sel[0]}
    return out


def training_mean(csv_path: str | Path, metric: str = "episode/success_rate") -> dict[float, dict]:
    """Per lambda, :func:`stats` over seeds of a metric averaged over all training updates
    (the normalised area under the learning curve: a sample-efficiency measure)."""
    data = read_csv(csv_path)
    out = {}
    for lam in np.unique(data["lam"]):
        sel = data["lam"] == lam
        per_seed = [data[metric][sel & (data["seed"] == s)].mean() for s in np.unique(data["seed"])]
        out[float(lam)] = stats(per_seed)
    return out


@dataclasses.dataclass(frozen=True)
class Claim:
    """One claim's verdict."""

    number: int
    """1-5 for the paper's claims (SPEC section 7); 0 for an extra check."""
    text: str
    """The claim."""
    held: bool | None
    """True: held; False: not held; None: not checked (a part it needs was not run)."""
    evidence: str
    """The measured numbers behind the verdict."""
    rule: str
    """The rule applied."""

    @property
    def verdict(self) -> str:
        return {True: "held", False: "not held", None: "not checked"}[self.held]


def fmt(s: dict, digits: int = 3) -> str:
    """``mean [low, high]`` of a :func:`stats` dict."""
    return f"{s['mean']:.{digits}g} [{s['ci_low']:.{digits}g}, {s['ci_high']:.{digits}g}]"


def _missing(number: int, what: str) -> Claim:
    return Claim(number, CLAIMS[number - 1], None, f"not run: {what}", "")


def claim_no_comm(summary: dict) -> Claim:
    base = summary.get("baselines", {}).get("no_comm")
    if base is None:
        return _missing(1, "the no-communication baseline")
    s = base["episode/success_rate"]
    return Claim(
        1,
        CLAIMS[0],
        s["mean"] < NO_COMM_MAX_SUCCESS,
        f"no-communication success {fmt(s)}, episode length {fmt(base['episode/episode_length'])}",
        f"held if the no-communication mean success < {NO_COMM_MAX_SUCCESS}",
    )


def claim_comm(summary: dict) -> Claim:
    base = summary.get("baselines", {}).get("no_comm")
    rl = summary.get(learners.RL.name)
    if base is None or not rl:
        return _missing(2, "the RL sweep and the no-communication baseline")
    b = base["episode/success_rate"]
    ok = True
    parts = []
    for lam, st in sorted(rl.items()):
        s = st["episode/success_rate"]
        ok &= s["mean"] >= b["mean"] + COMM_MIN_GAIN and s["ci_low"] > b["ci_high"]
        parts.append(f"λ={lam:g}: {fmt(s)}")
    return Claim(
        2,
        CLAIMS[1],
        bool(ok),
        f"success with communication: {'; '.join(parts)}; without: {fmt(b)}",
        f"held if for every RL λ mean success >= no-comm mean + {COMM_MIN_GAIN} and the CIs "
        "do not overlap",
    )


def claim_bits_fall(summary: dict) -> Claim:
    rl = summary.get(learners.RL.name)
    if not rl or len(rl) < 2:
        return _missing(3, "an RL sweep with at least two lambdas")
    lams = sorted(rl)
    bits = [rl[lam]["channel/bits_per_step"] for lam in lams]
    monotone = all(
        b1["mean"] <= b0["mean"] * (1 + BITS_MONOTONE_TOL) + BITS_ABS_TOL
        for b0, b1 in zip(bits, bits[1:], strict=False)
    )
    separated = bits[-1]["ci_high"] < bits[0]["ci_low"]
    return Claim(
        3,
        CLAIMS[2],
        monotone and separated,
        "bits/step: "
        + "; ".join(f"λ={lam:g}: {fmt(b)}" for lam, b in zip(lams, bits, strict=True)),
        f"held if mean bits never rise by more than {BITS_MONOTONE_TOL:.0%} + {BITS_ABS_TOL} "
        "from one λ to the next larger one, and the largest λ's CI lies below the smallest's",
    )


def keeps_performance(st: dict, ref: dict) -> bool:
    """Claim 4's test: ``st`` (a method's stats) keeps the success rate and episode length of
    ``ref`` (the smallest lambda's) within ``KEEP_MEAN_TOL`` (means) and ``KEEP_CI_TOL`` (CIs)."""
    s, s0 = st["episode/success_rate"], ref["episode/success_rate"]["mean"]
    n, n0 = st["episode/episode_length"], ref["episode/episode_length"]["mean"]
    success = s["mean"] >= (1 - KEEP_MEAN_TOL) * s0 and s["ci_high"] >= (1 - KEEP_CI_TOL) * s0
    length = n["mean"] <= (1 + KEEP_MEAN_TOL) * n0 and n["ci_low"] <= (1 + KEEP_CI_TOL) * n0
    return bool(success and length)


def claim_sparse_rl(summary: dict) -> Claim:
    rl = summary.get(learners.RL.name)
    if not rl or len(rl) < 3:
        return _missing(4, "an RL sweep with at least three lambdas")
    lams = sorted(rl)
    ref = rl[lams[0]]
    middle = lams[1:-1]
    kept = {lam: keeps_performance(rl[lam], ref) for lam in middle}
    sparse = {
        lam: rl[lam]["channel/bits_per_step"]["mean"]
        <= ref["channel/bits_per_step"]["mean"] / BITS_FACTOR
        for lam in middle
    }
    held = all(kept.values()) and any(sparse[lam] and kept[lam] for lam in middle)
    rows = "; ".join(
        f"λ={lam:g}: bits {fmt(rl[lam]['channel/bits_per_step'])}, success "
        f"{fmt(rl[lam]['episode/success_rate'])}, length {fmt(rl[lam]['episode/episode_length'])}"
        for lam in lams
    )
    return Claim(
        4,
        CLAIMS[3],
        held,
        f"{rows}; performance kept at: {[f'{x:g}' for x in middle if kept[x]] or 'none'}",
        f"held if every λ strictly between the smallest and the largest keeps mean success >= "
        f"{1 - KEEP_MEAN_TOL:.0%} and mean episode length <= {1 + KEEP_MEAN_TOL:.0%} of the "
        f"smallest λ's, with its success CI reaching >= {1 - KEEP_CI_TOL:.0%} and its length CI "
        f"<= {1 + KEEP_CI_TOL:.0%} of them (group reward is not used: hovering near the goal "
        f"raises it), and at least one of them sends <= 1/{BITS_FACTOR:g} of the smallest λ's "
        "mean bits",
    )


def claim_imitation(summary: dict) -> Claim:
    il = summary.get(learners.IMITATION.name)
    if not il or len(il) < 3:
        return _missing(5, "an imitation sweep with at least three lambdas")
    lams = sorted(il)
    ref, top = il[lams[0]], il[lams[-1]]
    s0 = ref["episode/success_rate"]["mean"]
    learned = s0 >= IL_MIN_SUCCESS
    sparse = [
        lam
        for lam in lams[1:-1]
        if il[lam]["channel/bits_per_step"]["mean"]
        <= ref["channel/bits_per_step"]["mean"] / BITS_FACTOR
        and il[lam]["episode/success_rate"]["mean"] >= s0 - IL_SUCCESS_TOL
    ]
    collapsed = top["episode/success_rate"]["mean"] < COLLAPSE_FRACTION * s0
    rows = "; ".join(
        f"λ={lam:g}: success {fmt(il[lam]['episode/success_rate'])}, "
        f"bits {fmt(il[lam]['channel/bits_per_step'])}"
        for lam in lams
    )
    return Claim(
        5,
        CLAIMS[4],
        bool(learned and sparse and collapsed),
        f"{rows}; sparse and not hurt: {[f'{x:g}' for x in sparse] or 'none'}",
        f"held if the smallest λ reaches mean success >= {IL_MIN_SUCCESS}, some λ strictly "
        f"between sends <= 1/{BITS_FACTOR:g} of its bits losing <= {IL_SUCCESS_TOL} success, "
        f"and the largest λ's success is < {COLLAPSE_FRACTION} x the smallest λ's",
    )


def claim_rcl(summary: dict) -> Claim:
    """Extra check (paper section II): learning through the channel is more sample-efficient
    than reinforced communication learning, compared at the same budget by the mean success
    over training (area under the learning curve) of the smallest RL lambda and RCL."""
    text = (
        "Extra (paper section II): learning through the channel is more sample-efficient than "
        "reinforced communication learning (RCL)."
    )
    auc = summary.get("training_success", {})
    rl = summary.get(learners.RL.name)
    if "rcl" not in auc or "rl" not in auc or not rl:
        return Claim(0, text, None, "not run: the RL sweep and the RCL baseline", "")
    lam0 = min(auc["rl"])
    d, r = auc["rl"][lam0], auc["rcl"]
    return Claim(
        0,
        text,
        d["ci_low"] > r["ci_high"],
        f"mean success over training: through the channel (λ={lam0:g}) {fmt(d)}, RCL {fmt(r)}",
        "held if the channel's CI lies entirely above RCL's",
    )


def decide_claims(summary: dict) -> list[Claim]:
    """The five claims of SPEC section 7, then the extra RCL check."""
    return [
        claim_no_comm(summary),
        claim_comm(summary),
        claim_bits_fall(summary),
        claim_sparse_rl(summary),
        claim_imitation(summary),
        claim_rcl(summary),
    ]


def _cell(s: dict, digits: int = 3) -> str:
    return f"{s['mean']:.{digits}g} [{s['ci_low']:.{digits}g}, {s['ci_high']:.{digits}g}]"


def metrics_table(rows: dict, first: str, metrics=None) -> str:
    """Markdown table: one row per key of ``rows`` (label -> stats), mean [95% CI] and IQM."""
    metrics = metrics or (
        "episode/episode_length",
        "episode/group_reward",
        "episode/success_rate",
        "channel/bits_per_step",
    )
    head = [first, "runs"] + [m.replace("_", " ") for m in metrics] + ["IQM success"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, st in rows.items():
        n = next(iter(st.values()))["n"]
        cells = [_cell(st[m], 4) if m in st else "-" for m in metrics]
        lines.append(
            f"| {label} | {n} | "
            + " | ".join(cells)
            + f" | {st['episode/success_rate']['iqm']:.3g} |"
        )
    return "\n".join(lines) + "\n"


def table1(imitation: dict[float, dict]) -> str:
    """Table I: per imitation lambda, final mean episode length, group reward, success and bits
    per step, each mean [95% bootstrap CI] over seeds."""
    rows = {f"{lam:g}": imitation[lam] for lam in sorted(imitation, reverse=True)}
    return (
        "# Table I: imitation of the oracle expert, final evaluation\n\n"
        "Mean over seeds with a 95% bootstrap CI; episode length: lower is better (256 = "
        "failure).\n\n" + metrics_table(rows, "λ")
    )


def write_summary(summary: dict, path: Path) -> None:
    """JSON of a summary (float lambda keys become strings)."""

    def keys(x):
        if isinstance(x, dict):
            return {(f"{k:g}" if isinstance(k, float) else k): keys(v) for k, v in x.items()}
        return x

    write_json(path, keys(summary))
