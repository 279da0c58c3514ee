r"""JaxMARL's own IPPO and MAPPO baselines on MPE simple_reference, for docs/plugin.md's table.

Their scripts run unchanged but for the environment's name, the budget, the seeds and logging.
None of their code is in this repository; fetch it into a scratch folder outside it:

    git clone https://github.com/FLAIROx/JaxMARL /tmp/jaxmarl       # their repository
    python -m venv /tmp/jm                                            # a scratch environment
    /tmp/jm/bin/pip install -c requirements-lock.txt jax flax optax numpy tyro distrax \
        hydra-core omegaconf wandb safetensors chex matplotlib pillow jaxtyping gymnax
    export PYTHONPATH=/tmp/jaxmarl                                    # their jaxmarl package
    # logging: delete the per-update wandb host callback (it stalls on a 2-core CPU, jax 0.10.2)
    sed -i 's/^\(\s*\)jax.experimental.io_callback(callback, None, metric)/\1pass/' \
        /tmp/jaxmarl/baselines/IPPO/ippo_ff_mpe.py /tmp/jaxmarl/baselines/MAPPO/mappo_rnn_mpe.py
    # logging: MAPPO's train logs only through that callback; return its metrics instead
    NEW='{"runner_state": runner_state, "metrics": metric}'
    sed -i "s/{\"runner_state\": runner_state}\$/$NEW/" \
        /tmp/jaxmarl/baselines/MAPPO/mappo_rnn_mpe.py
    /tmp/jm/bin/python benchmarks/jaxmarl_baselines.py --baselines /tmp/jaxmarl/baselines \
        --algo IPPO/ippo_ff_mpe:ippo_ff_mpe --out ippo.json
    /tmp/jm/bin/python benchmarks/jaxmarl_baselines.py --baselines /tmp/jaxmarl/baselines \
        --algo MAPPO/mappo_rnn_mpe:mappo_homogenous_rnn_mpe --out mappo.json

Their ``make_train(config)`` is called with their config file's values, except ``ENV_NAME``,
``TOTAL_TIMESTEPS``, ``NUM_SEEDS`` (1) and ``SEED``; ``wandb`` is replaced by an object whose
``log`` does nothing (and stands in for the module where it is not installed). Each seed is its
own compiled program (their ``main`` vmaps over ``NUM_SEEDS`` keys; vmapped over 2 or 5 seeds
the program stalled on the 2-core VM, every thread idle). Each seed's returns go to
``OUT.seedS.json`` as it ends, with the device and jax that ran it, and a later call with the
same ``--out`` and ``--steps`` reads them instead of running the seed again, so an interrupted
run continues where it stopped (with every seed read back, only their config file
and ``omegaconf`` are needed: their script is not imported); ``--seed S --seeds 1`` runs one
seed, so several processes can run seeds side by side. The return is their
``returned_episode_returns`` (``MPELogWrapper`` multiplies each agent's return by the number of
agents) averaged over agents, steps and environments: on
simple_reference the two agents' rewards sum to minus both distances to the goals, so this is
docs/plugin.md's team return. The final figure is the mean over the last 5% of updates (training
episodes, the sampled policy). Env steps per second are timed with the compile apart, per
device (``by_device``: a seed's time counts where it ran).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np
import tyro


@dataclasses.dataclass
class Args:
    baselines: Path
    """Their ``baselines`` folder (fetched outside this repository)."""
    algo: str
    """``FOLDER/SCRIPT:CONFIG``: ``IPPO/ippo_ff_mpe:ippo_ff_mpe`` or
    ``MAPPO/mappo_rnn_mpe:mappo_homogenous_rnn_mpe`` (their file names)."""
    out: Path
    """JSON file of the returns and timings."""
    env: str = "MPE_simple_reference_v3"
    """Their environment name."""
    steps: float = 6.4e6
    """``TOTAL_TIMESTEPS`` per seed: 6.4M, docs/plugin.md's budget per run."""
    seeds: int = 5
    """Seeds, one compiled program each."""
    seed: int = 31000
    """First seed (docs/plugin.md's seeds: 31000-31004)."""


class _NoLog:
    """Stands in for their ``wandb`` module: their logging only."""

    def log(self, *args, **kwargs):
        pass

    def init(self, *args, **kwargs):
        pass


def main(a: Args) -> dict:
    from omegaconf import OmegaConf  # their config loader (in the scratch environment)

    try:
        import wandb  # noqa: F401  (their import; absent where nothing can be installed)
    except ImportError:
        sys.modules["wandb"] = _NoLog()
    folder, names = a.algo.split("/")
    script, config_name = names.split(":")
    base = a.baselines / folder
    config = OmegaConf.to_container(OmegaConf.load(base / "config" / f"{config_name}.yaml"))
    config.update(ENV_NAME=a.env, TOTAL_TIMESTEPS=a.steps, NUM_SEEDS=1, SEED=a.seed)
    seeds = list(range(a.seed, a.seed + a.seeds))
    files = {seed: a.out.with_name(f"{a.out.stem}.seed{seed}.json") for seed in seeds}
    done = {}  # a seed already run is kept
    for seed, path in files.items():
        if path.exists() and json.loads(path.read_text())["steps"] == a.steps:
            done[seed] = json.loads(path.read_text())
            print(f"seed {seed}: read from {path}", flush=True)
    module = None  # their script, imported only where a seed is left to run
    for seed in [seed for seed in seeds if seed not in done]:
        if module is None:
            sys.path.insert(0, str(base))
            module = importlib.import_module(script)
            module.wandb = _NoLog()
        keys = jax.random.split(jax.random.PRNGKey(seed), 1)
        start = time.perf_counter()
        train = jax.jit(jax.vmap(module.make_train(dict(config, SEED=seed))))
        train = train.lower(keys).compile()
        one = {"steps": a.steps, "compile_s": time.perf_counter() - start}
        start = time.perf_counter()
        out = jax.block_until_ready(train(keys))
        one["run_s"] = time.perf_counter() - start
        one["device"] = jax.devices()[0].device_kind  # where run_s was timed
        one["jax"] = jax.__version__
        ret = np.asarray(out["metrics"]["returned_episode_returns"], np.float64)  # (1, updates, ..)
        one["returns"] = np.round(ret.reshape(ret.shape[1], -1).mean(-1), 4).tolist()  # (updates,)
        files[seed].write_text(json.dumps(one))
        done[seed] = one
        print(f"seed {seed}: {one['run_s']:.0f} s on {one['device']} -> {files[seed]}", flush=True)
    returns = [np.asarray(done[seed]["returns"]) for seed in seeds]
    timing = {}  # each device's seeds and seconds: env steps per second are per device
    for one in done.values():
        t = timing.setdefault(one["device"], {"seeds": 0, "compile_s": 0.0, "run_s": 0.0})
        t["seeds"] += 1
        t["compile_s"] += one["compile_s"]
        t["run_s"] += one["run_s"]
    returns = np.stack(returns)  # (seeds, updates)
    updates = returns.shape[1]
    final = returns[:, -max(1, updates // 20) :].mean(1)
    env_steps = config["NUM_ENVS"] * config["NUM_STEPS"] * updates
    for t in timing.values():
        t["env_steps_per_s"] = env_steps * t["seeds"] / t["run_s"]
    result = {
        "algo": a.algo,
        "env": a.env,
        "config": config,
        "seeds": seeds,
        "updates": updates,
        "env_steps_per_seed": env_steps,
        "by_device": timing,
        "final_return_per_seed": final.tolist(),
        "final_return_mean": float(final.mean()),
        "curve_mean": returns.mean(0)[:: max(1, updates // 200)].tolist(),
        "jax": jax.__version__,
    }
    a.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k not in ("config", "curve_mean")}))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
