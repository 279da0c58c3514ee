"""A pipeline's plan: its parts, each a folder under the command's ``out``, and what a trained
part runs (a :class:`Sweep`); the paper's lambdas and budgets, which both commands sweep.

A command lists its parts in order (:class:`Part`: the name, and the learner and series of the
part's rows in the frontier) and builds each one when its turn comes (a part may need an earlier
part's teams): a :class:`Sweep`, or a function for a part that trains nothing.
:mod:`sparsecomm.pipelines.runner` runs the plan.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from sparsecomm.configs import ILConfig, RLConfig
from sparsecomm.jsonfile import read_json
from sparsecomm.metric_names import aliased_results
from sparsecomm.runfolder import RESULTS, check_output, output_problem

RL_LAMS = (0.01, 0.005, 0.001, 0.0)
"""Paper, section V: the RL penalty weights."""
IL_LAMS = (0.001, 0.0007, 0.0004, 0.0001, 0.0)
"""Paper, section V and Table I: the imitation penalty weights (0 added as the reference)."""
BUDGETS = (64.0, 32.0, 16.0, 8.0, 4.0)
"""The bit budgets of the frontier (payload bits per step; lambda 0 sends ~160; docs/budget.md)."""


@dataclasses.dataclass(frozen=True)
class Part:
    """One part of a plan."""

    name: str
    """The part, and its folder under ``out``."""
    learner: str | None = None
    """The learner of the part's rows (``"rl"`` or ``"imitation"``); None: no frontier rows."""
    series: str | None = None
    """The series of its rows (compared with the series' own lambda 0); None: the learner's."""
    needs: str | None = None
    """A part whose teams this one reads (run before it, or found finished in ``out``)."""


@dataclasses.dataclass(frozen=True)
class Sweep:
    """What a trained part runs: one learner over seeds x lambdas x budgets, one vmapped program
    through :func:`sparsecomm.experiment.train`."""

    config: RLConfig | ILConfig
    """The learner (an ``ILConfig``: imitation)."""
    lams: tuple[float, ...] = (0.0,)
    """Penalty weights."""
    budgets: tuple[float | None, ...] = ()
    """Bit budgets (None: a lambda-0 reference in the same program); () : lambdas only."""
    record: tuple[tuple[str, object], ...] = ()
    """Entries the part's record (:meth:`budget`) adds to the sweep's own."""

    @property
    def imitate(self) -> bool:
        return isinstance(self.config, ILConfig)

    def budget(self, seeds: int) -> dict:
        """The part's training budget, for ``timings.json``."""
        c = self.config
        return {
            "seeds": seeds,
            "lams": [float(x) for x in self.lams],
            "num_updates": c.num_updates,
            "episodes_per_update": c.num_envs,
            "env_steps_per_run": c.num_updates * c.num_envs * c.env.max_steps,
        } | dict(self.record)


def expert_index(run: Path) -> int:
    """The expert of imitation of an RL team: the index (in ``run``'s sweep) of the lambda-0
    team without a budget with the highest final success, ties broken by the shortest
    episodes."""
    res = read_json(run / "results.json")
    if res is None:
        raise ValueError(
            f"imitation of the RL team needs the rl part's teams in {run}: run 'rl' first"
        )
    runs = [
        (i, r)
        for i, r in enumerate(aliased_results(res)["runs"])
        if float(r["lam"]) == 0.0 and r.get("budget") is None
    ]
    if not runs:
        raise ValueError(f"the rl part in {run} has no lambda = 0 runs")
    best = min(runs, key=lambda p: (-p[1]["episode/success_rate"], p[1]["episode/episode_length"]))
    return best[0]


def check_parts(args, plan: tuple[Part, ...]) -> None:
    """Refuse, with a ``ValueError`` naming the field, what would stop a command's parts
    (``args.parts`` of ``plan``) after others ran: ``args.out`` or a selected part's folder
    under it that cannot be written as a folder, and a part that needs another part's teams
    (:attr:`Part.needs`) that is neither selected nor found finished (its ``results.json``) in
    ``args.out``."""
    owner = type(args).__name__
    check_output(args, folder=True)
    for name in args.parts:
        problem = output_problem(Path(args.out) / name, folder=True)
        if problem:
            raise ValueError(
                f"{owner}.out {problem} (the {name} part's folder), got {str(args.out)!r}"
            )
    needs = {part.name: part.needs for part in plan}
    for name in args.parts:
        need = needs[name]
        if need and need not in args.parts and not (Path(args.out) / need / RESULTS).exists():
            raise ValueError(
                f"{owner}.parts (--parts) holds {name}, which needs the {need} part's teams: add "
                f"{need} to --parts, or keep a finished {need} part in {Path(args.out) / need} "
                f"(no {RESULTS} there), got {tuple(args.parts)}"
            )


def check_expert_unset(args, default: ILConfig) -> None:
    """Refuse an expert given in ``args.il`` (``--il.expert*``), naming the field: every
    imitation part of a pipeline sets its own expert (the oracle, or an RL part's team), so one
    given would be ignored. ``default``: the command's own ``il``."""
    for name in ("expert", "expert_checkpoint", "expert_index"):
        value = getattr(args.il, name)
        if value != getattr(default, name):
            raise ValueError(
                f"{type(args).__name__}.il.{name} is set by each imitation part (the oracle, or "
                f"the rl part's best lambda-0 team), so it must be left at "
                f"{getattr(default, name)!r}, got {value!r}"
            )
