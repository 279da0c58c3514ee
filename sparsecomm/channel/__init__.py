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

Between agents (``links``): ``ChannelConfig`` says how a team talks (mode, levels, elements,
code); ``transmit(cfg, z, u, keys, t)`` sends a batch of links ``(B, K, K-1, C)`` in any mode
and counts what it cost; ``deliver`` routes the reconstructions to their recipients. This
package imports nothing else of sparsecomm.

Any other team (``layer``, docs/plugin.md): ``send(key, z, routing, t=t)`` sends signals over any
routing (``Routing``) and returns ``Messages`` (symbols, inbox, penalty, bits per link).
"""

from sparsecomm.channel import ecc, permuted
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
from sparsecomm.channel.fitted import FittedCode, fit
from sparsecomm.channel.gate import GATES, gate, hard_gate
from sparsecomm.channel.layer import Messages, Routing, reconstruct, send
from sparsecomm.channel.links import (
    CHANNEL_MODES,
    ChannelConfig,
    Sent,
    deliver,
    link_dither,
    link_tables,
    others,
    step_dither,
    transmit,
)
from sparsecomm.channel.noise import NoiseConfig, NoisyLink, receive
from sparsecomm.channel.penalty import bit_penalty, expected_bits
from sparsecomm.channel.quantizer import (
    dequantize,
    dither,
    dither_key,
    quantize,
    quantize_dithered,
)

__all__ = [
    "CHANNEL_MODES",
    "CODE_NAMES",
    "GATES",
    "MAX_ELEMENTS",
    "NoiseConfig",
    "NoisyLink",
    "ChannelConfig",
    "Code",
    "FittedCode",
    "Messages",
    "PacketError",
    "Routing",
    "Sent",
    "as_code",
    "bit_penalty",
    "decode",
    "deliver",
    "dequantize",
    "dither",
    "dither_key",
    "ecc",
    "encode",
    "expected_bits",
    "fit",
    "frequency_remap",
    "gate",
    "hard_gate",
    "link_dither",
    "link_tables",
    "others",
    "permuted",
    "packet_bits",
    "paper_length",
    "payload_bits",
    "quantize",
    "quantize_dithered",
    "receive",
    "reconstruct",
    "send",
    "step_dither",
    "transmit",
    "wire_bits",
]
