"""How much a team's first messages say about each recipient's goal, per seed, before learning.

For each seed, the team of ``sparsecomm train --preset PRESET --config.seed SEED`` (its
parameters at initialisation: the key that command's run 0 draws them from) plays
``--episodes`` episodes; a linear least-squares read-out of every recipient's own goal (the
(x, y) it cannot see) from the symbols it receives at the first step is fitted on half of the
episodes and scored (R^2) on the other half. A recipient whose read-out is near 0 starts with
messages that say nothing about what it needs; a seed whose recipients all read about as
much as other seeds' did not stall for lack of information at the start (docs/paper-task.md,
"Why a seed stalls, and a learner that leaves no seed behind").

    python experiments/message_readout.py --preset paper_fast --seeds 7000 7001 7002 7003 7004
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from sparsecomm.configs import PRESETS
from sparsecomm.rl import make_train
from sparsecomm.rollout import rollout


def held_out_r2(x: np.ndarray, y: np.ndarray) -> float:
    """R^2 on the second half of the rows of a linear fit (with intercept) on the first half."""
    x = np.concatenate([x, np.ones((len(x), 1))], 1)
    half = len(x) // 2
    w, *_ = np.linalg.lstsq(x[:half], y[:half], rcond=None)
    residual = y[half:] - x[half:] @ w
    return float(1 - (residual**2).sum() / ((y[half:] - y[half:].mean(0)) ** 2).sum())


def first_step_readout(preset: str, seed: int, episodes: int) -> list[float]:
    """Each recipient's held-out R^2 (a list of K) for the team of ``seed`` at initialisation."""
    config = PRESETS[preset]["train"]
    learner = make_train(config)
    params = learner.init(jax.random.key(seed), 0.0).params["actor"]
    traj = rollout(
        learner.team,
        learner.env,
        config.channel,
        params,
        jax.random.key(seed + 1),
        episodes,
        keep_states=True,
        keep_symbols=True,
    )
    symbols = np.asarray(traj.aside.symbols[0], np.float64)  # (B, K, K - 1, C), step 0
    goals = np.asarray(traj.aside.env_states.goals[0], np.float64)  # (B, K, 2)
    k = goals.shape[1]
    scores = []
    for j in range(k):  # sender i's link to j is its slot j (j < i) or j - 1 (j > i)
        inbox = [symbols[:, i, j if j < i else j - 1] for i in range(k) if i != j]
        scores.append(held_out_r2(np.concatenate(inbox, -1), goals[:, j]))
    return scores


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="paper_fast", choices=sorted(PRESETS))
    p.add_argument("--seeds", type=int, nargs="+", default=[7000, 7001, 7002, 7003, 7004])
    p.add_argument("--episodes", type=int, default=2048)
    args = p.parse_args(argv)
    for seed in args.seeds:
        scores = first_step_readout(args.preset, seed, args.episodes)
        print(f"seed {seed}: R^2 by recipient " + " ".join(f"{s:.3f}" for s in scores))


if __name__ == "__main__":
    main()
