"""``sparsecomm paper-task`` end to end with tiny budgets: every part, the rows, the verdicts."""

import json
import shutil

import pytest

from sparsecomm.cli import main
from sparsecomm.pipelines.paper_task import PARTS, PaperTask, summarise
from sparsecomm.runfolder import read_config

TINY = [
    "--seeds", "2", "--budgets", "8", "--eval-episodes", "4", "--chunk", "2", "--no-progress",
    "--rl.env.max-steps", "8", "--rl.num-envs", "4", "--rl.num-updates", "4",
    "--il.env.max-steps", "8", "--il.num-envs", "4", "--il.num-updates", "4",
]  # fmt: skip


@pytest.mark.slow  # five parts compiled: ~1.5 minutes on 2 CPU cores
def test_every_part_then_the_issues_rows_and_verdicts(tmp_path, fast_compile):
    out, results = tmp_path / "runs", tmp_path / "results"
    main(["paper-task", *TINY, "--out", str(out), "--results", str(results)])
    for part in PARTS:
        assert (out / part / "results.json").exists() and (out / part / "wall.csv").exists()
    rows = json.loads((results / "summary.json").read_text())
    fields = {"learner", "algo", "expert", "budget", "lam", "seeds", "success", "episode_length",
              "payload_bits", "wire_bits", "env_steps_to_095", "wall_s_to_095"}  # fmt: skip
    assert all(fields <= set(r) for r in rows)
    got = {(r["part"], r["learner"], r["expert"], r["budget"], r["lam"]) for r in rows}
    want = {("rl", "rl", None, b, 0.0) for b in (None, 8.0)}
    want |= {("il_oracle", "imitation", "oracle", b, 0.0) for b in (None, 8.0)}
    want |= {("il_rl", "imitation", "rl", b, 0.0) for b in (None, 8.0)}
    want |= {("rl_lams", "rl", None, None, lam) for lam in (0.01, 0.005, 0.001)}
    want |= {("il_lams", "imitation", "oracle", None, lam) for lam in (0.001, 0.0007, 0.0004, 1e-4)}
    assert got == want
    for r in rows:
        assert r["seeds"] == 2 and r["algo"] == ("a2c" if r["learner"] == "rl" else "dagger")
        assert all(
            len(r[k]) == 3 and r[k][1] <= r[k][0] <= r[k][2] for k in ("success", "wire_bits")
        )
        assert r["env_steps_to_095"] is None or r["env_steps_to_095"] > 0
    config = read_config(out / "il_rl")
    assert config.expert == "checkpoint" and config.expert_checkpoint == str(out / "rl")
    verdicts = json.loads((results / "claims.json").read_text())
    assert {c["claim"] for c in verdicts["lambdas"]} == {4, 5}
    assert {c["claim"] for c in verdicts["budget_matched"]} <= {4, 5}
    assert (results / "frontier.png").stat().st_size > 0
    # Every run evaluated again on its most probable actions: each row carries those figures.
    greedy = json.loads((out / "rl" / "eval_greedy.json").read_text())
    assert greedy["greedy"] is True and len(greedy["runs"]) == 4
    (zero,) = [r for r in rows if r["part"] == "rl" and r["budget"] is None]
    assert zero["greedy"]["per_seed"]["success"] == [
        r["episode/success_rate"] for r in greedy["runs"] if r["budget"] is None
    ]
    assert all("greedy" in r for r in rows)
    assert {t["budget"] for t in verdicts["targets_greedy"]} <= {16.0, 32.0}
    # Finished parts are only re-evaluated: the same rows again.
    main(["paper-task", *TINY, "--parts", "rl", "--out", str(out), "--results", str(results)])
    again = json.loads((results / "summary.json").read_text())
    key = lambda r: (r["part"], str(r["budget"]), r["lam"])  # noqa: E731
    assert sorted(again, key=key) == sorted(rows, key=key)
    # Each row keeps its runs' per-seed figures.
    runs = json.loads((out / "rl_lams" / "results.json").read_text())["runs"]
    (top,) = [r for r in rows if r["part"] == "rl_lams" and r["lam"] == 0.01]
    assert top["per_seed"]["success"] == [
        r["episode/success_rate"] for r in runs if r["lam"] == 0.01
    ]
    # Parts whose run folders are gone (run on another machine) keep their rows and verdicts.
    for part in ("il_rl", "rl_lams", "il_lams", "il_oracle"):
        shutil.rmtree(out / part)
    assert len(summarise(PaperTask(out=out, results=results))) == len(rows)
    kept = json.loads((results / "summary.json").read_text())
    assert sorted(kept, key=key) == sorted(rows, key=key)
    assert json.loads((results / "claims.json").read_text())["lambdas"] == verdicts["lambdas"]
    # Without greedy, a part's earlier greedy evaluation goes and its rows carry none.
    main(["paper-task", *TINY, "--parts", "rl", "--no-greedy", "--out", str(out),
          "--results", str(results)])  # fmt: skip
    assert not (out / "rl" / "eval_greedy.json").exists()
    rl_rows = [r for r in json.loads((results / "summary.json").read_text()) if r["part"] == "rl"]
    assert rl_rows and not any("greedy" in r for r in rl_rows)


def test_bad_fields_are_refused_before_any_work(capsys):
    with pytest.raises(ValueError, match="PaperTask.parts must be a non-empty subset"):
        PaperTask(parts=("rl", "nope"))
    with pytest.raises(ValueError, match="PaperTask.seeds must be an integer >= 1"):
        PaperTask(seeds=0)
    with pytest.raises(ValueError, match="PaperTask.budgets must be <= "):
        PaperTask(budgets=(1e9,))
    with pytest.raises(SystemExit) as e:  # the command line: one message, exit 2
        main(["paper-task", "--budgets", "-1"])
    err = " ".join(capsys.readouterr().err.split())
    assert e.value.code == 2 and "PaperTask.budgets must be finite and >= 0" in err


def test_lambda_verdicts_come_from_the_rows_or_stay_as_they_were():
    """Claim 4 from rows alone (no run folder): lambdas 0.001 and 0.005 keep lambda 0's success
    and length, 0.005 at a third of its bits, 0.01 collapses; rows without per-seed figures
    (written before they existed) and parts without rows keep their earlier verdicts."""
    from sparsecomm.configs import RLConfig
    from sparsecomm.pipelines import rows as rowlib
    from sparsecomm.pipelines.paper_task import lambda_claims

    def runs(lam, success, length, bits):
        return [
            {"seed": s, "lam": lam, "budget": None, "success_rate": success + 0.001 * s,
             "episode_length": length + s, "bits_per_step": bits + s,
             "wire_bits_per_step": 3 * bits, "speaking_fraction": 0.5}
            for s in range(5)
        ]  # fmt: skip

    config = RLConfig()
    zero = rowlib.rows({"runs": runs(0.0, 0.98, 60.0, 135.0)}, "rl", config=config, task="paper")
    lams = [(0.001, 0.98, 61.0, 90.0), (0.005, 0.98, 62.0, 45.0), (0.01, 0.0, 256.0, 2.0)]
    lams = rowlib.rows(
        {"runs": [r for p in lams for r in runs(*p)]}, "rl", config=config, task="paper"
    )
    table = [r | {"part": "rl"} for r in zero] + [r | {"part": "rl_lams"} for r in lams]
    earlier = [{"part": "rl_lams", "claim": 4, "held": False}, {"part": "il_lams", "claim": 5}]
    verdict, kept = lambda_claims(table, earlier)  # no il_lams rows: its verdict is kept
    assert (verdict["part"], verdict["claim"], verdict["held"]) == ("rl_lams", 4, True)
    assert "λ=0.005: bits 47 " in verdict["evidence"] and kept == earlier[1]
    legacy = [{k: v for k, v in r.items() if k != "per_seed"} for r in table]
    assert lambda_claims(legacy, earlier) == earlier
    assert lambda_claims(legacy, []) == []


def test_greedy_figures_are_judged_apart_from_the_sampled_ones():
    """``targets_greedy`` judges the rows' greedy figures: a budget row that misses on sampled
    length (1.3x) but not on greedy length (1.2x) is met there and only there."""
    from sparsecomm.pipelines import frontier
    from sparsecomm.pipelines.paper_task import greedy_table

    def row(budget, success, length, bits, g_length):
        figures = dict(success=[success] * 3, episode_length=[length] * 3, payload_bits=[bits] * 3)
        greedy = figures | {"episode_length": [g_length] * 3}
        return {"learner": "rl", "budget": budget, "lam": 0.0, **figures, "greedy": greedy}

    table = [row(None, 0.99, 60.0, 135.0, 50.0), row(32.0, 0.97, 78.0, 33.0, 60.0)]
    table.append({k: v for k, v in row(16.0, 0.96, 80.0, 16.0, 55.0).items() if k != "greedy"})
    sampled = frontier.targets(table, (32.0, 16.0), max_length_ratio=1.25)
    assert [(t["budget"], t["met"]) for t in sampled] == [(32.0, False), (16.0, False)]
    greedy = frontier.targets(greedy_table(table), (32.0, 16.0), max_length_ratio=1.25)
    assert [(t["budget"], t["met"]) for t in greedy] == [(32.0, True)]  # 16 has no greedy row
    assert greedy[0]["length_ratio"] == pytest.approx(1.2)


def _refused(argv, capsys, *words):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = " ".join(capsys.readouterr().err.split())  # tyro's box wraps lines
    assert e.value.code == 2 and "Traceback" not in err and "__tyro" not in err, err
    assert all(word in err for word in words), err
    return err


def test_a_part_without_the_part_it_needs_is_refused_while_parsing(tmp_path, capsys):
    """``il_rl`` imitates the ``rl`` part's best team: without ``rl`` in ``--parts`` and no
    finished ``rl`` part in ``out`` it is refused naming ``--parts`` and what is missing; with
    the rl part's results there it is taken."""
    out = tmp_path / "paper"
    argv = ["paper-task", "--parts", "il_rl", "--out", str(out)]
    _refused([*argv, "--results", str(tmp_path / "r")], capsys, "PaperTask.parts", "--parts",
             "il_rl", "needs the rl part", "results.json")  # fmt: skip
    assert list(tmp_path.iterdir()) == []
    assert PaperTask(parts=("rl", "il_rl"), out=out).parts == ("rl", "il_rl")
    (out / "rl").mkdir(parents=True)
    (out / "rl" / "results.json").write_text("{}")
    assert PaperTask(parts=("il_rl",), out=out).parts == ("il_rl",)


@pytest.mark.parametrize(
    "flags, field",
    [(["--il.expert-checkpoint", "/nonexistent"], "expert_checkpoint"),
     (["--il.expert", "checkpoint", "--il.expert-checkpoint", "runs/x"], "expert"),
     (["--il.expert-index", "3"], "expert_index")],
)  # fmt: skip
def test_an_expert_given_to_the_parts_is_refused_not_ignored(flags, field, tmp_path, capsys):
    argv = ["paper-task", *flags, "--out", str(tmp_path / "p"), "--results", str(tmp_path / "r")]
    _refused(argv, capsys, f"PaperTask.il.{field} is set by each imitation part")
    assert list(tmp_path.iterdir()) == []
