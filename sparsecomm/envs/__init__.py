"""The hidden-goal cooperative navigation task (paper section V.A, SPEC section 4)."""

from sparsecomm.envs.navigation import NUM_ACTIONS, NavConfig, NavigationEnv, NavState
from sparsecomm.envs.oracle import (
    EpisodeStats,
    center_actions,
    oracle_actions,
    run_policy_episodes,
)

__all__ = [
    "NUM_ACTIONS",
    "EpisodeStats",
    "NavConfig",
    "NavState",
    "NavigationEnv",
    "NavigationParallelEnv",
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
