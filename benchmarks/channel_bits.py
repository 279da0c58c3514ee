"""Measured bits per message element against the bit penalty, as a function of z.

Monte Carlo over the dither: for each z on a grid, quantize N copies and count the real payload
bits (paper code) and wire bits (Elias-gamma framing) of the symbols, next to the penalty
log2(levels z + 1) that bounds the payload bits from above.

    python benchmarks/channel_bits.py --levels 15 --samples 100000
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import tyro

from sparsecomm import channel


@dataclasses.dataclass
class Args:
    levels: int = 15
    """|M|, the number of non-null symbols."""
    samples: int = 100_000
    """Dither draws per z."""
    points: int = 21
    """Grid points on [0, 1]."""
    seed: int = 0
    """PRNG seed."""


def main(args: Args) -> None:
    zs = jnp.linspace(0.0, 1.0, args.points)
    keys = jax.random.split(jax.random.key(args.seed), args.points)
    m, _ = jax.vmap(lambda k, z: channel.quantize(k, jnp.full((args.samples,), z), args.levels))(
        keys, zs
    )
    payload = np.asarray(channel.payload_bits(m, "paper"), np.float64)
    # Each element's share of a (non-silent) packet: its presence bit and its codeword (2 L(m)
    # bits); the byte padding and the CRC-32 are per packet (docs/channel.md).
    wire = 1.0 + 2.0 * payload
    penalty = np.asarray(channel.bit_penalty(zs, args.levels))
    print(f"levels={args.levels} samples/z={args.samples} seed={args.seed}")
    print(
        "| z | mean payload bits | 95% CI half-width | penalty log2(Mz+1) "
        "| element's wire share (bit + codeword) |"
    )
    print("|---|---|---|---|---|")
    for i, z in enumerate(np.asarray(zs)):
        half = 1.96 * payload[i].std() / np.sqrt(args.samples)
        print(
            f"| {z:.2f} | {payload[i].mean():.4f} | {half:.4f} | {penalty[i]:.4f} | "
            f"{wire[i].mean():.4f} |"
        )


if __name__ == "__main__":
    main(tyro.cli(Args))
