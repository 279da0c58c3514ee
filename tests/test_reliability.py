"""Nothing lost, nothing silent: bad input refused before any work with the field's
name and exit code 2, divergence stops a run with exit code 3, checkpoints that cannot lie, and
logs that hold each update once across kills and resumes."""

import functools
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from sparsecomm import checkpoint
from sparsecomm.cli import main
from sparsecomm.configs import RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.errors import CheckpointError
from sparsecomm.jsonfile import write_json
from sparsecomm.rl import make_train
from sparsecomm.runfolder import load_run
from sparsecomm.sharding import raw_keys
from sparsecomm.sweep import SweepSpec, record_digest, run_sweep

TINY = ["--config.env.max-steps", "8", "--config.num-envs", "4", "--no-progress", "--no-gif"]
TINY += ["--eval-episodes", "4", "--no-tensorboard"]


def _refused(argv, capsys, field):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = " ".join(capsys.readouterr().err.split())  # tyro's box wraps lines
    assert e.value.code == 2, err
    assert field in err and "Traceback" not in err, err
    return err


@pytest.mark.parametrize(
    "argv, field",
    [
        (["train", "--chunk", "0"], "Train.chunk"),
        (["train", "--chunk", "-1"], "Train.chunk"),
        (["train", "--checkpoint-every", "0"], "Train.checkpoint_every"),
        (["train", "--eval-episodes", "-3"], "Train.eval_episodes"),
        (["train", "--seeds", "0"], "Train.seeds"),
        (["train", "--lams", "-0.1"], "lams"),
        (["train", "--budgets", "nan"], "budgets"),
        (["train", "--budgets", "1e9"], "budgets"),
        (["imitate", "--chunk", "0"], "Imitate.chunk"),
        (["eval", "--episodes", "0"], "Eval.episodes"),
        (["render", "--fps", "0"], "Render.fps"),
        (["render", "--index", "-1"], "Render.index"),
        (["train", "--config.lr", "inf"], "RLConfig.lr"),
        (["train", "--config.lr", "0"], "RLConfig.lr"),
        (["imitate", "--config.lr", "nan"], "ILConfig.lr"),
        (["train", "--config.num-envs", "0"], "RLConfig.num_envs"),
        (["train", "--config.channel.levels", "0"], "ChannelConfig.levels"),
        (["train", "--config.budget.bits", "-1"], "BudgetConfig.bits"),
        # links that speak on news need a gate and held messages, and read back only what holds
        (["train", "--config.channel.news-margin", "0.1"], "ChannelConfig.news_margin"),
        (["train", "--preset", "silent", "--config.channel.news-margin", "2"], "news_margin"),
        (["train", "--config.agent.reads-sent"], "RLConfig.agent.reads_sent"),
        (["train", "--preset", "silent", "--config.experimental.decoupled"], "decoupled"),
        (["train", "--preset", "nope"], "--preset"),
        (["eval", "--preset", "small"], "--preset"),
        # Upper bounds (configs.MAX_UPDATES, configs.MAX_SEED, experiment.MAX_FPS).
        (["train", "--config.num-updates", str(10**23)], "RLConfig.num_updates"),
        (["train", "--config.num-updates", "10000001"], "RLConfig.num_updates"),
        (["train", "--config.seed", str(2**70)], "RLConfig.seed"),
        (["imitate", "--config.seed", "-1"], "ILConfig.seed"),
        (["render", "--fps", "100000"], "Render.fps"),
        (["render", "--seed", str(2**40)], "Render.seed"),
        # fit-code's own fields, before any rollout.
        (["fit-code", "--run", "nothing", "--group", "11"], "FitCode.group"),
        (["fit-code", "--run", "nothing", "--alpha", "-1"], "FitCode.alpha"),
        (["fit-code", "--run", "nothing", "--alpha", "nan"], "FitCode.alpha"),
        (["fit-code", "--run", "nothing", "--seed", "-1"], "FitCode.seed"),
        # deploy binds its sockets on this machine: an address literal of it, or a name.
        (["deploy", "--host", "999.1.1.1"], "Deploy.host"),
        (["deploy", "--host", "192.0.2.1"], "Deploy.host"),  # TEST-NET-1: not this machine
        # An empty path is not the current folder.
        (["train", "--out", ""], "Train.out"),
        (["imitate", "--out="], "Imitate.out"),
        (["eval", "--out", ""], "Eval.out"),
        (["export", "--run", "nothing", "--out", ""], "Export.out"),
        (["render", "--run", ""], "Render.run"),
    ],
)
def test_bad_input_is_refused_before_any_work(argv, field, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    err = _refused(argv, capsys, field)
    assert err.startswith("sparsecomm: error:") or "Error parsing" in err
    assert list(tmp_path.iterdir()) == []  # nothing written


def _read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write: a chmod'ed one, or (as root, whom modes do not
    stop) /proc/1."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    if os.access(folder, os.W_OK):
        folder = Path("/proc/1")
    if os.access(folder, os.W_OK):
        pytest.skip("no folder here is read-only to this process")
    return folder


def test_outputs_that_cannot_be_written_are_refused_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("kept")
    (tmp_path / "folder").mkdir()
    locked = _read_only_folder(tmp_path)
    cases = [
        (["train", *TINY, "--out", "file"], "Train.out must be a folder"),
        (["imitate", *TINY, "--out", "file"], "Imitate.out must be a folder"),
        (["train", *TINY, "--out", "file/run"], "Train.out cannot be created: file is a file"),
        (["train", *TINY, "--out", str(locked / "run")], "Train.out cannot be created"),
        (["export", "--run", "nothing", "--out", "file"], "Export.out must be a folder"),
        (["export", "--run", "x", "--out", str(locked / "t")], "Export.out cannot be created"),
        (["eval", "--out", "folder"], "Eval.out must be a file"),
        (["eval", "--out", str(locked / "eval.json")], "Eval.out cannot be created"),
        (["render", "--out", "folder"], "Render.out must be a file"),
        (["render", "--out", "file/team.gif"], "Render.out cannot be created"),
        (["fit-code", "--run", "nothing", "--out", "folder"], "FitCode.out must be a file"),
    ]
    before = sorted(p.name for p in tmp_path.iterdir())
    for argv, message in cases:
        _refused(argv, capsys, message)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written
    assert (tmp_path / "file").read_text() == "kept" and not any((tmp_path / "folder").iterdir())


@pytest.mark.parametrize(
    "flags",
    [
        ["--config.agent.hidden", "200000"],
        ["--config.channel.num-elements", "1000000"],
        ["--seeds", "100000"],
    ],
)
def test_a_sweep_too_large_for_the_devices_is_refused_with_its_estimate(flags, capsys, tmp_path):
    err = _refused(["train", *flags, "--out", str(tmp_path / "big")], capsys, "GiB")
    assert "this sweep needs about" in err and "lower --seeds" in err
    assert not (tmp_path / "big" / "checkpoint").exists()  # nothing was run


def test_index_outside_the_sweep_is_refused(tmp_path, capsys, fast_compile):
    out = tmp_path / "run"
    main(["train", *TINY, "--config.num-updates", "1", "--out", str(out)])
    _refused(["render", "--run", str(out), "--index", "5"], capsys, "Render.index")
    _refused(
        ["export", "--run", str(out), "--index", "1", "--out", str(tmp_path / "t")],
        capsys,
        "Export.index",
    )
    _refused(["eval", "--run", str(tmp_path / "nothing")], capsys, "no run folder")


def test_divergence_stops_the_run_names_it_and_keeps_the_last_good_checkpoint(
    tmp_path, capsys, fast_compile
):
    out = tmp_path / "diverged"
    argv = ["train", *TINY, "--config.num-updates", "6", "--chunk", "1", "--out", str(out)]
    with pytest.raises(SystemExit) as e:
        main([*argv, "--config.lr", "1e6", "--seeds", "2"])
    err = capsys.readouterr().err
    assert e.value.code == 3, err
    assert "training diverged: run" in err and "at update" in err and "Traceback" not in err
    assert not (out / "results.json").exists()  # nothing reported as if it were real
    if checkpoint.exists(out / "checkpoint"):  # the last good one: every parameter finite
        _, _, _, actor = load_run(out)
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(actor))


def test_results_files_never_hold_nan(tmp_path):
    path = write_json(tmp_path / "r.json", {"a": [1.0, float("nan")], "b": {"c": float("inf")}})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    assert data["a"] == [1.0, None] and data["b"]["c"] is None
    assert set(data["nulls"]) == {"a[1]", "b.c"}


CFG = RLConfig(env=NavConfig(max_steps=8), num_envs=4, num_updates=4)
KW = dict(
    chunk=1,
    checkpoint_every=1,
    tensorboard=False,
    progress=False,
)


@functools.cache
def _trainer():
    """CFG's learner, one object: sweeps of it share one compiled program."""
    return make_train(CFG)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ckpt") / "run"
    sweep = run_sweep(_trainer(), SweepSpec(seeds=2), folder, num_updates=2, **KW)
    return folder / "checkpoint", sweep.state


@pytest.fixture(scope="module")
def other(saved, tmp_path_factory):
    """Another run folder of the same learner and shapes (lambda 0.01, one update): only what
    its run folder records can tell its checkpoint from the saved run's."""
    folder = tmp_path_factory.mktemp("other") / "run"
    run_sweep(_trainer(), SweepSpec(seeds=2, lams=(0.01,)), folder, num_updates=1, **KW)
    return folder


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def test_checkpoint_round_trip_and_every_damage_is_named(saved, tmp_path):
    ckpt, state = saved
    back = checkpoint.load(ckpt, state)
    for x, y in zip(jax.tree.leaves(raw_keys(state)), jax.tree.leaves(raw_keys(back)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    flipped = _copy(ckpt, tmp_path / "flipped")
    data = bytearray((flipped / "state.msgpack").read_bytes())
    data[len(data) // 2] ^= 0x01
    (flipped / "state.msgpack").write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="state.msgpack is damaged"):
        checkpoint.load(flipped, state)
    cut = _copy(ckpt, tmp_path / "cut")
    (cut / "state.msgpack").write_bytes((ckpt / "state.msgpack").read_bytes()[:100])
    with pytest.raises(CheckpointError, match="state.msgpack is damaged"):
        checkpoint.load(cut, state)
    for part in ("state.msgpack", "config.json"):
        gone = _copy(ckpt, tmp_path / f"no-{part}")
        (gone / part).unlink()
        with pytest.raises(CheckpointError, match=f"incomplete: .*{part} is missing"):
            checkpoint.load(gone, state)
    bad_json = _copy(ckpt, tmp_path / "json")
    (bad_json / "config.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="config.json is damaged"):
        checkpoint.load(bad_json, state)
    edited = _copy(ckpt, tmp_path / "edited")  # valid JSON, one value changed
    text = (edited / "config.json").read_text()
    (edited / "config.json").write_text(text.replace('"seeds": 2', '"seeds": 3'))
    assert (edited / "config.json").read_text() != text
    with pytest.raises(CheckpointError, match="config.json is damaged"):
        checkpoint.load(edited, state)


def _edited(run: Path, dst: Path, edit) -> Path:
    """A copy of the run folder ``run`` whose ``config.json`` was edited by ``edit(meta)`` and
    its digest recomputed: consistent, so only its values can tell."""
    shutil.copytree(run, dst)
    path = dst / "checkpoint" / "config.json"
    meta = json.loads(path.read_text())
    edit(meta)
    meta["meta_sha256"] = checkpoint._meta_digest(meta)
    path.write_text(json.dumps(meta))
    return dst


EDITS = {
    "nan": (lambda m: m["config"].update(gamma=float("nan")), "RLConfig.gamma must be finite"),
    "missing key": (lambda m: m["config"].pop("gamma"), "config.gamma (checkpoint: missing"),
    "string for an integer": (
        lambda m: m["config"].update(num_envs="4"),
        "RLConfig.num_envs must be of type int, got '4'",
    ),
    "string seed": (lambda m: m["config"].update(seed="0"), "RLConfig.seed must be of type int"),
    "another number of seeds": (lambda m: m.update(seeds=3), "holds 2 run(s), but config.json"),
    "no seeds": (lambda m: m.pop("seeds"), "config.json has no field 'seeds'"),
    "not an object": (lambda m: m["config"].update(env=5), "RLConfig.env must be a NavConfig"),
}


@pytest.mark.parametrize("edit", list(EDITS))
def test_every_reader_refuses_an_edited_config_json_naming_the_field(saved, edit, tmp_path, capsys):
    change, message = EDITS[edit]
    run = _edited(saved[0].parent, tmp_path / "run", change)
    files = sorted(p.relative_to(run) for p in run.rglob("*"))
    commands = [
        ["eval", "--run", str(run), "--episodes", "2"],
        ["render", "--run", str(run)],
        ["export", "--run", str(run), "--out", str(tmp_path / "team")],
        ["fit-code", "--run", str(run), "--episodes", "2"],
    ]
    for argv in commands if edit == "nan" else commands[:1]:  # each reader once, eval each edit
        err = _refused(argv, capsys, message)
        assert "config.json" in err or "state.msgpack" in err, err
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == files  # nothing written
    assert not (tmp_path / "team").exists()


@pytest.mark.parametrize("part", ["state.msgpack", "config.json"])
def test_a_checkpoint_file_that_cannot_be_read_is_named_by_eval_and_resume(
    saved, part, tmp_path, capsys, fast_compile
):
    run = tmp_path / "run"
    shutil.copytree(saved[0].parent, run)
    (run / "checkpoint" / part).unlink()
    (run / "checkpoint" / part).mkdir()  # a folder where the file should be: an OSError
    message = f"checkpoint file {run / 'checkpoint' / part} cannot be read (Is a directory)"
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    _refused(["eval", "--run", str(run), "--episodes", "2"], capsys, message)
    # The resume of the same run (TINY is CFG's task and episodes; two seeds) refuses it too.
    _refused(["train", *TINY, "--seeds", "2", "--out", str(run)], capsys, message)
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before  # nothing written


def test_a_default_output_that_is_a_folder_is_refused_before_any_work(saved, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(saved[0].parent, run)
    for name, argv in [
        ("eval.json", ["eval", "--run", str(run)]),
        ("team.gif", ["render", "--run", str(run)]),
        ("code.json", ["fit-code", "--run", str(run)]),
    ]:
        (run / name).mkdir()
        _refused(argv, capsys, f"(default: {run / name}) must be a file to write")
        assert not any((run / name).iterdir())


def _one_line_refusal(argv, capsys, *words) -> str:
    """``main(argv)`` exits 2 with exactly one stderr line holding every one of ``words``."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert err.startswith("sparsecomm: error: ") and len(err.strip().splitlines()) == 1, err
    assert all(word in err for word in words), err
    return err


def test_a_checkpoint_not_of_its_run_folder_is_refused_by_eval_as_by_resume(
    saved, other, tmp_path, capsys
):
    """A checkpoint swapped in whole from another run folder, and one whose config.json was
    edited consistently (its digest recomputed): each reads as a valid run, so only the run
    folder's run.json can tell. Every reader refuses naming the field and both values, writing
    nothing; a resume of the run the folder holds refuses the same field."""
    run = saved[0].parent
    swapped = tmp_path / "swapped"
    shutil.copytree(run, swapped)
    shutil.rmtree(swapped / "checkpoint")
    shutil.copytree(other / "checkpoint", swapped / "checkpoint")
    edited = _edited(run, tmp_path / "edited", lambda m: m["config"]["env"].update(max_steps=4))
    cases = [
        (swapped, "lams (checkpoint: [0.01], run.json: [0.0])", "lams (checkpoint: [0.01], now"),
        (edited, "config.env.max_steps (checkpoint: 4, run.json: 8)", "max_steps (checkpoint: 4"),
    ]
    for folder, difference, resumed in cases:
        files = sorted(p.relative_to(folder) for p in folder.rglob("*"))
        refusal = f"run folder {folder} does not hold the run its run.json records"
        readers = [
            ["eval", "--run", str(folder), "--episodes", "2"],
            ["render", "--run", str(folder)],
            ["export", "--run", str(folder), "--out", str(tmp_path / "team")],
        ]
        for argv in readers if folder == swapped else readers[:1]:  # each reader once
            _one_line_refusal(argv, capsys, refusal, difference)
        assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == files  # nothing written
        assert not (tmp_path / "team").exists()
        # The resume of the run the folder holds (TINY is CFG's task and episodes, two seeds).
        argv = ["train", *TINY, "--seeds", "2", "--out", str(folder)]
        _one_line_refusal(argv, capsys, f"cannot resume from {folder / 'checkpoint'}", resumed)


def test_a_run_folder_evaluates_and_one_without_a_record_warns_once(
    saved, tmp_path, capsys, fast_compile
):
    """An untouched run folder evaluates without a word on stderr; the same folder without its
    run.json (as written before the record existed) evaluates to the same numbers, with one
    warning line."""
    run = tmp_path / "run"
    shutil.copytree(saved[0].parent, run)
    argv = ["eval", "--run", str(run), "--episodes", "2"]
    main(argv)
    assert capsys.readouterr().err == ""
    first = json.loads((run / "eval.json").read_text())
    assert len(first["runs"]) == 2
    (run / "run.json").unlink()
    (run / "eval.json").unlink()
    main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"sparsecomm: warning: {run} has no run.json (written by an older sparsecomm): its "
        "checkpoint is read without checking it against the run that trained it"
    ]
    assert json.loads((run / "eval.json").read_text()) == first


def _rewrite_record(run: Path, edit, digest: bool = True) -> None:
    path = run / "run.json"
    record = json.loads(path.read_text())
    edit(record)
    if digest:
        record["record_sha256"] = record_digest(record)
    path.write_text(json.dumps(record))


def test_a_damaged_run_record_or_one_of_other_shapes_is_refused(saved, tmp_path, capsys):
    run = saved[0].parent
    kernel = "actor/params/Dense_0/kernel"
    cases = {
        "edited, digest kept": (
            lambda r: r["config"]["env"].update(max_steps=4),
            False,
            "run.json is damaged: its record_sha256 is not the SHA-256 of its other fields",
        ),
        "a field the config refuses": (
            lambda r: r["config"].update(gamma=2.0),
            True,
            "run.json does not hold a valid run: RLConfig.gamma",
        ),
        "other shapes": (
            lambda r: r["params"][kernel].__setitem__(-1, r["params"][kernel][-1] + 1),
            True,
            f"differs in params {kernel} (checkpoint: [2, ",
        ),
    }
    for name, (edit, digest, message) in cases.items():
        folder = tmp_path / name.replace(" ", "-").replace(",", "")
        shutil.copytree(run, folder)
        _rewrite_record(folder, edit, digest)
        _one_line_refusal(["eval", "--run", str(folder), "--episodes", "2"], capsys, message)
    folder = tmp_path / "not-json"
    shutil.copytree(run, folder)
    (folder / "run.json").write_text("{not json")
    message = f"run record {folder / 'run.json'} is damaged (not valid JSON"
    _one_line_refusal(["eval", "--run", str(folder), "--episodes", "2"], capsys, message)


def test_an_exported_team_with_another_teams_actor_is_refused(tmp_path, capsys):
    """An exported team's actor.msgpack replaced by one of a team with 32 hidden units where
    its team.json says 16: refused naming the file, the parameter and both shapes."""
    import dataclasses

    from sparsecomm.runfolder import learner_for, write_team

    runs = SweepSpec(1, (0.0,), (None,)).runs()
    for hidden in (16, 32):
        config = dataclasses.replace(CFG, agent=dataclasses.replace(CFG.agent, hidden=hidden))
        actor = learner_for(config).team.init(jax.random.key(0))["actor"]
        write_team(tmp_path / str(hidden), config, runs, jax.tree.map(lambda x: x[None], actor), 0)
    (tmp_path / "16" / "actor.msgpack").write_bytes(
        (tmp_path / "32" / "actor.msgpack").read_bytes()
    )
    team = tmp_path / "16"
    message = f"team file {team / 'actor.msgpack'} does not hold the actor its team.json describes"
    argv = ["eval", "--run", str(team), "--episodes", "2"]
    _one_line_refusal(argv, capsys, message, "has shape [32] in actor.msgpack, [16] in the actor")


def test_a_save_killed_between_its_renames_leaves_the_previous_checkpoint(saved, tmp_path):
    ckpt, state = saved
    # The moment between "checkpoint -> checkpoint.old" and "checkpoint.new -> checkpoint".
    _copy(ckpt, tmp_path / "checkpoint.old")
    (tmp_path / "checkpoint.new").mkdir()
    assert checkpoint.exists(tmp_path / "checkpoint")
    back = checkpoint.load(tmp_path / "checkpoint", state)
    np.testing.assert_array_equal(back.update, state.update)
    checkpoint.save(tmp_path / "checkpoint", state, {"note": "again"})  # and saving recovers
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint"]


def test_resume_refuses_a_damaged_checkpoint_instead_of_starting_over(
    tmp_path, capsys, fast_compile
):
    out = tmp_path / "run"
    argv = ["train", *TINY, "--config.num-updates", "2", "--chunk", "1", "--out", str(out)]
    main(argv)
    (out / "checkpoint" / "state.msgpack").unlink()
    _refused(
        [*argv[:-4], "--config.num-updates", "3", "--chunk", "1", "--out", str(out)],
        capsys,
        "state.msgpack is missing",
    )
    # A resume that changes what the run is names the field, the old and the new value.
    main(argv + ["--no-resume"])
    err = _refused([*argv, "--config.gamma", "0.9"], capsys, "config.gamma (checkpoint: 0.95")
    assert "now: 0.9" in err


@pytest.mark.slow
def test_elapsed_time_adds_up_over_resumes(tmp_path):
    tr = make_train(CFG)
    first = run_sweep(tr, SweepSpec(), tmp_path / "r", num_updates=2, **KW)
    second = run_sweep(tr, SweepSpec(), tmp_path / "r", num_updates=4, **KW)
    meta = checkpoint.load_meta(tmp_path / "r" / "checkpoint")
    assert second.elapsed_s > first.elapsed_s > 0
    assert meta["elapsed_s"] == pytest.approx(second.elapsed_s, rel=0.05)


def _tb_scalars(folder: Path) -> dict[str, list[int]]:
    """The steps of every scalar of every run as TensorBoard shows them, by ``run/tag`` (one
    writer per run, in its own folder under ``folder``)."""
    shown: dict[str, list[int]] = {}
    for run in sorted({p.parent for p in folder.rglob("events.out.tfevents.*")}):
        name = run.relative_to(folder).as_posix()
        shown |= {f"{name}/{t}": v for t, v in _tb_run_scalars(run).items()}
    return shown


def _tb_run_scalars(folder: Path) -> dict[str, list[int]]:
    """The steps of every scalar of one writer's folder as TensorBoard shows them: event files
    in order, a session START at step S hiding the earlier events at steps >= S
    (``purge_step``)."""
    from tensorboardX.proto import event_pb2

    shown: dict[str, list[int]] = {}
    for path in sorted(folder.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime):
        data = path.read_bytes()
        i = 0
        while i + 12 <= len(data):
            (n,) = struct.unpack("<Q", data[i : i + 8])
            if i + 12 + n + 4 > len(data):  # a record cut short by the kill
                break
            event = event_pb2.Event.FromString(data[i + 12 : i + 12 + n])
            i += 12 + n + 4
            if event.HasField("session_log") and event.session_log.status == 1:  # START
                shown = {t: [s for s in v if s < event.step] for t, v in shown.items()}
            for value in event.summary.value:
                shown.setdefault(value.tag, []).append(event.step)
    return shown


@pytest.mark.slow
def test_kill_9_during_a_chunk_then_resume_gives_the_same_run_and_logs(tmp_path):
    """Multi-process: a training process killed with SIGKILL mid-run, resumed to the end, ends
    with the parameters of an uninterrupted run, one CSV row and one TensorBoard point per
    update and run."""
    args = [
        "train",
        "--config.env.max-steps",
        "8",
        "--config.num-envs",
        "4",
        "--config.num-updates",
        "40",
        "--chunk",
        "1",
        "--checkpoint-every",
        "3",
        "--seeds",
        "2",
        "--eval-episodes",
        "4",
        "--no-gif",
        "--no-progress",
    ]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "sparsecomm.cli", *args]
    subprocess.run([*cmd, "--out", str(tmp_path / "whole")], check=True, env=env)
    out = tmp_path / "killed"
    for kill_after_rows in (9, 31):  # two kills, each mid-run, then a resume to the end
        proc = subprocess.Popen([*cmd, "--out", str(out)], env=env)
        csv = out / "metrics.csv"
        while not csv.exists() or csv.read_text().count("\n") < 1 + 2 * kill_after_rows:
            assert proc.poll() is None, "finished before it could be killed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    subprocess.run([*cmd, "--out", str(out)], check=True, env=env)
    _, _, _, whole = load_run(tmp_path / "whole")
    _, _, _, resumed = load_run(out)
    for x, y in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rows = (out / "metrics.csv").read_text().splitlines()
    assert rows == (tmp_path / "whole" / "metrics.csv").read_text().splitlines()
    assert len(rows) == 1 + 40 * 2
    wall = [line.split(",") for line in (out / "wall.csv").read_text().splitlines()[1:]]
    assert [int(u) for u, _ in wall] == list(range(1, 41))  # one row per chunk, none twice
    assert all(float(a[1]) <= float(b[1]) for a, b in zip(wall[:-1], wall[1:], strict=True))
    shown = _tb_scalars(out / "tensorboard")
    assert shown and all(sorted(v) == sorted(set(v)) and len(v) == 40 for v in shown.values())


def test_a_checkpoint_written_before_a_field_existed_reads_back_as_its_default():
    """Run folders written before later fields (``agent.hears``, ``env.success_rule``, the
    config's ``task``, ...) read back and resume as those fields' defaults, and only as them."""
    import copy
    import dataclasses

    from sparsecomm.configs import AgentConfig, RLConfig
    from sparsecomm.sweep import ADDED_FIELDS, SweepSpec, differences, sweep_record

    record = sweep_record("train", RLConfig(), SweepSpec(seeds=2))
    old = copy.deepcopy(record)
    for section, field in ADDED_FIELDS:  # ("config", "task"): a field of the config itself
        del (old["config"] if section == "config" else old["config"][section])[field]
    assert differences(old, record) == []
    ring = RLConfig(agent=AgentConfig(neighbours=1, hears="ring"))
    ring = dataclasses.replace(ring, env=dataclasses.replace(ring.env, num_agents=3))
    diffs = differences(old, sweep_record("train", ring, SweepSpec(seeds=2)))
    assert any(d.startswith("config.agent.hears (checkpoint: missing") for d in diffs)
