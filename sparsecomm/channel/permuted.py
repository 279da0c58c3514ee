"""The permuted symbol channel: bit flips that corrupt symbols independently of the message.

Freed et al. (AAAI 2020, "Communication learning via backpropagation in discrete channels with
unknown noise") train through a noisy channel by sending every symbol through a fresh random
permutation of the codewords, known to sender and receiver alone. ``ChannelConfig.code =
"permuted"`` builds that channel from this module:

- **On the wire** each element's symbol ``m`` in ``{0, ..., levels}`` (``L = levels + 1``
  symbols) travels as a ``b = ceil(log2 L)``-bit codeword ``sigma[m]``, where ``sigma`` is a
  uniformly random permutation of the ``2^b`` codewords, drawn per element, link and step from
  the link's shared key. A link's packet is its ``C`` codewords packed into
  ``ceil(C b / 8)`` bytes: no bitmap, no length, no CRC, always sent (silence is a message
  like any other), so flips are never detected and never drop a packet.
- **The receiver** undoes the permutation: the flipped codeword ``c'`` gives the symbol
  ``sigma^-1[c']``, or, when ``c'`` is one of the ``2^b - L`` unused codewords, a fallback
  symbol drawn uniformly from the same shared key.
- **The error does not depend on the message.** Averaged over the permutation, the received
  symbol is the sent one with probability ``1 - eps`` and each other symbol with probability
  ``eps / (L - 1)``, whatever was sent and whatever the flip model (symmetric, asymmetric,
  bursts): an L-ary symmetric channel (:func:`symbol_error_rate` gives ``eps``). So the
  expected reconstruction is affine in the signal, ``E[z_hat | z] = alpha z + const`` with
  ``alpha = 1 - eps L / (L - 1)`` (:func:`gradient_scale`), and the rollout passes the gradient
  ``alpha`` through a corrupted message: the gradient of the expected message, unbiased.

Without the permutation the same flips would hit some symbols more than others (under
AAAI 2020's asymmetric 0.1 / 0.05 flips, ``1111`` breaks more often than ``0000``); the tests
check both. Erasure (whole packets lost) and delay work as for every code
(``sparsecomm.channel.noise``). The price: every link sends ``C b`` bits at every step (40 at
the paper's C = 10, levels = 15), what a fixed-width code costs, and no sparsity on the wire;
the payload bits and the penalty stay the paper's count.

Under ``jit`` the rollout draws the channel's law (:func:`corrupt`: each symbol wrong with
probability ``eps``, then uniform among the others; two draws per element), which the tests
check against the mechanism bit by bit (:func:`simulate`) and against real packets: the host
codec (:func:`tables`, :func:`encode`, :func:`decode`) draws each link's permutations from its
shared key, as a deployment does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.codes import PacketError
from sparsecomm.channel.noise import NoiseConfig
from sparsecomm.channel.quantizer import check_levels

__all__ = [
    "codeword_bits",
    "corrupt",
    "decode",
    "encode",
    "gradient_scale",
    "packet_bits",
    "simulate",
    "symbol_error_rate",
    "tables",
]


def codeword_bits(levels: int) -> int:
    """``b = ceil(log2(levels + 1))``: bits of each element's codeword."""
    return check_levels(levels).bit_length()


def packet_bits(num_elements: int, levels: int) -> int:
    """Bits of every link's packet: ``C`` codewords padded to whole bytes."""
    return 8 * -(-num_elements * codeword_bits(levels) // 8)


def symbol_error_rate(levels: int, p01, p10):
    """``eps``: the probability that the received symbol differs from the sent one, the same
    for every sent symbol, when each 0 bit of a codeword flips with probability ``p01`` and
    each 1 bit with ``p10`` (floats, or arrays under ``jit``).

    The codeword of a symbol under a uniform permutation is uniform over all ``2^b``, so each of
    its bits is 0 or 1 with probability 1/2 and it is changed with probability ``q = 1 - (1 -
    (p01 + p10) / 2)^b``. A changed codeword is one of the other ``L - 1`` symbols' with
    probability ``(L - 1) / (2^b - 1)`` (always wrong), else unused, and then the fallback
    symbol is wrong with probability ``(L - 1) / L``.
    """
    b, n = codeword_bits(levels), levels + 1
    q = 1.0 - (1.0 - 0.5 * (p01 + p10)) ** b
    used = (n - 1) / (2**b - 1)
    return q * (used + (1.0 - used) * (n - 1) / n)


def gradient_scale(levels: int, noise: NoiseConfig) -> float:
    """``alpha = 1 - eps L / (L - 1)``: the slope of the expected received symbol in the sent
    one (``E[r | m] = alpha m + eps L / 2``), the gradient a corrupted message passes back,
    with ``eps`` the symbol error rate of ``noise``'s flips (a burst channel's mean over its
    stationary share of bad steps)."""
    if noise.burst:
        share = noise.burst_bad_share
        eps = share * symbol_error_rate(levels, noise.burst_flip_bad, noise.burst_flip_bad)
        eps += (1 - share) * symbol_error_rate(levels, noise.burst_flip_good, noise.burst_flip_good)
    else:
        eps = symbol_error_rate(levels, *noise.flip_rates)
    n = levels + 1
    return 1.0 - eps * n / (n - 1)


def _draw(key: jax.Array, shape, levels: int) -> tuple[jax.Array, jax.Array]:
    """Per element of ``shape``: a uniform permutation of the 2^b codewords (argsort of uniform
    draws; ties have probability ~0) and a fallback symbol."""
    b = codeword_bits(levels)
    k_perm, k_fall = jax.random.split(key)
    sigma = jnp.argsort(jax.random.uniform(k_perm, (*shape, 2**b)), axis=-1).astype(jnp.int32)
    fallback = jax.random.randint(k_fall, shape, 0, levels + 1, jnp.int32)
    return sigma, fallback


def _flip(key: jax.Array, codewords: jax.Array, b: int, p01, p10) -> jax.Array:
    """Flip each bit of ``b``-bit codewords, 0 -> 1 with ``p01`` and 1 -> 0 with ``p10``
    (scalars or arrays broadcasting against ``codewords``)."""
    weights = 2 ** jnp.arange(b, dtype=jnp.int32)
    bits = (codewords[..., None] >> jnp.arange(b, dtype=jnp.int32)) & 1
    p = jnp.where(bits == 1, jnp.asarray(p10)[..., None], jnp.asarray(p01)[..., None])
    flips = jax.random.uniform(key, bits.shape) < p
    return codewords ^ (flips.astype(jnp.int32) * weights).sum(-1)


def _unpermute(sigma: jax.Array, fallback: jax.Array, codewords: jax.Array, levels: int):
    """The symbol whose codeword is ``codewords`` (the fallback for an unused codeword)."""
    index = jnp.argmax(sigma == codewords[..., None], axis=-1).astype(jnp.int32)
    return jnp.where(index <= levels, index, fallback)


def corrupt(key: jax.Array, m: jax.Array, levels: int, p01, p10) -> jax.Array:
    """Under ``jit``: the symbols a receiver gets when symbols ``m`` (any shape, int in [0,
    levels]) cross the permuted channel with bit flips ``p01``, ``p10`` (scalars, or arrays
    broadcasting against ``m``: a burst channel's per-link state).

    Draws from the channel's law: each symbol independently arrives wrong with probability
    ``eps`` (:func:`symbol_error_rate`), as a uniform choice among the other symbols; two draws
    per element. The law of :func:`simulate`, the bit-level mechanism, which the tests compare
    it with.
    """
    m = jnp.asarray(m, jnp.int32)
    k_err, k_off = jax.random.split(key)
    wrong = jax.random.uniform(k_err, m.shape) < symbol_error_rate(levels, p01, p10)
    offset = jax.random.randint(k_off, m.shape, 1, levels + 1, jnp.int32)
    return jnp.where(wrong, (m + offset) % (levels + 1), m)


def simulate(key: jax.Array, m: jax.Array, levels: int, p01, p10, permute: bool = True):
    """The permuted channel bit by bit, under ``jit``: a fresh permutation per symbol, its
    codeword's bits flipped (0 -> 1 with ``p01``, 1 -> 0 with ``p10``), the flipped codeword
    unpermuted (:func:`corrupt` draws the same law, cheaply).

    ``permute=False`` sends the plain binary codeword ``m`` instead (an unused codeword reads as
    ``levels``): the corruption then depends on the message, the contrast the tests measure.
    """
    m = jnp.asarray(m, jnp.int32)
    b = codeword_bits(levels)
    k_tables, k_flip = jax.random.split(key)
    if not permute:
        return jnp.minimum(_flip(k_flip, m, b, p01, p10), levels)
    sigma, fallback = _draw(k_tables, m.shape, levels)
    sent = jnp.take_along_axis(sigma, m[..., None], axis=-1)[..., 0]
    return _unpermute(sigma, fallback, _flip(k_flip, sent, b, p01, p10), levels)


# -- host side: the real packets of one link -------------------------------------------------


def tables(link_key: jax.Array, num_elements: int, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma, fallback)`` of one link at one step, from its shared key (e.g.
    ``jax.random.fold_in(channel.dither_key(key, t, sender, recipient), 1)``): ``sigma[k, m]``
    is element k's codeword for symbol m, ``fallback[k]`` its symbol for an unused codeword."""
    sigma, fallback = _draw(link_key, (num_elements,), levels)
    return np.asarray(sigma), np.asarray(fallback)


def encode(m, link_key: jax.Array, levels: int) -> bytes:
    """The packet of one link's symbols ``m`` (C,): each symbol's permuted ``b``-bit codeword,
    most significant bit first, zero-padded to whole bytes. Raises ``ValueError`` for symbols
    outside [0, levels]."""
    m = np.asarray(m)
    if m.ndim != 1 or not np.issubdtype(m.dtype, np.integer) or m.size == 0:
        raise ValueError(f"m must be a non-empty 1-d integer array, got {m.dtype} {m.shape}")
    if m.min() < 0 or m.max() > levels:
        raise ValueError(f"symbols must lie in [0, {levels}], got [{m.min()}, {m.max()}]")
    sigma, _ = tables(link_key, m.size, levels)
    b = codeword_bits(levels)
    codewords = sigma[np.arange(m.size), m]
    bits = (codewords[:, None] >> np.arange(b - 1, -1, -1)) & 1
    return np.packbits(bits.reshape(-1).astype(np.uint8)).tobytes()


def decode(packet: bytes, link_key: jax.Array, levels: int, num_elements: int) -> np.ndarray:
    """The symbols (C,) int32 in a packet of :func:`encode`, possibly with flipped bits: every
    packet of the right length decodes (flips give other symbols, not errors). Raises
    :class:`~sparsecomm.channel.codes.PacketError` for any other length."""
    b = codeword_bits(levels)
    size = packet_bits(num_elements, levels) // 8
    if not isinstance(packet, (bytes, bytearray)) or len(packet) != size:
        got = len(packet) if isinstance(packet, (bytes, bytearray)) else type(packet).__name__
        raise PacketError(
            f"a permuted packet of {num_elements} elements has {size} bytes, got {got}"
        )
    bits = np.unpackbits(np.frombuffer(bytes(packet), np.uint8))[: num_elements * b]
    codewords = bits.reshape(num_elements, b) @ (1 << np.arange(b - 1, -1, -1))
    sigma, fallback = tables(link_key, num_elements, levels)
    index = np.argmax(sigma == codewords[:, None], axis=1)
    return np.where(index <= levels, index, fallback).astype(np.int32)
