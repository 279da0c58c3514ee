"""The differentiable discrete channel: quantizer, bit penalty, codes and wire format.

Usable on its own in any JAX model::

    from sparsecomm import channel
    key = channel.dither_key(episode_key, t, sender, recipient)
    m, z_hat = channel.quantize(key, z, levels=15)         # symbols, reconstruction (grad = 1)
    cost = lam * channel.bit_penalty(z, levels=15).sum()   # differentiable bit cost
    bits = channel.payload_bits(m, "paper").sum()          # real bits sent (paper code)
    wire = channel.wire_bits(m, "paper")                   # packet bits of each link (last axis)
    code = channel.fit(links, levels=15)                   # a code fitted to (N, T, C) symbols
    packet = channel.encode(m, "paper")                    # one packet, b"" when m is all null
    assert (channel.decode(packet, "paper", m.shape) == m).all()  # malformed: PacketError

Between agents: ``ChannelConfig`` (``config``) says how a team talks (mode, levels, elements,
code) and what its mode does (``speaks``, ``quantizes``, ``sends_symbols``, ...). The one
channel (``links``), used by the rollout, the plug-in layer and every deployed agent:
``transmit(cfg, z, u, keys, t, live=live)`` is the sender side for links laid out by sender
slot ``(..., K, K-1, C)``, in any mode, with what it cost; ``receive(cfg, message, u, ok=ok,
last=last)`` the receiver side, with the one rule for a missing packet. Its layout and routing
(``routing``): ``live_links`` turns a ``Routing`` or a traced mask into the links that exist;
``deliver`` routes reconstructions to their recipients; ``lossy.LossyLinks`` is the noise
between them inside a rollout. This package imports nothing else of sparsecomm.

A team's link rules (``team``): ``build(cfg, num_agents)`` is the channel built once for a
team, a ``TeamChannel`` that owns its links' state (``LinkState``), answers its actors' inbox
width and steps its links (``exchange``; a deployed agent's own row: ``agent_send``,
``agent_receive``).
Any other team (``layer``, docs/plugin.md): ``send(key, z, routing, t=t)`` sends signals over any
routing (``Routing``) and returns ``Messages`` (symbols, inbox, penalty, bits per link).
"""

from sparsecomm.channel import ecc, lossy, permuted
from sparsecomm.channel.codes import (
    CODE_NAMES,
    MAX_ELEMENTS,
    Code,
    PacketError,
    as_code,
    decode,
    encode,
    frequency_remap,
    packet_bits,
    paper_length,
    payload_bits,
    wire_bits,
)
from sparsecomm.channel.config import CHANNEL_MODES, PRICES, ChannelConfig
from sparsecomm.channel.fitted import FittedCode, fit
from sparsecomm.channel.frames import (
    CHECK_BITS,
    FrameError,
    check_width,
    decode_frame,
    encode_frame,
    frame_bits,
    link_bits,
)
from sparsecomm.channel.gate import GATES, gate, hard_gate
from sparsecomm.channel.layer import Messages, reconstruct, send
from sparsecomm.channel.links import (
    Received,
    Sent,
    decode_link,
    decode_sender,
    dither_links,
    encode_link,
    encode_sender,
    last_delivered,
    link_dither,
    listed_dither,
    news_gate,
    null_message,
    price,
    receive,
    step_dither,
    transmit,
)
from sparsecomm.channel.noise import NoiseConfig, NoisyLink
from sparsecomm.channel.penalty import bit_penalty, expected_bits, expected_frame_bits
from sparsecomm.channel.quantizer import (
    dequantize,
    dither,
    dither_key,
    quantize,
    quantize_dithered,
)
from sparsecomm.channel.routing import (
    Routing,
    deliver,
    inbox,
    link_tables,
    listed,
    listed_pairs,
    live_links,
    others,
    pairs,
    routing_mask,
    slots,
)
from sparsecomm.channel.team import Exchange, LinkState, TeamChannel, build

__all__ = [
    "Exchange",
    "LinkState",
    "TeamChannel",
    "build",
    "CHANNEL_MODES",
    "CHECK_BITS",
    "PRICES",
    "CODE_NAMES",
    "GATES",
    "MAX_ELEMENTS",
    "NoiseConfig",
    "NoisyLink",
    "ChannelConfig",
    "Code",
    "FittedCode",
    "FrameError",
    "Messages",
    "PacketError",
    "Received",
    "Routing",
    "Sent",
    "as_code",
    "bit_penalty",
    "check_width",
    "decode",
    "decode_frame",
    "decode_link",
    "decode_sender",
    "deliver",
    "dequantize",
    "dither",
    "dither_key",
    "dither_links",
    "ecc",
    "lossy",
    "encode",
    "encode_frame",
    "encode_link",
    "encode_sender",
    "expected_bits",
    "expected_frame_bits",
    "fit",
    "frame_bits",
    "frequency_remap",
    "gate",
    "hard_gate",
    "inbox",
    "last_delivered",
    "link_bits",
    "link_dither",
    "link_tables",
    "listed",
    "listed_dither",
    "listed_pairs",
    "live_links",
    "news_gate",
    "null_message",
    "others",
    "pairs",
    "permuted",
    "packet_bits",
    "paper_length",
    "payload_bits",
    "price",
    "quantize",
    "quantize_dithered",
    "receive",
    "reconstruct",
    "routing_mask",
    "send",
    "slots",
    "step_dither",
    "transmit",
    "wire_bits",
]
