"""The one runner of the pipelines: a plan's parts in order (each sweep through
:func:`sparsecomm.experiment.train`, so a part that dies resumes from its checkpoint), and the
frontier rows of the parts found under ``out`` (:mod:`sparsecomm.pipelines.rows`)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from sparsecomm.experiment import Imitate, Train, train
from sparsecomm.pipelines.plan import Part, Sweep
from sparsecomm.pipelines.rows import Row, read_rows
from sparsecomm.runfolder import RESULTS

Step = Sweep | Callable[[], dict]
"""What a part runs: a sweep, or a function that returns the part's record."""


@dataclasses.dataclass(frozen=True)
class SweepOptions:
    """What every sweep of a command shares (the ``Train`` fields besides the learner)."""

    seeds: int
    eval_episodes: int
    chunk: int | None = None
    """Updates per compiled call; None: all of a sweep's updates in one."""
    checkpoint_every: int = 5
    resume: bool = True
    tensorboard: bool = False
    gif: bool = False
    progress: bool = True


def sweep_args(sweep: Sweep, options: SweepOptions, out: Path) -> Train:
    """The ``Train`` (``Imitate`` for an imitation sweep) arguments of one part."""
    return (Imitate if sweep.imitate else Train)(
        config=sweep.config,
        seeds=options.seeds,
        lams=tuple(float(x) for x in sweep.lams),
        budgets=sweep.budgets,
        out=out,
        chunk=options.chunk or max(sweep.config.num_updates, 1),
        checkpoint_every=options.checkpoint_every,
        resume=options.resume,
        tensorboard=options.tensorboard,
        eval_episodes=options.eval_episodes,
        gif=options.gif,
        progress=options.progress,
    )


def run_parts(
    plan: Sequence[Part],
    selected: Sequence[str],
    build: Callable[[str], Step],
    options: SweepOptions,
    out: Path,
    header: str = "== {part}",
    after: Callable[[str, dict, float], None] | None = None,
) -> None:
    """Run the ``selected`` parts of ``plan`` in its order: each one built by ``build`` when its
    turn comes, announced by ``header`` (``{part}``, ``{folder}``), then ``after(part, record,
    seconds)`` (the record: :meth:`Sweep.budget`, or what the part's function returned)."""
    for part in plan:
        if part.name not in selected:
            continue
        print(header.format(part=part.name, folder=out / part.name), flush=True)
        t0 = time.time()
        step = build(part.name)
        if isinstance(step, Sweep):
            train(sweep_args(step, options, out / part.name))
            record = step.budget(options.seeds)
        else:
            record = step()
        if after is not None:
            after(part.name, record, time.time() - t0)


def part_rows(plan: Sequence[Part], out: Path, task: str | None = None) -> dict[str, list[Row]]:
    """The frontier rows of every part of ``plan`` with a learner whose results are found in
    ``out``, by part: of the plain form, or with ``task`` of the wire form."""
    found = {}
    for part in plan:
        path = out / part.name / RESULTS
        if part.learner is not None and path.exists():
            found[part.name] = read_rows(path, part.learner, part.series, task=task)
    return found
