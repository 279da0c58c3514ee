"""The arguments of ``sparsecomm deploy`` (:class:`Deploy`), checked when they are made; the
command itself is :func:`sparsecomm.deploy.launcher.deploy`."""

from __future__ import annotations

import dataclasses
import ipaddress
import socket
from pathlib import Path

from sparsecomm.deploy.faults import Deadlines, Faults
from sparsecomm.runfolder import at_least, check_output


@dataclasses.dataclass
class Deploy:
    """Run a trained team decentralised: one OS process per agent and one for the world, the
    channel's real packets as UDP datagrams between them, faults injected and survived
    (docs/deploy.md). Writes ``<out>/deploy.json`` (eval's metrics, CIs over episodes, and the
    simulation of the same episodes beside them)."""

    run: Path | None = None
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team; default: the
    sparse team shipped with the package (:data:`PRETRAINED`), as ``sparsecomm eval``."""
    index: tuple[int, ...] = (0,)
    """Which runs of the sweep to deploy, one after another (lambda-major, then budget, then
    seed); run r plays the episodes ``sparsecomm eval`` plays for it (key ``config.seed +
    EVAL_SEED_OFFSET + r``). Default: the first, as ``sparsecomm render``."""
    episodes: int = 100
    """Episodes per run. With the same number, deploy plays the very episodes of ``sparsecomm
    eval --episodes N`` (the draws depend on N). ours: 100 (eval: 1000; a deployed step is a
    round of datagrams, ~1 ms on loopback)."""
    greedy: bool = False
    """Take the most probable action instead of sampling (as ``sparsecomm eval --greedy``)."""
    out: Path | None = None
    """Output folder: deploy.json, and per run the exported team, the world's episodes.jsonl
    and links.csv (bytes per link and step), the processes' logs. Default: ``<run>/deploy``
    (``runs/pretrained/deploy`` for the shipped team). A folder this user can write, or a path
    where one can be created: checked before anything is loaded."""
    loss: float = 0.0
    """Probability that a datagram between agents is lost. ours: 0 (the fault test of
    tests/test_deploy.py: 0.2). A packet missing at the step's deadline is the null message
    (``on_drop``)."""
    duplicate: float = 0.0
    """Probability that a datagram between agents arrives twice. ours: 0."""
    reorder: float = 0.0
    """Probability that a datagram between agents is held back up to ``reorder_delay`` seconds
    and overtaken by later ones. ours: 0."""
    reorder_delay: float = 0.02
    """Longest hold of a reordered datagram, seconds. ours: 0.02 (a tenth of the message
    deadline)."""
    garbage: float = 0.0
    """Probability that a garbage datagram (random bytes, or the datagram with bits flipped)
    is sent beside a datagram between agents. ours: 0 (tests/test_deploy.py's fault test: 0.01)."""
    kills_per_episode: int = 0
    """Agent processes SIGKILLed per episode (a seeded agent at a seeded step in [1,
    ``kill_window``]); each is restarted and rejoins with its recurrent state reset. ours: 0
    (tests/test_deploy.py's fault test: 1)."""
    kill_window: int = 8
    """Kills happen at a step in [1, kill_window]. ours: 8 (well inside a trained team's
    ~20-step episodes, so the kill and the rejoin happen mid-episode)."""
    fault_seed: int = 0
    """Seed of every fault draw (losses, duplicates, reordering, garbage, kills). ours: 0."""
    on_drop: str = "null"
    """What a receiver uses for a packet missing at the deadline: ``null`` (the null message,
    the paper's "nothing sent") or ``last`` (the link's last good message, as
    ``NoiseConfig.on_drop`` for teams trained with it)."""
    message_deadline: float = 0.2
    """Seconds an agent waits, from its observation's arrival, for its peers' packets of the
    previous step (``Deadlines.message``). ours: 0.2."""
    action_deadline: float = 2.0
    """Seconds the world waits for each action; a missing action is 0, no force
    (``Deadlines.action``). ours: 2."""
    startup_deadline: float = 120.0
    """Seconds the world waits for every agent's first hello (``Deadlines.startup``). ours:
    120 (several processes import JAX and compile at once)."""
    host: str = "127.0.0.1"
    """Interface the processes listen on (free UDP ports are picked on it): an IPv4 address of
    this machine (``127.0.0.1``, or one of its interfaces' addresses) or a name that resolves to
    one, checked by binding a UDP socket there. ours: loopback. For agents on separate hosts
    start the processes by hand (docs/deploy.md)."""
    forgeries_per_second: float = 0.0
    """A hostile peer without the team's secret sends every process (the world, each agent,
    the launcher) this many forged datagrams per second in all, of every kind
    (``sparsecomm.deploy.hostile``), while the team plays: a drill of the MAC and the parsers
    (docs/deploy.md, "Who can stop the team"). ``inf``: as fast as it can. ours: 0 (no peer)."""
    replay: bool = False
    """A replaying peer without the team's secret captures every datagram the team's processes
    send each other (a packet socket: Linux, root or ``CAP_NET_RAW``; checked before anything
    is loaded) and sends copies of each at once, duplicated, reordered, late, to the wrong
    process, and old ones at random, while the team plays (``sparsecomm.deploy.replay``): a
    drill of the protocol's replay rules (docs/deploy.md, "Who can stop the team"). ours: off."""
    reference: bool = True
    """Also play the same episodes in simulation (the run's ``sparsecomm eval`` draws, with
    ``loss`` as the simulator's packet erasure) and report them side by side, with the count of
    identical episodes."""

    def __post_init__(self):
        at_least(self, episodes=1, kills_per_episode=0, kill_window=1, fault_seed=0)
        rate = self.forgeries_per_second
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not rate >= 0:
            raise ValueError(
                f"Deploy.forgeries_per_second must be a number >= 0 (inf: as fast as it can), "
                f"got {rate!r}"
            )
        if isinstance(self.index, int):
            self.index = (self.index,)
        if not self.index:
            raise ValueError("Deploy.index must name at least one run, got ()")
        for i in self.index:
            if isinstance(i, bool) or not isinstance(i, int) or i < 0:
                raise ValueError(f"Deploy.index must hold integers >= 0, got {self.index!r}")
        if self.on_drop not in ("null", "last"):
            raise ValueError(
                f"Deploy.on_drop must be one of ('null', 'last'), got {self.on_drop!r}"
            )
        if self.run is not None and not Path(self.run).is_dir():
            raise ValueError(f"Deploy.run must be a run folder, got {str(self.run)!r} (missing)")
        if self.replay:
            from sparsecomm.deploy.replay import can_capture

            why = can_capture()
            if why:
                raise ValueError(
                    f"Deploy.replay needs a packet capture socket (Linux, root or CAP_NET_RAW) "
                    f"on this host: {why}"
                )
        check_output(self, folder=True)
        _check_host(self.host)
        try:
            self.faults()
            self.deadlines()
        except ValueError as e:  # name the flag, not the inner dataclass
            raise ValueError(_deploy_field(str(e))) from None

    def faults(self) -> Faults:
        """The faults injected on the agents' links."""
        return Faults(
            self.loss,
            self.duplicate,
            self.reorder,
            self.reorder_delay,
            self.garbage,
            self.fault_seed,
        )

    def deadlines(self) -> Deadlines:
        """The deadlines of every wait."""
        return Deadlines(
            self.message_deadline,
            self.action_deadline,
            self.startup_deadline,
            max(30.0, 2 * (self.action_deadline + self.message_deadline)),
        )


HOST_RULE = (
    "an IPv4 address of this machine (127.0.0.1, or one of its interfaces' addresses) or a name "
    "that resolves to one: every process of the deploy binds its UDP sockets there"
)


def _check_host(host) -> None:
    """Refuse a ``--host`` that the deploy's sockets (IPv4, ``wire.udp_socket``) cannot bind:
    not an IPv4 address literal (``999.1.1.1``), an IPv6 address (``::1``), a name that does not
    resolve to an IPv4 address, or an address of another machine. Binds a UDP socket to port 0
    there and closes it; nothing else."""
    if not isinstance(host, str) or not host.strip():
        raise ValueError(f"Deploy.host must be {HOST_RULE}, got {host!r}")
    if ":" in host:  # an IPv6 literal (or host:port): the sockets are IPv4 only
        try:
            ipaddress.IPv6Address(host.strip("[]"))
            why = "an IPv6 address: the deploy's UDP sockets are IPv4 only, use 127.0.0.1"
        except ValueError:
            why = "not an IPv4 address or a name: give the address alone, without a port"
        raise ValueError(f"Deploy.host must be {HOST_RULE}, got {host!r} ({why})")
    looks_numeric = all(part.isdigit() for part in host.split("."))
    try:
        address = str(ipaddress.IPv4Address(host)) if looks_numeric else None
    except ValueError:
        raise ValueError(
            f"Deploy.host must be {HOST_RULE}, got {host!r} (not an IPv4 address)"
        ) from None
    try:
        address = address or socket.gethostbyname(host)
    except (OSError, UnicodeError):
        raise ValueError(
            f"Deploy.host must be {HOST_RULE}, got {host!r} (the name does not resolve to an "
            "IPv4 address)"
        ) from None
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind((address, 0))
    except OSError as e:
        raise ValueError(
            f"Deploy.host must be {HOST_RULE}, got {host!r} ({address}: {e.strerror or e})"
        ) from None


_DEPLOY_NAMES = {
    "Faults.seed": "Deploy.fault_seed",
    "Faults.": "Deploy.",
    "Deadlines.message": "Deploy.message_deadline",
    "Deadlines.action": "Deploy.action_deadline",
    "Deadlines.startup": "Deploy.startup_deadline",
}


def _deploy_field(message: str) -> str:
    for inner, outer in _DEPLOY_NAMES.items():
        message = message.replace(inner, outer)
    return message
