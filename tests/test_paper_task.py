"""``sparsecomm paper-task`` end to end with tiny budgets: every part, the rows, the verdicts."""

import json
import shutil

import pytest

from sparsecomm.cli import main
from sparsecomm.paper_task import PARTS, PaperTask, summarise
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
    # Finished parts are only re-evaluated: the same rows again.
    main(["paper-task", *TINY, "--parts", "rl", "--out", str(out), "--results", str(results)])
    again = json.loads((results / "summary.json").read_text())
    key = lambda r: (r["part"], str(r["budget"]), r["lam"])  # noqa: E731
    assert sorted(again, key=key) == sorted(rows, key=key)
    # A part whose run folder is gone (run in another session) keeps its rows.
    shutil.rmtree(out / "il_rl")
    assert len(summarise(PaperTask(out=out, results=results))) == len(rows)
    kept = json.loads((results / "summary.json").read_text())
    assert sorted(kept, key=key) == sorted(rows, key=key)


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
