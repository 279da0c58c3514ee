"""The command line end to end with tiny budgets: every artefact written, and readable."""

import json

import imageio.v3 as iio

from sparsecomm.cli import main

TINY = [
    "--config.env.max-steps",
    "12",
    "--config.num-envs",
    "4",
    "--config.num-updates",
    "2",
    "--chunk",
    "1",
    "--eval-episodes",
    "8",
    "--no-progress",
]


def test_train_eval_render(tmp_path, fast_compile):
    out = tmp_path / "run"
    main(["train", *TINY, "--seeds", "2", "--lams", "0", "0.01", "--out", str(out)])
    for name in ("metrics.csv", "results.json", "curves.png", "team.gif"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "tensorboard").is_dir() and (out / "checkpoint" / "state.msgpack").exists()
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    for col in (
        "seed",
        "lam",
        "update",
        "env_steps",
        "episodes",
        "group_reward",
        "episode_length",
        "success_rate",
        "bits_per_step",
        "wire_bits_per_step",
        "penalty",
    ):
        assert col in header
    rows = (out / "metrics.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 * 2 * 2  # updates x seeds x lambdas
    results = json.loads((out / "results.json").read_text())
    assert set(results["by_group"]) == {"0", "0.01"} and len(results["runs"]) == 4
    main(["eval", "--run", str(out), "--episodes", "4"])
    ev = json.loads((out / "eval.json").read_text())
    assert ev["episodes_per_run"] == 4 and len(ev["runs"]) == 4
    main(["render", "--run", str(out), "--index", "3", "--out", str(tmp_path / "t.gif")])
    frames = iio.imread(tmp_path / "t.gif", index=None)
    assert frames.ndim == 4 and 2 <= frames.shape[0] <= 13


def test_imitate_writes_imitation_loss(tmp_path, fast_compile):
    out = tmp_path / "im"
    main(["imitate", *TINY, "--no-gif", "--no-tensorboard", "--out", str(out)])
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "imitation_loss" in header and "beta" in header
    assert json.loads((out / "results.json").read_text())["runs"][0]["lam"] == 0.0
