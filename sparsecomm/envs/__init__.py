"""The tasks: the interface (``task.py``), the registry by name (``registry.py``), the paper's
hidden-goal cooperative navigation (paper section V.A, SPEC section 4), JaxMARL's
``simple_reference``, and IC3Net's Predator-Prey (``predator_prey``) and Traffic Junction
(``traffic_junction``)."""

from sparsecomm.envs.navigation import NUM_ACTIONS, NavConfig, NavigationEnv, NavState
from sparsecomm.envs.oracle import (
    EpisodeStats,
    center_actions,
    oracle_actions,
    run_policy_episodes,
)
from sparsecomm.envs.registry import make, names, register
from sparsecomm.envs.task import Task, TaskConfig, check_task

__all__ = [
    "NUM_ACTIONS",
    "EpisodeStats",
    "NavConfig",
    "NavState",
    "NavigationEnv",
    "NavigationParallelEnv",
    "Task",
    "TaskConfig",
    "check_task",
    "make",
    "names",
    "register",
    "center_actions",
    "oracle_actions",
    "record_episode",
    "render_frames",
    "run_policy_episodes",
    "trim_episode",
    "write_gif",
]


_LAZY = {
    "NavigationParallelEnv": "sparsecomm.envs.pettingzoo_env",
    "record_episode": "sparsecomm.envs.render",
    "render_frames": "sparsecomm.envs.render",
    "trim_episode": "sparsecomm.envs.render",
    "write_gif": "sparsecomm.envs.render",
}


def __getattr__(name: str):
    # PettingZoo/gymnasium and PIL/imageio are imported only when asked for (this also keeps
    # `python -m sparsecomm.envs.render` free of a double-import warning).
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
