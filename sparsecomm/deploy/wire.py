"""The datagram around every packet: an 11-byte header, a MAC, the payload (docs/deploy.md).

Every UDP datagram of the runtime, between agents, with the world or with the launcher, is::

    offset  bytes  field
    0       2      magic b"SC"
    2       1      version (high 4 bits, 3) and kind (low 4 bits, :data:`KINDS`)
    3       1      sender (agent id, or 255: the world)
    4       1      recipient (agent id, or 255: the world)
    5       4      episode (unsigned, big-endian)
    9       2      step (unsigned, big-endian)
    11      8      MAC: HMAC-SHA-256 (RFC 2104, ``hmac``) under the team's secret of the 11
                   bytes above and the payload, truncated to its first :data:`MAC_BYTES`
    19      ...    payload, in the fixed binary layout of its kind (below)

**Authentication.** Only a holder of the team's secret (:func:`read_secret`; the launcher makes
a new one per deployment, :func:`write_secret`) can make a datagram that :meth:`Auth.parse`
accepts: a forger guesses the 64-bit MAC with probability 2^-64 per try. The MAC covers the
header, so the sender, kind, episode and step cannot be changed or a datagram moved to another
step; each receiver then checks that they are ones it expects from that sender now (a replayed
datagram of an earlier step is stale: dropped). Verification happens before any payload is
read, and it is constant-time (``hmac.compare_digest``). A datagram that fails it is dropped and
counted (``bad``). docs/deploy.md, "Who can stop the team", states the threat model.

**Payloads** (every parser takes ``bytes`` and returns ``None`` for anything but the exact
layout; none raises):

======== =============== ========================================================================
kind     from -> to      payload
======== =============== ========================================================================
``msg``  agent -> agent  the sender's **frame** of the step, exactly as
                         ``sparsecomm.channel.encode_sender`` writes it; one copy per recipient
                         whose link speaks, none for a silent link
``obs``  world -> agent  the **nonce** of the agent's hello this observation answers to
                         (:data:`NONCE_BYTES`), ``obs_dim`` float32 (big-endian), then the
                         **heard map**
                         (:func:`pack_obs`): ``ceil((K-1)/8)`` bytes whose bit ``s`` (byte
                         ``s // 8``, bit ``s % 8``, least significant first) is set when the
                         agent's ``s``-th sender (``channel.others``) spoke to it at the previous
                         step, as that sender reported to the world
``act``  agent -> world  its action and what it sent and heard: :class:`Report`
                         (:func:`pack_report`, :data:`REPORT_HEAD` then :data:`REPORT_LINK` per
                         link)
``hello`` agent -> world "I am up" (at start and after a restart): a **nonce**, 8 random
                         bytes drawn once per process (``secrets``)
``bye``  world -> agent  shut down: empty
``step`` world -> launcher progress: empty
``done`` world -> launcher every episode played: empty
======== =============== ========================================================================

The episode and step of the header are what discards a stale frame: no sequence number is
needed. **Replays.** A copy of a real datagram passes the MAC, so each receiver also asks
whether it is news. The nonce binds observations to one agent process: the world answers each
hello's nonce once (a copy of a hello, or a hello of a process since replaced, is never answered,
so nothing is reflected), keeps the latest nonce of each agent and writes it first in every
observation; an agent acts only on observations carrying its own nonce, so a restarted agent
never acts on its predecessor's, and among its own only on a step newer than the last it acted
on (a copy of the one in progress or already answered is a duplicate, an older one stale). A
frame already received is a duplicate, one of a step already acted on stale; an action of a
step the world already counted is a duplicate. Each is counted where it is dropped.

Counting: the header and MAC are :data:`HEADER_BYTES` per datagram, and the IPv4 and UDP
headers add :data:`UDP_IP_BYTES` more on the network (counted, not measured: loopback carries
them too).
"""

from __future__ import annotations

import hmac
import os
import secrets
import signal
import socket
import stat
import struct
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

MAGIC = b"SC"
VERSION = 3
"""3: the hello's nonce and its echo in every observation (version 2 sent the process id and
answered every hello; version 1 had a CRC-16 where the MAC is and JSON reports; both are
refused)."""
MSG, OBS, ACT, HELLO, BYE, STEP, DONE = 1, 2, 3, 4, 5, 6, 7
KINDS = {MSG: "msg", OBS: "obs", ACT: "act", HELLO: "hello", BYE: "bye", STEP: "step", DONE: "done"}
"""The kinds of datagram (module docstring)."""
WORLD = 255
"""The id of the world process (and of the launcher's monitor) in the sender and recipient
fields."""
FIELDS = struct.Struct("!2sBBBIH")
"""The 11 bytes of fields before the MAC: magic, version and kind, sender, recipient, episode,
step."""
MAC_BYTES = 8
"""Bytes of the truncated HMAC-SHA-256. ours: 8 (64 bits: RFC 2104 section 5 asks for at least
half the hash's output for general use, NIST SP 800-107 allows truncation to 64 bits and more
where the number of tries is bounded; a deployed team's few thousand datagrams per second give
a forger one success in ~10^15 years). Counted in every datagram's bits."""
HEADER_BYTES = FIELDS.size + MAC_BYTES
"""19: the header and MAC of every datagram."""
UDP_IP_BYTES = 28
"""IPv4 (20 bytes, no options) and UDP (8 bytes) headers of every datagram on the network
(IPv6: 48)."""
MAX_DATAGRAM = 65_507
"""The largest UDP payload over IPv4; the receive buffer size."""
SECRET_BYTES = 32
"""Bytes of a secret :func:`write_secret` makes (256 bits, the hash's block strength)."""
MIN_SECRET_BYTES = 16
"""The shortest secret :func:`read_secret` accepts (128 bits)."""


class Datagram(NamedTuple):
    kind: int
    sender: int
    recipient: int
    episode: int
    step: int
    payload: bytes


class Auth:
    """The team's secret: seals datagrams (:meth:`pack`) and checks them (:meth:`parse`)."""

    def __init__(self, secret: bytes):
        secret = bytes(secret)
        if len(secret) < MIN_SECRET_BYTES:
            raise ValueError(
                f"the team secret must have at least {MIN_SECRET_BYTES} bytes, got {len(secret)}"
            )
        self._key = secret

    def _mac(self, head: bytes, payload: bytes) -> bytes:
        return hmac.digest(self._key, head + payload, "sha256")[:MAC_BYTES]

    def pack(
        self, kind: int, sender: int, recipient: int, episode: int, step: int, payload=b""
    ) -> bytes:
        """One datagram (header, MAC, payload). Raises ``ValueError`` for fields out of
        range."""
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {sorted(KINDS)}, got {kind!r}")
        for name, value, top in (
            ("sender", sender, 255),
            ("recipient", recipient, 255),
            ("episode", episode, 2**32 - 1),
            ("step", step, 2**16 - 1),
        ):
            if not 0 <= value <= top:
                raise ValueError(f"{name} must be in [0, {top}], got {value}")
        head = FIELDS.pack(MAGIC, VERSION << 4 | kind, sender, recipient, episode, step)
        payload = bytes(payload)
        if HEADER_BYTES + len(payload) > MAX_DATAGRAM:
            raise ValueError(f"payload of {len(payload)} bytes does not fit in one datagram")
        return head + self._mac(head, payload) + payload

    def parse(self, data) -> Datagram | None:
        """The datagram in ``data`` if it is one of ours sealed with this secret, else ``None``
        (never raises; the MAC is checked before anything else is read)."""
        if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < HEADER_BYTES:
            return None
        data = bytes(data)
        head, mac, payload = (
            data[: FIELDS.size],
            data[FIELDS.size : HEADER_BYTES],
            data[HEADER_BYTES:],
        )
        if not hmac.compare_digest(mac, self._mac(head, payload)):
            return None
        magic, vk, sender, recipient, episode, step = FIELDS.unpack(head)
        if magic != MAGIC or vk >> 4 != VERSION or (vk & 15) not in KINDS:
            return None
        return Datagram(vk & 15, sender, recipient, episode, step, payload)


def write_secret(path: str | Path) -> Path:
    """A new secret of :data:`SECRET_BYTES` random bytes (``secrets``), written as hex to a new
    file ``path`` that only its owner can read or write (created with mode 0600; an existing
    file is refused, ``FileExistsError``)."""
    path = Path(path)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(SECRET_BYTES) + "\n")
    return path


def read_secret(path: str | Path, name: str = "secret_file") -> bytes:
    """The secret in ``path``: hex digits (at least ``2 * MIN_SECRET_BYTES``; surrounding
    whitespace ignored), in a regular file that neither its group nor others may read or write
    (POSIX). Raises ``ValueError`` naming ``name`` otherwise."""
    path = Path(path)
    try:
        info = path.stat()
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{name} must be a file, got {str(path)!r} (not a regular file)")
        if os.name == "posix" and info.st_mode & 0o077:
            raise ValueError(
                f"{name} {str(path)!r} may be read by others (mode {info.st_mode & 0o777:o}): "
                f"chmod 600 it"
            )
        if info.st_size > 4096:
            raise ValueError(f"{name} {str(path)!r} is not a secret (over 4096 bytes)")
        text = path.read_text("ascii").strip()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{name} {str(path)!r} cannot be read: {e}") from None
    try:
        secret = bytes.fromhex(text)
    except ValueError:
        raise ValueError(f"{name} {str(path)!r} must hold hex digits only") from None
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(
            f"{name} {str(path)!r} must hold at least {2 * MIN_SECRET_BYTES} hex digits "
            f"({MIN_SECRET_BYTES} bytes), got {len(text)}"
        )
    return secret


class Report(NamedTuple):
    """What an agent sent and heard at one step, in its action datagram (kind ``act``). Per
    link ``r`` (recipient slot, ``channel.others``): ``payload[r]`` payload bits,
    ``spoke[r]`` 1 when it spoke, ``datagram[r]`` the bytes of the datagram due (0: none),
    ``sent[r]`` / ``sent_n[r]`` the bytes and datagrams the fault layer sent for it. The
    counts of datagrams dropped since the agent's last report: ``dup`` (copies of a frame or
    of an observation already in hand), ``stale`` (for a step already acted on), ``foreign``
    (observations carrying another process's nonce: a predecessor's, or replays of them),
    ``bad`` (failing the MAC, not addressed to this agent, or malformed); ``no_map``: steps
    waited without a heard map."""

    action: int
    rejoined: bool
    sim_wire: int
    frame: int
    missing: int
    dup: int
    stale: int
    foreign: int
    bad: int
    no_map: int
    payload: tuple[int, ...]
    spoke: tuple[int, ...]
    datagram: tuple[int, ...]
    sent: tuple[int, ...]
    sent_n: tuple[int, ...]


REPORT_HEAD = struct.Struct("!HBIIIIIIII")
"""action (u16), rejoined (u8: 0 or 1), sim_wire, frame (bits), missing, dup, stale, foreign,
bad, no_map (u32 each)."""
REPORT_LINK = struct.Struct("!IBHIB")
"""Per link: payload bits (u32), spoke (u8: 0 or 1), datagram bytes (u16), sent bytes (u32),
sent datagrams (u8)."""
_LINK_FIELDS = ("payload", "spoke", "datagram", "sent", "sent_n")


def report_bytes(num_links: int) -> int:
    """Bytes of a report of ``num_links`` links."""
    return REPORT_HEAD.size + num_links * REPORT_LINK.size


def pack_report(report: Report) -> bytes:
    """A report's payload (``struct.error`` for a field out of its type's range)."""
    head = REPORT_HEAD.pack(*report[: len(Report._fields) - len(_LINK_FIELDS)])
    links = zip(*(getattr(report, f) for f in _LINK_FIELDS), strict=True)
    return head + b"".join(REPORT_LINK.pack(*link) for link in links)


def parse_report(payload, num_links: int) -> Report | None:
    """The report in ``payload``, or ``None`` when it is not one of ``num_links`` links (another
    length, a flag that is not 0 or 1). Never raises."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or num_links < 0:
        return None
    payload = bytes(payload)
    if len(payload) != report_bytes(num_links):
        return None
    head = REPORT_HEAD.unpack_from(payload)
    links = [
        REPORT_LINK.unpack_from(payload, REPORT_HEAD.size + r * REPORT_LINK.size)
        for r in range(num_links)
    ]
    columns = tuple(zip(*links, strict=True)) if links else ((),) * len(_LINK_FIELDS)
    if head[1] > 1 or any(flag > 1 for flag in columns[1]):
        return None
    return Report(head[0], bool(head[1]), *head[2:], *columns)


NONCE_BYTES = 8
"""Bytes of an agent process's nonce (64 random bits: two processes of one deployment share one
with probability ~2^-64 per pair)."""
HELLO_BYTES = NONCE_BYTES
"""A hello's payload: the agent process's nonce."""


def new_nonce() -> bytes:
    """A fresh nonce for one agent process (``secrets``)."""
    return secrets.token_bytes(NONCE_BYTES)


def parse_hello(payload) -> bytes | None:
    """The nonce in a hello's payload, or ``None`` (never raises)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) != HELLO_BYTES:
        return None
    return bytes(payload)


def map_bytes(num_links: int) -> int:
    """Bytes of a heard map of ``num_links`` links (K - 1 per agent): ``ceil(num_links / 8)``."""
    return -(-int(num_links) // 8)


def pack_map(heard) -> bytes:
    """The heard map of a sequence of booleans, one per sender slot: bit ``s`` of byte
    ``s // 8`` (least significant first) set when slot ``s`` spoke; padding bits zero."""
    bits = np.asarray(heard, bool).reshape(-1)
    return np.packbits(bits, bitorder="little").tobytes()


def parse_map(data: bytes, num_links: int) -> np.ndarray | None:
    """The (num_links,) bool heard map in ``data``, or ``None`` when ``data`` is not one: another
    length than :func:`map_bytes`, or a padding bit set (never raises)."""
    if not isinstance(data, (bytes, bytearray, memoryview)) or num_links < 0:
        return None
    data = bytes(data)
    if len(data) != map_bytes(num_links):
        return None
    bits = np.unpackbits(np.frombuffer(data, np.uint8), bitorder="little").astype(bool)
    if bits[num_links:].any():
        return None
    return bits[:num_links]


def pack_obs(nonce: bytes, obs, heard=None) -> bytes:
    """An observation's payload: the agent's ``nonce`` (:data:`NONCE_BYTES`), the float32
    values (big-endian), then the heard map of ``heard`` (one boolean per sender slot;
    ``None``: no map, the receivers wait for every sender until the deadline)."""
    nonce = bytes(nonce)
    if len(nonce) != NONCE_BYTES:
        raise ValueError(f"nonce must have {NONCE_BYTES} bytes, got {len(nonce)}")
    body = nonce + np.asarray(obs, ">f4").reshape(-1).tobytes()
    return body if heard is None else body + pack_map(heard)


def obs_nonce(payload) -> bytes | None:
    """The nonce an observation's payload starts with, or ``None`` (never raises)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) < NONCE_BYTES:
        return None
    return bytes(payload[:NONCE_BYTES])


def parse_obs(payload: bytes, obs_dim: int, num_links: int):
    """``(nonce, values (obs_dim,) float32, heard (num_links,) bool | None)`` of an
    observation's payload; ``nonce`` and ``values`` are ``None`` when the payload holds no
    nonce and observation of ``obs_dim`` floats, ``heard`` ``None`` when it holds no valid map
    (fall back to waiting for every sender). Never raises."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        return None, None, None
    payload, n = bytes(payload), NONCE_BYTES + 4 * int(obs_dim)
    if len(payload) < n:
        return None, None, None
    nonce = payload[:NONCE_BYTES]
    values = np.frombuffer(payload[NONCE_BYTES:n], ">f4").astype(np.float32)
    rest = payload[n:]
    if len(rest) != map_bytes(num_links):  # no map, or one of another length: no map
        return (nonce, values, None) if not rest else (None, None, None)
    return nonce, values, parse_map(rest, num_links)


def parse_address(text: str, name: str = "address") -> tuple[str, int]:
    """``host:port`` (IPv4 address or name; port 0-65535) as a socket address."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{name} must be host:port with a port in [0, 65535], got {text!r}")
    return host, int(port)


def udp_socket(address: tuple[str, int]) -> socket.socket:
    """A UDP socket bound to ``address`` (large receive buffer: a burst of datagrams while a
    process compiles must not overflow it)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    except OSError:
        pass
    sock.bind(address)
    return sock


def free_ports(host: str, count: int) -> list[int]:
    """``count`` UDP ports free on ``host`` now (bound to port 0, read, released)."""
    socks = [udp_socket((host, 0)) for _ in range(count)]
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def die_with_parent() -> None:
    """Ask Linux to send this process SIGTERM when its parent dies (``PR_SET_PDEATHSIG``), so a
    launcher killed outright leaves no orphan; elsewhere a no-op (the idle deadline remains)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
