"""The learner kinds: the one registry that names them.

A **learner kind** is one way to train a team: reinforcement learning through the channel
(:data:`RL`) or imitation of an expert's actions (:data:`IMITATION`). Each has one name, the
one a run folder's checkpoint and exported team record (``kind``), the results' summaries and
the frontiers use, and it says the rest: its config class, its ``make_*`` function, the
command that trains it, the docs page that measures it and its update rules (algorithms).
:mod:`sparsecomm.runfolder`, :mod:`sparsecomm.cli`, :mod:`sparsecomm.experiment` and the
results' readers read them here instead of spelling them.

Run folders and exported teams written before the kinds had these names recorded the command
instead (``train``, ``imitate``): :func:`named` reads either, so they load as before.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from sparsecomm.configs import ALGOS, ILConfig, RLConfig
from sparsecomm.imitation import make_imitate
from sparsecomm.rl import make_train


@dataclasses.dataclass(frozen=True)
class LearnerKind:
    """One learner kind and everything that is named after it."""

    name: str
    """The kind's one name: recorded in run folders (``kind``), results and summaries."""
    config: type
    """Its config class (``RLConfig``, ``ILConfig``)."""
    make: Callable
    """Its learner from a config (imitation also takes the expert): ``rl.make_train``,
    ``imitation.make_imitate``."""
    command: str
    """The ``sparsecomm`` command that trains it (and the key of its config in
    ``configs.PRESETS``)."""
    docs: str
    """The docs page that measures it."""
    algos: tuple[str, ...]
    """Its update rules, as :attr:`algo_of` names them."""
    algo_of: Callable[[object], str]
    """The update rule a config of this kind runs (one of :attr:`algos`)."""


def _imitation_algo(config: ILConfig) -> str:
    """``dagger`` while the expert's share of the driving falls (``beta_end < beta_start``),
    else ``bc`` (behaviour cloning: the expert drives throughout)."""
    return "dagger" if config.beta_end < config.beta_start else "bc"


RL = LearnerKind(
    name="rl",
    config=RLConfig,
    make=make_train,
    command="train",
    docs="docs/rl.md",
    algos=ALGOS,
    algo_of=lambda config: config.algo,
)
"""Actor-critic reinforcement learning through the channel (``RLConfig.algo``: a2c or ppo)."""

IMITATION = LearnerKind(
    name="imitation",
    config=ILConfig,
    make=make_imitate,
    command="imitate",
    docs="docs/imitation.md",
    algos=("bc", "dagger"),
    algo_of=_imitation_algo,
)
"""Imitation of an expert's actions through the channel (behaviour cloning or DAgger)."""

KINDS: dict[str, LearnerKind] = {kind.name: kind for kind in (RL, IMITATION)}
"""Every learner kind by its name."""


def named(name: str) -> LearnerKind:
    """The kind called ``name``, or whose command is ``name`` (what run folders and exported
    teams written before the kinds had names recorded); a ``ValueError`` naming the kinds."""
    for kind in KINDS.values():
        if name in (kind.name, kind.command):
            return kind
    raise ValueError(f"a learner kind must be one of {list(KINDS)}, got {name!r}")


def of_config(config) -> LearnerKind:
    """The kind whose config class ``config`` is exactly; a ``TypeError`` otherwise."""
    for kind in KINDS.values():
        if type(config) is kind.config:
            return kind
    classes = [kind.config.__name__ for kind in KINDS.values()]
    raise TypeError(f"a run's config must be one of {classes}, got {type(config).__name__}")


def by_command(command: str) -> LearnerKind | None:
    """The kind the command ``command`` trains, or None (a command that trains nothing)."""
    return next((kind for kind in KINDS.values() if kind.command == command), None)


COMMANDS = tuple(kind.command for kind in KINDS.values())
"""The commands that train a learner (``sparsecomm train``, ``sparsecomm imitate``)."""
