"""When do a trained team's links speak? Against the news they could carry.

On the navigation task link i -> j is worth something to j when it tells j its own goal, which
i sees and j does not: at the first step and whenever j's goal jumps. For each run of a run
folder this plays ``--episodes`` episodes (the rollout, sampled actions, key ``--seed + run``)
and reports the share of link-steps that speak, split by the steps since the recipient's goal
last changed (0: the step the sender first sees the new goal; the episode's first step apart).
A link that speaks on news speaks at step 0 and at ``since 0``, and rarely after.

    python scripts/when_links_speak.py RUN_FOLDER [--episodes 500] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from sparsecomm import channel, runfolder
from sparsecomm.rollout import rollout

SINCE = 8
"""Steps since news are reported one by one up to this, then pooled."""


def when_links_speak(folder: str, episodes: int, seed: int) -> list[dict]:
    """One row per run: ``speaking`` (all valid link-steps), ``first_step``, ``news`` (the
    step a recipient's goal jumped), ``since`` (a list over 1 .. SINCE - 1, then SINCE or more),
    each a share of link-steps that speak, with its count ``n``."""
    actors = runfolder.load_actors(folder)
    cfg, team, env = actors.config, actors.team, actors.env
    c, k = cfg.channel.num_elements, env.num_agents
    play = jax.jit(
        lambda p, key: rollout(
            team, env, cfg.channel, p, key, episodes, keep_states=True, keep_symbols=True
        )
    )
    recipients = np.asarray(channel.others(k))  # (K, K-1): link (i, r) goes to recipients[i, r]
    rows = []
    for r in range(len(actors.runs)):
        params = jax.tree.map(lambda x, r=r: x[r], actors.actor)
        traj = play(params, jax.random.key(seed + r))
        speak = (np.asarray(traj.aside.symbols)[..., :c] != 0).any(-1)  # (T, B, K, K-1)
        goals = np.asarray(traj.aside.env_states.goals)[:, :, recipients]  # (T, B, K, K-1, 2)
        valid = np.broadcast_to(np.asarray(traj.valid)[..., None, None], speak.shape)
        jump = np.zeros(speak.shape, bool)
        jump[1:] = np.abs(goals[1:] - goals[:-1]).sum(-1) > 0
        since = np.zeros(speak.shape, int)
        for t in range(1, speak.shape[0]):
            since[t] = np.where(jump[t], 0, since[t - 1] + 1)
        first = np.zeros(speak.shape, bool)
        first[0] = True

        rows.append(
            {
                "run": r,
                "speaking": _share(speak, valid),
                "first_step": _share(speak, first & valid),
                "news": _share(speak, jump & valid),
                "since": [_share(speak, (since == s) & ~first & valid) for s in range(1, SINCE)]
                + [_share(speak, (since >= SINCE) & valid)],
            }
        )
    return rows


def _share(speak: np.ndarray, mask: np.ndarray) -> dict:
    """The share of the link-steps in ``mask`` that speak, and their count."""
    n = int(mask.sum())
    return {"speaks": float(speak[mask].mean()) if n else None, "n": n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run folder or an exported team")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=123, help="key of run r: seed + r")
    parser.add_argument("--out", default="", help="write the rows to this JSON file")
    args = parser.parse_args()
    rows = when_links_speak(args.run, args.episodes, args.seed)
    for row in rows:
        after = ", ".join(f"{s['speaks']:.2f}" for s in row["since"])
        print(
            f"run {row['run']}: speaking {row['speaking']['speaks']:.3f}; first step "
            f"{row['first_step']['speaks']:.3f}; news {row['news']['speaks']:.3f} "
            f"(n={row['news']['n']}); 1..{SINCE - 1}, {SINCE}+ steps after: {after}"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"run": str(args.run), "episodes": args.episodes, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
