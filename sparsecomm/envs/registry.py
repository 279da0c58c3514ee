"""Tasks by name: a task is a class and its config, plus one line here (JaxMARL's ``make``).

    from sparsecomm.envs import registry
    env = registry.make(config.env)          # the task a config holds
    registry.names()                         # every registered name

A task's config class names it: ``LearnerConfig.env`` holds the config, run folders and
exported teams record its name (``"task"``), and ``sparsecomm train --task NAME`` starts from
its defaults. A task of one's own is registered with :func:`register` in one's own module;
for the command line and the processes of ``sparsecomm deploy`` to see it, name that module in
the environment variable :data:`PLUGINS_VAR` (``SPARSECOMM_TASKS=mytasks sparsecomm train
--task mytask``: comma-separated modules, imported the first time a name is looked up and not
found) or, for an installed package, in the entry-point group :data:`ENTRY_POINTS`. The
interface and its conformance check: :mod:`sparsecomm.envs.task`.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
from collections.abc import Callable

from sparsecomm.envs.jaxmarl_reference import ReferenceConfig, SimpleReference
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.envs.navigation_task import NavigationTask
from sparsecomm.envs.predator_prey import PredatorPrey, PredatorPreyConfig
from sparsecomm.envs.task import TaskConfig
from sparsecomm.envs.traffic_junction import TrafficJunction, TrafficJunctionConfig

PLUGINS_VAR = "SPARSECOMM_TASKS"
"""Environment variable: comma-separated modules that register tasks when imported."""

ENTRY_POINTS = "sparsecomm.tasks"
"""Entry-point group of installed packages that register tasks (each entry point is loaded)."""

DEFAULT = "navigation"
"""The task of a config, run folder or exported team that names none: the paper's."""


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """One registered task."""

    name: str
    """The name configs, run folders and ``--task`` use."""
    env: Callable
    """The task's class, built as ``env(config)``."""
    config: type
    """The task's config class (a :class:`~sparsecomm.envs.task.TaskConfig` subclass)."""


_TASKS: dict[str, TaskSpec] = {}
_plugins_loaded = False


def register(name: str, env: Callable, config: type) -> TaskSpec:
    """Register the task ``env`` (built as ``env(config)``) under ``name``, with its config
    class ``config``. Registering the same pair again is a no-op; another pair under a taken
    name, or a config class that names another task, is refused."""
    if not isinstance(name, str) or not name or name != name.strip():
        raise ValueError(f"a task's name must be a non-empty string, got {name!r}")
    if not (isinstance(config, type) and issubclass(config, TaskConfig)):
        raise TypeError(f"task {name!r}: its config must subclass envs.task.TaskConfig")
    if not dataclasses.is_dataclass(config) or not config.__dataclass_params__.frozen:
        raise TypeError(f"task {name!r}: its config {config.__name__} must be a frozen dataclass")
    if not hasattr(config, "num_agents") and "num_agents" not in config.__dataclass_fields__:
        raise TypeError(f"task {name!r}: its config {config.__name__} must expose num_agents")
    spec = TaskSpec(name, env, config)
    old = _TASKS.get(name)
    if old is not None and old != spec:
        raise ValueError(f"task {name!r} is registered already, by {old.env!r}")
    for other in _TASKS.values():
        if other.config is config and other.name != name:
            raise ValueError(f"{config.__name__} is the config of task {other.name!r} already")
    _TASKS[name] = spec
    return spec


def _load_plugins() -> None:
    """Import the modules of :data:`PLUGINS_VAR` and load the entry points of
    :data:`ENTRY_POINTS`, once."""
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    for module in filter(None, (m.strip() for m in os.environ.get(PLUGINS_VAR, "").split(","))):
        try:
            importlib.import_module(module)
        except ImportError as e:
            raise ValueError(
                f"{PLUGINS_VAR} names the module {module!r}, which fails to import: {e}"
            ) from e
    from importlib.metadata import entry_points

    for point in entry_points(group=ENTRY_POINTS):
        point.load()


def names() -> tuple[str, ...]:
    """Every registered task's name (plug-ins loaded)."""
    _load_plugins()
    return tuple(sorted(_TASKS))


def spec(name: str) -> TaskSpec:
    """The task registered as ``name``; an unknown name is a ``ValueError`` listing the
    registered ones."""
    if name not in _TASKS:
        _load_plugins()
    if name not in _TASKS:
        raise ValueError(
            f"task must be one of the registered tasks {list(names())}, got {name!r} (a task "
            f"of your own: envs.registry.register, and its module in ${PLUGINS_VAR})"
        )
    return _TASKS[name]


def task_of(config) -> str:
    """The name of the task whose config ``config`` is; a ``ValueError`` if none is."""
    for s in _TASKS.values():
        if type(config) is s.config:
            return s.name
    raise ValueError(
        f"env must be the config of a registered task ({', '.join(names())}), got "
        f"{type(config).__name__}"
    )


def make(config):
    """The task that ``config`` (a registered task's config) configures."""
    return spec(task_of(config)).env(config)


register("navigation", NavigationTask, NavConfig)
register("simple_reference", SimpleReference, ReferenceConfig)
register("predator_prey", PredatorPrey, PredatorPreyConfig)
register("traffic_junction", TrafficJunction, TrafficJunctionConfig)
