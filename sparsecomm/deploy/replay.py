"""A replaying peer: the team's own datagrams, captured on the host and sent again
(docs/deploy.md, "Who can stop the team").

The peer holds no secret and forges nothing: it captures every datagram the team's processes
send each other (the world, each agent, the launcher's monitor) with a packet socket on the host
(Linux ``AF_PACKET``: root or ``CAP_NET_RAW``), and from :meth:`Replay.go` sends copies of each
one it captures, in every way a network or an attacker could (:data:`MODES`):

``once``        a copy at once, to its recipient;
``duplicated``  :data:`DUPLICATES` more copies at once;
``reordered``   a copy held back ``U(0, REORDER_S)`` seconds, overtaken by later datagrams;
``late``        a copy held back ``U(LATE_S)`` seconds: steps, and often episodes, later;
``wrong``       a copy to another process of the team than its recipient;
``old``         besides, :data:`OLD_PER_S` copies per second of datagrams drawn at random from
                all captured so far, the start-up hellos and every earlier episode's included.

Every kind is copied: hellos, observations, actions, frames, the world's ``step`` and ``done``.
The peer's own copies are not captured again (they come from its own port). ``sparsecomm deploy
--replay`` points it at a deployment on one host (``launcher.play(peer=...)``), as
``tests/test_deploy.py`` and ``benchmarks/replay_peer.py`` do.
"""

from __future__ import annotations

import contextlib
import heapq
import json
import os
import select
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np

from sparsecomm.deploy import wire
from sparsecomm.errors import RunError

MODES = ("once", "duplicated", "reordered", "late", "wrong", "old")
"""How the peer sends its copies (module docstring)."""
DUPLICATES = 2
"""Extra copies of each datagram sent at once (``duplicated``)."""
REORDER_S = 0.02
"""Longest hold of a ``reordered`` copy, seconds (as ``Deploy.reorder_delay``)."""
LATE_S = (0.2, 3.0)
"""Range of the hold of a ``late`` copy, seconds: a step of a trained team on one host is a few
milliseconds, the message deadline 0.2 s."""
OLD_PER_S = 200.0
"""Copies per second of datagrams drawn from everything captured so far (``old``)."""
HISTORY = 100_000
"""Captured datagrams kept for ``old`` copies (the oldest are forgotten first)."""
NICE = 19
"""The peer's process runs at the lowest CPU priority: on one host it shares the team's cores,
where an attacker elsewhere would not; the copies still cost each receiver its HMAC."""
ETH_P_IP = 0x0800
PACKET_OUTGOING = 4
"""``sll_pkttype`` of a packet this host sends: on loopback every packet is seen twice, once
going out and once coming in; only the second is kept."""


def capture_socket() -> socket.socket:
    """A packet socket receiving every IPv4 packet of this host, link header removed. Raises
    ``OSError`` where the platform or the user may not open one (not Linux; not root and
    without ``CAP_NET_RAW``)."""
    if not hasattr(socket, "AF_PACKET"):
        raise OSError("packet sockets (AF_PACKET) exist on Linux only")
    return socket.socket(socket.AF_PACKET, socket.SOCK_DGRAM, socket.htons(ETH_P_IP))


def can_capture() -> str:
    """``""`` when this process may capture packets, else why not."""
    try:
        capture_socket().close()
    except OSError as e:
        return str(e.strerror or e)
    return ""


def udp_of(packet: bytes):
    """``((source ip, port), (destination ip, port), payload)`` of an IPv4 packet carrying a
    whole UDP datagram, else ``None`` (never raises)."""
    if len(packet) < 28 or packet[0] >> 4 != 4 or packet[9] != 17:
        return None
    ihl = 4 * (packet[0] & 15)
    flags_offset = struct.unpack_from("!H", packet, 6)[0]
    if ihl < 20 or flags_offset & 0x3FFF or len(packet) < ihl + 8:  # a fragment
        return None
    src = socket.inet_ntoa(packet[12:16])
    dst = socket.inet_ntoa(packet[16:20])
    sport, dport, length = struct.unpack_from("!HHH", packet, ihl)
    if length < 8 or len(packet) < ihl + length:
        return None
    return (src, sport), (dst, dport), bytes(packet[ihl + 8 : ihl + length])


class Replay:
    """The replaying peer (module docstring) in a process of its own (``python -m
    sparsecomm.deploy.replay``), aimed at ``targets`` (``{name: (address, recipient id)}``,
    as ``launcher.play`` gives a peer): it captures from construction and replays from
    :meth:`go` until :meth:`stop`. Raises ``RunError`` when it cannot capture."""

    def __init__(self, targets: dict, *, seed: int = 0):
        spec = [f"{host}:{port}" for (host, port), _ in targets.values()]
        cmd = [sys.executable, "-m", "sparsecomm.deploy.replay", str(seed), *spec]
        self.process = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, start_new_session=True
        )
        line = self.process.stdout.readline().strip()
        if line != "ready":
            self.process.kill()
            self.process.wait()
            raise RunError(f"the replaying peer (Deploy.replay) did not start: {line}")

    def go(self) -> None:
        """Start sending copies."""
        self._say("go")

    def stop(self) -> dict:
        """Stop; ``{"captured": {kind: n}, "sent": {mode: n}}``."""
        self._say("stop")
        try:
            out, _ = self.process.communicate(timeout=10)
            return json.loads(out.strip().splitlines()[-1])
        except (subprocess.TimeoutExpired, ValueError, IndexError):
            self.process.kill()
            self.process.wait()
            raise RunError("the replaying peer did not stop in 10 s") from None

    def _say(self, word: str) -> None:
        try:
            self.process.stdin.write(word + "\n")
            self.process.stdin.flush()
        except (BrokenPipeError, ValueError):
            pass


class _Peer:
    """The peer's loop: capture, schedule copies, send them when due."""

    def __init__(self, seed: int, team: list[tuple[str, int]]):
        self.rng = np.random.default_rng([seed, 7919])
        self.team = team
        self.members = set(team)
        self.capture = capture_socket()
        self.capture.setblocking(False)
        try:
            self.capture.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        except OSError:
            pass
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.heap: list = []
        self.n = 0
        self.history: list[tuple[bytes, tuple[str, int]]] = []
        self.captured = {name: 0 for name in (*wire.KINDS.values(), "other")}
        self.sent = dict.fromkeys(MODES, 0)
        self.replaying = False

    def _later(self, delay: float, data: bytes, address, mode: str) -> None:
        self.n += 1
        heapq.heappush(self.heap, (time.monotonic() + delay, self.n, data, address, mode))

    def _captured(self, packet: bytes) -> None:
        udp = udp_of(packet)
        if udp is None or udp[0] not in self.members or udp[1] not in self.members:
            return  # not the team's (the peer's own copies come from its own port)
        _, dst, data = udp
        kind = wire.KINDS.get(data[2] & 15, "other") if len(data) > 2 else "other"
        self.captured[kind] += 1
        if len(self.history) >= HISTORY:
            self.history[int(self.rng.integers(len(self.history)))] = (data, dst)
        else:
            self.history.append((data, dst))
        if not self.replaying:
            return
        rng = self.rng
        self._later(0.0, data, dst, "once")
        for _ in range(DUPLICATES):
            self._later(0.0, data, dst, "duplicated")
        self._later(float(rng.uniform(0, REORDER_S)), data, dst, "reordered")
        self._later(float(rng.uniform(*LATE_S)), data, dst, "late")
        others = [m for m in self.team if m != dst]
        self._later(0.0, data, others[int(rng.integers(len(others)))], "wrong")

    def _send_due(self) -> float:
        """Send what is due; seconds until the next copy."""
        now = time.monotonic()
        while self.heap and self.heap[0][0] <= now:
            _, _, data, address, mode = heapq.heappop(self.heap)
            try:
                self.out.sendto(data, address)
            except OSError:  # nobody listening there now, or a full buffer
                pass
            self.sent[mode] += 1
        return self.heap[0][0] - now if self.heap else 0.05

    def run(self, stop: threading.Event, go: threading.Event) -> None:
        next_old = None
        while not stop.is_set():
            if go.is_set() and not self.replaying:
                self.replaying, next_old = True, time.monotonic()
            wait = self._send_due()
            if self.replaying:
                now = time.monotonic()
                while next_old <= now and self.history:  # old copies, at their rate
                    data, dst = self.history[int(self.rng.integers(len(self.history)))]
                    self._later(0.0, data, dst, "old")
                    next_old += 1.0 / OLD_PER_S
                wait = min(wait, max(next_old - now, 0.0))
            ready, _, _ = select.select([self.capture], [], [], min(max(wait, 0.0), 0.05))
            for _ in range(256):  # drain what has arrived
                if not ready:
                    break
                try:
                    packet, where = self.capture.recvfrom(wire.MAX_DATAGRAM + 60)
                except BlockingIOError:
                    break
                if where[2] != PACKET_OUTGOING:
                    self._captured(packet)
                ready, _, _ = select.select([self.capture], [], [], 0)


def main(argv: list[str] | None = None) -> int:
    """The peer's process: ``SEED host:port ...`` (the team's addresses); says ``ready`` once it
    captures (or why it cannot, and exits 2), replays from the line ``go`` on stdin to the line
    ``stop`` (or the end of stdin), then prints what it captured and sent as JSON."""
    argv = sys.argv[1:] if argv is None else argv
    seed = int(argv[0])
    with contextlib.suppress(OSError, AttributeError):
        os.nice(NICE)  # an attacker elsewhere would not share the team's cores
    team = []
    for text in argv[1:]:
        host, port = wire.parse_address(text, "address")
        team.append((socket.gethostbyname(host), port))
    try:
        peer = _Peer(seed, team)
    except OSError as e:
        print(f"cannot capture packets: {e.strerror or e}", flush=True)
        return 2
    stop, go = threading.Event(), threading.Event()

    def commands():
        for line in sys.stdin:
            if line.strip() == "go":
                go.set()
            elif line.strip() == "stop":
                break
        stop.set()

    threading.Thread(target=commands, daemon=True).start()
    print("ready", flush=True)
    peer.run(stop, go)
    peer.capture.close()
    peer.out.close()
    print(json.dumps({"captured": peer.captured, "sent": peer.sent}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
