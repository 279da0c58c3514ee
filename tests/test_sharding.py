"""Scale-out: a sweep split over 4 (forced CPU) devices, in one process and in two processes
under ``jax.distributed``, matches the single-device run."""

import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
from flax import serialization

# Tiny runs whose time is compilation: compile with most XLA optimisations off (as the other
# end-to-end tests do, tests/conftest.py); the SPMD partitioner still runs.
FAST = {"JAX_DISABLE_MOST_OPTIMIZATIONS": "true"}


def test_sweep_sharded_over_devices_and_processes_matches_one_device(tmp_path):
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
        from sparsecomm.sweep import SweepSpec, _compiled, run_sweep

        assert len(jax.devices()) == 4, jax.devices()
        cfg = RLConfig(env=NavConfig(max_steps=8), num_envs=4)
        tr = make_train(cfg)
        spec = SweepSpec(seeds=1, lams=(0.0, 0.01))
        mesh = make_mesh(2, 4)
        assert dict(mesh.shape) == {{"runs": 2, "episodes": 2}}, mesh.shape
        # The rollout constrains its episode axis to the mesh's episodes axis (XLA then sums
        # each run's gradient over its two episode shards; the equality below checks that sum).
        init, steps = _compiled(tr, True)
        keys = jax.numpy.stack([jax.random.key(0), jax.random.key(1)])
        with use_mesh(mesh):
            state = init(*place_runs((keys, jax.numpy.zeros(2)), mesh))
            lowered = steps.lower(state, 1).as_text()
        assert "sharding_constraint" in lowered and '"episodes"' in lowered
        kw = dict(num_updates=3, episodes_per_update=4, steps_per_episode=8, chunk=3,
                  tensorboard=False, progress=False)
        sharded, _ = run_sweep(tr, cfg, spec, r"{tmp_path}/a", **kw)
        devs = {{d for leaf in jax.tree.leaves(sharded.params) for d in leaf.devices()}}
        assert len(devs) == 4, devs
        single, _ = run_sweep(tr, cfg, spec, r"{tmp_path}/b", devices=[jax.devices()[0]], **kw)
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

    # The same sweep on two processes (2 CPU devices each) joined by jax.distributed: the mesh
    # spans both; process 0 alone writes the log and the checkpoint.
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        port = sock.getsockname()[1]
    worker = textwrap.dedent(
        f"""
        import sys, jax
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize("localhost:{port}", num_processes=2, process_id=int(sys.argv[1]))
        assert len(jax.devices()) == 4 and len(jax.local_devices()) == 2
        from sparsecomm.configs import RLConfig
        from sparsecomm.envs.navigation import NavConfig
        from sparsecomm.rl import make_train
        from sparsecomm.sweep import SweepSpec, run_sweep

        cfg = RLConfig(env=NavConfig(max_steps=8), num_envs=4)
        run_sweep(make_train(cfg), cfg, SweepSpec(seeds=1, lams=(0.0, 0.01)), r"{tmp_path}/c",
                  devices=jax.devices(), num_updates=3, episodes_per_update=4,
                  steps_per_episode=8, chunk=3, tensorboard=False, progress=False)
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

    multi, single = params("c"), params("b")
    leaves = zip(_leaves(multi), _leaves(single), strict=True)
    for x, y in leaves:
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4)
    rows = (tmp_path / "c" / "metrics.csv").read_text().splitlines()
    assert (
        len(rows) == 1 + 3 * 2
        and rows[0] == (tmp_path / "b" / "metrics.csv").read_text().splitlines()[0]
    )


def _leaves(tree):
    if isinstance(tree, dict):
        return [leaf for k in sorted(tree) for leaf in _leaves(tree[k])]
    return [np.asarray(tree)]


def test_mesh_layout():
    import jax

    from sparsecomm.sharding import make_mesh

    devs = jax.devices() * 8  # stand-ins: make_mesh only lays them out
    assert make_mesh(5, 256, devs[:1]) is None
    assert dict(make_mesh(4, 256, devs[:4]).shape) == {"runs": 4, "episodes": 1}
    assert dict(make_mesh(2, 256, devs[:8]).shape) == {"runs": 2, "episodes": 4}
    assert dict(make_mesh(1, 6, devs[:4]).shape) == {"runs": 1, "episodes": 2}
    assert dict(make_mesh(20, 64, devs[:8]).shape) == {"runs": 4, "episodes": 2}
    assert make_mesh(3, 5, devs[:4]) is None
