"""The paper's navigation task as the registry builds it (``"navigation"``): the dynamics of
:mod:`sparsecomm.envs.navigation` with the task interface's optional parts, its centralised
oracle expert (:mod:`sparsecomm.envs.oracle`) and its renderer (:mod:`sparsecomm.envs.render`).
"""

from __future__ import annotations

import jax

from sparsecomm.envs.navigation import NavigationEnv, NavState
from sparsecomm.envs.oracle import oracle_actions


class NavigationTask(NavigationEnv):
    """:class:`~sparsecomm.envs.navigation.NavigationEnv` with an expert and a renderer."""

    def __repr__(self) -> str:
        return f"NavigationTask({self.config!r})"

    def expert_actions(self, state: NavState) -> jax.Array:
        """(K,) int32: the centralised oracle that sees every goal and sends nothing
        (:func:`sparsecomm.envs.oracle.oracle_actions`, the paper's communication-free
        expert)."""
        return oracle_actions(state, self.config)

    def render(self, states: NavState, link_bits=None) -> list:
        """One RGB frame per state of ``states`` (leading time axis), each link drawn with the
        payload bits ``link_bits`` (T, K, K) it carried
        (:func:`sparsecomm.envs.render.render_frames`; PIL is imported here, when drawing)."""
        from sparsecomm.envs.render import render_frames

        return render_frames(states, self.config, link_bits=link_bits)
