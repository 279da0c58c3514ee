"""Hyperparameter probe for RL at lambda = 0: several configurations x seeds, one budget each.

Each configuration runs as one vmapped program over seeds; prints the learning curve (success
rate, episode length, bits per step; mean over seeds) every ``--every`` env steps and appends the
rows to ``--out`` (JSON lines). With ``--vmap``, configurations that differ only in the numeric
fields of ``VMAP_FIELDS`` run as one program over (configurations, seeds) (throughput on an
H100: docs/benchmarks.md). Used to choose the RLConfig defaults: the
rounds, commands and figures are in docs/tuning.md. The ``GRID`` entries override today's
``RLConfig()`` defaults, which have changed since those rounds (e.g. shared actor parameters).

    python experiments/tune_rl.py --vmap --budget 100e6 --seeds 4 --every 4e6 \
        --names lr1e3_b256_ent_g95 lr1e3_b256_ent_g90 lr1e3_b256_g90

Seed s of a configuration uses the key of seed s of ``sparsecomm train --config.FIELD VALUE ...
--seeds N``; to train, evaluate and keep one configuration, use that command.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.configs import AgentConfig, ChannelConfig, RLConfig
from sparsecomm.rl import make_train

GRID = {
    "base": dict(lr=3e-4, num_envs=64),
    "lr1e3": dict(lr=1e-3, num_envs=64),
    "lr1e3_b256": dict(lr=1e-3, num_envs=256),
    "lr3e3_b256": dict(lr=3e-3, num_envs=256),
    "lr1e3_gae": dict(lr=1e-3, num_envs=64, gae_lambda=0.95),
    "lr1e3_ent": dict(lr=1e-3, num_envs=64, ent_coef=0.01),
    "lr1e3_b256_gae": dict(lr=1e-3, num_envs=256, gae_lambda=0.95),
    "lr2e3_b128_gae": dict(lr=2e-3, num_envs=128, gae_lambda=0.95),
    "nocomm": dict(lr=1e-3, num_envs=64, channel=ChannelConfig(mode="off")),
    "big": dict(lr=1e-3, num_envs=256, agent=AgentConfig(hidden=128, gru=128)),
    # num_envs = 64 sweep (run together with --vmap)
    "lr3e3": dict(lr=3e-3, num_envs=64),
    "lr3e3_gae": dict(lr=3e-3, num_envs=64, gae_lambda=0.95),
    "lr2e3_gae": dict(lr=2e-3, num_envs=64, gae_lambda=0.95),
    "lr1e3_gae09": dict(lr=1e-3, num_envs=64, gae_lambda=0.9),
    "lr1e3_gae_ent": dict(lr=1e-3, num_envs=64, gae_lambda=0.95, ent_coef=0.01),
    "lr1e3_rs1e3": dict(lr=1e-3, num_envs=64, reward_scale=1e-3),
    "lr1e3_clip10": dict(lr=1e-3, num_envs=64, max_grad_norm=10.0),
    "lr1e3_g98_gae": dict(lr=1e-3, num_envs=64, gamma=0.98, gae_lambda=0.95),
    # num_envs = 256
    "lr3e3_b256_gae": dict(lr=3e-3, num_envs=256, gae_lambda=0.95),
    "lr3e4_b256": dict(lr=3e-4, num_envs=256),
    "lr3e4_b256_ent": dict(lr=3e-4, num_envs=256, ent_coef=0.01),
    "lr5e4_b256_ent": dict(lr=5e-4, num_envs=256, ent_coef=0.01),
    "lr5e4_b256_ent03": dict(lr=5e-4, num_envs=256, ent_coef=0.03),
    "lr1e3_b256_ent": dict(lr=1e-3, num_envs=256, ent_coef=0.01),
    # lower discount: with gamma 0.99 hovering in radius (+250/step) outpays the terminal 1200
    "lr1e3_b256_ent_g95": dict(lr=1e-3, num_envs=256, ent_coef=0.01, gamma=0.95),
    "lr1e3_b256_ent_g90": dict(lr=1e-3, num_envs=256, ent_coef=0.01, gamma=0.9),
    "lr1e3_b256_g90": dict(lr=1e-3, num_envs=256, gamma=0.9),
    # after clipping actor and critic gradients separately
    "sep_g99": dict(lr=1e-3, num_envs=256, ent_coef=0.01, gamma=0.99),
    "sep_g95": dict(lr=1e-3, num_envs=256, ent_coef=0.01, gamma=0.95),
    "sep_g90": dict(lr=1e-3, num_envs=256, ent_coef=0.01, gamma=0.9),
    "sep_g90_lr3e4": dict(lr=3e-4, num_envs=256, ent_coef=0.01, gamma=0.9),
    # after hoisting the rollout's randomness out of the loop (new random streams)
    "default": dict(),
    "noadvnorm": dict(normalize_advantages=False),
    "advnorm_b64": dict(normalize_advantages=True, num_envs=64),
    "advnorm_b64_lr3e3": dict(normalize_advantages=True, num_envs=64, lr=3e-3),
    "advnorm_b64_lr5e4": dict(normalize_advantages=True, num_envs=64, lr=5e-4),
    "advnorm_b128": dict(normalize_advantages=True, num_envs=128),
    "advnorm_b128_lr2e3": dict(normalize_advantages=True, num_envs=128, lr=2e-3),
    "advnorm": dict(normalize_advantages=True),
    "advnorm_lr3e4": dict(normalize_advantages=True, lr=3e-4),
    "advnorm_b512": dict(normalize_advantages=True, num_envs=512),
    "b512": dict(num_envs=512),
    "advnorm_gae95": dict(normalize_advantages=True, gae_lambda=0.95),
    "advnorm_ent03": dict(normalize_advantages=True, ent_coef=0.03),
    "advnorm_gae95_ent03": dict(normalize_advantages=True, gae_lambda=0.95, ent_coef=0.03),
    # the paper task, shared actor parameters (the default since docs/rl.md), tuning seeds 1000-1001
    "i32_b256": dict(seed=1000),
    "i32_b64": dict(seed=1000, num_envs=64),
    "i32_b32": dict(seed=1000, num_envs=32),
    "i32_b64_gae95": dict(seed=1000, num_envs=64, gae_lambda=0.95),
    "nocomm_lr3e4_b256_ent": dict(
        lr=3e-4, num_envs=256, ent_coef=0.01, channel=ChannelConfig(mode="off")
    ),
    "nocomm_lr1e3_b256_ent": dict(
        lr=1e-3, num_envs=256, ent_coef=0.01, channel=ChannelConfig(mode="off")
    ),
}

VMAP_FIELDS = ("lr", "max_grad_norm", "gamma", "gae_lambda", "ent_coef", "vf_coef", "reward_scale")
"""RLConfig fields that only enter the program as numbers: configurations that differ only in
these run as one program (``--vmap``), vmapped over configurations and seeds. The trainer is
built inside the vmap with these fields set to traced scalars (bypassing RLConfig's checks,
which ran on the concrete values)."""


def seed_keys(seed: int, seeds: int):
    """The keys ``sparsecomm train --seeds N`` uses (seed s: ``key(seed + s)``), so a tuning
    seed is the same run as the CLI's seed. (Rounds 1-5 used ``split(key(seed), N)``.)"""
    return jnp.stack([jax.random.key(seed + s) for s in range(seeds)])


class _TracedConfig(RLConfig):
    """An RLConfig whose ``VMAP_FIELDS`` may hold traced scalars. RLConfig's checks compare
    fields with numbers, which tracers cannot answer; they already ran on the concrete
    configurations (``RLConfig(**GRID[name])``), so this subclass skips them."""

    def __post_init__(self):
        pass


def static_part(cfg: RLConfig) -> RLConfig:
    return RLConfig(
        **{f: getattr(cfg, f) for f in cfg.__dataclass_fields__ if f not in VMAP_FIELDS}
    )


def run_vmapped(names, budget, seeds, every, out, max_wall):
    """Configurations sharing ``static_part`` as one program: vmap over (configs, seeds)."""
    cfgs = [RLConfig(**GRID[n]) for n in names]
    base = cfgs[0]
    assert all(static_part(c) == static_part(base) for c in cfgs), names
    hp = {f: jnp.asarray([float(getattr(c, f)) for c in cfgs], jnp.float32) for f in VMAP_FIELDS}

    traced_base = _TracedConfig(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})

    def trainer_of(h):
        return make_train(dataclasses.replace(traced_base, **h))

    steps_per_update = base.num_envs * base.env.max_steps
    n_updates = int(budget // steps_per_update)
    chunk = max(1, int(every // steps_per_update))
    keys = seed_keys(base.seed, seeds)
    init = jax.jit(
        jax.vmap(jax.vmap(lambda h, k: trainer_of(h).init(k, 0.0), (None, 0)), (0, None))
    )
    step = jax.jit(
        jax.vmap(jax.vmap(lambda h, s: trainer_of(h).update_chunk(s, chunk), (None, 0)), (0, 0))
    )
    t0 = time.time()
    state = init(hp, keys)
    rows = {n: [] for n in names}
    done = 0
    tag = "+".join(names) if len(names) <= 3 else f"{names[0]}+{len(names) - 1}"
    last = None
    while done < n_updates:
        tc = time.time()
        state, m = step(hp, state)
        m = jax.tree.map(lambda x: np.asarray(x)[:, :, -max(1, chunk // 4) :].mean(2), m)
        done += chunk
        now = time.time()
        env_steps = done * steps_per_update
        print(
            f"[{tag}] {env_steps / 1e6:6.1f}M/cfg wall {now - t0:5.0f}s chunk {now - tc:5.1f}s "
            f"({seeds * len(names) * chunk * steps_per_update / (now - tc) / 1e6:.2f}M "
            f"env steps/s all runs)",
            flush=True,
        )
        for c, n in enumerate(names):
            row = dict(
                name=n,
                env_steps=env_steps,
                wall=now - t0,
                success=m["success_rate"][c].tolist(),
                length=m["episode_length"][c].tolist(),
                reward=m["group_reward"][c].tolist(),
                bits=float(m["bits_per_step"][c].mean()),
            )
            rows[n].append(row)
            print(
                f"  {n:16s} succ {np.mean(row['success']):.2f} len {np.mean(row['length']):6.1f}"
                f" bits {row['bits']:6.1f}  per-seed succ "
                + " ".join(f"{x:.2f}" for x in row["success"]),
                flush=True,
            )
        if last is not None and now - t0 + (now - tc) > max_wall:
            break
        last = now
    with open(out, "a") as f:
        for n in names:
            f.write(
                json.dumps(
                    dict(
                        name=n,
                        overrides=str(GRID[n]),
                        seeds=seeds,
                        vmapped_with=names,
                        rows=rows[n],
                    )
                )
                + "\n"
            )


def run(name, overrides, budget, seeds, every, out):
    cfg = RLConfig(**overrides)
    steps_per_update = cfg.num_envs * cfg.env.max_steps
    n_updates = int(budget // steps_per_update)
    chunk = max(1, int(every // steps_per_update))
    trainer = make_train(cfg)
    keys = seed_keys(cfg.seed, seeds)
    state = jax.jit(jax.vmap(trainer.init, (0, None)))(keys, 0.0)
    step = jax.jit(jax.vmap(lambda s: trainer.update_chunk(s, chunk)))
    t0 = time.time()
    done = 0
    rows = []
    while done < n_updates:
        state, m = step(state)
        done += chunk
        m = jax.tree.map(lambda x: np.asarray(x)[:, -max(1, chunk // 4) :].mean(1), m)
        row = dict(
            name=name,
            env_steps=done * steps_per_update,
            wall=time.time() - t0,
            success=m["success_rate"].tolist(),
            length=m["episode_length"].tolist(),
            bits=float(m["bits_per_step"].mean()),
        )
        rows.append(row)
        print(
            f"{name:16s} {row['env_steps'] / 1e6:7.1f}M {row['wall']:6.0f}s "
            f"succ {np.mean(row['success']):.2f} len {np.mean(row['length']):6.1f} "
            f"bits {row['bits']:6.1f}",
            flush=True,
        )
    with open(out, "a") as f:
        f.write(json.dumps(dict(name=name, overrides=str(overrides), rows=rows)) + "\n")


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--budget", type=float, default=30e6)
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--every", type=float, default=2e6)
    p.add_argument("--names", nargs="+", default=list(GRID))
    p.add_argument("--out", default="tune.jsonl")
    p.add_argument(
        "--vmap",
        action="store_true",
        help="run the named configurations that differ only in VMAP_FIELDS as one "
        "program (one group per distinct static part, in order of appearance)",
    )
    p.add_argument(
        "--max-wall",
        type=float,
        nargs="+",
        default=[float("inf")],
        help="with --vmap: stop a group once its next chunk would end past this many "
        "seconds (one value, or one per group)",
    )
    a = p.parse_args()
    print(jax.devices(), flush=True)
    if a.vmap:
        groups = {}
        for n in a.names:
            groups.setdefault(static_part(RLConfig(**GRID[n])), []).append(n)
        walls = a.max_wall * len(groups) if len(a.max_wall) == 1 else a.max_wall
        for names, wall in zip(groups.values(), walls, strict=True):
            run_vmapped(names, a.budget, a.seeds, a.every, a.out, wall)
    else:
        for n in a.names:
            run(n, GRID[n], a.budget, a.seeds, a.every, a.out)
