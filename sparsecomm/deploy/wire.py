"""The datagram around every packet: a 13-byte header, then the payload (docs/deploy.md).

Every UDP datagram of the runtime, between agents or with the world, is::

    offset  bytes  field
    0       2      magic b"SC"
    2       1      version (high 4 bits, 1) and kind (low 4 bits, :data:`KINDS`)
    3       1      sender (agent id, or 255: the world)
    4       1      recipient (agent id, or 255: the world)
    5       4      episode (unsigned, big-endian)
    9       2      step (unsigned, big-endian)
    11      2      CRC-16/CCITT of the 11 bytes above and the payload (``binascii.crc_hqx``,
                   initial value 0xFFFF)
    13      ...    payload

Between agents (kind ``MSG``) the payload is the sender's **frame** of the step exactly as
``sparsecomm.channel.encode_sender`` writes it (every non-silent link of the sender, error
correction applied), one copy per recipient whose link speaks; a silent link sends **no**
datagram. The world tells each agent whom to wait for: the observation's payload (kind ``OBS``)
is the float32 observation followed by the **heard map** (:func:`pack_obs`), ``ceil((K-1)/8)``
bytes whose bit ``s`` (byte ``s // 8``, bit ``s % 8``, least significant first) is set when the
agent's ``s``-th sender (``channel.others``) spoke to it at the previous step, as that sender
reported to the world. The episode and step of the header are what discards a stale frame: no
sequence number is needed. :func:`parse`, :func:`parse_map` and :func:`parse_obs` never raise: a
datagram too short, with another magic or version, an unknown kind or a CRC-16 mismatch is
``None`` (garbage), and so is a map of another length or with a padding bit set. Counting: the
header is :data:`HEADER_BYTES` per datagram, and the IPv4 and UDP headers add
:data:`UDP_IP_BYTES` more on the network (counted, not measured: loopback carries them too).
"""

from __future__ import annotations

import binascii
import signal
import socket
import struct
import sys
from typing import NamedTuple

import numpy as np

MAGIC = b"SC"
VERSION = 1
MSG, OBS, ACT, HELLO, BYE, STEP = 1, 2, 3, 4, 5, 6
KINDS = {MSG: "msg", OBS: "obs", ACT: "act", HELLO: "hello", BYE: "bye", STEP: "step"}
"""``msg``: agent -> agent, the sender's frame; ``obs``: world -> agent, its observation
(float32, big-endian) and heard map; ``act``: agent -> world, its action and what it sent and
heard (JSON); ``hello``: agent -> world, "I am up" (at start and after a restart); ``bye``:
world -> agent, shut down; ``step``: world -> launcher, progress (empty)."""
WORLD = 255
"""The id of the world process in the sender and recipient fields."""
_HEAD = struct.Struct("!2sBBBIH")
HEADER_BYTES = _HEAD.size + 2
"""13: the header of every datagram."""
UDP_IP_BYTES = 28
"""IPv4 (20 bytes, no options) and UDP (8 bytes) headers of every datagram on the network
(IPv6: 48)."""
MAX_DATAGRAM = 65_507
"""The largest UDP payload over IPv4; the receive buffer size."""


class Datagram(NamedTuple):
    kind: int
    sender: int
    recipient: int
    episode: int
    step: int
    payload: bytes


def pack(kind: int, sender: int, recipient: int, episode: int, step: int, payload=b"") -> bytes:
    """One datagram (header + payload). Raises ``ValueError`` for fields out of range."""
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
    head = _HEAD.pack(MAGIC, VERSION << 4 | kind, sender, recipient, episode, step)
    payload = bytes(payload)
    if HEADER_BYTES + len(payload) > MAX_DATAGRAM:
        raise ValueError(f"payload of {len(payload)} bytes does not fit in one datagram")
    crc = binascii.crc_hqx(payload, binascii.crc_hqx(head, 0xFFFF))
    return head + crc.to_bytes(2, "big") + payload


def parse(data: bytes) -> Datagram | None:
    """The datagram in ``data``, or ``None`` when it is not one of ours (never raises)."""
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < HEADER_BYTES:
        return None
    data = bytes(data)
    head, crc, payload = data[: _HEAD.size], data[_HEAD.size : HEADER_BYTES], data[HEADER_BYTES:]
    magic, vk, sender, recipient, episode, step = _HEAD.unpack(head)
    if magic != MAGIC or vk >> 4 != VERSION or (vk & 15) not in KINDS:
        return None
    if binascii.crc_hqx(payload, binascii.crc_hqx(head, 0xFFFF)) != int.from_bytes(crc, "big"):
        return None
    return Datagram(vk & 15, sender, recipient, episode, step, payload)


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


def pack_obs(obs, heard=None) -> bytes:
    """An observation's payload: the float32 values (big-endian), then the heard map of
    ``heard`` (one boolean per sender slot; ``None``: no map, the receivers wait for every
    sender until the deadline)."""
    body = np.asarray(obs, ">f4").reshape(-1).tobytes()
    return body if heard is None else body + pack_map(heard)


def parse_obs(payload: bytes, obs_dim: int, num_links: int):
    """``(values (obs_dim,) float32, heard (num_links,) bool | None)`` of an observation's
    payload; ``values`` is ``None`` when the payload holds no observation of ``obs_dim`` floats,
    ``heard`` ``None`` when it holds no valid map (fall back to waiting for every sender).
    Never raises."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        return None, None
    payload, n = bytes(payload), 4 * int(obs_dim)
    if len(payload) < n:
        return None, None
    values = np.frombuffer(payload[:n], ">f4").astype(np.float32)
    rest = payload[n:]
    if len(rest) != map_bytes(num_links):  # no map, or one of another length: no map
        return (values, None) if not rest else (None, None)
    return values, parse_map(rest, num_links)


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
