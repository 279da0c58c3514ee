"""A deployed team under a flood of forged datagrams (docs/deploy.md): crashes, accepted forgeries,
hangs.

Deploys a team (default: the one shipped with the package) with a hostile peer that does not
hold the team's secret (``Deploy.forgeries_per_second``, ``sparsecomm.deploy.hostile``: random
bytes, random MACs, datagrams of every kind sealed under another secret, version-1 datagrams
with the JSON payloads that once crashed the world, cut-short and oversized ones), sent
round-robin to the world, every agent and the launcher, from the team's first step to its last.
Then, in the same run, the same episodes without the peer. Records per target the forgeries
sent and, from the processes' own counts, those they read and dropped; crashes (restarts, a
process's exit status), accepted forgeries (episodes that differ from the simulation of the
same draws: a forgery accepted as an action, an observation or a frame changes them) and hangs
(missing actions, the wall-clock beside the run without the peer).

    python benchmarks/hostile_flood.py --episodes 4000 --rate 30000 \
        --out docs/results/deploy/hostile_flood.json

A forgery the kernel drops because a receive buffer is full is sent but never read: the counts
of what each process read are the processes', not the peer's.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import tyro

from sparsecomm.deploy.args import Deploy
from sparsecomm.deploy.launcher import deploy


@dataclasses.dataclass
class Args:
    run: Path | None = None
    """The team (``sparsecomm deploy --run``); default: the shipped team."""
    episodes: int = 1500
    """Episodes of each deployment (the flood lasts as long as the play)."""
    rate: float = 20_000.0
    """Forged datagrams per second, over all targets (``Deploy.forgeries_per_second``)."""
    baseline: bool = True
    """Also play the same episodes without the peer (the wall-clock and episodes beside)."""
    out: Path = Path("hostile_flood.json")
    """Where the figures go."""
    work: Path = Path("runs/hostile_flood")
    """Folder of the deployments."""


def main(args: Args) -> dict:
    rows = {}
    for name, rate in (("flood", args.rate), ("clean", 0.0)):
        if name == "clean" and not args.baseline:
            continue
        spec = Deploy(
            run=args.run, episodes=args.episodes, out=args.work / name, forgeries_per_second=rate
        )
        start = time.monotonic()
        (row,) = deploy(spec)["runs"]
        row["command_wall_s"] = time.monotonic() - start
        rows[name] = row
    flood = rows["flood"]
    sim = flood["simulation"]
    sent = flood["forgeries_sent"]
    result = {
        "command": "python benchmarks/hostile_flood.py "
        f"--episodes {args.episodes} --rate {args.rate:g}",
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}",
        "episodes": args.episodes,
        "rate_per_s": args.rate,
        "forgeries_sent": sent,
        "forgeries_sent_min_per_target": min(sent.values()),
        "dropped_by_agents": flood["garbage_dropped"],
        "dropped_by_world": flood["world_dropped"],
        "crashes": flood["restarts"],
        "different_episodes": sim["different_episodes"],
        "identical_episodes": sim["identical_episodes"],
        "missing_actions_per_step": flood["missing_actions_per_step"],
        "missing_messages_per_step": flood["missing_messages_per_step"],
        "wall_s": {name: row["wall_clock_s"] for name, row in rows.items()},
        "success_rate": {name: row["success_rate"] for name, row in rows.items()},
    }
    if "clean" in rows:
        result["identical_episodes_clean"] = rows["clean"]["simulation"]["identical_episodes"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
