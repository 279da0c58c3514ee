"""The differentiable bit penalty of paper eq. (2) and SPEC section 3.

Per message element ``l(z) = log2(levels * z + 1)``. It bounds the expected length of the paper's
code from above: ``E[L(m) | z] <= E[log2(m + 1) | z] <= log2(E[m | z] + 1) = log2(levels z + 1)``
(``L(m) = floor(log2(m + 1))``, then Jensen). Learners sum it over senders, recipients and
elements of a step; how they normalise it over steps and episodes is documented where it is used
(:mod:`sparsecomm.rl`, :mod:`sparsecomm.imitation`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.quantizer import check_levels, check_unit_interval

__all__ = ["bit_penalty", "expected_bits", "expected_frame_bits"]


def bit_penalty(z: jax.Array, levels: int) -> jax.Array:
    """Elementwise surrogate bit cost ``log2(levels * z + 1)`` of signals ``z`` in [0, 1]."""
    levels = check_levels(levels)
    check_unit_interval(z)
    return jnp.log2(levels * jnp.asarray(z, jnp.float32) + 1.0)


def expected_bits(z: jax.Array, levels: int, lengths) -> jax.Array:
    """Exact expected codeword bits of dithered symbols of ``z`` (..., C) under a code whose
    element k spends ``lengths[k, m]`` bits on symbol m (``(C, levels + 1)``, e.g. a learned
    code's ``Code.lengths()``).

    With the dither, ``m = floor(levels z) + 1`` with probability ``f``, the fractional part of
    ``levels z``, else ``floor(levels z)``, so the expectation is ``(1 - f) lengths[lo] +
    f lengths[lo + 1]``: piecewise linear in z, its gradient the price of moving toward the
    next symbol (0 where neighbouring symbols cost the same). For the paper's code it is the
    quantity ``log2(levels z + 1)`` bounds from above.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    x = levels * jnp.asarray(z, jnp.float32)
    lo = jnp.clip(jnp.floor(jax.lax.stop_gradient(x)), 0, levels).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, levels)
    frac = x - lo
    table = jnp.asarray(lengths, jnp.float32)
    k = jnp.arange(table.shape[0])
    return (1.0 - frac) * table[k, lo] + frac * table[k, hi]


_COS8 = np.cos(2 * np.pi * np.arange(8) / 8).astype(np.float32)  # numpy: no device at import
_SIN8 = np.sin(2 * np.pi * np.arange(8) / 8).astype(np.float32)
_OMEGA = np.arange(1, 5)  # the residues w = 1..4 of the characteristic function (w = 0 is 1)


def _turn(lengths, omega=_OMEGA):
    """``exp(-2 pi i w lengths / 8)`` for w = 1..4, as (cos, -sin): (..., 4) each."""
    turn = (jnp.asarray(lengths)[..., None] * omega) % 8
    return jnp.asarray(_COS8)[turn], -jnp.asarray(_SIN8)[turn]


def expected_frame_bits(
    z: jax.Array, levels: int, wire_lengths, check_bits: int = 32, gate=None
) -> jax.Array:
    """Exact expected bits of one sender's frame under the dithered quantizer, ``E[8 *
    len(channel.encode_frame(m))]``, differentiable (piecewise linear in each element between
    symbol boundaries, smooth in the gates).

    Args:
      z: (..., L, C) the signals of the sender's L links, in [0, 1].
      levels: |M|.
      wire_lengths: (C, levels + 1) the bits each element's symbol adds to its link's body
        beyond the presence bitmap (``Code.wire_lengths``; 0 for the null).
      check_bits: the frame's check (``ChannelConfig.check_bits``).
      gate: (..., L) each link's probability of opening (``ChannelConfig.link_gate``), or
        ``None``: always open.

    Returns:
      (...) float32 expected frame bits.

    The frame (``channel.frames``) is an L-bit recipient map, then each speaking link's C-bit
    presence bitmap and codewords, zero padding to a byte and the check. A link speaks when its
    gate opens and one of its symbols is not null; a sender none of whose links speaks sends no
    frame. Element k's symbol is ``floor(levels z_k)`` or one more (probability ``f_k``, the
    fractional part), independently of the others (each has its own dither), so with
    ``p0_l = prod_k max(0, 1 - levels z_lk)`` the chance that link l's symbols are all null and
    ``q = prod_l (1 - g_l (1 - p0_l))`` the chance that no link speaks::

        E[W] = (1 - q) (L + check_bits) + sum_l g_l ((1 - p0_l) C + E[S_l])
               + E[pad(L + X); some link speaks]

    ``S_l`` the codeword bits of link l and ``X`` the links' bits after the recipient map. The
    padding term comes from the distribution of ``X mod 8``: the product of the links'
    characteristic functions on the 8 residues, each the gate's mixture of silence and of its
    bitmap plus the product of its elements' characteristic functions. The cliff: ``p0_l`` is
    0, with no gradient, as soon as one element has ``levels z_lk >= 1``; a gate's ``g_l`` then
    still prices the link's whole body.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    x = levels * jnp.asarray(z, jnp.float32)
    num_links, c = x.shape[-2], x.shape[-1]
    g = jnp.ones(x.shape[:-1], jnp.float32) if gate is None else jnp.asarray(gate, jnp.float32)
    lo = jnp.clip(jnp.floor(jax.lax.stop_gradient(x)), 0, levels).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, levels)
    f = x - lo
    table = jnp.asarray(wire_lengths, jnp.int32)
    k = jnp.arange(c)
    len_lo, len_hi = table[k, lo], table[k, hi]
    codewords = ((1.0 - f) * len_lo + f * len_hi).sum(-1)  # (..., L): E[S_l]
    p0 = jnp.prod(jnp.where(lo == 0, 1.0 - f, 0.0), -1)  # (..., L)
    speaks = g * (1.0 - p0)
    quiet = jnp.prod(1.0 - speaks, -1)  # (...): no link speaks
    # Phi_l(w) = E[exp(-2 pi i w S_l / 8)], w = 1..4: the product over the link's elements of
    # each one's two symbols, in real arithmetic.
    (a_lo, b_lo), (a_hi, b_hi) = _turn(len_lo), _turn(len_hi)
    fw = f[..., None]
    a, b = (1.0 - fw) * a_lo + fw * a_hi, (1.0 - fw) * b_lo + fw * b_hi  # (..., L, C, 4)
    re, im = a[..., 0, :], b[..., 0, :]
    for j in range(1, c):
        re, im = re * a[..., j, :] - im * b[..., j, :], re * b[..., j, :] + im * a[..., j, :]
    # psi_l(w) = (1 - g) + g (p0 + exp(-2 pi i w C / 8) (Phi_l(w) - p0)): the link's bits
    cw, sw = _turn(np.int32(c))
    p0w, gw = p0[..., None], g[..., None]
    spoke_re, spoke_im = cw * (re - p0w) - sw * im, cw * im + sw * (re - p0w)
    link_re, link_im = 1.0 - gw + gw * (p0w + spoke_re), gw * spoke_im  # (..., L, 4)
    re, im = link_re[..., 0, :], link_im[..., 0, :]
    for j in range(1, num_links):
        lr, li = link_re[..., j, :], link_im[..., j, :]
        re, im = re * lr - im * li, re * li + im * lr
    # E[pad(L + X)] = sum_w Phi_X(w) Q(w), Q the inverse DFT of the padding after r = X mod 8;
    # X is real, so Phi_X(8 - w) is Phi_X(w)'s conjugate and w = 1..4 suffice (Phi_X(0) = 1).
    r = np.arange(8)
    pad = (-(num_links + r)) % 8
    angle = 2 * np.pi * np.outer(_OMEGA, r) / 8
    twice = np.array([2.0, 2.0, 2.0, 1.0])  # w and 8 - w, and w = 4 once
    q_re = jnp.asarray(twice * (pad * np.cos(angle)).sum(1) / 8, jnp.float32)
    q_im = jnp.asarray(twice * (pad * np.sin(angle)).sum(1) / 8, jnp.float32)
    padding = pad.mean() + (re * q_re - im * q_im).sum(-1) - quiet * pad[0]
    body = (g * ((1.0 - p0) * c + codewords)).sum(-1)
    return (1.0 - quiet) * (num_links + check_bits) + body + padding


def code_penalty(z: jax.Array, levels: int, code) -> jax.Array:
    """The differentiable bit cost of each element of ``z`` under ``code``: the paper's
    :func:`bit_penalty`, or for a learned code (a ``channel.Code`` with ``remap``) the exact
    expected bits of its codewords (:func:`expected_bits`)."""
    if getattr(code, "remap", ()):
        return expected_bits(z, levels, code.lengths())
    return bit_penalty(z, levels)
