"""Record episodes of IC3Net's original Predator-Prey and Traffic Junction (``ic3net-envs``, MIT
licence, Copyright (c) 2019 Amanpreet Singh, Tushar Jain and Sainbayar Sukhbaatar) for the
parity tests of their JAX ports, :mod:`sparsecomm.envs.predator_prey`
(``tests/test_predator_prey.py``) and :mod:`sparsecomm.envs.traffic_junction`
(``tests/test_traffic_junction.py``).

It needs the original package on the path, with ``numpy<2`` (1.26.4 was used: the original
fails under numpy 2) and ``gym`` (0.25.2 was used), and
not sparsecomm nor JAX::

    git clone https://github.com/IC3Net/IC3Net /tmp/ic3net-orig   # or any copy of it
    python3 -m venv /tmp/venv-ic3 && /tmp/venv-ic3/bin/pip install "numpy<2" "gym<0.26"
    /tmp/venv-ic3/bin/python scripts/record_ic3net_parity.py \\
        --orig /tmp/ic3net-orig/ic3net-envs --out tests/data/ic3net_predator_prey.npz \\
        --tj-out tests/data/ic3net_traffic_junction.npz

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

Traffic Junction (``--tj-out``): per level (easy, medium, hard, vocabulary ``bool``, the arrival
rate at the end of the README's curriculum) three episodes of ``max_steps`` steps, each car
pressing gas with probability 0.5, 0.8 and 1 (``np.random.RandomState(seed + 100)``), the
original's arrivals drawn after ``np.random.seed(seed)``. Written per episode as above
(``actions``, ``rewards``, ``success``, sparse ``obs_idx``/``obs_val`` with float values) and
``e/arrivals`` (T, entries, 2) the car that entered at each entry point and its route among
the entry point's (-1: none), ``e/alive`` (T, K) the active cars after each step, and the
original's routes: ``e/routes`` (all cells), ``e/route_lengths``, ``e/group_sizes``.
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


TJ_LEVELS = {  # IC3Net's README: dim, cars (nagents), vision, max_steps, the final add rate
    "easy": (6, 5, 0, 20, 0.3),
    "medium": (14, 10, 0, 40, 0.05),
    "hard": (18, 20, 0, 80, 0.05),
}


def make_tj(level: str):
    from ic3net_envs.traffic_junction_env import TrafficJunctionEnv

    dim, k, vision, _, rate = TJ_LEVELS[level]
    args = argparse.Namespace(
        dim=dim,
        vision=vision,
        add_rate_min=rate,
        add_rate_max=rate,
        curr_start=0,
        curr_end=0,
        difficulty=level,
        vocab_type="bool",
        nagents=k,
    )
    env = TrafficJunctionEnv()
    env.multi_agent_init(args)
    return env


def flat_tj_obs(obs) -> np.ndarray:
    """IC3Net's ``GymWrapper._flatten_obs`` of a tuple of per-car (act, route, window)."""
    return np.stack([np.concatenate([np.array(x).flatten() for x in car]) for car in obs])


def record_tj(level: str, seed: int, p_gas: float) -> dict:
    """One Traffic Junction episode: the cars that arrive each step and their routes are
    recorded (the original draws them with numpy's global generator inside ``step``)."""
    env = make_tj(level)
    k, max_steps = TJ_LEVELS[level][1], TJ_LEVELS[level][3]
    n_groups = len(env.routes)
    events = []
    add_cars = env._add_cars

    def recorded_add_cars():
        before = env.alive_mask.copy()
        add_cars()
        row = np.full((n_groups, 2), -1, np.int32)
        for car in np.flatnonzero((env.alive_mask == 1) & (before == 0)):
            group = next(g for g in range(n_groups) if _is(env, car, g))
            row[group] = (car, env.route_id[car] - group * len(env.routes[group]))
        events.append(row)

    env._add_cars = recorded_add_cars
    np.random.seed(seed)  # noqa: NPY002 (the original draws from numpy's global generator)
    obs = [flat_tj_obs(env.reset())]
    rng = np.random.RandomState(seed + 100)
    actions, rewards, alive, success = [], [], [], []
    for _ in range(max_steps):
        a = (rng.rand(k) > p_gas).astype(np.int64)  # 0 gas, 1 brake
        o, r, done, info = env.step(a.copy())
        assert not done  # the original never ends an episode; the trainer cuts it
        actions.append(a)
        rewards.append(np.asarray(r, np.float64))
        alive.append(info["alive_mask"].astype(bool))
        success.append(env.stat["success"])
        obs.append(flat_tj_obs(o))
    obs = np.stack(obs)
    idx = np.argwhere(obs)
    paths = [np.asarray(p) for group in env.routes for p in group]
    return {
        "actions": np.stack(actions).astype(np.int8),
        "arrivals": np.stack(events),
        "rewards": np.stack(rewards),
        "alive": np.stack(alive),
        "success": np.array(success, np.int8),
        "obs_idx": idx.astype(np.int32),
        "obs_val": obs[tuple(idx.T)],
        "routes": np.concatenate(paths).astype(np.int16),
        "route_lengths": np.array([len(p) for p in paths], np.int16),
        "group_sizes": np.array([len(g) for g in env.routes], np.int16),
    }


def _is(env, car, group) -> bool:
    """Whether ``car`` was put on a route of ``group`` (its start cell is that group's)."""
    return any(np.array_equal(env.chosen_path[car], p) for p in env.routes[group])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--orig", required=True, help="the folder that holds ic3net_envs/")
    parser.add_argument("--out", required=True, help="the Predator-Prey .npz to write")
    parser.add_argument("--tj-out", help="the Traffic Junction .npz to write, if given")
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
    if args.tj_out:
        arrays, meta = {}, []
        plan = [
            (level, seed, p) for level in TJ_LEVELS for seed, p in ((1, 0.5), (2, 0.8), (3, 1.0))
        ]
        for e, (level, seed, p_gas) in enumerate(plan):
            rec = record_tj(level, seed, p_gas)
            arrays.update({f"{e}/{name}": value for name, value in rec.items()})
            meta.append({"level": level, "seed": seed, "p_gas": p_gas})
            print(
                f"TJ {e}: {level} seed {seed} p_gas {p_gas}: arrivals "
                f"{int((rec['arrivals'][..., 0] >= 0).sum())}, crashes "
                f"{int((rec['rewards'] <= -10).sum())}, success {rec['success'][-1]}"
            )
        arrays["meta"] = np.array(json.dumps(meta))
        np.savez_compressed(args.tj_out, **arrays)
        print(f"wrote {args.tj_out} ({Path(args.tj_out).stat().st_size} bytes)")


if __name__ == "__main__":
    main()
