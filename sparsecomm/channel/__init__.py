"""The differentiable discrete channel: quantizer, bit penalty, codes and wire format.

Usable on its own in any JAX model::

    from sparsecomm import channel
    key = channel.dither_key(episode_key, t, sender, recipient)
    m, z_hat = channel.quantize(key, z, levels=15)         # symbols, reconstruction (grad = 1)
    cost = lam * channel.bit_penalty(z, levels=15).sum()   # differentiable bit cost
    bits = channel.payload_bits(m, "paper").sum()          # real bits sent (paper code)
    packet = channel.encode(m, "paper")                    # bytes on the wire
    assert (channel.decode(packet, "paper", m.shape) == m).all()
"""

from sparsecomm.channel.codes import (
    CODE_NAMES,
    Code,
    as_code,
    decode,
    encode,
    packet_bits,
    paper_length,
    payload_bits,
    wire_bits,
)
from sparsecomm.channel.gate import GATES, gate, hard_gate
from sparsecomm.channel.penalty import bit_penalty
from sparsecomm.channel.quantizer import (
    dequantize,
    dither,
    dither_key,
    quantize,
    quantize_dithered,
)

__all__ = [
    "CODE_NAMES",
    "GATES",
    "Code",
    "as_code",
    "bit_penalty",
    "decode",
    "dequantize",
    "dither",
    "dither_key",
    "encode",
    "gate",
    "hard_gate",
    "packet_bits",
    "paper_length",
    "payload_bits",
    "quantize",
    "quantize_dithered",
    "wire_bits",
]
