"""The world as its own process: ``python -m sparsecomm.deploy.world --team T ...``.

The simulator stands in for the world: it waits for every agent's hello (``Deadlines.startup``),
then plays the batch's episodes one after another with the draws of ``sparsecomm eval``
(``core.episode_draws``). At each step it sends every agent its observation, waits for every
agent's action (``Deadlines.action`` at most; an agent that says hello meanwhile with a nonce
never seen, restarted, is sent the observation again, once, and the wait is extended to a whole
``Deadlines.action`` from then, so that its first action is not late), takes action 0 (no force)
for an agent still silent, and steps.

Hellos and nonces. A hello carries its process's nonce (``wire.parse_hello``). The world keeps
every nonce it has seen; a hello with a new one makes it the agent's current nonce (the process
that sent it replaced the one before), a hello with one already seen (the agent repeating itself
before an answer came, or a copy) is not answered and is counted (``hellos_ignored``). Every
observation carries its agent's current nonce, so only the latest process acts on it.
Each agent's action datagram also says what the agent sent and heard that step; the world adds
them up per link and per step (``links.csv``), per sender and step (``frames.csv``) and per
episode (``episodes.jsonl``), and at the end tells every agent ``bye``. With ``--monitor`` it
reports each step to the launcher, which may kill agents on schedule
(``Deploy.kills_per_episode``).

The heard map. Every observation of step ``t`` carries, after the floats, the map of which of
the agent's senders spoke to it at step ``t - 1`` (:func:`heard_maps`, ``wire.pack_obs``), from
the senders' own reports: the runtime's stand-in for a link-layer acknowledgement, so that a
receiver waits only for frames that were sent and can call a missing one a loss. A sender whose
report of ``t - 1`` the world lacks (dead, or its action late) is marked as speaking: its
receivers wait the deadline and count a loss if nothing came. The map is world traffic, not
counted in the network bits (``map_bytes`` in the episode records).

Every datagram is sealed with the team's secret (``wire.Auth``). The world drops, before reading
its payload, any datagram that fails its MAC, is not addressed to the world, comes from no
agent of the team, is not an action or hello, or whose report is not the exact layout of
``wire.Report``; an action of another episode or of a later step is dropped too. Drops are
counted per episode (``world_bad``). When every episode is played it tells the launcher
(``done``) before its ``bye``s, so that an agent exiting earlier is known to be a failure.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from sparsecomm.cmdline import refuse_empty_paths
from sparsecomm.deploy import wire
from sparsecomm.deploy.faults import Deadlines

LINK_FIELDS = (
    "episode",
    "step",
    "sender",
    "recipient",
    "payload_bits",
    "spoke",
    "datagram_bytes",
    "sent_bytes",
    "sent_datagrams",
)
"""Columns of ``links.csv``: one row per link and step, as the sender reported it.
``payload_bits``: the library's count of the symbols sent (``channel.transmit``); ``spoke``: 1
when the link spoke (a copy of the sender's frame was due to the recipient), 0 when silent;
``datagram_bytes``: the datagram due on the link (header + frame; 0: none); ``sent_bytes`` /
``sent_datagrams``: what the fault layer really put on the network for it (0 when lost or
silent; duplicates and garbage included)."""
FRAME_FIELDS = ("episode", "step", "sender", "sim_wire_bits", "frame_bits", "copies")
"""Columns of ``frames.csv``: one row per sender and step. ``sim_wire_bits``: the library's
count of the sender's frame (``Sent.wire_bits`` summed over its links); ``frame_bits``: 8 x the
bytes ``channel.encode_sender`` wrote (0: a silent sender); ``copies``: the datagrams it was
due to send, one per speaking link."""
SUMS = (
    "payload_bits",
    "sim_wire_bits",
    "frame_bits",
    "spoke",
    "datagrams",
    "datagram_bytes",
    "sent_bytes",
    "sent_datagrams",
    "missing",
    "dup",
    "stale",
    "foreign",
    "bad",
    "no_map",
    "rejoined",
    "map_bytes",
    "world_bad",
    "world_dup",
    "late_actions",
)
"""The counts of an episode record (``episodes.jsonl``), summed over its steps: the links'
(``LINK_FIELDS``) and frames' counts, ``datagrams`` (MSG datagrams due, before faults),
``missing`` (frames a map promised that did not arrive: losses), the datagrams the agents
dropped (``dup``, ``stale``, ``foreign``: observations for another process of the agent,
``bad``: garbage, forgeries and datagrams not expected), those the world dropped
(``world_bad``: failing the MAC, malformed, or of another episode or a step not yet played;
``world_dup``: actions of a step already counted, copies and replays), ``late_actions``
(actions counted after their step was played), ``no_map`` (steps an agent waited without a
map), ``rejoined`` (restarted agents) and ``map_bytes`` (the heard maps the world sent)."""


def heard_maps(spoke: dict, num_agents: int) -> list[list[bool]]:
    """Each agent's heard map: ``maps[j][s]`` is True when agent ``j``'s ``s``-th sender
    (``channel.others``) spoke to it, read from ``spoke[i]``, sender ``i``'s report (one flag
    per recipient slot); a sender without a report (or with a malformed one) counts as
    speaking (its receivers wait, and call a missing frame a loss)."""
    from sparsecomm.deploy.core import frame_slot

    k = num_agents
    maps = []
    for j in range(k):
        row = []
        for i in (i for i in range(k) if i != j):
            flags = spoke.get(i)
            try:
                row.append(bool(flags[frame_slot(i, j)]))
            except (IndexError, TypeError, KeyError):
                row.append(True)
        maps.append(row)
    return maps


@dataclasses.dataclass
class WorldArgs:
    """The world process of a deployed team."""

    team: Path
    """Folder of the exported team (its config: the task and the channel)."""
    agents: tuple[str, ...]
    """Every agent's address (host:port), in id order."""
    seed: int
    """The batch seed (the agents' ``--seed``)."""
    episodes: int
    """Episodes to play (the agents' ``--episodes``)."""
    out: Path
    """Folder for ``episodes.jsonl`` and ``links.csv``."""
    secret_file: Path
    """File of the team's secret (hex; only its owner may read it: ``wire.read_secret``), the
    agents' ``--secret-file``."""
    listen: str = "127.0.0.1:9000"
    """Address to bind (host:port), the agents' ``--world``. Default: loopback port 9000."""
    monitor: str = ""
    """The launcher's address (host:port), told of every step; empty: nobody."""
    deadlines: Deadlines = Deadlines()
    """How long each wait lasts."""
    jax_cache: str = ""
    """Folder of JAX's persistent compilation cache; empty: none."""

    def __post_init__(self):
        for name, low in (("seed", 0), ("episodes", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"WorldArgs.{name} must be an integer >= {low}, got {value!r}")
        for text in self.agents:
            wire.parse_address(text, "WorldArgs.agents")
        wire.parse_address(self.listen, "WorldArgs.listen")
        if self.monitor:
            wire.parse_address(self.monitor, "WorldArgs.monitor")


class World:
    def __init__(self, args: WorldArgs):
        import jax

        from sparsecomm.deploy import core

        self.auth = wire.Auth(wire.read_secret(args.secret_file, "WorldArgs.secret_file"))
        core.use_compile_cache(args.jax_cache)
        loaded = core.read_team(args.team, weights=False)
        self.env = loaded.env
        k = self.env.num_agents
        if len(args.agents) != k:
            raise ValueError(f"WorldArgs.agents must list the team's {k} agents, got {args.agents}")
        self.args, self.k = args, k
        self.agents = [wire.parse_address(a) for a in args.agents]
        self.monitor = wire.parse_address(args.monitor) if args.monitor else None
        self.steps = self.env.max_steps
        key = core.batch_key(args.seed)
        self.reset_keys, self.env_keys = core.world_draws(key, args.episodes, self.steps)
        self.reset, self.step = core.world_fns(self.env)
        obs, state = self.reset(self.reset_keys[0])  # compile before listening
        self.step(self.env_keys[0, 0], state, jax.numpy.zeros(k, jax.numpy.int32))
        self.sock = wire.udp_socket(wire.parse_address(args.listen))
        args.out.mkdir(parents=True, exist_ok=True)
        self.nonces: dict[int, bytes] = {}  # each agent's current process's nonce
        self.seen: set[bytes] = set()  # every nonce ever answered
        self.dropped = 0  # datagrams dropped since the last episode record

    def _send(self, data: bytes, address) -> None:
        try:
            self.sock.sendto(data, address)
        except OSError:  # nobody listening (a dead agent): lost, as on a network
            pass

    def _recv(self, until: float):
        """The next datagram for the world by ``until``: a hello, or an action whose
        ``payload`` is its parsed ``wire.Report``; ``False`` for one dropped (counted), ``None``
        at the deadline."""
        wait = until - time.monotonic()
        if wait <= 0:
            return None
        self.sock.settimeout(wait)
        try:
            data, _ = self.sock.recvfrom(wire.MAX_DATAGRAM)
        except (TimeoutError, BlockingIOError):
            return None
        except ConnectionError:
            return False
        dg = self.auth.parse(data)
        if dg is None or dg.recipient != wire.WORLD or dg.sender >= self.k:
            self.dropped += 1
            return False
        if dg.kind == wire.HELLO and wire.parse_hello(dg.payload) is not None:
            return dg
        if dg.kind == wire.ACT and dg.episode < self.args.episodes and dg.step < self.steps:
            report = wire.parse_report(dg.payload, self.k - 1)
            if report is not None:
                return dg._replace(payload=report)
        self.dropped += 1
        return False

    def _greet(self) -> int:
        """Wait for every agent's hello; 0, or 2 when one never came."""
        until = time.monotonic() + self.args.deadlines.startup
        while len(self.nonces) < self.k:
            dg = self._recv(until)
            if dg is None:
                missing = sorted(set(range(self.k)) - set(self.nonces))
                print(f"world: agents {missing} never said hello", file=sys.stderr)
                return 2
            if dg and dg.kind == wire.HELLO:
                self._hello(dg)
        self.dropped = 0  # repeated hellos while the others start are not the first episode's
        return 0

    def _hello(self, dg: wire.Datagram) -> bool:
        """Note a hello; True when its nonce is new (the agent's process is new: answer it
        once), False for a nonce already seen (a repeat or a copy: never answered)."""
        nonce = wire.parse_hello(dg.payload)
        if nonce in self.seen:
            return False
        self.seen.add(nonce)
        self.nonces[dg.sender] = nonce
        return True

    def run(self) -> int:
        if self._greet():
            return 2
        out = self.args.out
        with (
            open(out / "episodes.jsonl", "w") as eps,
            open(out / "links.csv", "w") as lf,
            open(out / "frames.csv", "w") as ff,
        ):
            tables = csv.writer(lf), csv.writer(ff)
            tables[0].writerow(LINK_FIELDS)
            tables[1].writerow(FRAME_FIELDS)
            for b in range(self.args.episodes):
                record = self._episode(b, tables)
                eps.write(json.dumps(record) + "\n")
                eps.flush()
        if self.monitor is not None:
            done = self.auth.pack(wire.DONE, wire.WORLD, wire.WORLD, self.args.episodes - 1, 0)
            self._send(done, self.monitor)
        for _ in range(3):  # datagrams may be lost: say it thrice
            for i, address in enumerate(self.agents):
                self._send(self.auth.pack(wire.BYE, wire.WORLD, i, 0, 0), address)
        return 0

    def _episode(self, b: int, tables) -> dict:
        import jax.numpy as jnp

        obs, state = self.reset(self.reset_keys[b])
        k = self.k
        rec = {
            "episode": b,
            "length": 0,
            "success": False,
            "group_reward": 0.0,
            "missing_actions": 0,
            "hellos": 0,
            "hellos_ignored": 0,
            "rejoins_at": [],
        }
        sums = dict.fromkeys(SUMS, 0)
        per_link, counted = {}, set()
        spoke = {i: [False] * (k - 1) for i in range(k)}  # who spoke at t - 1 (none at t = 0)
        for t in range(self.steps):
            if bool(state.done):
                break
            obs_np = np.asarray(obs, ">f4")
            maps = heard_maps(spoke, k)
            packets = [self._observation(i, b, t, obs_np[i], maps[i]) for i in range(k)]
            sums["map_bytes"] += k * wire.map_bytes(k - 1)
            spoke = {}
            for i in range(k):
                self._send(packets[i], self.agents[i])
            if self.monitor is not None:
                step = self.auth.pack(wire.STEP, wire.WORLD, wire.WORLD, b, t)
                self._send(step, self.monitor)
            actions = np.zeros(k, np.int32)
            answered = set()
            until = time.monotonic() + self.args.deadlines.action
            while len(answered) < k:
                dg = self._recv(until)
                if dg is None:
                    break
                if not dg:
                    continue
                if dg.kind == wire.HELLO:
                    if self._hello(dg):  # a restarted agent: tell it where we are, once,
                        rec["hellos"] += 1  # and give it the whole deadline to act on it
                        rec["rejoins_at"].append([dg.sender, t])
                        i = dg.sender
                        packets[i] = self._observation(i, b, t, obs_np[i], maps[i])
                        self._send(packets[i], self.agents[i])
                        until = max(until, time.monotonic() + self.args.deadlines.action)
                    else:
                        rec["hellos_ignored"] += 1
                    continue
                if dg.episode != b or dg.step > t:  # another episode's, or a step not yet played
                    self.dropped += 1
                    continue
                if (dg.sender, dg.step) in counted:  # a copy of an action already counted
                    sums["world_dup"] += 1
                    continue
                report, late = dg.payload, dg.step < t
                if late:
                    sums["late_actions"] += 1
                else:
                    answered.add(dg.sender)
                    actions[dg.sender] = report.action % self.env.num_actions
                    spoke[dg.sender] = report.spoke
                counted.add((dg.sender, dg.step))
                self._count(report, b, dg.step, dg.sender, sums, per_link, tables)
            rec["missing_actions"] += k - len(answered)
            obs, state, rewards, _, info = self.step(
                self.env_keys[t, b], state, jnp.asarray(actions)
            )
            rec["length"] += 1
            rec["success"] |= bool(info["success"])
            rec["group_reward"] += float(np.asarray(rewards).sum())
        sums["world_bad"], self.dropped = self.dropped, 0
        rec.update(sums)
        rec["links"] = per_link
        return rec

    def _observation(self, i: int, b: int, t: int, obs, heard) -> bytes:
        """Agent ``i``'s observation datagram of step ``t`` of episode ``b``, for its current
        process (its nonce first)."""
        payload = wire.pack_obs(self.nonces[i], obs, heard)
        return self.auth.pack(wire.OBS, wire.WORLD, i, b, t, payload)

    def _count(self, report: wire.Report, b, t, sender, sums, per_link, tables) -> None:
        """Add one agent's report of step ``t`` (what it sent and heard) to the episode."""
        from sparsecomm import channel

        recipients = channel.others(self.k)[sender]
        copies = 0
        for r, j in enumerate(recipients):
            row = {
                "payload_bits": report.payload[r],
                "spoke": report.spoke[r],
                "datagram_bytes": report.datagram[r],
                "sent_bytes": report.sent[r],
                "sent_datagrams": report.sent_n[r],
            }
            tables[0].writerow([b, t, sender, int(j), *row.values()])
            link = per_link.setdefault(f"{sender}->{int(j)}", dict.fromkeys(row, 0))
            for name, value in row.items():
                link[name] += value
                sums[name] += value
            copies += row["datagram_bytes"] > 0
        frame = {"sim_wire_bits": report.sim_wire, "frame_bits": report.frame}
        tables[1].writerow([b, t, sender, *frame.values(), copies])
        for name, value in frame.items():
            sums[name] += value
        sums["datagrams"] += copies
        for name in ("missing", "dup", "stale", "foreign", "bad", "no_map", "rejoined"):
            sums[name] += int(getattr(report, name))


def main(argv: list[str] | None = None) -> int:
    import tyro

    wire.die_with_parent()
    argv = sys.argv[1:] if argv is None else argv
    try:
        refuse_empty_paths(WorldArgs, argv)  # the parser would read '' as the current folder
        args = tyro.cli(WorldArgs, args=argv)
        world = World(args)
    except ValueError as e:
        print(f"sparsecomm.deploy.world: error: {e}", file=sys.stderr)
        return 2
    try:
        return world.run()
    except KeyboardInterrupt:
        return 130
    finally:
        world.sock.close()


if __name__ == "__main__":
    sys.exit(main())
