"""Scale-out: a sweep split over 4 (forced CPU) devices matches the single-device run."""

import os
import subprocess
import sys
import textwrap


def test_sweep_sharded_over_four_devices_matches_one_device(tmp_path):
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        from sparsecomm.configs import RLConfig
        from sparsecomm.envs.navigation import NavConfig
        from sparsecomm.rl import make_train
        from sparsecomm.sweep import SweepSpec, run_sweep

        assert len(jax.devices()) == 4, jax.devices()
        cfg = RLConfig(env=NavConfig(max_steps=8), num_envs=4)
        tr = make_train(cfg)
        spec = SweepSpec(seeds=2, lams=(0.0, 0.01))
        kw = dict(num_updates=3, episodes_per_update=4, steps_per_episode=8, chunk=3,
                  tensorboard=False, progress=False)
        sharded, _ = run_sweep(tr, cfg, spec, r"{tmp_path}/a", **kw)
        devs = {{d for leaf in jax.tree.leaves(sharded.params) for d in leaf.devices()}}
        assert len(devs) == 4, devs
        single, _ = run_sweep(tr, cfg, spec, r"{tmp_path}/b", devices=[jax.devices()[0]], **kw)
        for x, y in zip(jax.tree.leaves(sharded.params), jax.tree.leaves(single.params)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
        print("SHARDED_OK")
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SHARDED_OK" in out.stdout
