"""SHA-256 of the parameters after a few updates of RL and imitation, for refactors.

A refactor that should not change behaviour must leave these digests unchanged on the same
machine (CPU, same jax): ``python scripts/param_digest.py`` before and after, and compare.
Covers fixed-lambda and budgeted RL, shared and separate actor parameters, the reinforced
channel baseline, DAgger imitation of the oracle, and the channel's paths: continuous, off,
lossy and late links (fixed code, null and last), links that fall silent but speak on news
(priced on the wire for RL, on the payload for imitation, each under a budget), and links
routed by position with aggregated inboxes.

``--record tests/data/rl3.json`` writes the first case's record for ``tests/test_digest.py``:
its digest, every parameter leaf's sum and norm, and the machine it ran on.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from pathlib import Path

import jax
import numpy as np

from sparsecomm.budget import BudgetConfig
from sparsecomm.channel import NoiseConfig
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


def trained(make, cfg, lam=0.0, budget=float("nan")):
    """The parameters after ``UPDATES`` updates."""
    learner = make(cfg)
    state = jax.jit(learner.init)(jax.random.key(cfg.seed), lam, budget)
    update = jax.jit(learner.update)
    for _ in range(UPDATES):
        state, _ = update(state)
    return state.params


def run(make, cfg, lam=0.0, budget=float("nan")):
    return digest(trained(make, cfg, lam, budget))


def summary(tree) -> dict:
    """The digest, and each leaf's sum and Euclidean norm (float64), in leaf order."""
    leaves = [np.asarray(x, np.float64) for x in jax.tree.leaves(tree)]
    return {
        "digest": digest(tree),
        "sums": [float(x.sum()) for x in leaves],
        "norms": [float(np.linalg.norm(x)) for x in leaves],
    }


def cases() -> dict:
    """The cases, by name: ``(make, config, lambda, budget)``."""
    env = NavConfig(max_steps=24)
    rl = RLConfig(env=env, num_envs=8, seed=3)
    hard = AgentConfig(message_gate="hard")
    engaged = BudgetConfig(engage_success=0.0, relief_floor=0.5)
    # links that fall silent but speak on news: priced on the wire (the `silent` preset's) and
    # on the payload (the paper task's `NEWS`)
    silent = ChannelConfig(
        prices="wire", link_gate=True, on_silence="hold", check_bits=16, news_margin=0.1
    )
    news = ChannelConfig(link_gate=True, on_silence="hold", news_margin=0.1)
    return {
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
        "rl continuous channel": (
            make_train,
            dataclasses.replace(rl, channel=ChannelConfig(mode="continuous")),
            0.0,
            float("nan"),
        ),
        "rl channel off": (
            make_train,
            dataclasses.replace(rl, channel=ChannelConfig(mode="off")),
            0.0,
            float("nan"),
        ),
        "rl erasure 0.3, last, fixed code": (
            make_train,
            dataclasses.replace(
                rl, channel=ChannelConfig(code="fixed", noise=NoiseConfig(erasure=0.3))
            ),
            0.01,
            float("nan"),
        ),
        "rl delay 2, null": (
            make_train,
            dataclasses.replace(
                rl, channel=ChannelConfig(noise=NoiseConfig(delay=2, flip=0.01, on_drop="null"))
            ),
            0.01,
            float("nan"),
        ),
        "rl 4 agents, 2 nearest, attention": (
            make_train,
            dataclasses.replace(
                rl,
                env=NavConfig(num_agents=4, max_steps=24),
                agent=AgentConfig(neighbours=2, aggregate="attention"),
            ),
            0.01,
            float("nan"),
        ),
        "rl silent links, news, prices wire, budget 8": (
            make_train,
            dataclasses.replace(rl, agent=hard, channel=silent, budget=engaged),
            0.0,
            8.0,
        ),
        "il dagger, links held on silence, news": (
            make_imitate,
            ILConfig(env=env, num_envs=8, seed=3, agent=hard, channel=news, budget=engaged),
            0.0,
            8.0,
        ),
        "rl 4 agents, radius, mean, off": (
            make_train,
            dataclasses.replace(
                rl,
                env=NavConfig(num_agents=4, max_steps=24),
                agent=AgentConfig(radius=0.5, aggregate="mean"),
                channel=ChannelConfig(mode="off"),
            ),
            0.0,
            float("nan"),
        ),
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--record", type=Path, help="write the first case's record here and stop")
    a = p.parse_args()
    if a.record is not None:
        from sparsecomm.provenance import hardware

        name, (make, cfg, lam, budget) = next(iter(cases().items()))
        record = {"case": name, "machine": hardware(), **summary(trained(make, cfg, lam, budget))}
        a.record.parent.mkdir(parents=True, exist_ok=True)
        a.record.write_text(json.dumps(record, indent=1) + "\n")
        print(f"{name}: {record['digest']} -> {a.record}")
        return
    for name, (make, cfg, lam, budget) in cases().items():
        print(f"{name:32s} {run(make, cfg, lam, budget)}")


if __name__ == "__main__":
    main()
