"""The frontier's rows, budget-matched claims and targets, on made-up evaluation results."""

import json

import numpy as np
import pytest

from sparsecomm.metric_names import aliased
from sparsecomm.pipelines import frontier
from sparsecomm.pipelines import rows as rowlib
from sparsecomm.stats import curves, read_csv


def _results(groups):
    """A results.json with one run per (budget, lam, success, bits, length) per seed offset."""
    runs = []
    for budget, lam, success, bits, length in groups:
        for s, d in enumerate((-0.01, 0.0, 0.01)):
            runs.append(
                {
                    "seed": s,
                    "lam": lam,
                    "budget": budget,
                    "success_rate": success + d,
                    "bits_per_step": bits + 10 * d,
                    "wire_bits_per_step": 2 * bits + 1,
                    "episode_length": length,
                }
            )
    return {"runs": runs}


RL = _results([(None, 0.0, 0.95, 160.0, 70.0), (16.0, 0.0, 0.93, 16.5, 72.0)])
IL = _results([(None, 0.0, 0.90, 150.0, 80.0), (8.0, 0.0, 0.50, 8.0, 150.0)])


def test_rows_group_by_budget_and_lambda_with_cis():
    rows = rowlib.rows(RL, "rl")
    assert [(r["budget"], r["lam"], r["seeds"]) for r in rows] == [(None, 0.0, 3), (16.0, 0.0, 3)]
    success = rows[1]["success"]
    assert success[0] == pytest.approx(0.93) and success[1] <= 0.93 <= success[2]
    assert rows[1]["wire_bits"][0] == pytest.approx(34.0)


def test_budget_matched_claims_and_targets():
    table = rowlib.rows(RL, "rl") + rowlib.rows(IL, "imitation")
    claims = {c["claim"]: c for c in frontier.budget_claims(table)}
    assert claims[4]["held"] and claims[4]["budgets_held"] == [16.0]
    assert not claims[5]["held"]  # budget 8 loses 0.4 success
    targets = {(t["learner"], t["budget"]): t for t in frontier.targets(table)}
    assert targets[("rl", 16.0)]["met"]  # 0.93 >= 0.95 * 0.95, 16.5 within 10% of 16
    assert not targets[("imitation", 8.0)]["met"]
    assert targets[("rl", 16.0)]["success_ratio"] == pytest.approx(0.93 / 0.95)


def test_write_makes_json_without_nan_and_a_figure(tmp_path):
    nan_run = _results([(4.0, 0.0, 0.0, 0.0, 256.0)])
    table = frontier.write(tmp_path, {"rl": [RL, nan_run], "imitation": [IL]})
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text and json.loads(text)[0]["learner"] == "rl"
    assert len(table) == 5 and (tmp_path / "frontier.png").stat().st_size > 10_000
    assert np.isfinite(table[-1]["success"][0])


def test_curves_group_fixed_lambda_runs_once(tmp_path):
    rows = ["seed,lam,budget,update,env_steps,success_rate"]
    for u in (1, 2, 3):
        for s in (0, 1):
            rows.append(f"{s},0.0,,{u},{u * 10},{0.1 * u}")
            rows.append(f"{s},0.0,8,{u},{u * 10},{0.2 * u}")
    (tmp_path / "m.csv").write_text("\n".join(rows))
    groups = curves(read_csv(tmp_path / "m.csv"), "success_rate")
    assert list(groups)[0][1] == 0.0 and np.isnan(list(groups)[0][0]) and len(groups) == 2
    steps, vals = groups[list(groups)[1]]
    np.testing.assert_allclose(vals, [[0.2, 0.4, 0.6]] * 2)


def test_each_series_is_judged_against_its_own_lambda_zero(tmp_path):
    # The same budget 8 run: lost against a strong reference, kept against a weak one.
    weak = _results([(None, 0.0, 0.52, 150.0, 80.0), (8.0, 0.0, 0.50, 8.0, 150.0)])
    table = rowlib.rows(IL, "imitation", "strong") + rowlib.rows(weak, "imitation", "weak")
    assert frontier.series_of(table) == [("imitation", "strong"), ("imitation", "weak")]
    targets = {t["series"]: t for t in frontier.targets(table)}
    assert not targets["strong"]["met"] and targets["weak"]["met"]
    assert targets["weak"]["success_ratio"] == pytest.approx(0.50 / 0.52)
    claims = {c["series"]: c for c in frontier.budget_claims(table)}
    assert not claims["strong"]["held"] and claims["weak"]["budgets_held"] == [8.0]
    # On the command line a series is named SERIES=PATH; rows keep the name.
    path = tmp_path / "weak.json"
    path.write_text(json.dumps(weak))
    frontier.main(["--il", f"weak={path}", str(path), "--out", str(tmp_path / "f")])
    rows = json.loads((tmp_path / "f" / "summary.json").read_text())
    assert [r.get("series") for r in rows] == ["weak", "weak", None, None]


def test_wire_frontier_rows_count_the_network_from_the_datagrams():
    from sparsecomm.channel import ChannelConfig
    from sparsecomm.configs import RLConfig

    config = RLConfig(channel=ChannelConfig(prices="wire", link_gate=True, check_bits=8))
    runs = [
        {
            "seed": s,
            "lam": 0.0,
            "budget": 24.0,
            "success_rate": 0.9 + 0.01 * s,
            "episode_length": 20.0 + s,
            "bits_per_step": 10.0,
            "wire_bits_per_step": 24.0 + s,
            "speaking_fraction": 0.25,
            "datagrams_per_step": 0.5,
            "datagram_bits_per_step": 24.0 + s,
        }
        for s in range(5)
    ]
    (row,) = rowlib.rows({"runs": runs}, "rl", config=config, task="small")
    assert (row["counts"], row["budget"], row["seeds"], row["check_bits"]) == ("wire", 24.0, 5, 8)
    assert row["network_bits"][0] == pytest.approx(26.0 + 0.5 * 8 * (19 + 28))
    lo, mean, hi = row["success"][1], row["success"][0], row["success"][2]
    assert lo < mean < hi and mean == pytest.approx(0.92)
    old = [{k: v for k, v in r.items() if not k.startswith("datagram")} for r in runs]
    assert rowlib.rows({"runs": old}, "rl", config=config, task="small")[0]["network_bits"] is None
    with pytest.raises(ValueError, match="task"):
        rowlib.rows({"runs": runs}, "rl", config=config, task="big")
    # a row of event-triggered links stands beside the learned gate's, not in its place
    news = ChannelConfig(prices="wire", link_gate=True, on_silence="hold", news_margin=0.1)
    (other,) = rowlib.rows({"runs": runs}, "rl", config=RLConfig(channel=news), task="small")
    assert other["news_margin"] == 0.1 and row["news_margin"] is None
    assert rowlib.row_key(other) != rowlib.row_key(row)
    legacy = {k: v for k, v in row.items() if k != "news_margin"}  # written before the field
    assert rowlib.row_key(legacy) == rowlib.row_key(row)
    # the per-seed figures give the runs back, through JSON, for a verdict without the folder
    back = rowlib.seed_runs(json.loads(json.dumps(row)))
    keys = ("seed", "lam", "budget", *rowlib.WIRE_COLUMNS.values())
    assert back == [{k: aliased(r)[k] for k in keys} for r in runs]  # flat names read grouped
    assert rowlib.seed_runs(legacy | {"per_seed": None}) == []


def test_wire_frontier_rows_say_the_learner_and_when_its_mean_success_passed(tmp_path):
    """Group (None, 0): 2 seeds fail for 10 updates, then always succeed; the moving average over
    10 updates first exceeds 0.95 at update 20, inside the chunk that ended at update 21.
    Budget 16: never. ``time_to_target`` reads it from the folder's CSVs."""
    import csv

    from sparsecomm.configs import ILConfig, RLConfig

    steps = 1024  # env steps per update
    with open(tmp_path / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seed", "lam", "budget", "update", "env_steps", "episodes", "success_rate"])
        for u in range(1, 29):
            for budget in ("", "16"):
                for seed in (0, 1):
                    ok = budget == "" and u > 10
                    w.writerow([seed, 0.0, budget, u, u * steps, u * 4, 1.0 if ok else 0.5])
    (tmp_path / "wall.csv").write_text("update,wall_s\n7,7.5\n14,14.5\n21,21.5\n28,28.5\n")
    times = rowlib.time_to_target(tmp_path)
    assert times == {(None, 0.0): (20.0 * steps, 21.5), (16.0, 0.0): (None, None)}
    (tmp_path / "wall.csv").unlink()
    assert rowlib.time_to_target(tmp_path)[(None, 0.0)] == (20.0 * steps, None)
    assert rowlib.time_to_target(tmp_path / "nothing") == {}

    runs = [
        {"seed": s, "lam": 0.0, "budget": b, "success_rate": 0.9, "episode_length": 20.0,
         "bits_per_step": 10.0, "wire_bits_per_step": 30.0, "speaking_fraction": 1.0}
        for b in (None, 16.0) for s in (0, 1)
    ]  # fmt: skip
    ppo = RLConfig(algo="ppo", num_envs=32)
    rl = rowlib.rows({"runs": runs}, "rl", config=ppo, task="paper", times=times)
    learners = [(r["algo"], r["expert"], r["episodes_per_update"]) for r in rl]
    assert learners == [("ppo", None, 32)] * 2
    assert [(r["env_steps_to_095"], r["wall_s_to_095"]) for r in rl] == [
        (20.0 * steps, 21.5),
        (None, None),
    ]
    il = rowlib.rows({"runs": runs}, "imitation", config=ILConfig(), task="paper")
    assert {(r["algo"], r["expert"], r["env_steps_to_095"]) for r in il} == {
        ("dagger", "oracle", None)
    }


def test_wire_frontier_reads_a_deployments_figures_over_its_runs():

    runs = [
        {"success_rate": s, "network_bits_per_step": b, "simulation": {"identical_episodes": 50}}
        for s, b in ((0.9, 140.0), (0.95, 160.0), (0.92, 150.0))
    ]
    got = rowlib.deployed({"runs": runs, "episodes_per_run": 50})
    assert got["runs"] == 3 and got["episodes"] == 50 and got["identical_episodes"] == 150
    assert got["network_bits"][0] == pytest.approx(150.0)
    assert got["network_bits"][1] < 150.0 < got["network_bits"][2]
