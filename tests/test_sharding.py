"""Scale-out: a sweep split over 4 (forced CPU) devices, in one process and in two processes
under ``jax.distributed``, matches the single-device run."""

import json
import os
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from flax import serialization

from sparsecomm.experiment import evaluate_runs
from sparsecomm.runfolder import load_run

# Tiny runs whose time is compilation: compile with most XLA optimisations off (as the other
# end-to-end tests do, tests/conftest.py); the SPMD partitioner still runs.
FAST = {"JAX_DISABLE_MOST_OPTIMIZATIONS": "true"}


@pytest.mark.slow
def test_sweep_sharded_over_devices_and_processes_matches_one_device(tmp_path, fast_compile):
    # 2 runs x 4 episodes on 4 devices: a (runs 2, episodes 2) mesh, so both axes are split.
    # The episode split changes the order of the gradient sums, and Adam's normalised steps
    # carry that difference (about 1e-5 after 3 updates) into the parameters.
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        from sparsecomm.configs import RLConfig
        from sparsecomm.envs.navigation import NavConfig
        from sparsecomm.rl import make_train
        from sparsecomm.sharding import make_mesh, place_runs, use_mesh
        from sparsecomm.sweep import SweepSpec, compiled, run_sweep

        assert len(jax.devices()) == 4, jax.devices()
        cfg = RLConfig(env=NavConfig(max_steps=8), num_envs=4)
        tr = make_train(cfg)
        spec = SweepSpec(seeds=1, lams=(0.0, 0.01))
        mesh = make_mesh(2, 4)
        assert dict(mesh.shape) == {{"runs": 2, "episodes": 2}}, mesh.shape
        # The rollout constrains its episode axis to the mesh's episodes axis (XLA then sums
        # each run's gradient over its two episode shards; the equality below checks that sum).
        init, steps = compiled(tr, True)
        keys = jax.numpy.stack([jax.random.key(0), jax.random.key(1)])
        with use_mesh(mesh):
            state = init(*place_runs((keys, jax.numpy.zeros(2)), mesh))
            lowered = steps.lower(state, 1).as_text()
        assert "sharding_constraint" in lowered and '"episodes"' in lowered
        kw = dict(num_updates=3, chunk=3, tensorboard=False, progress=False)
        sharded = run_sweep(tr, spec, r"{tmp_path}/a", **kw).state
        devs = {{d for leaf in jax.tree.leaves(sharded.params) for d in leaf.devices()}}
        assert len(devs) == 4, devs
        single = run_sweep(tr, spec, r"{tmp_path}/b", devices=[jax.devices()[0]], **kw).state
        for x, y in zip(jax.tree.leaves(sharded.params), jax.tree.leaves(single.params)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-4)
        a = open(r"{tmp_path}/a/metrics.csv").read().splitlines()
        b = open(r"{tmp_path}/b/metrics.csv").read().splitlines()
        assert len(a) == len(b) == 1 + 3 * 2
        print("SHARDED_OK")
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", **FAST)
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SHARDED_OK" in out.stdout

    # The same sweep as the rl part of `sparsecomm reproduce` (then the fixed-code evaluation,
    # the scripted policies and the report), on two processes of 2 CPU devices each joined by
    # jax.distributed: the mesh spans both; process 0 alone writes the files.
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        port = sock.getsockname()[1]
    worker = textwrap.dedent(
        f"""
        import sys
        import jax
        from sparsecomm.cli import main

        main(["reproduce", "--parts", "rl", "fixed", "oracle", "--seeds", "1",
              "--rl-lams", "0", "0.01", "--rl-updates", "3", "--rl-envs", "4",
              "--rl.env.max-steps", "8", "--eval-episodes", "4", "--chunk", "3", "--gif", "False",
              "--no-progress", "--out", r"{tmp_path}/c", "--distributed.enabled",
              "--distributed.coordinator-address", "localhost:{port}",
              "--distributed.num-processes", "2", "--distributed.process-id", sys.argv[1]])
        assert jax.process_count() == 2 and len(jax.devices()) == 4
        print("WORKER_OK")
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", **FAST)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", worker, str(i)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (stdout, stderr) in zip(procs, outs, strict=True):
        assert p.returncode == 0 and "WORKER_OK" in stdout, stderr[-3000:]

    def params(run):
        raw = (tmp_path / run / "checkpoint" / "state.msgpack").read_bytes()
        return serialization.msgpack_restore(raw)["params"]

    multi, single = params("c/rl"), params("b")
    leaves = zip(_leaves(multi), _leaves(single), strict=True)
    for x, y in leaves:
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4)
    rl = tmp_path / "c" / "rl"
    rows = (rl / "metrics.csv").read_text().splitlines()
    assert (
        len(rows) == 1 + 3 * 2
        and rows[0] == (tmp_path / "b" / "metrics.csv").read_text().splitlines()[0]
    )
    for name in ("rl/curves.png", "fixed/results.json", "oracle/results.json", "report.md"):
        assert (tmp_path / "c" / name).stat().st_size > 0, name
    timings = json.loads((tmp_path / "c" / "timings.json").read_text())
    assert {timings[p]["processes"] for p in ("rl", "fixed", "oracle")} == {2}
    # The two processes' evaluation (runs and episodes split over 4 devices) equals a
    # single-device evaluation of the checkpoint they wrote.
    results = json.loads((rl / "results.json").read_text())
    assert results["processes"] == 2 and results["devices"] == 4
    _, trainer, runs, actor = load_run(rl)
    again = evaluate_runs(trainer, runs, actor, 4, devices=[jax.devices()[0]])
    assert len(results["runs"]) == len(again["runs"]) == 2
    for a, b in zip(results["runs"], again["runs"], strict=True):
        assert a.keys() == b.keys()
        assert a["budget"] is b["budget"] is None  # a fixed-lambda sweep
        for name in (n for n in a if n != "budget"):
            np.testing.assert_allclose(a[name], b[name], rtol=1e-4, atol=1e-4, err_msg=name)


def _leaves(tree):
    if isinstance(tree, dict):
        return [leaf for k in sorted(tree) for leaf in _leaves(tree[k])]
    return [np.asarray(tree)]


def test_mesh_layout():
    from sparsecomm.sharding import make_mesh

    devs = jax.devices() * 8  # stand-ins: make_mesh only lays them out
    assert make_mesh(5, 256, devs[:1]) is None
    assert dict(make_mesh(4, 256, devs[:4]).shape) == {"runs": 4, "episodes": 1}
    assert dict(make_mesh(2, 256, devs[:8]).shape) == {"runs": 2, "episodes": 4}
    assert dict(make_mesh(1, 6, devs[:4]).shape) == {"runs": 1, "episodes": 2}
    assert dict(make_mesh(20, 64, devs[:8]).shape) == {"runs": 4, "episodes": 2}
    assert make_mesh(3, 5, devs[:4]) is None


def test_distributed_flags_are_checked_before_joining():
    from sparsecomm.sharding import Distributed

    Distributed().initialize()  # disabled: a no-op, one process
    assert jax.process_count() == 1
    with pytest.raises(ValueError, match=r"distributed.process_id must be in \[0, 1\] \("):
        Distributed(True, "localhost:1", 2, 2)  # refused by the config itself, before joining
    with pytest.raises(ValueError, match="distributed.num_processes must be"):
        Distributed(True, "localhost:1", 0, 0)


def test_sweep_devices_split_runs_over_host_devices_but_never_a_runs_episodes():
    from types import SimpleNamespace

    from sparsecomm.sharding import make_mesh, sweep_devices

    cpu = [SimpleNamespace(platform="cpu", id=i) for i in range(4)]
    gpu = [SimpleNamespace(platform="gpu", id=i) for i in range(4)]
    assert [d.id for d in sweep_devices(10, cpu)] == [0, 1]
    assert [d.id for d in sweep_devices(20, cpu)] == [0, 1, 2, 3]
    assert [d.id for d in sweep_devices(5, cpu)] == [0]  # not 4 devices on one run's episodes
    assert sweep_devices(5, gpu) == gpu  # accelerators split episodes too
    for runs in (1, 2, 3, 5, 6, 10, 20):  # so the mesh never has an episodes axis on CPU
        mesh = make_mesh(runs, 256, jax.devices() * len(sweep_devices(runs, cpu)))
        assert mesh is None or dict(mesh.shape)["episodes"] == 1, (runs, mesh)


def _devices_in_a_fresh_process(env_extra: dict) -> tuple[str, int]:
    """What ``use_host_cores`` returns and how many devices JAX then has, in a new process."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    script = (
        "import jax\nfrom sparsecomm.sharding import use_host_cores\n"
        "n = use_host_cores()\nprint(n, len(jax.devices('cpu')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", script],
        env={**env, "JAX_PLATFORMS": "cpu", **env_extra},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    chosen, count = out.stdout.split()
    return chosen, int(count)


def test_a_sharded_sweep_compiles_its_chunk_once(tmp_path):
    """Each run's state sits on its own device from the start, as a chunk returns it, so the
    chunk compiles once (a replicated first state made it compile again for the second chunk,
    ~30-60 s of a 10-seed sweep on 2 CPU cores)."""
    script = textwrap.dedent(
        f"""
        import jax
        from sparsecomm.configs import RLConfig
        from sparsecomm.envs.navigation import NavConfig
        from sparsecomm.rl import make_train
        from sparsecomm.sweep import SweepSpec, run_sweep

        assert len(jax.devices()) == 2, jax.devices()
        tr = make_train(RLConfig(env=NavConfig(max_steps=8), num_envs=2))
        kw = dict(num_updates=3, chunk=1, tensorboard=False, progress=False)
        state = run_sweep(tr, SweepSpec(seeds=2), r"{tmp_path}/a", **kw).state
        assert len({{d for x in jax.tree.leaves(state.params) for d in x.devices()}}) == 2
        """
    )
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    env.update(JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="2", JAX_LOG_COMPILES="1", **FAST)
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stderr.count("Finished XLA compilation of jit(update_chunk)") == 1, done.stderr


def test_use_host_cores_gives_one_cpu_device_per_core_unless_the_user_chose():
    from sparsecomm.sharding import usable_cores

    cores = usable_cores()
    assert _devices_in_a_fresh_process({}) == (str(cores), cores)
    assert _devices_in_a_fresh_process({"JAX_NUM_CPU_DEVICES": "1"}) == ("None", 1)
    flags = {"XLA_FLAGS": "--xla_force_host_platform_device_count=3"}
    assert _devices_in_a_fresh_process(flags) == ("None", 3)


def test_the_command_splits_a_sweeps_runs_over_the_cores(tmp_path):
    """``sparsecomm train`` (here ``python -m sparsecomm.cli``) with 2 runs: on 2 or more
    cores they train on 2 CPU devices (results.json's ``devices``); with
    ``JAX_NUM_CPU_DEVICES=1`` on one."""
    import math

    from sparsecomm.sharding import usable_cores

    args = ["train", "--config.env.max-steps", "8", "--config.num-envs", "4"]
    args += ["--config.num-updates", "2", "--chunk", "2", "--seeds", "2", "--eval-episodes", "4"]
    args += ["--no-gif", "--no-progress", "--no-tensorboard"]
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    env.update(JAX_PLATFORMS="cpu", **FAST)
    for extra, devices in (({}, math.gcd(2, usable_cores())), ({"JAX_NUM_CPU_DEVICES": "1"}, 1)):
        out = tmp_path / str(devices)
        cmd = [sys.executable, "-m", "sparsecomm.cli", *args, "--out", str(out)]
        done = subprocess.run(cmd, env={**env, **extra}, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-3000:]
        assert json.loads((out / "results.json").read_text())["devices"] == devices


def test_a_process_id_outside_the_cluster_is_refused_while_parsing(capsys):
    from sparsecomm.cli import main
    from sparsecomm.sharding import Distributed

    with pytest.raises(ValueError, match=r"distributed.process_id must be in \[0, 1\]"):
        Distributed(num_processes=2, process_id=5)
    with pytest.raises(ValueError, match="distributed.num_processes must be an integer >= 1"):
        Distributed(num_processes=0)
    with pytest.raises(ValueError, match="distributed.process_id must be an integer >= 0"):
        Distributed(process_id=-1)
    assert Distributed(num_processes=2, process_id=1).process_id == 1
    argv = ["--distributed.num-processes", "2", "--distributed.process-id", "5"]
    for command in (["train"], ["reproduce", "--quick"]):
        with pytest.raises(SystemExit) as e:
            main([*command, *argv, "--distributed.enabled"])
        err = " ".join(capsys.readouterr().err.split())
        assert e.value.code == 2 and "Traceback" not in err, err
        assert "distributed.process_id must be in [0, 1]" in err and "got 5" in err, err


@pytest.mark.parametrize(
    "variable, value",
    [
        ("JAX_NUM_CPU_DEVICES", "0"),
        ("JAX_NUM_CPU_DEVICES", "abc"),
        ("JAX_NUM_CPU_DEVICES", "-2"),
        ("JAX_NUM_CPU_DEVICES", ""),
        ("XLA_FLAGS", "--xla_force_host_platform_device_count=abc"),
        ("XLA_FLAGS", "--xla_cpu_foo=1 --xla_force_host_platform_device_count=0"),
        ("XLA_FLAGS", "--xla_force_host_platform_device_count"),
    ],
)
def test_a_device_count_that_is_not_a_positive_integer_is_refused(variable, value, tmp_path):
    """The ``sparsecomm`` command checks the variables before JAX reads them: exit 2, one line
    naming the variable and the rule, for every command."""
    from sparsecomm.cmdline import check_device_counts

    with pytest.raises(ValueError, match=f"{variable}.*must be a positive integer"):
        check_device_counts({variable: value})
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    for command in ("train", "eval", "deploy"):
        done = subprocess.run(
            [sys.executable, "-m", "sparsecomm.cli", command, "--out", str(tmp_path / "o")],
            env={**env, variable: value},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 2, done.stderr[-2000:]
        assert done.stderr.startswith(f"sparsecomm: error: {variable}"), done.stderr[-2000:]
        assert "positive integer" in done.stderr and "Traceback" not in done.stderr
    assert list(tmp_path.iterdir()) == []
    check_device_counts({"JAX_NUM_CPU_DEVICES": "2", "XLA_FLAGS": "--xla_cpu_foo=1"})
    check_device_counts({"XLA_FLAGS": "--xla_force_host_platform_device_count=3"})
