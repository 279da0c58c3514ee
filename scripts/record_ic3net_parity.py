"""Record episodes of IC3Net's original Predator-Prey (``ic3net-envs``, MIT licence, Copyright
(c) 2019 Amanpreet Singh, Tushar Jain and Sainbayar Sukhbaatar) for the parity test of its JAX
port, :mod:`sparsecomm.envs.predator_prey` (``tests/test_predator_prey.py``).

It needs the original package on the path, with ``numpy`` and ``gym`` (0.25.2 was used), and
not sparsecomm nor JAX::

    git clone https://github.com/IC3Net/IC3Net /tmp/ic3net-orig   # or any copy of it
    python3 -m venv /tmp/venv-ic3 && /tmp/venv-ic3/bin/pip install numpy "gym<0.26"
    /tmp/venv-ic3/bin/python scripts/record_ic3net_parity.py \\
        --orig /tmp/ic3net-orig/ic3net-envs --out tests/data/ic3net_predator_prey.npz

For each level (easy, medium, hard, in the ``mixed`` reward mode) it plays three seeded
episodes: two of uniformly random actions and one of a noisy chaser (towards the prey with
probability 0.8, else random), so that predators reach the prey, freeze there and end the
episode; and on the easy level one chaser episode in each of the ``cooperative`` and
``competitive`` modes. The initial positions come from the original's own draw
(``np.random.seed(seed)`` then ``reset()``); the actions from ``np.random.RandomState(seed)``.
An episode runs until the original says it is over or for the level's ``max_steps`` (IC3Net's
trainer cuts it there). Written per episode ``e``: ``e/predators`` (K, 2) and ``e/prey`` (2,)
the initial positions, ``e/actions`` (T, K), ``e/rewards`` (T, K), ``e/dones`` (T,), the
original's ``stat["success"]`` ``e/success`` (T,) (-1 where it sets none), and the
observations, (T + 1, K, obs_dim) as IC3Net's ``GymWrapper`` flattens them, stored sparse:
``e/obs_idx`` (N, 3) the (time, agent, index) of each non-zero entry and ``e/obs_val`` (N,)
its value; ``meta`` a JSON list of each episode's level, mode, seed and kind.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

LEVELS = {  # IC3Net's README: dim, predators (nagents), vision, max_steps
    "easy": (5, 3, 0, 20),
    "medium": (10, 5, 1, 40),
    "hard": (20, 10, 1, 80),
}


def make_env(level: str, mode: str):
    from ic3net_envs.predator_prey_env import PredatorPreyEnv

    dim, k, vision, _ = LEVELS[level]
    args = argparse.Namespace(
        dim=dim,
        vision=vision,
        moving_prey=False,
        mode=mode,
        enemy_comm=False,
        nenemies=1,
        nfriendly=k,
        no_stay=False,
    )
    env = PredatorPreyEnv()
    env.multi_agent_init(args)
    return env


def chase(rng, pred, prey, p=0.8):
    """Each predator steps towards the prey (rows first) with probability ``p``, else acts at
    random (0 up, 1 right, 2 down, 3 left, 4 stay)."""
    acts = rng.randint(0, 5, len(pred))
    for i, (r, c) in enumerate(pred):
        if rng.rand() < p:
            dr, dc = prey[0] - r, prey[1] - c
            acts[i] = 2 if dr > 0 else 0 if dr < 0 else 1 if dc > 0 else 3 if dc < 0 else 4
    return acts


def record(level: str, mode: str, seed: int, kind: str) -> dict:
    env = make_env(level, mode)
    k, max_steps = LEVELS[level][1], LEVELS[level][3]
    np.random.seed(seed)  # noqa: NPY002 (the original draws from numpy's global generator)
    obs = [env.reset().reshape(k, -1).copy()]
    pred0, prey0 = env.predator_loc.copy(), env.prey_loc[0].copy()
    rng = np.random.RandomState(seed)
    actions, rewards, dones, success = [], [], [], []
    for _ in range(max_steps):
        if kind == "random":
            a = rng.randint(0, 5, k)
        else:
            a = chase(rng, env.predator_loc, env.prey_loc[0])
        o, r, done, _ = env.step(a.copy())
        actions.append(a)
        rewards.append(np.asarray(r, np.float64))
        dones.append(bool(done))
        success.append(env.stat.get("success", -1))
        obs.append(o.reshape(k, -1).copy())
        if done:
            break
    obs = np.stack(obs)
    idx = np.argwhere(obs)
    return {
        "predators": pred0.astype(np.int32),
        "prey": prey0.astype(np.int32),
        "actions": np.stack(actions).astype(np.int8),
        "rewards": np.stack(rewards),
        "dones": np.array(dones),
        "success": np.array(success, np.int8),
        "obs_idx": idx.astype(np.int32),
        "obs_val": obs[tuple(idx.T)].astype(np.int8),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--orig", required=True, help="the folder that holds ic3net_envs/")
    parser.add_argument("--out", required=True, help="the .npz to write")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(args.orig).resolve()))
    plan = [
        (level, "mixed", seed, kind)
        for level in LEVELS
        for seed, kind in ((1, "random"), (2, "random"), (3, "chase"))
    ]
    plan += [("easy", "cooperative", 4, "chase"), ("easy", "competitive", 5, "chase")]
    arrays, meta = {}, []
    for e, (level, mode, seed, kind) in enumerate(plan):
        rec = record(level, mode, seed, kind)
        arrays.update({f"{e}/{name}": value for name, value in rec.items()})
        meta.append({"level": level, "mode": mode, "seed": seed, "kind": kind})
        print(
            f"{e}: {level} {mode} {kind} seed {seed}: {len(rec['dones'])} steps, "
            f"done {bool(rec['dones'][-1])}, on-prey rewards {int((rec['rewards'] >= 0).sum())}"
        )
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size} bytes)")


if __name__ == "__main__":
    main()
