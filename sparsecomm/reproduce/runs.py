"""Running the parts of ``sparsecomm reproduce``: the trained sweeps through
:func:`sparsecomm.experiment.train`, the fixed-width re-evaluation and the scripted policies."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from sparsecomm import checkpoint
from sparsecomm.configs import ChannelConfig, ILConfig, RLConfig, from_dict
from sparsecomm.envs.oracle import center_actions, oracle_actions, run_policy_episodes
from sparsecomm.experiment import EVAL_SEED_OFFSET, Imitate, Train, evaluate_runs, train
from sparsecomm.jsonfile import read_json, write_json
from sparsecomm.metric_names import aliased_results, written_row
from sparsecomm.reproduce.plan import PARTS, Reproduce
from sparsecomm.rl import make_train
from sparsecomm.sharding import is_primary
from sparsecomm.sweep import run_arrays, spec_from_meta


def fast_compile(on: bool) -> bool:
    """Set ``jax_disable_most_optimizations``; returns its previous value."""
    try:
        previous = bool(jax.config._read("jax_disable_most_optimizations"))
    except (AttributeError, KeyError):
        previous = False
    jax.config.update("jax_disable_most_optimizations", on)
    return previous


def _rl_config(args: Reproduce, channel: ChannelConfig | None = None) -> RLConfig:
    return dataclasses.replace(
        args.rl,
        num_updates=args.resolved("rl_updates"),
        num_envs=args.resolved("rl_envs"),
        channel=channel or args.rl.channel,
    )


def _il_config(args: Reproduce, **expert) -> ILConfig:
    """The imitation learner of the parts, with the oracle as expert unless ``expert`` says."""
    return dataclasses.replace(
        args.il,
        num_updates=args.resolved("il_updates"),
        num_envs=args.resolved("il_envs"),
        **({"expert": "oracle"} | expert),
    )


def _train_args(args: Reproduce, config, lams, out: Path, imitate: bool = False, budgets=None):
    updates = config.num_updates
    chunk = args.resolved("chunk") or max(updates, 1)
    return (Imitate if imitate else Train)(
        config=config,
        seeds=args.resolved("seeds"),
        lams=tuple(float(x) for x in lams),
        budgets=budgets,
        out=out,
        chunk=chunk,
        checkpoint_every=5,
        resume=args.resume,
        tensorboard=args.tensorboard,
        eval_episodes=args.resolved("eval_episodes"),
        gif=args.resolved("gif"),
        progress=args.progress,
    )


def _budget(config, seeds: int, lams) -> dict:
    return {
        "seeds": seeds,
        "lams": [float(x) for x in lams],
        "num_updates": config.num_updates,
        "episodes_per_update": config.num_envs,
        "env_steps_per_run": config.num_updates * config.num_envs * config.env.max_steps,
    }


def expert_index(run: Path) -> int:
    """The expert of ``il_budget_rl``: the index (in ``run``'s sweep) of the lambda-0 team
    without a budget with the highest final success, ties broken by the shortest episodes."""
    res = read_json(run / "results.json")
    if res is None:
        raise ValueError(
            f"the il_budget_rl part needs the rl part's teams in {run}: run 'rl' first"
        )
    runs = [
        (i, r)
        for i, r in enumerate(aliased_results(res)["runs"])
        if float(r["lam"]) == 0.0 and r.get("budget") is None
    ]
    if not runs:
        raise ValueError(f"the rl part in {run} has no lambda = 0 runs")
    return min(runs, key=lambda p: (-p[1]["episode/success_rate"], p[1]["episode/episode_length"]))[
        0
    ]


def run_fixed(args: Reproduce, out: Path) -> dict:
    """The ``rl`` teams of lambda 0, evaluated with the fixed-width code on the wire."""
    ckpt = out / "rl" / "checkpoint"
    if not checkpoint.exists(ckpt):
        raise ValueError(
            f"the fixed part needs the rl part's teams in {out / 'rl'}: run 'rl' first"
        )
    meta = checkpoint.load_meta(ckpt)
    config = from_dict(RLConfig, meta["config"])
    runs = spec_from_meta(meta).runs()
    # A jitted init as the restore template (cli.load_run's eager one is slower to trace).
    template = jax.jit(jax.vmap(make_train(config).init))(*run_arrays(config, runs))
    state = checkpoint.load(ckpt, template)
    idx = [i for i, run in enumerate(runs) if run.lam == 0.0 and run.budget is None]
    if not idx:
        raise ValueError(f"the rl part in {out / 'rl'} has no lambda = 0 runs")
    fixed = dataclasses.replace(config, channel=dataclasses.replace(config.channel, code="fixed"))
    sub = jax.tree.map(lambda x: x[np.asarray(idx)], state.params["actor"])
    results = evaluate_runs(
        make_train(fixed),
        [runs[i] for i in idx],
        sub,
        args.resolved("eval_episodes"),
        devices=jax.devices(),
    )
    results["source"] = "rl teams of lambda 0, channel code 'fixed'"
    if is_primary():
        (out / "fixed").mkdir(parents=True, exist_ok=True)
        write_json(out / "fixed" / "results.json", results)
    return _budget(config, len(idx), (0.0,))


def run_scripted(args: Reproduce, out: Path) -> dict:
    """The oracle and the centre policy over ``seeds`` x ``eval_episodes`` episodes."""
    env = args.rl.env
    seeds, episodes = args.resolved("seeds"), args.resolved("eval_episodes")
    if not is_primary():  # scripted policies need no devices of other processes
        return {"seeds": seeds, "episodes_per_seed": episodes}
    folder = out / "oracle"
    folder.mkdir(parents=True, exist_ok=True)
    for name, policy in (("results.json", oracle_actions), ("centre.json", center_actions)):
        runs = []
        for s in range(seeds):
            key = jax.random.key(args.rl.seed + EVAL_SEED_OFFSET + s)
            st = run_policy_episodes(key, env, policy, episodes)
            metrics = {
                "success_rate": float(np.mean(st.success)),
                "episode_length": float(np.mean(st.length)),
                "group_reward": float(np.mean(st.group_reward)),
                "bits_per_step": 0.0,
                "wire_bits_per_step": 0.0,
                "penalty": 0.0,
            }
            runs.append({"seed": s, "lam": 0.0, **written_row(metrics)})
        doc = {"policy": policy.__name__, "episodes_per_run": episodes, "runs": runs}
        write_json(folder / name, doc)
    return {"seeds": seeds, "episodes_per_seed": episodes}


def run_part(args: Reproduce, part: str) -> dict:
    """Run one part; returns its budget."""
    out = args.out
    seeds = args.resolved("seeds")
    if part == "rl":
        cfg = _rl_config(args)
        train(_train_args(args, cfg, args.rl_lams, out / "rl"))
        return _budget(cfg, seeds, args.rl_lams)
    if part == "rl_budget":
        cfg = _rl_config(args)
        train(_train_args(args, cfg, (0.0,), out / part, budgets=args.budgets))
        return _budget(cfg, seeds, (0.0,)) | {"bit_budgets": list(args.budgets)}
    if part == "il_budget_rl":
        index = expert_index(out / "rl")
        cfg = _il_config(
            args, expert="checkpoint", expert_checkpoint=str(out / "rl"), expert_index=index
        )
        budgets = (None, *args.budgets)  # its own lambda-0 reference, same expert, same program
        train(_train_args(args, cfg, (0.0,), out / part, imitate=True, budgets=budgets))
        return _budget(cfg, seeds, (0.0,)) | {"bit_budgets": list(args.budgets), "expert": index}
    if part in ("imitation", "il_budget"):
        cfg = _il_config(args)
        if part == "il_budget":
            train(_train_args(args, cfg, (0.0,), out / part, imitate=True, budgets=args.budgets))
            return _budget(cfg, seeds, (0.0,)) | {"bit_budgets": list(args.budgets)}
        train(_train_args(args, cfg, args.il_lams, out / "imitation", imitate=True))
        return _budget(cfg, seeds, args.il_lams)
    if part in ("no_comm", "continuous", "rcl"):
        ch = args.rl.channel
        channel = {
            "no_comm": lambda: dataclasses.replace(ch, mode="off"),
            "continuous": lambda: dataclasses.replace(ch, mode="continuous"),
            "rcl": lambda: dataclasses.replace(ch, mode="reinforced", bit_cost=args.rcl_bit_cost),
        }[part]()
        cfg = _rl_config(args, channel)
        train(_train_args(args, cfg, (0.0,), out / part))
        return _budget(cfg, seeds, (0.0,))
    if part == "fixed":
        return run_fixed(args, out)
    if part == "oracle":
        return run_scripted(args, out)
    raise ValueError(f"part must be one of {PARTS}, got {part!r}")
