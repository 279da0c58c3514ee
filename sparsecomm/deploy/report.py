"""A deployment's figures from the world's ``episodes.jsonl``: eval's metrics, bits per step
counted from the payload to the network, datagrams and losses per step, and 95% CIs over
episodes (``sparsecomm.stats``).

``python -m sparsecomm.deploy.report FOLDER`` prints them for a world's output folder (a
deployment started by hand, on separate hosts)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from sparsecomm.deploy import wire
from sparsecomm.deploy.world import SUMS
from sparsecomm.stats import bootstrap_ci

CI_METRICS = (
    "success_rate",
    "episode_length",
    "bits_per_step",
    "wire_bits_per_step",
    "network_bits_per_step",
)
"""The metrics given a 95% CI over episodes."""


def summarize(episodes: list[dict]) -> tuple[dict, dict]:
    """Eval's metrics of a deployment's episodes and their 95% CIs over episodes:
    ``(means, {metric: [low, high]})``. Bits and counts per step are ratios over all steps (as
    ``rollout.episode_metrics``; per step of the whole team), their CIs resample episodes:

    * ``bits_per_step``: payload bits (the paper's count); ``wire_bits_per_step``: the
      library's frame bits (``Sent.wire_bits``), as ``eval`` reports them;
      ``frame_bits_per_step``: 8 x the bytes ``channel.encode_sender`` wrote, once per
      speaking sender;
    * ``datagram_bits_per_step``: the frames the MSG datagrams due carry (one copy of its
      sender's frame per speaking link), as ``eval`` counts them; ``header_bits_per_step``:
      their headers (``wire.HEADER_BYTES``, 19: 11 of fields and the 8-byte MAC);
      ``mac_bits_per_step``: the MACs of every datagram really sent;
      ``network_bits_per_step``: what the fault layer really sent (lost datagrams not,
      duplicates and garbage yes), each with the ``wire.UDP_IP_BYTES`` of
      IPv4 and UDP;
    * ``datagrams_per_step`` (due) and ``network_datagrams_per_step`` (sent);
      ``speaking_links_per_step``; ``missing_messages_per_step``: frames a heard map promised
      that did not arrive by the deadline (losses; without a map, senders not heard);
    * ``map_bits_per_step``: the heard maps the world sent (world traffic, not in the network
      bits);
    * the totals of :data:`TOTALS`.

    A record lacking a field (an older world's) counts 0 for it."""
    col = {n: np.array([float(e.get(n, 0)) for e in episodes], np.float64) for n in _COUNTED}
    steps = col["length"]
    per_step = {
        "bits_per_step": col["payload_bits"],
        "wire_bits_per_step": col["sim_wire_bits"],
        "frame_bits_per_step": col["frame_bits"],
        "datagram_bits_per_step": 8
        * (col["datagram_bytes"] - wire.HEADER_BYTES * col["datagrams"]),
        "header_bits_per_step": 8 * wire.HEADER_BYTES * col["datagrams"],
        "mac_bits_per_step": 8 * wire.MAC_BYTES * col["sent_datagrams"],
        "network_bits_per_step": 8
        * (col["sent_bytes"] + wire.UDP_IP_BYTES * col["sent_datagrams"]),
        "datagrams_per_step": col["datagrams"],
        "network_datagrams_per_step": col["sent_datagrams"],
        "speaking_links_per_step": col["spoke"],
        "missing_messages_per_step": col["missing"],
        "missing_actions_per_step": col["missing_actions"],
        "map_bits_per_step": 8 * col["map_bytes"],
    }
    means = {
        "success_rate": float(col["success"].mean()),
        "episode_length": float(steps.mean()),
        "group_reward": float(col["group_reward"].mean()),
    }
    means.update({name: float(v.sum() / steps.sum()) for name, v in per_step.items()})
    means.update({name: int(col[field].sum()) for name, field in TOTALS.items()})
    cis = {}
    for name in CI_METRICS:
        if name in per_step:
            num = per_step[name]

            def ratio(idx, axis=-1, num=num):
                idx = idx.astype(np.int64)
                return num[idx].sum(axis) / steps[idx].sum(axis)

            values = np.arange(len(steps), dtype=np.float64)
            if np.all(num == num[0]) and np.all(steps == steps[0]):
                low = high = means[name]
            else:
                _, low, high = bootstrap_ci(values, statistic=ratio)
        else:
            x = col["success"] if name == "success_rate" else steps
            _, low, high = bootstrap_ci(x)
        cis[name] = [low, high]
    return means, cis


TOTALS = {
    "duplicates_dropped": "dup",
    "stale_dropped": "stale",
    "foreign_dropped": "foreign",
    "garbage_dropped": "bad",
    "world_dropped": "world_bad",
    "world_duplicates_dropped": "world_dup",
    "late_actions": "late_actions",
    "hellos_answered": "hellos",
    "hellos_ignored": "hellos_ignored",
    "rejoins": "rejoined",
    "steps_without_map": "no_map",
}
"""The totals over a deployment's episodes, by name in the report and field of the episode
records (``world.SUMS``): the datagrams the agents dropped as copies of what they hold
(``duplicates_dropped``), for a step already acted on (``stale_dropped``), for another process
of the agent (``foreign_dropped``: a predecessor's nonce) or as forged, garbage or not
addressed to them (``garbage_dropped``); those the world dropped (``world_dropped``) and the
copies of actions it had counted (``world_duplicates_dropped``); actions counted after their
step was played (``late_actions``); hellos answered (``hellos_answered``: restarted agents
told where the world is) and never answered (``hellos_ignored``: a nonce already seen);
restarted agents that rejoined; steps waited without a heard map."""
_COUNTED = (
    "success",
    "length",
    "group_reward",
    "missing_actions",
    "hellos",
    "hellos_ignored",
    *SUMS,
)
"""The fields of an episode record that :func:`summarize` reads."""


def read_episodes(folder: str | Path) -> list[dict]:
    """The episode records the world wrote to ``folder/episodes.jsonl``."""
    lines = (Path(folder) / "episodes.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m sparsecomm.deploy.report WORLD_OUT_FOLDER", file=sys.stderr)
        return 2
    means, cis = summarize(read_episodes(argv[0]))
    print(json.dumps({**means, "ci": cis}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
