"""The plan of ``sparsecomm reproduce``: the parts, their lambdas and budgets, the config.

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
from pathlib import Path

import numpy as np

from sparsecomm.configs import ILConfig, RLConfig
from sparsecomm.sharding import Distributed

RL_LAMS = (0.01, 0.005, 0.001, 0.0)
"""Paper, section V: the RL penalty weights."""
IL_LAMS = (0.001, 0.0007, 0.0004, 0.0001, 0.0)
"""Paper, section V and Table I: the imitation penalty weights (0 added as the reference)."""
BUDGETS = (64.0, 32.0, 16.0, 8.0, 4.0)
"""The bit budgets of the frontier (payload bits per step; lambda 0 sends ~160; docs/budget.md)."""
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
    "il_budget_rl",
)
"""Every part, in the order they run."""
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
BASELINE_LABELS = {
    "no_comm": "no communication (RL)",
    "continuous": "real-valued messages, float32 (RL)",
    "fixed": "fixed-width code (RL, λ=0 teams)",
    "rcl": "reinforced comm. learning (RCL)",
    "oracle": "oracle (centralised, upper bound)",
    "centre": "scripted, no communication (centre)",
}
"""Each baseline's label in the figures and the report (``centre`` comes with ``oracle``)."""


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
    """Bit budgets of the ``rl_budget``, ``il_budget`` and ``il_budget_rl`` parts (payload bits
    per step). ours (docs/budget.md)."""
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
