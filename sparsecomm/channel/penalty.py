"""The differentiable bit penalty of paper eq. (2) and SPEC section 3.

Per message element ``l(z) = log2(levels * z + 1)``. It bounds the expected length of the paper's
code from above: ``E[L(m) | z] <= E[log2(m + 1) | z] <= log2(E[m | z] + 1) = log2(levels z + 1)``
(``L(m) = floor(log2(m + 1))``, then Jensen). Learners sum it over senders, recipients and
elements of a step; how they normalise it over steps and episodes is documented where it is used
(:mod:`sparsecomm.rl`, :mod:`sparsecomm.imitation`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

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
    padding term comes from the distribution of ``X mod 8``, through its characteristic
    function: the product over links of each one's (the gate's mixture of silence and of its
    bitmap plus codewords), each of those the product over its elements of one step between
    two symbols. Every length and C share the factor ``d = gcd(8, C, lengths)`` (2 for the
    paper's code, whose codewords have even lengths), so only ``X / d`` modulo ``8 / d``
    matters: frequencies 1 and 2 of 4 for the paper's code instead of 1 to 4 of 8.

    The gradient is written out, not traced (``jax.custom_vjp``): the derivative of a product
    in one factor is the product of the others, formed as the product over the factor (a
    factor below 1e-15 in modulus stands in as 1e-15 there, so that the others' product of an
    exact zero is exact and a product that holds a zero comes out 1e-15 times too large
    instead of 0). The forward pass computes value and gradient together in a few fused
    passes; the backward pass is one multiplication. The cliff: ``p0_l`` is 0, with no
    gradient, as soon as one element has ``levels z_lk >= 1``; a gate's ``g_l`` then still
    prices the link's whole body.
    """
    levels = check_levels(levels)
    check_unit_interval(z)
    x = levels * jnp.asarray(z, jnp.float32)
    num_links, c = x.shape[-2], x.shape[-1]
    g = jnp.ones(x.shape[:-1], jnp.float32) if gate is None else jnp.asarray(gate, jnp.float32)
    lo = jnp.clip(jnp.floor(jax.lax.stop_gradient(x)), 0, levels).astype(jnp.int32)
    table = np.asarray(wire_lengths, np.int64)
    k = jnp.arange(c)
    len_lo = jnp.asarray(table, jnp.float32)[k, lo]  # (..., L, C) bits of the lower symbol
    dlen = jnp.asarray(_step_up(table), jnp.float32)[k, lo]  # and the step up's
    frame = _FrameShape.of(table, num_links, check_bits)
    return _frame_bits(frame, x - lo, g, len_lo, dlen, (lo == 0).astype(jnp.float32))


def _step_up(table: np.ndarray) -> np.ndarray:
    """(C, levels + 1) the bits each element's symbol gains by one step up to the next symbol,
    from a (C, levels + 1) length table (0 at the top symbol, which has no next)."""
    hi = np.minimum(np.arange(table.shape[1]) + 1, table.shape[1] - 1)
    return table[:, hi] - table


@dataclasses.dataclass(frozen=True)
class _FrameShape:
    """What :func:`expected_frame_bits` needs to know of a code and a frame, all static.

    ``d``: the factor shared by C and every length; ``period = 8 / d``; per frequency ``w`` of
    ``X / d mod period`` that matters (1 to period / 2; the others are their conjugates),
    ``steps``: each step up between symbols that turns by ``v`` (a
    residue) as ``(v, exp(-2 pi i w v / period) - 1)``, ``turn``: ``exp(-2 pi i w r /
    period)`` for each residue ``r``, ``weight``: the padding's Fourier weight; ``head``: ``L
    + check_bits``, ``pad``: the padding after each residue of ``X / d``.
    """

    c: int
    d: int
    period: int
    steps: tuple
    turn: tuple
    weight: tuple
    head: float
    pad: tuple

    @staticmethod
    @functools.lru_cache(maxsize=64)
    def _build(lengths: bytes, shape: tuple, num_links: int, check_bits: int) -> _FrameShape:
        table = np.frombuffer(lengths, np.int64).reshape(shape)
        c = shape[0]
        d = math.gcd(8, c, *np.unique(table).tolist())
        period = 8 // d
        omega = tuple(range(1, period // 2 + 1))
        ups = sorted(set(((_step_up(table) // d) % period).ravel().tolist()) - {0})
        r = np.arange(period)
        pad = (-(num_links + d * r)) % 8
        return _FrameShape(
            c=c,
            d=d,
            period=period,
            steps=tuple(tuple((v, _unit(w * v, period) - 1) for v in ups) for w in omega),
            turn=tuple(tuple(_unit(w * r, period).tolist()) for w in omega),
            weight=tuple(
                complex(
                    (1.0 if 2 * w == period else 2.0)  # w and period - w, or w once
                    * (pad * np.exp(2j * np.pi * w * r / period)).sum()
                    / period
                )
                for w in omega
            ),
            head=float(num_links + check_bits),
            pad=tuple(float(p) for p in pad),
        )

    @classmethod
    def of(cls, table: np.ndarray, num_links: int, check_bits: int) -> _FrameShape:
        return cls._build(table.tobytes(), table.shape, num_links, int(check_bits))


def _unit(k, period: int):
    """``exp(-2 pi i k / period)``, exact on the quarter turns (complex or array)."""
    v = np.exp(-2j * np.pi * np.asarray(k) / period)
    v = np.round(v.real, 12) + 1j * np.round(v.imag, 12)
    return complex(v) if v.ndim == 0 else v


_TINY = 1e-15  # a factor's stand-in modulus when forming the product of the others


def _and_others(re, im=None):
    """Product along the last axis of factors ``re + i im`` (``im`` None: real) and, for each
    factor, the product of all the others: ((...), (..., n)) as (re, im) pairs (im None when
    real). A factor below ``_TINY`` in modulus stands in as ``_TINY`` for the others' products
    (see :func:`expected_frame_bits`)."""
    if im is None:
        safe = jnp.where(jnp.abs(re) < _TINY, _TINY, re)
        both = jnp.prod(safe, -1, keepdims=True)
        return (jnp.prod(re, -1), None), (both / safe, None)
    tiny = re * re + im * im < _TINY * _TINY
    safe_re, safe_im = jnp.where(tiny, _TINY, re), jnp.where(tiny, 0.0, im)
    both = jnp.prod(jax.lax.complex(safe_re, safe_im), -1, keepdims=True)
    b_re, b_im = jnp.real(both), jnp.imag(both)
    modulus = safe_re * safe_re + safe_im * safe_im
    others_re = (b_re * safe_re + b_im * safe_im) / modulus  # both / safe
    others_im = (b_im * safe_re - b_re * safe_im) / modulus
    whole = jnp.prod(jax.lax.complex(re, im), -1)
    return (jnp.real(whole), jnp.imag(whole)), (others_re, others_im)


def _complex(re, im):
    return re if im is None else jax.lax.complex(re, im)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _frame_bits(s: _FrameShape, f, g, len_lo, dlen, null):
    """Expected frame bits from each element's step probability ``f`` (..., L, C), the gates
    ``g`` (..., L), the lower symbol's bits ``len_lo``, the step's ``dlen`` and whether the
    lower symbol is the null (all (..., L, C))."""
    return _frame_bits_and_grads(s, f, g, len_lo, dlen, null)[0]


def _frame_bits_and_grads(s: _FrameShape, f, g, len_lo, dlen, null):
    """(value (...), (d value / d f (..., L, C), d value / d g (..., L)))."""
    a = null * (1.0 - f)  # (..., L, C): the element is null
    (p0, _), (a_others, _) = _and_others(a)
    u = 1.0 - g * (1.0 - p0)  # (..., L): the link is silent
    (q, _), (u_others, _) = _and_others(u)
    codewords = (len_lo + f * dlen).sum(-1)  # (..., L): E[S_l]
    value = (1.0 - q) * s.head + (g * ((1.0 - p0) * s.c + codewords)).sum(-1)
    value += sum(s.pad) / s.period - q * s.pad[0]  # the padding's mean, none without a frame
    d_q = -(s.head + s.pad[0])
    d_p0 = d_q * u_others * g - g * s.c
    d_f = g[..., None] * dlen
    d_g = -d_q * u_others * (1.0 - p0) + (1.0 - p0) * s.c + codewords
    up = jnp.mod(dlen.astype(jnp.int32) // s.d, s.period)  # (..., L, C) residue of a step up
    first = jnp.mod(s.c // s.d + len_lo.sum(-1).astype(jnp.int32) // s.d, s.period)  # (..., L)
    for steps, turn, weight in zip(s.steps, s.turn, s.weight, strict=True):
        # link l's characteristic function at this frequency: its bitmap and lower symbols'
        # turn times the product over elements of (1 + f (e - 1)), e the step up's turn
        e_re = sum(jnp.where(up == v, e.real, 0.0) for v, e in steps)
        real = all(e.imag == 0 for _, e in steps)
        e_im = None if real else sum(jnp.where(up == v, e.imag, 0.0) for v, e in steps)
        (phi_re, phi_im), (x_re, x_im) = _and_others(1.0 + f * e_re, None if real else f * e_im)
        base = jnp.asarray(np.asarray(turn, np.complex64))[first]  # (..., L)
        c_w = turn[(s.c // s.d) % s.period]
        phi = base * _complex(phi_re, phi_im)
        psi = 1.0 - g + g * p0 * (1.0 - c_w) + g * phi  # the link's bits, gate included
        (all_re, all_im), (o_re, o_im) = _and_others(jnp.real(psi), jnp.imag(psi))
        value += jnp.real(weight * jax.lax.complex(all_re, all_im))
        d_psi = weight * jax.lax.complex(o_re, o_im)  # (..., L)
        d_p0 += jnp.real(d_psi * g * (1.0 - c_w))
        d_g += jnp.real(d_psi * (p0 * (1.0 - c_w) + phi - 1.0))
        d_phi = (d_psi * g * base)[..., None]  # (..., L, 1) per unit of the element product
        if real:  # Re(d_phi e x_others), e and the others' products real
            d_f += e_re * jnp.real(d_phi) * x_re
        else:
            ex_re, ex_im = e_re * x_re - e_im * x_im, e_re * x_im + e_im * x_re
            d_f += jnp.real(d_phi) * ex_re - jnp.imag(d_phi) * ex_im
    d_f -= d_p0[..., None] * null * a_others
    return value, (d_f, d_g)


def _frame_bits_fwd(s, f, g, len_lo, dlen, null):
    value, grads = _frame_bits_and_grads(s, f, g, len_lo, dlen, null)
    return value, (grads, len_lo, dlen, null)


def _frame_bits_bwd(s, residuals, ct):
    (d_f, d_g), *constants = residuals
    zeros = [jnp.zeros_like(x) for x in constants]  # the symbols' tables: no gradient
    return (ct[..., None, None] * d_f, ct[..., None] * d_g, *zeros)


_frame_bits.defvjp(_frame_bits_fwd, _frame_bits_bwd)


def code_penalty(z: jax.Array, levels: int, code) -> jax.Array:
    """The differentiable bit cost of each element of ``z`` under ``code``: the paper's
    :func:`bit_penalty`, or for a learned code (a ``channel.Code`` with ``remap``) the exact
    expected bits of its codewords (:func:`expected_bits`)."""
    if getattr(code, "remap", ()):
        return expected_bits(z, levels, code.lengths())
    return bit_penalty(z, levels)
