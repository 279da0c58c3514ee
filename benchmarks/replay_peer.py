"""A deployed team under a replaying peer (docs/deploy.md, "Who can stop the team"): episodes
changed, stale actions, rejoins, crashes and processes left.

Deploys a team (default: the one shipped with the package) with the faults given (by default
the drill's: ``--reorder 0.5``, 20% loss, one agent killed per episode) twice, or three times,
on the same draws: with the replaying peer (``Deploy.replay``, ``sparsecomm.deploy.replay``:
every datagram of every kind the team's processes send each other, captured on the host and
sent again at once, duplicated, reordered, late, to the wrong process, and old ones at random),
without it, and without it again (how much two deployments without any peer differ by timing
alone: a restarted agent rejoins at whichever step its start-up takes it to). Each episode of
the world's ``episodes.jsonl`` is compared on what the team did (:data:`OUTCOME`). Needs a
packet socket (Linux, root or ``CAP_NET_RAW``).

    python benchmarks/replay_peer.py --episodes 30 --out docs/results/deploy/replay_peer.json
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import tyro

from sparsecomm import provenance
from sparsecomm.deploy.args import Deploy
from sparsecomm.deploy.launcher import deploy
from sparsecomm.deploy.report import read_episodes

OUTCOME = ("success", "length", "group_reward", "payload_bits", "sim_wire_bits", "datagrams")
"""The fields of an episode record compared between deployments: what the team did and said."""
COUNTS = (
    "duplicates_dropped",
    "world_duplicates_dropped",
    "stale_dropped",
    "foreign_dropped",
    "garbage_dropped",
    "world_dropped",
    "hellos_answered",
    "hellos_ignored",
    "late_actions",
    "rejoins",
    "restarts",
    "kills",
    "missing_actions_per_step",
    "missing_messages_per_step",
    "success_rate",
    "episode_length",
    "wall_clock_s",
)
"""The figures of each deployment's row reported side by side."""


@dataclasses.dataclass
class Args:
    run: Path | None = None
    """The team (``sparsecomm deploy --run``); default: the shipped team."""
    episodes: int = 30
    """Episodes of each deployment."""
    loss: float = 0.2
    """``Deploy.loss``."""
    reorder: float = 0.5
    """``Deploy.reorder``."""
    kills_per_episode: int = 1
    """``Deploy.kills_per_episode``."""
    fault_seed: int = 0
    """``Deploy.fault_seed`` (the peer's draws too)."""
    again: bool = True
    """Also deploy a second time without the peer: the differences timing alone makes."""
    out: Path = Path("replay_peer.json")
    """Where the figures go."""
    work: Path = Path("runs/replay_peer")
    """Folder of the deployments."""


def different(a: list[dict], b: list[dict]) -> list[int]:
    """The episodes whose :data:`OUTCOME` differs between two deployments of the same draws."""
    return [
        e["episode"]
        for e, f in zip(a, b, strict=True)
        if any(e.get(n) != f.get(n) for n in OUTCOME)
    ]


TIMING = ("missing_actions", "rejoins_at")
"""The fields of an episode record that the timing of a kill decides (how many actions the
killed agent missed, at which step its successor's hello was answered)."""


def same_timing(a: list[dict], b: list[dict]) -> list[int]:
    """The episodes whose kills and rejoins (:data:`TIMING`) fell at the same steps in two
    deployments."""
    return [
        e["episode"] for e, f in zip(a, b, strict=True) if all(e.get(n) == f.get(n) for n in TIMING)
    ]


def left_behind(folder: Path) -> list[int]:
    """Process ids still running whose command line names ``folder`` (a deployment's)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if str(folder).encode() in cmdline and b"sparsecomm.deploy" in cmdline:
            found.append(int(entry.name))
    return found


def main(args: Args) -> dict:
    plays = [("replay", True), ("clean", False)] + ([("clean_again", False)] if args.again else [])
    rows, episodes, left = {}, {}, {}
    for name, replay in plays:
        out = (args.work / name).resolve()
        spec = Deploy(
            run=args.run,
            episodes=args.episodes,
            out=out,
            loss=args.loss,
            reorder=args.reorder,
            kills_per_episode=args.kills_per_episode,
            fault_seed=args.fault_seed,
            replay=replay,
        )
        start = time.monotonic()
        (row,) = deploy(spec)["runs"]
        row["command_wall_s"] = time.monotonic() - start
        time.sleep(1.0)
        rows[name], left[name] = row, left_behind(out)
        episodes[name] = read_episodes(out / "run_0")
    flags = f"--episodes {args.episodes} --loss {args.loss:g} --reorder {args.reorder:g} "
    flags += f"--kills-per-episode {args.kills_per_episode} --fault-seed {args.fault_seed}"
    result = {
        "command": f"python benchmarks/replay_peer.py {flags}",
        "machine": provenance.hardware(),
        "commit": provenance.git_commit(),
        "episodes": args.episodes,
        "replays": rows["replay"]["replays"],
        "different_episodes_replay_vs_clean": different(episodes["replay"], episodes["clean"]),
        "processes_left": left,
        "figures": {name: {n: row.get(n) for n in COUNTS} for name, row in rows.items()},
    }
    timed = same_timing(episodes["replay"], episodes["clean"])
    result["same_timing_replay_vs_clean"] = len(timed)
    result["different_among_same_timing"] = sorted(
        set(timed) & set(result["different_episodes_replay_vs_clean"])
    )
    if args.again:
        result["different_episodes_clean_vs_clean_again"] = different(
            episodes["clean"], episodes["clean_again"]
        )
        result["different_episodes_replay_vs_clean_again"] = different(
            episodes["replay"], episodes["clean_again"]
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
