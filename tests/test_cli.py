"""The command line end to end with tiny budgets: every artefact written, and readable."""

import dataclasses
import json

import imageio.v3 as iio
import jax
import numpy as np
import pytest

from sparsecomm import learners
from sparsecomm.cli import main, parse
from sparsecomm.configs import SMALL_TASK, ILConfig, RLConfig
from sparsecomm.runfolder import (
    ACTOR,
    PRETRAINED,
    TEAM,
    load_actors,
    load_run,
    read_team,
    runs_of,
    write_team,
)

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
        "episode/group_reward",
        "episode/episode_length",
        "episode/success_rate",
        "channel/bits_per_step",
        "channel/wire_bits_per_step",
        "loss/penalty",
    ):
        assert col in header
    _assert_every_metric_grouped(header, out / "tensorboard", runs=4)
    rows = (out / "metrics.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 * 2 * 2  # updates x seeds x lambdas
    wall = [line.split(",") for line in (out / "wall.csv").read_text().splitlines()]
    assert wall[0] == ["update", "wall_s"] and [int(u) for u, _ in wall[1:]] == [1, 2]
    assert 0 < float(wall[1][1]) <= float(wall[2][1])  # seconds trained when each chunk ended
    results = json.loads((out / "results.json").read_text())
    assert set(results["by_group"]) == {"0", "0.01"} and len(results["runs"]) == 4
    main(["eval", "--run", str(out), "--episodes", "4"])
    ev = json.loads((out / "eval.json").read_text())
    assert ev["episodes_per_run"] == 4 and len(ev["runs"]) == 4
    main(["render", "--run", str(out), "--index", "3", "--out", str(tmp_path / "t.gif")])
    frames = iio.imread(tmp_path / "t.gif", index=None)
    assert frames.ndim == 4 and 2 <= frames.shape[0] <= 13
    # An exported team is the run's team, weights only: its config, its run, its actor exactly.
    main(["export", "--run", str(out), "--index", "3", "--out", str(tmp_path / "team")])
    config, _, runs, actor = load_run(out)
    team = read_team(tmp_path / "team")
    assert team.config == config and team.run == runs[3] and runs_of(tmp_path / "team") == [runs[3]]
    _assert_same(jax.tree.map(lambda x: np.asarray(x)[3], actor), team.actor)


def _assert_every_metric_grouped(header: list[str], tensorboard=None, runs: int = 0) -> None:
    """Every metric column of a ``metrics.csv`` header, and every TensorBoard tag of every run
    (one writer per run), is ``group/key`` with the group :data:`GROUPS` gives the key."""
    from sparsecomm.metric_names import GROUPS, group_of
    from sparsecomm.sweep import FIRST_COLUMNS

    def grouped(name):
        group, _, key = name.partition("/")
        return group in GROUPS and group_of(key) == group

    metrics = header[len(FIRST_COLUMNS) :]
    assert header[: len(FIRST_COLUMNS)] == FIRST_COLUMNS and metrics
    assert [m for m in metrics if not grouped(m)] == []
    if tensorboard is None:
        return
    folders = sorted({p.parent for p in tensorboard.rglob("events.out.tfevents.*")})
    assert len(folders) == runs  # one writer (a TensorBoard run) per run of the sweep
    for folder in folders:
        tags = {t for f in folder.glob("events.out.tfevents.*") for t in _scalar_tags(f)}
        assert tags and [t for t in tags if not grouped(t)] == [], folder
        assert tags <= set(metrics)


def _scalar_tags(path) -> set[str]:
    """The scalar tags of a TensorBoard event file (TFRecord framing: an 8-byte length, a 4-byte
    CRC, the ``Event`` protobuf, a 4-byte CRC)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event

    data, tags, at = path.read_bytes(), set(), 0
    while at < len(data):
        (length,) = struct.unpack("<Q", data[at : at + 8])
        event = Event.FromString(data[at + 12 : at + 12 + length])
        tags |= {v.tag for v in event.summary.value}
        at += 12 + length + 4
    return tags


def _assert_same(a, b) -> None:
    """Two parameter trees hold the same arrays, bit for bit and dtype for dtype."""
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(leaves_a) == len(leaves_b) > 0
    for x, y in zip(leaves_a, leaves_b, strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_exported_team_is_written_and_read_back_exactly(tmp_path):
    # One function writes an exported team and one reads it: the shipped team written again
    # has the same weights byte for byte, the same config and the same run.
    shipped = read_team(PRETRAINED)
    batched = jax.tree.map(lambda x: np.asarray(x)[None], shipped.actor)
    folder = write_team(tmp_path / "again", shipped.config, [shipped.run], batched, 0, "again")
    assert (folder / ACTOR).read_bytes() == (PRETRAINED / ACTOR).read_bytes()
    meta, shipped_meta = (json.loads((f / TEAM).read_text()) for f in (folder, PRETRAINED))
    # the shipped team names its kind as teams did before the learner registry ("train"); the
    # team written again names it by the registry's name
    assert meta["note"] == "again" and shipped_meta["kind"] == "train"
    assert meta["kind"] == learners.named(shipped_meta["kind"]).name == "rl"
    again = read_team(folder)
    assert again.config == shipped.config and again.run == shipped.run
    _assert_same(again.actor, shipped.actor)
    assert read_team(folder, weights=False).actor is None
    # Every reader of a folder sees the same team: with a learner, and without one.
    config, _, runs, actor = load_run(folder)
    fast = load_actors(folder)
    assert config == fast.config == shipped.config and runs == fast.runs == [shipped.run]
    _assert_same(actor, batched)
    _assert_same(fast.actor, batched)


@pytest.mark.parametrize("command, cls", [("train", RLConfig), ("imitate", ILConfig)])
def test_the_small_preset_serves_both_learners(command, cls):
    cmd = parse([command, "--preset", "small", "--config.num-updates", "7", "--seeds", "3"])
    config = cmd.config
    assert type(config) is cls and config.env == SMALL_TASK
    assert config.budget.bits == 16.0 and config.agent.message_gate == "hard"
    assert config.num_envs == 64 and config.num_updates == 7 and cmd.seeds == 3  # flags win
    # Each learner keeps its own controller defaults: imitation's bounded relief, RL's none.
    assert config.budget.relief_floor == cls.budget.relief_floor
    assert config.budget.weight_init == cls.budget.weight_init
    assert str(cmd.out) == ("runs/small" if command == "train" else "runs/imitate_small")


@pytest.mark.slow
def test_imitate_writes_imitation_loss(tmp_path, fast_compile):
    out = tmp_path / "im"
    main(["imitate", *TINY, "--no-gif", "--no-tensorboard", "--out", str(out)])
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "loss/imitation_loss" in header and "schedule/beta" in header
    _assert_every_metric_grouped(header)
    assert json.loads((out / "results.json").read_text())["runs"][0]["lam"] == 0.0


@pytest.mark.slow
def test_budget_sweep_export_and_the_shipped_team(tmp_path, fast_compile, monkeypatch):
    out = tmp_path / "budgets"
    main(["train", *TINY, "--budgets", "None", "8", "--no-gif", "--out", str(out)])
    results = json.loads((out / "results.json").read_text())
    assert list(results["by_group"]) == ["0", "budget=8/0"]
    assert [r["budget"] for r in results["runs"]] == [None, 8.0]
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"budget", "budget/price", "budget/bit_target"} <= set(header)
    # An exported team is the run's team, weights only (msgpack + JSON, no pickle).
    main(["export", "--run", str(out), "--index", "1", "--out", str(tmp_path / "team")])
    config, _, runs, actor = load_run(out)
    config_t, _, runs_t, actor_t = load_run(tmp_path / "team")
    assert config_t == config and runs_t == [runs[1]]
    for x, y in zip(jax.tree.leaves(actor), jax.tree.leaves(actor_t), strict=True):
        np.testing.assert_array_equal(np.asarray(x)[1], np.asarray(y)[0])
    main(["eval", "--run", str(tmp_path / "team"), "--episodes", "4"])
    alone = json.loads((tmp_path / "team" / "eval.json").read_text())["runs"][0]
    assert alone["budget"] == 8.0 and alone["episode/episode_length"] > 0
    # The shipped sparse team: `sparsecomm eval` with no run. It was measured at success 0.988
    # and 14.5 payload bits per step over 500 episodes (docs/budget.md).
    monkeypatch.chdir(tmp_path)
    main(["eval", "--episodes", "64"])
    shipped = json.loads((tmp_path / "runs" / "pretrained" / "eval.json").read_text())["runs"][0]
    assert shipped["budget"] == 16.0
    assert shipped["episode/success_rate"] > 0.85, shipped
    assert 10 < shipped["channel/bits_per_step"] < 20, shipped


def test_the_silent_preset_prices_the_wire_and_holds_silent_links():
    cmd = parse(["train", "--preset", "silent", "--config.num-updates", "5"])
    channel = cmd.config.channel
    assert (channel.prices, channel.link_gate, channel.on_silence) == ("wire", True, "hold")
    assert channel.check_bits == 16 and channel.deployable and channel.news_margin == 0.1
    assert cmd.config.budget.bits == 24.0 and cmd.config.budget.relief_floor == 0.5
    assert str(cmd.out) == "runs/silent" and cmd.config.num_updates == 5
    assert parse(["imitate", "--preset", "silent"]).config.channel == channel


def test_the_paper_preset_is_the_fast_learner_on_the_paper_task():
    cmd = parse(["train", "--preset", "paper", "--config.num-updates", "9"])
    cfg = cmd.config
    assert cfg.env == RLConfig().env and cfg.algo == "a2c" and cfg.num_updates == 9
    assert (cfg.num_envs, cfg.lr, cfg.lr_final, cfg.lr_decay_steps) == (32, 1e-3, 1e-4, 1000)
    assert str(cmd.out) == "runs/paper"
    il = parse(["imitate", "--preset", "paper"]).config  # docs/budget.md's bounded relief
    assert il.env == ILConfig().env and il.agent.message_gate == "hard" and il.num_envs == 32
    assert (il.num_updates, il.budget.halving_updates, il.budget.relief_floor) == (1000, 40, 0.1)
    fast = parse(["train", "--preset", "paper_fast"]).config  # docs/paper-task.md's race
    assert fast.env == RLConfig().env and fast.agent.message_gate == "hard"
    assert (fast.num_envs, fast.lr_final, fast.lr_decay_steps, fast.num_updates) == (
        16,
        1e-4,
        2000,
        1750,
    )
    serves = "--preset paper serves only 'sparsecomm train' and 'sparsecomm imitate', not 'eval'"
    with pytest.raises(ValueError, match=serves):
        parse(["eval", "--preset", "paper"])


def _refused(argv, capsys, *words):
    """``main(argv)`` exits 2 with one line naming ``words``, no traceback."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = " ".join(capsys.readouterr().err.split())  # tyro's box wraps lines
    assert e.value.code == 2, err
    assert "Traceback" not in err and "__tyro" not in err, err
    assert all(word in err for word in words), err
    return err


def test_every_output_path_is_checked_before_any_work(tmp_path, capsys, monkeypatch):
    """A file where a folder is wanted, for the pipelines' and deploy's outputs (a part's own
    folder under ``out`` included): refused while parsing, naming the field, nothing written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("kept")
    (tmp_path / "paper").mkdir()
    (tmp_path / "paper" / "rl").write_text("kept")
    cases = [
        (["paper-task", "--parts", "rl", "--results", "file"], "PaperTask.results must be a"),
        (["paper-task", "--parts", "rl", "--out", "file"], "PaperTask.out must be a folder"),
        (["paper-task", "--parts", "rl", "--out", "paper"], "PaperTask.out", "rl part's folder"),
        (["reproduce", "--quick", "--out", "file"], "Reproduce.out must be a folder"),
        (["deploy", "--out", "file"], "Deploy.out must be a folder"),
    ]
    for argv, *words in cases:
        _refused(argv, capsys, *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "paper"]  # nothing written
    assert [p.name for p in (tmp_path / "paper").iterdir()] == ["rl"]


def test_errors_of_nested_fields_name_the_commands_field(capsys):
    err = _refused(["paper-task", "--rl.lr", "-1"], capsys, "RLConfig.lr must be > 0")
    assert "rl" in err.split("RLConfig")[0]
    _refused(["paper-task", "--il.num-envs", "0"], capsys, "il", "ILConfig.num_envs")
    _refused(["train", "--config.lr", "0"], capsys, "config", "RLConfig.lr")


def test_init_from_a_run_of_another_size_is_refused_before_the_output_folder(tmp_path, capsys):
    """An exported team whose actor has 16 hidden units, fine-tuned at 32: refused naming the
    field, and no output folder made (nothing trained)."""
    from sparsecomm.runfolder import learner_for
    from sparsecomm.sweep import SweepSpec

    config = RLConfig()
    config = dataclasses.replace(config, agent=dataclasses.replace(config.agent, hidden=16))
    actor = learner_for(config).team.init(jax.random.key(0))["actor"]
    runs = SweepSpec(1, (0.0,), (None,)).runs()
    team = write_team(tmp_path / "team", config, runs, jax.tree.map(lambda x: x[None], actor), 0)
    out = tmp_path / "run"
    argv = ["train", *TINY, "--config.agent.hidden", "32", "--init-from", str(team)]
    _refused([*argv, "--out", str(out)], capsys, "Train.init_from", "other shapes")
    assert not out.exists()
