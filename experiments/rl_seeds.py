"""Issue-4 measurement: the default RL learner, 5 seeds, with and without communication.

Runs ``sparsecomm train`` twice through its Python entry point (no tyro needed), each a vmapped
program over seeds, and copies the small artefacts to ``--out``. Used for docs/results/rl.

    python experiments/rl_seeds.py --updates 2000 --seeds 5 --out docs/results/rl
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path

from sparsecomm.configs import ChannelConfig, RLConfig
from sparsecomm.experiment import Train, train

if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--updates", type=int, default=2000)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--work", type=Path, default=Path("runs/rl_seeds"))
    p.add_argument("--out", type=Path, default=Path("docs/results/rl"))
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--num-envs", type=int, default=RLConfig().num_envs)
    p.add_argument("--parts", nargs="+", default=["comm", "nocomm"], choices=["comm", "nocomm"])
    a = p.parse_args()
    base = RLConfig(num_updates=a.updates, num_envs=a.num_envs)
    for name, cfg in (
        ("comm", base),
        ("nocomm", dataclasses.replace(base, channel=ChannelConfig(mode="off"))),
    ):
        if name not in a.parts:
            continue
        work = a.work / name
        train(
            Train(
                config=cfg,
                seeds=a.seeds,
                lams=(0.0,),
                out=work,
                chunk=50,
                tensorboard=False,
                eval_episodes=a.eval_episodes,
                gif=name == "comm",
                progress=False,
            )
        )
        a.out.mkdir(parents=True, exist_ok=True)
        for f in ("metrics.csv", "results.json", "curves.png", "team.gif"):
            if (work / f).exists():
                shutil.copy(work / f, a.out / f"{name}_{f}")
