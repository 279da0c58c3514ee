"""A hostile peer: forged datagrams of every kind, aimed at a deployed team (docs/deploy.md).

The peer does not hold the team's secret. It knows everything else: the format
(``sparsecomm.deploy.wire``), the team's size, the batch's episodes and steps, every process's
address. :func:`forgeries` makes the datagrams it sends, in equal shares of six families:

1. random bytes (0-96 of them);
2. the runtime's header with plausible fields (any kind, a sender of the team or the world, the
   target as recipient, an episode and step of the batch), a payload of the kind's exact size,
   and a random MAC;
3. the same, sealed under another secret (a forged ``bye``, ``hello``, observation, action,
   frame, ``step`` or ``done``: everything an agent or the world could send);
4. version-1 datagrams (a CRC-16 where the MAC is) with the JSON payloads that crashed the world
   before the MAC (``null``, ``[]``, ``{"a": 1e999}``) and empty ones (a forged ``bye``);
5. a datagram cut short (fewer bytes than a header and MAC);
6. an oversized one (a plausible header, then 1-8 KB).

:class:`Flood` sends them from a process of its own to a list of addresses, round-robin, at a
given rate, until stopped. ``sparsecomm deploy --forgeries-per-second`` points it at every
process of a deployment (``launcher.play(peer=...)``), as ``tests/test_deploy.py`` and
``benchmarks/hostile_flood.py`` do.
"""

from __future__ import annotations

import binascii
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

from sparsecomm.deploy import wire
from sparsecomm.errors import RunError

FAMILIES = ("random", "random_mac", "stranger", "version_1", "short", "oversized")
"""The families of :func:`forgeries`, in the order they take turns."""
_V1_PAYLOADS = (b"null", b"[]", b'{"a": 1e999}', b'{"a": "x", "spoke": null}', b"")


def forgeries(
    seed: int, num_agents: int, episodes: int, steps: int, obs_dim: int, recipient: int
) -> Iterator[bytes]:
    """An endless generator of forged datagrams for the process ``recipient`` (an agent's id,
    or ``wire.WORLD``) of a team of ``num_agents`` playing ``episodes`` of ``steps`` steps
    (module docstring); datagram ``n`` is of family ``FAMILIES[n % 6]``."""
    rng = np.random.default_rng([seed, recipient, 104729])
    stranger = wire.Auth(rng.bytes(wire.SECRET_BYTES))
    k = num_agents
    sizes = {
        wire.MSG: lambda: int(rng.integers(1, 40)),
        wire.OBS: lambda: wire.NONCE_BYTES + 4 * obs_dim + wire.map_bytes(k - 1),
        wire.ACT: lambda: wire.report_bytes(k - 1),
        wire.HELLO: lambda: wire.HELLO_BYTES,
    }
    kinds = list(wire.KINDS)
    n = 0
    while True:
        family = FAMILIES[n % len(FAMILIES)]
        n += 1
        if family == "random":
            yield rng.bytes(int(rng.integers(0, 97)))
            continue
        kind = int(rng.choice(kinds))
        sender = int(rng.choice([*range(k), wire.WORLD]))
        episode, step = int(rng.integers(0, episodes)), int(rng.integers(0, steps))
        payload = rng.bytes(sizes.get(kind, lambda: 0)())
        if family == "stranger":
            yield stranger.pack(kind, sender, recipient, episode, step, payload)
        elif family == "random_mac":
            head = wire.FIELDS.pack(
                wire.MAGIC, wire.VERSION << 4 | kind, sender, recipient, episode, step
            )
            yield head + rng.bytes(wire.MAC_BYTES) + payload
        elif family == "version_1":
            body = _V1_PAYLOADS[int(rng.integers(0, len(_V1_PAYLOADS)))]
            head = wire.FIELDS.pack(wire.MAGIC, 1 << 4 | kind, sender, recipient, episode, step)
            crc = binascii.crc_hqx(body, binascii.crc_hqx(head, 0xFFFF))
            yield head + crc.to_bytes(2, "big") + body
        elif family == "short":
            sealed = stranger.pack(kind, sender, recipient, episode, step, payload)
            yield sealed[: int(rng.integers(0, wire.HEADER_BYTES))]
        else:
            sealed = stranger.pack(kind, sender, recipient, episode, step)
            yield sealed + rng.bytes(int(rng.integers(1024, 8193)))


class Flood:
    """Forged datagrams (:func:`forgeries`) sent by a process of its own (``python -m
    sparsecomm.deploy.hostile``: the peer is not one of the team's) to ``targets`` (``{name:
    (address, recipient id)}``), one target after another, ``rate`` datagrams per second in all
    (0 or ``inf``: as fast as it can), from :meth:`go` until :meth:`stop`. Each target gets a
    pool of ``pool`` distinct forgeries, drawn once and sent over and over (drawing each anew
    would cost the peer more time than the team spends refusing it). The constructor returns
    once the pools are drawn."""

    def __init__(
        self,
        targets: dict,
        *,
        num_agents: int,
        episodes: int,
        steps: int,
        obs_dim: int,
        rate: float = 0.0,
        seed: int = 0,
        pool: int = 4096,
    ):
        self.names = list(targets)
        spec = [f"{host}:{port}:{who}" for (host, port), who in targets.values()]
        shape = [num_agents, episodes, steps, obs_dim, rate, seed, pool]
        cmd = [sys.executable, "-m", "sparsecomm.deploy.hostile", *map(str, shape), *spec]
        self.process = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, start_new_session=True
        )
        if self.process.stdout.readline().strip() != "ready":
            self.process.kill()
            raise RunError("the hostile peer (Deploy.forgeries_per_second) did not start")

    def go(self) -> None:
        """Start sending."""
        self._say("go")

    def stop(self) -> dict:
        """Stop sending; ``{target name: datagrams sent}``."""
        self._say("stop")
        try:
            out, _ = self.process.communicate(timeout=10)
            sent = json.loads(out.strip().splitlines()[-1])
        except (subprocess.TimeoutExpired, ValueError, IndexError):
            self.process.kill()
            self.process.wait()
            raise RunError("the hostile peer did not stop in 10 s") from None
        return dict(zip(self.names, sent, strict=True))

    def _say(self, word: str) -> None:
        try:
            self.process.stdin.write(word + "\n")
            self.process.stdin.flush()
        except (BrokenPipeError, ValueError):  # gone, or already told
            pass


def main(argv: list[str] | None = None) -> int:
    """The peer's process: ``K EPISODES STEPS OBS_DIM RATE SEED POOL host:port:id ...``; says
    ``ready`` once its pools are drawn, sends from the line ``go`` on stdin to the line
    ``stop`` (or the end of stdin), then prints the datagrams sent per target as JSON."""
    argv = sys.argv[1:] if argv is None else argv
    k, episodes, steps, obs_dim = (int(x) for x in argv[:4])
    rate, seed, pool = float(argv[4]), int(argv[5]), int(argv[6])
    targets = []
    for text in argv[7:]:
        host, port, who = text.rsplit(":", 2)
        targets.append(((host, int(port)), int(who)))
    pools = []
    for _, who in targets:
        source = forgeries(seed, k, episodes, steps, obs_dim, who)
        pools.append([next(source) for _ in range(pool)])
    sent = [0] * len(targets)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    print("ready", flush=True)
    if sys.stdin.readline().strip() == "go":
        stop = threading.Event()
        threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
        started, n = time.monotonic(), 0
        while not stop.is_set():
            for _ in range(64):
                i = n % pool
                for t, (address, _) in enumerate(targets):
                    try:
                        sock.sendto(pools[t][i], address)
                    except OSError:  # nobody listening there (yet, or any more), a full buffer
                        pass
                    sent[t] += 1
                n += 1
            if 0 < rate < float("inf"):  # keep to the rate: sleep until the next round is due
                wait = started + n * len(targets) / rate - time.monotonic()
                if wait > 0:
                    stop.wait(wait)
    sock.close()
    print(json.dumps(sent), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
