"""Learners side by side on one machine: success against env steps and against wall-clock.

Each learner (a name and ``RLConfig`` overrides) trains its seeds as one vmapped program, in
chunks of updates, one learner after the other in the same process, until the mean training
success over its seeds, as a moving average over ``--window`` updates, first exceeds
``--target`` (then ``--extra`` more updates, or ``--extra-for NAME=N``'s for that learner), or
``--max-env-steps`` / ``--max-wall`` runs out, or, for every learner after the first, its
wall-clock passes ``--max-wall-ratio`` times the first learner's wall-clock to the target (it is
then at least that many times slower, which is all a race for a ratio needs to know).
Seed s of every learner is ``key(seed + s)``, the key ``sparsecomm train --seeds N`` gives it.
Then each seed's team is evaluated on ``--eval-episodes`` fresh episodes. Env steps count whole
episodes (``num_envs * max_steps`` per update), as docs/rl.md does; wall-clock includes
compiling, which is also reported alone.

    python benchmarks/learner_race.py --seeds 5 --out race.json \\
        --learner today: \\
        --learner ppo:algo=ppo,num_envs=64,ppo_epochs=2,ppo_minibatches=2

The JSON written to ``--out`` holds, per learner, its overrides, the per-update mean success
and length, the wall-clock at the end of each chunk, the env steps and wall-clock at which the
target was first passed (null if never) and each seed's evaluation. docs/paper-task.md has
the figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm import sharding
from sparsecomm.configs import RLConfig
from sparsecomm.rl import make_train
from sparsecomm.stats import first_pass
from sparsecomm.sweep import compiled as compiled_sweep


def parse_learner(text: str) -> tuple[str, dict]:
    """``NAME:FIELD=VALUE,...`` -> (name, overrides), each value parsed by its field's type; a
    field of a nested config is named with dots (``agent.message_gate=hard``)."""
    name, _, rest = text.partition(":")
    overrides = {}
    for item in filter(None, rest.split(",")):
        field, _, value = item.partition("=")
        owner = RLConfig()
        *path, last = field.split(".")
        for part in path:
            owner = getattr(owner, part)
        types = {f.name: f.type for f in dataclasses.fields(owner)}
        kind = str(types[last])  # e.g. "int", "float | None" (the annotation's text)
        if value == "None" and "None" in kind:
            overrides[field] = None
        elif kind.startswith("int"):
            overrides[field] = int(value)
        elif kind.startswith("float"):
            overrides[field] = float(value)
        elif kind.startswith("bool"):
            overrides[field] = value.lower() in ("1", "true", "yes")
        else:
            overrides[field] = value
    return name, overrides


def make_config(overrides: dict) -> RLConfig:
    """``RLConfig()`` with the overrides of :func:`parse_learner` (dotted names nested), each
    config built once with all of its fields (a field's rule may read another's)."""

    def build(config, fields: dict):
        nested = {}
        for field, value in fields.items():
            head, _, rest = field.partition(".")
            nested.setdefault(head, {} if rest else value)
            if rest:
                nested[head][rest] = value
        return dataclasses.replace(
            config,
            **{
                k: build(getattr(config, k), v) if isinstance(v, dict) else v
                for k, v in nested.items()
            },
        )

    return build(RLConfig(), overrides)


def race(name: str, overrides: dict, args, max_wall: float, extra: int) -> dict:
    cfg = make_config({"seed": args.seed, **overrides})
    tr = make_train(cfg)
    steps_per_update = cfg.num_envs * cfg.env.max_steps
    chunk = max(1, round(args.chunk_env_steps / steps_per_update))
    keys = jnp.stack([jax.random.key(cfg.seed + s) for s in range(args.seeds)])
    t0 = time.time()
    # the seeds split over the host's CPU devices as ``sparsecomm train`` splits a sweep's runs
    mesh = sharding.make_mesh(args.seeds, cfg.num_envs, sharding.sweep_devices(args.seeds))
    init, steps = compiled_sweep(tr, mesh is not None)
    zeros = jnp.zeros(args.seeds)
    with sharding.use_mesh(mesh):
        state = init(*sharding.place_runs((keys, zeros, zeros + jnp.nan), mesh))
        state = sharding.runs_on_devices(state, mesh)  # as sweep._first_state: one compile
        jax.block_until_ready(steps(state, chunk))  # compiled by a chunk thrown away
    compile_s = time.time() - t0
    t0 = time.time()
    success, length, walls, per_seed = [], [], [], []
    passed, stop_at = None, None
    while True:
        with sharding.use_mesh(mesh):
            state, m = steps(state, chunk)
        per_seed += np.asarray(m["success_rate"]).T.tolist()  # (chunk, seeds)
        success += np.asarray(m["success_rate"]).mean(0).tolist()
        length += np.asarray(m["episode_length"]).mean(0).tolist()
        elapsed = time.time() - t0
        if not walls:  # compiling alone: the warm-up less its chunk's compute
            compile_s -= elapsed
        walls.append(elapsed + compile_s)  # wall-clock includes compiling
        done = len(success)
        if passed is None:
            passed = first_pass(np.asarray(success), args.target, args.window)
            if passed is not None:
                stop_at = done + extra
        print(
            f"[{name}] update {done:5d} env steps {done * steps_per_update / 1e6:6.1f}M "
            f"wall {walls[-1]:6.0f}s success {np.mean(success[-chunk:]):.3f} "
            f"length {np.mean(length[-chunk:]):6.1f}"
            + ("" if passed is None else f"  passed at update {passed + 1}"),
            flush=True,
        )
        if stop_at is not None and done >= stop_at:
            break
        if done * steps_per_update >= args.max_env_steps or walls[-1] >= max_wall:
            break
    train_s = walls[-1]
    ev = jax.jit(jax.vmap(lambda p, k: tr.evaluate(p, k, args.eval_episodes)))
    eval_keys = jnp.stack([jax.random.key(10_000 + cfg.seed + s) for s in range(args.seeds)])
    evaluation = jax.tree.map(
        lambda x: np.asarray(x).tolist(), ev(state.params["actor"], eval_keys)
    )

    def wall_at(update):  # the wall-clock at the end of the chunk holding that update
        return walls[update // chunk]

    return dict(
        name=name,
        overrides=overrides,
        seeds=args.seeds,
        seed=cfg.seed,
        updates=len(success),
        chunk=chunk,
        env_steps_per_update=steps_per_update,
        compile_s=compile_s,
        train_s=train_s,
        max_wall_s=max_wall,
        extra=extra,
        success=success,
        success_per_seed=per_seed,
        episode_length=length,
        chunk_wall_s=walls,
        passed_update=None if passed is None else passed + 1,
        env_steps_to_target=None if passed is None else (passed + 1) * steps_per_update,
        wall_s_to_target=None if passed is None else wall_at(passed),
        evaluation=evaluation,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--learner", action="append", required=True, help="NAME:FIELD=VALUE,...")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--seed", type=int, default=0, help="base seed (seed s: key(seed + s))")
    p.add_argument("--target", type=float, default=0.95)
    p.add_argument("--window", type=int, default=10, help="updates in the moving average")
    p.add_argument("--extra", type=int, default=0, help="updates to run past the target")
    p.add_argument(
        "--extra-for",
        action="append",
        default=[],
        help="NAME=N: updates past the target for that learner (instead of --extra)",
    )
    p.add_argument("--chunk-env-steps", type=float, default=1e6, help="env steps per chunk")
    p.add_argument("--max-env-steps", type=float, default=60e6, help="per seed")
    p.add_argument("--max-wall", type=float, default=3600.0, help="seconds per learner")
    p.add_argument(
        "--max-wall-ratio",
        type=float,
        default=None,
        help="stop a later learner at this many times the first one's wall-clock to the target",
    )
    p.add_argument("--eval-episodes", type=int, default=500)
    p.add_argument("--out", default="race.json")
    args = p.parse_args()
    devices = sharding.use_host_cores()  # one CPU device per core, unless the user chose
    results = dict(
        machine=dict(
            platform=platform.platform(),
            processor=platform.processor(),
            cpus=os.cpu_count(),
            jax=jax.__version__,
            device=str(jax.devices()[0]),
            devices=len(sharding.sweep_devices(args.seeds)),
            devices_set=devices,
        ),
        target=args.target,
        window=args.window,
        learners=[],
    )
    extra_for = dict(item.split("=") for item in args.extra_for)
    for text in args.learner:
        name, overrides = parse_learner(text)
        max_wall = args.max_wall
        first = results["learners"][0] if results["learners"] else None
        if args.max_wall_ratio and first and first["wall_s_to_target"] is not None:
            max_wall = min(max_wall, args.max_wall_ratio * first["wall_s_to_target"])
        extra = int(extra_for.get(name, args.extra))
        results["learners"].append(race(name, overrides, args, max_wall, extra))
        with open(args.out, "w") as f:
            json.dump(results, f)
    for r in results["learners"]:
        succ = np.mean(r["evaluation"]["success_rate"])
        print(
            f"{r['name']:12s} to {args.target}: "
            f"{r['env_steps_to_target'] and r['env_steps_to_target'] / 1e6}M env steps, "
            f"{r['wall_s_to_target']} s wall (compile {r['compile_s']:.0f} s); final eval "
            f"success {succ:.3f}"
        )


if __name__ == "__main__":
    main()
