"""SHA-256 of the parameters after a few updates of RL and imitation, for refactors.

A refactor that should not change behaviour must leave these digests unchanged on the same
machine (CPU, same jax): ``python scripts/param_digest.py`` before and after, and compare.
Covers fixed-lambda and budgeted RL, shared and separate actor parameters, the reinforced
channel baseline, and DAgger imitation of the oracle.
"""

from __future__ import annotations

import dataclasses
import hashlib

import jax
import numpy as np

from sparsecomm.budget import BudgetConfig
from sparsecomm.configs import AgentConfig, ChannelConfig, ILConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.imitation import make_imitate
from sparsecomm.rl import make_train

UPDATES = 3


def digest(tree) -> str:
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()[:16]


def run(make, cfg, lam=0.0, budget=float("nan")):
    learner = make(cfg)
    state = jax.jit(learner.init)(jax.random.key(cfg.seed), lam, budget)
    update = jax.jit(learner.update)
    for _ in range(UPDATES):
        state, _ = update(state)
    return digest(state.params)


def main():
    env = NavConfig(max_steps=24)
    rl = RLConfig(env=env, num_envs=8, seed=3)
    cases = {
        "rl lam 0": (make_train, rl, 0.0, float("nan")),
        "rl lam 0.01": (make_train, rl, 0.01, float("nan")),
        "rl budget 8 (engaged at once)": (
            make_train,
            dataclasses.replace(rl, budget=BudgetConfig(engage_success=0.0)),
            0.0,
            8.0,
        ),
        "rl separate params, hard gate": (
            make_train,
            dataclasses.replace(rl, agent=AgentConfig(share_params=False, message_gate="hard")),
            0.0,
            float("nan"),
        ),
        "rl reinforced channel": (
            make_train,
            dataclasses.replace(rl, channel=ChannelConfig(mode="reinforced")),
            0.0,
            float("nan"),
        ),
        "il dagger": (make_imitate, ILConfig(env=env, num_envs=8, seed=3), 0.001, float("nan")),
    }
    for name, (make, cfg, lam, budget) in cases.items():
        print(f"{name:32s} {run(make, cfg, lam, budget)}")


if __name__ == "__main__":
    main()
