"""``sparsecomm reproduce --quick`` end to end with a tiny budget, and the claim-deciding rules."""

import json

import pytest

from sparsecomm.cli import main
from sparsecomm.pipelines import claims
from sparsecomm.pipelines.plan import expert_index
from sparsecomm.pipelines.reproduce import BUDGETS, IL_LAMS, PARTS, RL_LAMS, Reproduce
from sparsecomm.provenance import source_digest

TINY = [
    "--quick",
    "--seeds",
    "2",
    "--rl-updates",
    "2",
    "--rl-envs",
    "2",
    "--il-updates",
    "2",
    "--il-envs",
    "2",
    "--eval-episodes",
    "4",
    "--rl.env.max-steps",
    "12",
    "--il.env.max-steps",
    "12",
    "--no-progress",
]


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    main(["reproduce", *TINY, "--out", str(out)])
    return out


@pytest.mark.slow
def test_quick_writes_every_artefact(quick_run):
    out = quick_run
    for name in (
        "fig1.png",
        "fig2.png",
        "fig3.png",
        "pareto.png",
        "table1.md",
        "report.md",
        "summary.json",
        "timings.json",
        "frontier.png",
        "budget_summary.json",
    ):
        assert (out / name).stat().st_size > 0, name
    for part in ("rl", "imitation", "no_comm", "continuous", "fixed", "rcl", "il_budget_rl"):
        assert (out / part / "results.json").stat().st_size > 0, part
    assert (out / "oracle" / "results.json").exists() and (out / "oracle" / "centre.json").exists()
    timings = json.loads((out / "timings.json").read_text())
    assert set(PARTS) <= set(timings)
    assert timings["rl"]["budget"]["env_steps_per_run"] == 2 * 2 * 12
    assert timings["rl"]["hardware"]["cpu_cores"] >= 1
    assert timings["rl"]["source_sha256"] == source_digest() and len(source_digest()) == 16
    # the RL-team expert is the rl part's best lambda-0 team, with its own lambda-0 reference
    assert timings["il_budget_rl"]["budget"]["expert"] == expert_index(out / "rl")
    runs = json.loads((out / "il_budget_rl" / "results.json").read_text())["runs"]
    assert sorted({r["budget"] for r in runs if r["budget"] is not None}) == sorted(BUDGETS)
    assert sum(r["budget"] is None for r in runs) == 2  # lambda 0, both seeds


@pytest.mark.slow
def test_report_decides_every_claim(quick_run):
    text = (quick_run / "report.md").read_text()
    for n, claim in enumerate(claims.CLAIMS, 1):
        line = next(ln for ln in text.splitlines() if ln.startswith(f"| {n} | {claim}"))
        assert "**held**" in line or "**not held**" in line, line
    for heading in ("Hardware and wall-clock", "Baselines", "Budgets"):
        assert heading in text
    for label in ("no communication", "float32", "fixed-width", "oracle", "RCL"):
        assert label in text
    extra = next(ln for ln in text.splitlines() if ln.startswith("| extra |"))
    assert "**held**" in extra or "**not held**" in extra, extra


@pytest.mark.slow
def test_table1_has_every_lambda(quick_run):
    table = (quick_run / "table1.md").read_text()
    rows = [ln.split("|")[1].strip() for ln in table.splitlines() if ln.startswith("| ")][1:]
    assert rows == [f"{lam:g}" for lam in sorted(IL_LAMS, reverse=True)]
    summary = json.loads((quick_run / "summary.json").read_text())
    assert set(summary["rl"]) == {f"{lam:g}" for lam in RL_LAMS}
    # the fixed-width code sends ceil(log2(16)) = 4 bits for each of 60 elements every step
    assert summary["baselines"]["fixed"]["channel/bits_per_step"]["mean"] == 240.0
    assert summary["baselines"]["continuous"]["channel/bits_per_step"]["mean"] == 32 * 60
    assert summary["baselines"]["no_comm"]["channel/bits_per_step"]["mean"] == 0.0
    assert summary["baselines"]["oracle"]["episode/success_rate"]["mean"] == 0.0  # 12-step episodes


@pytest.mark.parametrize(
    "field,value",
    [
        ("seeds", 0),
        ("rl_updates", -1),
        ("eval_episodes", 0),
        ("parts", ("rl", "nope")),
        ("rl_lams", (0.01, -1.0)),
        ("rl_lams", (0.01,)),  # the fixed part needs lambda 0
        ("chunk", 0),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"Reproduce.{field}"):
        Reproduce(**{field: value})


def test_the_rl_team_expert_needs_lambda_zero():
    with pytest.raises(ValueError, match="Reproduce.rl_lams must contain 0 for the il_budget_rl"):
        Reproduce(parts=("rl", "il_budget_rl"), rl_lams=(0.01,))


def test_the_rl_team_expert_is_the_best_lambda_zero_team(tmp_path):
    def run(lam, success, length, budget=None):
        return {
            "lam": lam,
            "budget": budget,
            "episode/success_rate": success,
            "episode/episode_length": length,
        }

    runs = [
        run(0.01, 1.0, 10.0),  # best, but not lambda 0
        run(0.0, 0.99, 12.0),
        run(0.0, 1.0, 15.0, budget=16.0),  # best, but with a budget
        run(0.0, 0.998, 14.0),
        run(0.0, 0.998, 13.0),  # tie on success: the shorter episodes win
    ]
    (tmp_path / "results.json").write_text(json.dumps({"runs": runs}))
    assert expert_index(tmp_path) == 4
    (tmp_path / "results.json").write_text(json.dumps({"runs": runs[:1]}))
    with pytest.raises(ValueError, match="no lambda = 0"):
        expert_index(tmp_path)
    with pytest.raises(ValueError, match="run 'rl' first"):
        expert_index(tmp_path / "missing")


# ---- the claim rules on synthetic numbers -------------------------------------------------


def st(mean, half=0.0):
    return {"mean": mean, "ci_low": mean - half, "ci_high": mean + half, "iqm": mean, "n": 5}


def method(success, reward, bits, length=100.0, half=0.01):
    return {
        "episode/success_rate": st(success, half),
        "episode/group_reward": st(reward, abs(reward) * half),
        "channel/bits_per_step": st(bits, bits * half),
        "episode/episode_length": st(length, 1.0),
    }


def paper_like():
    """Numbers shaped like the paper's results: every claim holds."""
    return {
        "rl": {
            0.0: method(0.9, 10000, 120),
            0.001: method(0.88, 9900, 50),
            0.005: method(0.86, 9800, 30),
            0.01: method(0.6, 6000, 10),
        },
        "imitation": {
            0.0: method(0.9, 13000, 110),
            0.0001: method(0.89, 13000, 60),
            0.0004: method(0.87, 13000, 40),
            0.0007: method(0.85, 13000, 30),
            0.001: method(0.01, 3700, 2),
        },
        "baselines": {"no_comm": method(0.0, 1000, 0.0)},
        "training_success": {"rl": {0.0: st(0.5, 0.05)}, "rcl": st(0.1, 0.05)},
    }


def verdicts(summary):
    return [c.held for c in claims.decide_claims(summary)]


def test_claims_hold_on_paper_like_numbers():
    assert verdicts(paper_like()) == [True] * 6


def test_claim_1_fails_when_no_comm_succeeds():
    s = paper_like()
    s["baselines"]["no_comm"] = method(0.3, 5000, 0.0)
    assert verdicts(s)[0] is False


def test_claim_2_fails_when_one_lambda_does_not_beat_no_comm():
    s = paper_like()
    s["rl"][0.01] = method(0.1, 2000, 10)
    assert verdicts(s)[1] is False


def test_claim_3_fails_when_bits_rise_with_lambda():
    s = paper_like()
    s["rl"][0.005] = method(0.86, 9800, 80)  # more than at lambda 0.001
    assert verdicts(s)[2] is False
    s = paper_like()
    for lam in s["rl"]:
        s["rl"][lam]["channel/bits_per_step"] = st(100.0, 5.0)  # flat: CIs overlap
    assert verdicts(s)[2] is False


def test_claim_4_is_judged_on_success_and_length_not_group_reward():
    s = paper_like()
    s["rl"][0.001] = method(0.7, 12000, 50)  # reward up 20%, success down 22%: hovering
    assert verdicts(s)[3] is False
    s = paper_like()
    s["rl"][0.001] = method(0.88, 12000, 50, length=150.0)  # success kept, 50% longer episodes
    assert verdicts(s)[3] is False
    s = paper_like()
    s["rl"][0.001] = method(0.88, 5000, 50)  # reward halved, success and length kept
    s["rl"][0.005] = method(0.86, 4000, 30)
    assert verdicts(s)[3] is True


def test_claim_4_tolerances_on_means_and_cis():
    # lambda 0: success 0.9, length 100; means may lose 10%, CIs must reach within 5%
    s = paper_like()
    s["rl"][0.001]["episode/success_rate"] = st(0.80, 0.1)  # mean 89% of lambda 0's: too low
    assert verdicts(s)[3] is False
    s["rl"][0.001]["episode/success_rate"] = st(0.83, 0.005)  # mean 92%, but CI high 0.835 < 0.855
    assert verdicts(s)[3] is False
    s["rl"][0.001]["episode/success_rate"] = st(0.83, 0.05)  # mean 92%, CI reaches 0.88
    assert verdicts(s)[3] is True
    s["rl"][0.001]["episode/episode_length"] = st(111.0, 10.0)  # mean 111% of lambda 0's
    assert verdicts(s)[3] is False
    s["rl"][0.001]["episode/episode_length"] = st(108.0, 1.0)  # mean 108%, CI low 107 > 105
    assert verdicts(s)[3] is False
    s["rl"][0.001]["episode/episode_length"] = st(108.0, 4.0)  # CI low 104
    assert verdicts(s)[3] is True
    s["rl"][0.01] = method(0.1, 500, 1, length=250.0)  # the largest lambda may be hurt
    assert verdicts(s)[3] is True


def test_claim_4_needs_half_the_bits():
    s = paper_like()
    s["rl"][0.001] = method(0.88, 9900, 100)
    s["rl"][0.005] = method(0.86, 9800, 70)  # never <= 120 / 2
    assert verdicts(s)[3] is False


def test_claim_5_needs_learning_sparsity_and_collapse():
    s = paper_like()
    s["imitation"][0.001] = method(0.8, 12000, 10)  # no collapse
    assert verdicts(s)[4] is False
    s = paper_like()
    for lam in (0.0001, 0.0004, 0.0007):
        s["imitation"][lam]["channel/bits_per_step"] = st(100.0, 1.0)  # not sparse
    assert verdicts(s)[4] is False
    s = paper_like()
    s["imitation"][0.0] = method(0.3, 8000, 110)  # never learned
    assert verdicts(s)[4] is False


def test_extra_rcl_check_and_missing_parts():
    s = paper_like()
    s["training_success"]["rcl"] = st(0.5, 0.05)
    assert verdicts(s)[5] is False
    assert verdicts({"rl": paper_like()["rl"]}) == [None, None, True, True, None, None]


@pytest.mark.slow
def test_budget_parts_write_the_frontier(quick_run):
    rows = json.loads((quick_run / "budget_summary.json").read_text())
    keys = {"learner", "budget", "lam", "seeds", "success", "payload_bits", "wire_bits"}
    named = {"RL team"}  # the imitators of the RL team: a series of their own
    assert all(set(r) == keys | {"episode_length"} | ({"series"} & set(r)) for r in rows)
    for learner, series in (("rl", None), ("imitation", None), ("imitation", "RL team")):
        budgets = {
            r["budget"] for r in rows if (r["learner"], r.get("series")) == (learner, series)
        }
        assert budgets == {None, *BUDGETS}, (learner, series, budgets)
        assert all(r["seeds"] == 2 and len(r["success"]) == 3 for r in rows)
    assert {r.get("series") for r in rows} - {None} == named
    text = (quick_run / "report.md").read_text()
    assert "## Bit budgets: the frontier" in text
    assert "claim 4 at budget-matched points (rl)" in text
    assert "claim 5 at budget-matched points (imitation)" in text
    assert "claim 5 at budget-matched points (imitation, RL team)" in text
    assert "| imitation, RL team | 16 | 0 | 2 |" in text


@pytest.mark.parametrize("part", ["fixed", "il_budget_rl"])
def test_a_part_that_reads_the_rl_teams_needs_the_rl_part(part, tmp_path):
    out = tmp_path / "repro"
    with pytest.raises(ValueError, match=rf"Reproduce.parts \(--parts\) holds {part}, which"):
        Reproduce(parts=(part,), out=out)
    assert Reproduce(parts=("rl", part), out=out).parts == ("rl", part)
    (out / "rl").mkdir(parents=True)
    (out / "rl" / "results.json").write_text("{}")
    assert Reproduce(parts=(part,), out=out).parts == (part,)


def test_an_expert_given_to_the_parts_is_refused(tmp_path):
    from sparsecomm.configs import ILConfig

    with pytest.raises(ValueError, match="Reproduce.il.expert_checkpoint is set by each"):
        Reproduce(il=ILConfig(expert_checkpoint="/nonexistent"), out=tmp_path / "r")
    assert list(tmp_path.iterdir()) == []
