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
============== ===============================================================================

Then :func:`write_report` reads every part found under ``out`` (also parts run earlier) and
writes ``fig1.png``, ``fig2.png``, ``fig3.png``, ``pareto.png``, ``table1.md``, ``report.md``
and ``summary.json``, and with the budget parts ``frontier.png`` and ``budget_summary.json``
(:mod:`sparsecomm.frontier`). All numbers in them come from the runs' ``results.json`` and
``metrics.csv``.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from sparsecomm import frontier, report_md
from sparsecomm.configs import ChannelConfig, ILConfig, RLConfig
from sparsecomm.report import plot_curves, plot_pareto
from sparsecomm.sharding import Distributed, is_primary

RL_LAMS = (0.01, 0.005, 0.001, 0.0)
"""Paper, section V: the RL penalty weights."""
IL_LAMS = (0.001, 0.0007, 0.0004, 0.0001, 0.0)
"""Paper, section V and Table I: the imitation penalty weights (0 added as the reference)."""
BUDGETS = (64.0, 32.0, 16.0, 8.0, 4.0)
"""Issue 14: the bit budgets of the frontier (payload bits per step; lambda 0 sends ~160)."""
PARTS = (
    "rl",
    "imitation",
    "no_comm",
    "continuous",
    "fixed",
    "rcl",
    "oracle",
    "rl_budget",
    "il_budget",
)
"""Every part, in the order they run."""
FULL = {"seeds": 10, "eval_episodes": 500, "chunk": 10}
"""Defaults of the full run for fields left at None (budgets: the RLConfig/ILConfig defaults).
10 seeds: the 95% CIs (``report.bootstrap_ci``) need at least 6 runs to cover honestly."""
QUICK = {
    "seeds": 2,
    "rl_updates": 10,
    "rl_envs": 8,
    "il_updates": 10,
    "il_envs": 8,
    "eval_episodes": 32,
}
"""Defaults of ``--quick`` for fields left at None (a few minutes on a 2-core CPU)."""
BASELINE_LABELS = {
    "no_comm": "no communication (RL)",
    "continuous": "real-valued messages, float32 (RL)",
    "fixed": "fixed-width code (RL, λ=0 teams)",
    "rcl": "reinforced comm. learning (RCL)",
    "oracle": "oracle (centralised, upper bound)",
    "centre": "scripted, no communication (centre)",
}


@dataclasses.dataclass
class Reproduce:
    """Reproduce the paper: RL and imitation sweeps, baselines, figures, report.md."""

    out: Path = Path("runs/reproduce")
    """Output folder: one sub-folder per part, figures, table1.md, report.md, summary.json."""
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
    """Bit budgets of the ``rl_budget`` and ``il_budget`` parts (payload bits per step). ours,
    issue 14."""
    rcl_bit_cost: float = 0.001
    """RCL's reward per payload bit sent, negated (paper reward units). The paper gives none.
    ours: 0.001, the price per bit that the surrogate penalty sets at the smallest non-zero RL
    lambda (lambda is a price per bit in the same units, see ``sparsecomm.rl``)."""
    rl: RLConfig = RLConfig()
    """The RL learner (sweep and baselines; each baseline changes only its channel)."""
    il: ILConfig = ILConfig()
    """The imitation learner (its expert is the oracle)."""
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
        if "fixed" in self.parts and 0.0 not in self.rl_lams:
            raise ValueError(
                f"Reproduce.rl_lams must contain 0 for the fixed part, got {self.rl_lams}"
            )
        if not self.budgets or any(not np.isfinite(b) or b < 0 for b in self.budgets):
            raise ValueError(
                f"Reproduce.budgets must be non-empty, finite and >= 0, got {self.budgets}"
            )
        if not (np.isfinite(self.rcl_bit_cost) and self.rcl_bit_cost >= 0):
            raise ValueError(f"Reproduce.rcl_bit_cost must be >= 0, got {self.rcl_bit_cost!r}")

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


def hardware() -> dict:
    """The machine and software a part ran on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import jaxlib

    dev = jax.devices()[0]
    return {
        "cpu": cpu,
        "cpu_cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "device": str(dev),
        "device_kind": dev.device_kind,
        "devices": len(jax.devices()),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "python": platform.python_version(),
        "os": platform.platform(),
    }


def _fast_compile(on: bool) -> bool:
    """Set ``jax_disable_most_optimizations``; returns its previous value."""
    try:
        previous = bool(jax.config._read("jax_disable_most_optimizations"))
    except (AttributeError, KeyError):
        previous = False
    jax.config.update("jax_disable_most_optimizations", on)
    return previous


def _source_digest() -> str:
    """SHA-256 (first 16 hex digits) of the package's Python sources, in path order: names the
    code that ran even where the git metadata is missing or stale."""
    root = Path(__file__).parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:16]


def _git_commit() -> str | None:
    """The short commit of the code, with ``+changes`` if tracked files differ from it."""

    def git(*args: str) -> str:
        out = subprocess.run(
            ["git", *args], capture_output=True, text=True, cwd=Path(__file__).parent, timeout=10
        )
        return out.stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        if commit and git("status", "--porcelain", "--untracked-files=no"):
            commit += "+changes"
        return commit or None
    except (OSError, subprocess.SubprocessError):
        return None


def _rl_config(args: Reproduce, channel: ChannelConfig | None = None) -> RLConfig:
    return dataclasses.replace(
        args.rl,
        num_updates=args.resolved("rl_updates"),
        num_envs=args.resolved("rl_envs"),
        channel=channel or args.rl.channel,
    )


def _train_args(args: Reproduce, config, lams, out: Path, imitate: bool = False, budgets=None):
    from sparsecomm.experiment import Imitate, Train

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


def run_fixed(args: Reproduce, out: Path) -> dict:
    """The ``rl`` teams of lambda 0, evaluated with the fixed-width code on the wire."""
    from sparsecomm import checkpoint
    from sparsecomm.configs import from_dict
    from sparsecomm.experiment import evaluate_runs
    from sparsecomm.rl import make_train
    from sparsecomm.sweep import run_arrays, spec_from_meta

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
        (out / "fixed" / "results.json").write_text(json.dumps(results, indent=2))
    return _budget(config, len(idx), (0.0,))


def run_scripted(args: Reproduce, out: Path) -> dict:
    """The oracle and the centre policy over ``seeds`` x ``eval_episodes`` episodes."""
    from sparsecomm.envs.oracle import center_actions, oracle_actions, run_policy_episodes
    from sparsecomm.experiment import EVAL_SEED_OFFSET

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
            runs.append(
                {
                    "seed": s,
                    "lam": 0.0,
                    "success_rate": float(np.mean(st.success)),
                    "episode_length": float(np.mean(st.length)),
                    "group_reward": float(np.mean(st.group_reward)),
                    "bits_per_step": 0.0,
                    "wire_bits_per_step": 0.0,
                    "penalty": 0.0,
                }
            )
        doc = {"policy": policy.__name__, "episodes_per_run": episodes, "runs": runs}
        (folder / name).write_text(json.dumps(doc, indent=2))
    return {"seeds": seeds, "episodes_per_seed": episodes}


def run_part(args: Reproduce, part: str) -> dict:
    """Run one part; returns its budget."""
    from sparsecomm.experiment import train

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
    if part in ("imitation", "il_budget"):
        cfg = dataclasses.replace(
            args.il,
            expert="oracle",
            num_updates=args.resolved("il_updates"),
            num_envs=args.resolved("il_envs"),
        )
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


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def collect(out: Path) -> dict:
    """The summary (see :mod:`sparsecomm.report_md`) of every part found under ``out``."""
    summary: dict = {}
    for part in ("rl", "imitation"):
        res = _read(out / part / "results.json")
        if res is not None:
            summary[part] = report_md.summarize_runs(res["runs"])
    baselines = {}
    files = {
        "no_comm": "no_comm/results.json",
        "continuous": "continuous/results.json",
        "fixed": "fixed/results.json",
        "rcl": "rcl/results.json",
        "oracle": "oracle/results.json",
        "centre": "oracle/centre.json",
    }
    for name, rel in files.items():
        res = _read(out / rel)
        if res is not None:
            baselines[name] = next(iter(report_md.summarize_runs(res["runs"]).values()))
    if baselines:
        summary["baselines"] = baselines
    auc = {}
    if (out / "rl" / "metrics.csv").exists():
        auc["rl"] = report_md.training_mean(out / "rl" / "metrics.csv")
    if (out / "rcl" / "metrics.csv").exists():
        auc["rcl"] = next(iter(report_md.training_mean(out / "rcl" / "metrics.csv").values()))
    if auc:
        summary["training_success"] = auc
    sources = {
        learner: [doc for doc in (_read(out / p / "results.json") for p in parts) if doc]
        for learner, parts in (
            ("rl", ("rl", "rl_budget")),
            ("imitation", ("imitation", "il_budget")),
        )
    }
    if (out / "rl_budget").exists() or (out / "il_budget").exists():
        summary["frontier"] = [
            r for lr, docs in sources.items() for d in docs for r in frontier.rows(d, lr)
        ]
    return summary


def _points(summary: dict) -> list[dict]:
    def tup(st, m):
        return (st[m]["mean"], st[m]["ci_low"], st[m]["ci_high"])

    pts = []
    for part, group in (("rl", "RL through the channel"), ("imitation", "imitation (oracle)")):
        for lam, st in summary.get(part, {}).items():
            pts.append(
                {"label": f"λ={lam:g}", "group": group}
                | {m: tup(st, m) for m in ("bits_per_step", "success_rate", "group_reward")}
            )
    for name, st in summary.get("baselines", {}).items():
        label = BASELINE_LABELS[name]
        pts.append(
            {"label": label, "group": label}
            | {m: tup(st, m) for m in ("bits_per_step", "success_rate", "group_reward")}
        )
    return pts


def write_figures(out: Path, summary: dict) -> list[Path]:
    """fig1.png, fig2.png, fig3.png and pareto.png from the parts found in ``out``."""
    made = []
    rl_csv, il_csv = out / "rl" / "metrics.csv", out / "imitation" / "metrics.csv"
    if rl_csv.exists():
        made.append(
            plot_curves(
                rl_csv,
                out / "fig1.png",
                ("group_reward", "episode_length"),
                title="Fig. 1: RL through the channel, group reward and episode length",
            )
        )
        made.append(
            plot_curves(
                rl_csv, out / "fig2.png", ("bits_per_step",), title="Fig. 2: RL, bits per step"
            )
        )
    if il_csv.exists():
        made.append(
            plot_curves(
                il_csv,
                out / "fig3.png",
                ("imitation_loss", "bits_per_step"),
                title="Fig. 3: imitation of the oracle, loss and bits per step",
            )
        )
    if summary.get("frontier"):
        made.append(frontier.plot(summary["frontier"], out / "frontier.png"))
    pts = _points(summary)
    if pts:
        made.append(
            plot_pareto(
                pts, out / "pareto.png", title="Final evaluation: mean and 95% CI over seeds"
            )
        )
    return made


def _hardware_lines(timings: dict) -> list[str]:
    lines = [
        "| part | wall-clock | CPU | cores (usable) | device | jax | commit | finished |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    for part in PARTS:
        t = timings.get(part)
        if t is None:
            continue
        h = t["hardware"]
        lines.append(
            f"| {part} | {t['wall_clock_s']:.0f} s | {h['cpu']} | {h['cpu_cores']} "
            f"({h['usable_cores']}) | {h['device_kind']} x{h['devices']} | {h['jax']} | "
            f"{t.get('commit') or '?'} | {t['finished']} |"
        )
    return lines


def _budget_lines(timings: dict) -> list[str]:
    lines = ["| part | budget |", "|---|---|"]
    for part in PARTS:
        if part in timings:
            b = timings[part]["budget"]
            lines.append(f"| {part} | " + ", ".join(f"{k} {v}" for k, v in b.items()) + " |")
    return lines


def _frontier_lines(table: list[dict]) -> list[str]:
    """The bit-budget section: the frontier table, the budget-matched verdicts of claims 4 and
    5 (labelled as such), and issue 14's targets."""
    md = ["## Bit budgets: the frontier (not in the paper)", ""]
    md += [
        "| learner | budget | λ | seeds | success | episode length | payload bits/step | "
        "wire bits/step |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table:
        cells = [
            f"{r[k][0]:.4g} [{r[k][1]:.4g}, {r[k][2]:.4g}]"
            for k in ("success", "episode_length", "payload_bits", "wire_bits")
        ]
        budget = "-" if r["budget"] is None else f"{r['budget']:g}"
        md.append(
            f"| {r['learner']} | {budget} | {r['lam']:g} | {r['seeds']} | "
            + " | ".join(cells)
            + " |"
        )
    md.append("")
    for c in frontier.budget_claims(table):
        verdict = "held" if c["held"] else "not held"
        md.append(
            f"- **{c['label']}: {verdict}** (budgets that hold: {c['budgets_held'] or 'none'})."
        )
    for t in frontier.targets(table):
        met = "met" if t["met"] else "not met"
        md.append(
            f"- Target, {t['learner']} budget {t['budget']:g}: **{met}** (success "
            f"{t['success_ratio']:.1%} of λ=0's, payload bits {t['bits']:.3g})."
        )
    return md + [""]


def _seeds_text(summary: dict) -> str:
    """How many runs (seeds) each method's statistics are over, e.g. "10 seeds per method"."""
    counts = set()
    for key in ("rl", "imitation", "baselines"):
        for st in summary.get(key, {}).values():
            counts.add(next(iter(st.values()))["n"])
    if len(counts) == 1:
        return f"{counts.pop()} seeds per method"
    return f"{min(counts)}-{max(counts)} seeds per method, the runs column" if counts else "seeds"


def write_report(out: Path, command: str = "") -> dict:
    """Figures, table1.md, summary.json and report.md from every part found in ``out``."""
    summary = collect(out)
    if not summary:
        raise ValueError(f"no part results found in {out}")
    report_md.write_summary(
        {k: v for k, v in summary.items() if k != "frontier"}, out / "summary.json"
    )
    if summary.get("frontier"):
        frontier.write_rows(summary["frontier"], out / "budget_summary.json")
    figures = write_figures(out, summary)
    if "imitation" in summary:
        (out / "table1.md").write_text(report_md.table1(summary["imitation"]))
    timings = _read(out / "timings.json") or {}
    claims = report_md.decide_claims(summary)
    md = ["# Reproduction of Freed et al. (IROS 2020): report", ""]
    md += [
        "Generated by `sparsecomm reproduce` from the runs in this folder; every number below was "
        "measured by those runs (final evaluation of each trained run over fresh episodes, "
        f"sampled actions). Statistics over runs ({_seeds_text(summary)}): mean with a 95% "
        "BCa bootstrap CI at Hesterberg's expanded level (Student-t where BCa has no answer; "
        "`sparsecomm.report.bootstrap_ci`), and the interquartile mean (IQM). Env steps count "
        "episodes x max_steps (the scan length), masked steps after an episode ended included.",
        "",
    ]
    if command:
        md += [f"Invoked as: `{command}`", ""]
    commit = _git_commit()
    if commit:
        md += [f"Report written at commit `{commit}` (each part's: hardware table).", ""]
    quick = timings.get("_meta", {}).get("quick")
    if quick:
        md += [
            "**Quick run (`--quick`): tiny budgets. The verdicts below test the pipeline, "
            "not the paper.**",
            "",
        ]
    md += ["## The paper's claims (SPEC section 7)", ""]
    md += ["| # | claim | verdict | numbers | rule |", "|---|---|---|---|---|"]
    for c in claims:
        num = str(c.number) if c.number else "extra"
        md.append(f"| {num} | {c.text} | **{c.verdict}** | {c.evidence} | {c.rule} |")
    md.append("")
    if "rl" in summary:
        md += ["## RL through the channel (Fig. 1, Fig. 2)", ""]
        md.append(
            report_md.metrics_table(
                {f"{k:g}": v for k, v in sorted(summary["rl"].items(), reverse=True)}, "λ"
            )
        )
    if "imitation" in summary:
        md += ["## Imitation of the oracle (Fig. 3, Table I)", ""]
        md.append(
            report_md.metrics_table(
                {f"{k:g}": v for k, v in sorted(summary["imitation"].items(), reverse=True)}, "λ"
            )
        )
    if "baselines" in summary:
        md += ["## Baselines", ""]
        rows = {BASELINE_LABELS[k]: v for k, v in summary["baselines"].items()}
        md.append(report_md.metrics_table(rows, "method"))
    if summary.get("frontier"):
        md += _frontier_lines(summary["frontier"])
    if "training_success" in summary:
        md += ["## Mean success over training (area under the learning curve)", ""]
        md += ["| run | mean success over training |", "|---|---|"]
        for lam, st in sorted(summary["training_success"].get("rl", {}).items(), reverse=True):
            md.append(f"| RL λ={lam:g} | {report_md.fmt(st)} |")
        if "rcl" in summary["training_success"]:
            md.append(f"| RCL | {report_md.fmt(summary['training_success']['rcl'])} |")
        md.append("")
    if figures:
        md += ["## Figures", ""]
        md += [f"![{p.stem}]({p.name})" for p in figures]
        md.append("")
    if timings:
        md += ["## Hardware and wall-clock", ""]
        md += _hardware_lines(timings) + [""]
        md += ["## Budgets", ""]
        md += _budget_lines(timings) + [""]
    (out / "report.md").write_text("\n".join(md))
    return summary


def reproduce(args: Reproduce) -> dict:
    """Run the selected parts (in ``PARTS`` order), then write the figures and the report."""
    args.distributed.initialize()
    primary = is_primary()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timings_path = out / "timings.json"
    timings = _read(timings_path) or {}
    timings["_meta"] = {"quick": args.quick}
    fast = bool(args.resolved("fast_compile"))
    previous = _fast_compile(True) if fast else None
    try:
        for part in (p for p in PARTS if p in args.parts):
            print(f"== {part}")
            t0 = time.time()
            budget = run_part(args, part)
            timings[part] = {
                "wall_clock_s": time.time() - t0,
                "budget": budget,
                "hardware": hardware(),
                "fast_compile": fast,
                "commit": _git_commit(),
                "source_sha256": _source_digest(),
                "finished": datetime.datetime.now().isoformat(timespec="seconds"),
                "processes": jax.process_count(),
            }
            if primary:
                timings_path.write_text(json.dumps(timings, indent=2))
    finally:
        if previous is not None:
            _fast_compile(previous)
    if not primary:
        return {}
    summary = write_report(out, shlex.join(sys.argv))
    print(f"report -> {out / 'report.md'}")
    for c in report_md.decide_claims(summary):
        print(f"  claim {c.number or 'extra'}: {c.verdict}")
    return summary
