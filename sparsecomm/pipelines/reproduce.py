"""``sparsecomm reproduce``: the paper's experiments, the baselines, the figures and a report.

Parts (each written to its own folder under ``out``, each sweep one vmapped program through
:func:`sparsecomm.experiment.train`, so a part that dies resumes from its checkpoint):

============== ===============================================================================
``rl``         actor-critic through the channel, lambda in {0.01, 0.005, 0.001, 0} (Fig. 1, 2)
``imitation``  imitation of the oracle's actions, lambda in {0.001, ..., 0} (Fig. 3, Table I)
``no_comm``    baseline: RL with the channel off (messages are zeros, 0 bits)
``continuous`` baseline: RL with unquantized real-valued messages, counted as 32-bit floats
``fixed``      baseline: the ``rl`` teams of the smallest lambda (0) re-evaluated with a
               fixed-width code, ceil(log2(|M|+1)) bits per element. With lambda = 0 the code
               only counts bits, so training with it would give the same teams (new seeds).
``rcl``        baseline: reinforced communication learning, messages sampled as actions and
               learned by policy gradient with a per-bit negative reward, no gradient through
               the channel (``ChannelConfig.mode = "reinforced"``)
``oracle``     the centralised scripted expert (upper bound, sends nothing) and, for reference,
               the best scripted policy without communication (drive to the centre)
``rl_budget``  RL with a bit budget in {64, 32, 16, 8, 4} payload bits per step instead of a
               fixed lambda (``sparsecomm.budget``; compared with the ``rl`` part's lambda 0)
``il_budget``  imitation of the oracle with the same budgets (compared with ``imitation``'s 0)
``il_budget_rl`` imitation of an RL-trained team (the ``rl`` part's lambda-0 team with the
               highest success, ties to the shortest episodes) with lambda 0 and the same
               budgets; the expert's messages stay private, the learners see its actions
============== ===============================================================================
"""

from __future__ import annotations

import dataclasses
import datetime
import shlex
import sys
from pathlib import Path

import jax
import numpy as np

from sparsecomm import checkpoint
from sparsecomm.configs import ChannelConfig, ILConfig, RLConfig, from_dict
from sparsecomm.envs.oracle import center_actions, oracle_actions, run_policy_episodes
from sparsecomm.experiment import EVAL_SEED_OFFSET, evaluate_runs
from sparsecomm.jsonfile import read_json, write_json
from sparsecomm.metric_names import written_row
from sparsecomm.pipelines import claims
from sparsecomm.pipelines.plan import (
    BUDGETS,
    IL_LAMS,
    RL_LAMS,
    Part,
    Sweep,
    check_expert_unset,
    check_parts,
    expert_index,
)
from sparsecomm.pipelines.report import write_report
from sparsecomm.pipelines.runner import SweepOptions, run_parts
from sparsecomm.provenance import git_commit, hardware, source_digest
from sparsecomm.rl import make_train
from sparsecomm.sharding import Distributed, fast_compile, is_primary
from sparsecomm.sweep import run_arrays, spec_from_meta

PLAN = (
    Part("rl", "rl"),
    Part("imitation", "imitation"),
    Part("no_comm"),
    Part("continuous"),
    Part("fixed", needs="rl"),
    Part("rcl"),
    Part("oracle"),
    Part("rl_budget", "rl"),
    Part("il_budget", "imitation"),
    Part("il_budget_rl", "imitation", "RL team", needs="rl"),
)
"""Every part, in the order they run; those with a learner give the frontier's rows (each series
judged against its own lambda 0)."""
PARTS = tuple(p.name for p in PLAN)
"""Every part's name, in the order they run."""
FULL = {"seeds": 10, "eval_episodes": 500, "chunk": 10}
"""Defaults of the full run for fields left at None (budgets: the RLConfig/ILConfig defaults).
10 seeds: the 95% CIs (``stats.bootstrap_ci``) need at least 6 runs to cover honestly."""
QUICK = {
    "seeds": 2,
    "rl_updates": 10,
    "rl_envs": 8,
    "il_updates": 10,
    "il_envs": 8,
    "eval_episodes": 32,
}
"""Defaults of ``--quick`` for fields left at None (a few minutes on a 2-core CPU)."""


@dataclasses.dataclass
class Reproduce:
    """Reproduce the paper: RL and imitation sweeps, baselines, figures, report.md."""

    out: Path = Path("runs/reproduce")
    """Output folder: one sub-folder per part, figures, table1.md, report.md, summary.json (a
    folder this user can write, or a path where one can be created: checked before any part
    runs)."""
    quick: bool = False
    """Tiny budgets (see ``QUICK``) for fields left unset: every artefact in a few minutes on a
    laptop CPU. The numbers then say nothing about the paper."""
    seeds: int | None = None
    """Seeds per lambda and per baseline. None: 10 (2 with --quick)."""
    rl_updates: int | None = None
    """Updates of every RL run (sweep and RL baselines). None: ``rl.num_updates`` (10 quick)."""
    rl_envs: int | None = None
    """Episodes per RL update. None: ``rl.num_envs`` (8 quick)."""
    il_updates: int | None = None
    """Updates of every imitation run. None: ``il.num_updates`` (10 quick)."""
    il_envs: int | None = None
    """Episodes per imitation update. None: ``il.num_envs`` (8 quick)."""
    eval_episodes: int | None = None
    """Final-evaluation episodes per run (and per seed of the scripted policies). None: 500 (32
    quick)."""
    parts: tuple[str, ...] = PARTS
    """Parts to run (any of ``PARTS``); the report covers every part found in ``out``."""
    rl_lams: tuple[float, ...] = RL_LAMS
    """RL penalty weights. Paper: 0.01, 0.005, 0.001, 0."""
    il_lams: tuple[float, ...] = IL_LAMS
    """Imitation penalty weights. Paper: 0.001, 0.0007, 0.0004, 0.0001 (and 0 here)."""
    budgets: tuple[float, ...] = BUDGETS
    """Bit budgets of the ``rl_budget``, ``il_budget`` and ``il_budget_rl`` parts (payload bits
    per step). ours (docs/budget.md)."""
    rcl_bit_cost: float = 0.001
    """RCL's reward per payload bit sent, negated (paper reward units). The paper gives none.
    ours: 0.001, the price per bit that the surrogate penalty sets at the smallest non-zero RL
    lambda (lambda is a price per bit in the same units, see ``sparsecomm.rl``)."""
    rl: RLConfig = RLConfig()
    """The RL learner (sweep and baselines; each baseline changes only its channel)."""
    il: ILConfig = ILConfig()
    """The imitation learner (its expert is set by each part: the oracle, or the ``rl`` part's
    team; ``--il.expert*`` refused)."""
    chunk: int | None = None
    """Updates per compiled call (logging granularity). None: 10 (all updates in one call with
    --quick, one compilation)."""
    fast_compile: bool | None = None
    """Set ``jax_disable_most_optimizations`` while running: programs compile several times
    faster and run about 3x slower. None: on with --quick only."""
    gif: bool | None = None
    """Render team.gif of the first run of each trained part. None: off with --quick."""
    tensorboard: bool = False
    """Write TensorBoard scalars in every trained part."""
    resume: bool = True
    """Continue parts from their checkpoints in ``out`` (a finished part is only re-evaluated)."""
    progress: bool = True
    """Show progress bars."""
    distributed: Distributed = dataclasses.field(default_factory=Distributed)
    """Multi-host: every process runs this command; each part's runs and episodes are split over
    all processes' devices, process 0 writes the files."""

    def __post_init__(self):
        for name in ("seeds", "rl_updates", "rl_envs", "il_updates", "il_envs", "eval_episodes"):
            v = getattr(self, name)
            low = 0 if name.endswith("updates") else 1
            if v is not None and (not isinstance(v, int) or v < low):
                raise ValueError(f"Reproduce.{name} must be an integer >= {low} or None, got {v!r}")
        if self.chunk is not None and self.chunk < 1:
            raise ValueError(f"Reproduce.chunk must be >= 1 or None, got {self.chunk!r}")
        bad = [p for p in self.parts if p not in PARTS]
        if bad or not self.parts:
            raise ValueError(f"Reproduce.parts must be a non-empty subset of {PARTS}, got {bad}")
        for name in ("rl_lams", "il_lams"):
            lams = getattr(self, name)
            if not lams or any(not np.isfinite(x) or x < 0 for x in lams):
                raise ValueError(f"Reproduce.{name} must be non-empty, finite and >= 0, got {lams}")
        for part in ("fixed", "il_budget_rl"):
            if part in self.parts and 0.0 not in self.rl_lams:
                raise ValueError(
                    f"Reproduce.rl_lams must contain 0 for the {part} part, got {self.rl_lams}"
                )
        if not self.budgets or any(not np.isfinite(b) or b < 0 for b in self.budgets):
            raise ValueError(
                f"Reproduce.budgets must be non-empty, finite and >= 0, got {self.budgets}"
            )
        if not (np.isfinite(self.rcl_bit_cost) and self.rcl_bit_cost >= 0):
            raise ValueError(f"Reproduce.rcl_bit_cost must be >= 0, got {self.rcl_bit_cost!r}")
        check_expert_unset(self, ILConfig())
        check_parts(self, PLAN)

    def resolved(self, name: str):
        """A field's value, with None replaced by the quick or full default."""
        value = getattr(self, name)
        if value is not None:
            return value
        if self.quick and name in QUICK:
            return QUICK[name]
        if name in FULL:
            return FULL[name]
        return {
            "rl_updates": self.rl.num_updates,
            "rl_envs": self.rl.num_envs,
            "il_updates": self.il.num_updates,
            "il_envs": self.il.num_envs,
            "chunk": None,  # quick: one chunk
            "fast_compile": self.quick,
            "gif": not self.quick,
        }[name]


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
    return Sweep(config, (0.0,)).budget(len(idx))


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


def build_part(args: Reproduce, part: str):
    """What one part runs: its :class:`~sparsecomm.pipelines.plan.Sweep`, or for ``fixed`` and
    ``oracle`` the function that evaluates it."""
    bits = (("bit_budgets", list(args.budgets)),)
    if part == "rl":
        return Sweep(_rl_config(args), args.rl_lams)
    if part == "rl_budget":
        return Sweep(_rl_config(args), (0.0,), args.budgets, bits)
    if part == "il_budget_rl":
        index = expert_index(args.out / "rl")
        cfg = _il_config(
            args, expert="checkpoint", expert_checkpoint=str(args.out / "rl"), expert_index=index
        )
        # its own lambda-0 reference, same expert, same program
        return Sweep(cfg, (0.0,), (None, *args.budgets), (*bits, ("expert", index)))
    if part == "il_budget":
        return Sweep(_il_config(args), (0.0,), args.budgets, bits)
    if part == "imitation":
        return Sweep(_il_config(args), args.il_lams)
    if part in ("no_comm", "continuous", "rcl"):
        ch = args.rl.channel
        channel = {
            "no_comm": lambda: dataclasses.replace(ch, mode="off"),
            "continuous": lambda: dataclasses.replace(ch, mode="continuous"),
            "rcl": lambda: dataclasses.replace(ch, mode="reinforced", bit_cost=args.rcl_bit_cost),
        }[part]()
        return Sweep(_rl_config(args, channel))
    if part == "fixed":
        return lambda: run_fixed(args, args.out)
    if part == "oracle":
        return lambda: run_scripted(args, args.out)
    raise ValueError(f"part must be one of {PARTS}, got {part!r}")


def _options(args: Reproduce) -> SweepOptions:
    return SweepOptions(
        seeds=args.resolved("seeds"),
        eval_episodes=args.resolved("eval_episodes"),
        chunk=args.resolved("chunk"),
        checkpoint_every=5,
        resume=args.resume,
        tensorboard=args.tensorboard,
        gif=args.resolved("gif"),
        progress=args.progress,
    )


def reproduce(args: Reproduce) -> dict:
    """Run the selected parts (in ``PARTS`` order), recording where and how long each ran
    (``timings.json``), then write the figures and the report."""
    args.distributed.initialize()
    primary = is_primary()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timings_path = out / "timings.json"
    timings = read_json(timings_path) or {}
    timings["_meta"] = {"quick": args.quick}
    fast = bool(args.resolved("fast_compile"))

    def record(part: str, budget: dict, seconds: float) -> None:
        timings[part] = {
            "wall_clock_s": seconds,
            "budget": budget,
            "hardware": hardware(),
            "fast_compile": fast,
            "commit": git_commit(),
            "source_sha256": source_digest(),
            "finished": datetime.datetime.now().isoformat(timespec="seconds"),
            "processes": jax.process_count(),
        }
        if primary:
            write_json(timings_path, timings)

    previous = fast_compile(True) if fast else None
    try:
        build = lambda part: build_part(args, part)  # noqa: E731
        run_parts(PLAN, args.parts, build, _options(args), out, after=record)
    finally:
        if previous is not None:
            fast_compile(previous)
    if not primary:
        return {}
    summary = write_report(out, PLAN, shlex.join(sys.argv))
    print(f"report -> {out / 'report.md'}")
    for c in claims.decide_claims(summary):
        print(f"  claim {c.number or 'extra'}: {c.verdict}")
    return summary
