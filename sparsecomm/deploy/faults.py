"""Faults on the links between agents, and the deadlines that keep every wait finite.

The fault layer sits on the sender's side of every link ``i -> j``: each datagram it is handed
for step ``t`` of episode ``b`` draws its fate from its own generator,
``numpy.random.default_rng([seed, b, t, i, j])``, so the faults are reproducible from the seed
and do not depend on timing, on the other links or on a process restart. Four uniforms are drawn
per datagram, always (a fault switched off still draws), in this order:

1. **loss** (``loss``): the datagram is not sent;
2. **duplication** (``duplicate``): it is sent twice;
3. **reordering** (``reorder``): it is held back a uniform ``[0, reorder_delay]`` seconds, so
   datagrams sent after it overtake it (a copy held past the receiver's deadline is late: the
   receiver drops it as stale);
4. **garbage** (``garbage``): one more datagram of garbage is sent beside it: half the time random
   bytes (1-64 of them), half the time the datagram itself with 1-3 bits flipped.

The faults apply to the agents' packets (the channel); the world's observations and the agents'
actions stand for sensors and actuators and travel unharmed (on loopback they are not lost).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

PROBABILITIES = ("loss", "duplicate", "reorder", "garbage")


def _probability(owner: str, name: str, value) -> None:
    real = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (real and 0 <= value <= 1):  # NaN fails too
        raise ValueError(f"{owner}.{name} must be a probability in [0, 1], got {value!r}")


def _seconds(owner: str, name: str, value, low: float = 0.0, strict: bool = True) -> None:
    real = isinstance(value, numbers.Real) and not isinstance(value, bool)
    ok = real and math.isfinite(value) and (value > low if strict else value >= low)
    if not ok:
        sign = ">" if strict else ">="
        raise ValueError(f"{owner}.{name} must be finite seconds {sign} {low}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class Faults:
    """What the network does to the agents' datagrams (module docstring). Default: nothing."""

    loss: float = 0.0
    """Probability that a datagram is lost. Default 0 (ours: a clean network; the fault test
    of tests/test_deploy.py: 0.2)."""
    duplicate: float = 0.0
    """Probability that a datagram arrives twice. Default 0 (ours)."""
    reorder: float = 0.0
    """Probability that a datagram is held back (``reorder_delay``) and overtaken. Default 0
    (ours)."""
    reorder_delay: float = 0.02
    """Longest hold of a reordered datagram, in seconds (uniform in [0, this]). Default 0.02
    (ours: a tenth of the default message deadline, so most reordered datagrams still arrive in
    time and some do not)."""
    garbage: float = 0.0
    """Probability that a garbage datagram is sent beside a datagram. Default 0 (ours; the
    fault test of tests/test_deploy.py: 0.01)."""
    seed: int = 0
    """Seed of the fault draws (with the episode, step, sender and recipient). Default 0."""

    def __post_init__(self):
        for name in PROBABILITIES:
            _probability("Faults", name, getattr(self, name))
        _seconds("Faults", "reorder_delay", self.reorder_delay, strict=False)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"Faults.seed must be an integer >= 0, got {self.seed!r}")

    @property
    def clean(self) -> bool:
        return not any(getattr(self, name) for name in PROBABILITIES)


@dataclasses.dataclass(frozen=True)
class Deadlines:
    """How long each wait of the runtime lasts at most, in seconds. Nothing waits longer."""

    message: float = 0.2
    """An agent waits this long, from the moment its observation arrives, for the packets of
    the previous step; a packet missing then is the null message (or the last one, ``on_drop``).
    Only a lost or late packet costs the wait: silence is an explicit datagram. Default 0.2
    (ours: loopback delivers in well under a millisecond; a loaded 2-core machine can stall a
    process for tens of milliseconds, which must not count as a loss)."""
    action: float = 2.0
    """The world waits this long for each agent's action; an action missing then is action 0
    (no force). Only a dead or late agent costs the wait. Default 2 (ours: above ``message``
    plus the slowest step of a loaded machine)."""
    startup: float = 120.0
    """The world waits this long for every agent's first hello, and an agent this long for
    its first observation. Default 120 (ours: importing JAX and compiling in several processes
    at once on 2 cores takes tens of seconds)."""
    idle: float = 30.0
    """An agent that hears nothing from the world for this long exits (the world is gone: no
    orphan agent outlives it). Default 30 (ours: well above ``action`` + ``message``)."""

    def __post_init__(self):
        for field in dataclasses.fields(self):
            _seconds("Deadlines", field.name, getattr(self, field.name))
        if self.action <= self.message:
            raise ValueError(
                f"Deadlines.action must exceed Deadlines.message ({self.message}), got "
                f"{self.action!r}"
            )
        if self.idle <= self.action + self.message:
            raise ValueError(
                f"Deadlines.idle must exceed action + message ({self.action + self.message}), "
                f"got {self.idle!r}"
            )


def inject(
    faults: Faults, datagram: bytes, episode: int, step: int, sender: int, recipient: int
) -> list[tuple[float, bytes]]:
    """What the network makes of one datagram of link ``sender -> recipient``: the datagrams to
    send, each with its delay in seconds (module docstring). Pure: the same arguments give the
    same list."""
    if faults.clean:
        return [(0.0, datagram)]
    rng = np.random.default_rng([faults.seed, episode, step, sender, recipient])
    u = rng.random(4)
    out = []
    if u[0] >= faults.loss:
        delay = float(rng.uniform(0, faults.reorder_delay)) if u[2] < faults.reorder else 0.0
        out.append((delay, datagram))
        if u[1] < faults.duplicate:
            out.append((0.0, datagram))
    if u[3] < faults.garbage:
        out.append((0.0, garbage(rng, datagram)))
    return out


def garbage(rng: np.random.Generator, datagram: bytes) -> bytes:
    """Random bytes, or ``datagram`` with 1-3 bits flipped (even odds)."""
    if rng.random() < 0.5 or not datagram:
        return rng.bytes(int(rng.integers(1, 65)))
    bits = np.unpackbits(np.frombuffer(datagram, np.uint8))
    flips = rng.choice(bits.size, size=min(bits.size, int(rng.integers(1, 4))), replace=False)
    bits[flips] ^= 1
    return np.packbits(bits).tobytes()
