"""The one channel between agents: each link's dither, the sender side (:func:`transmit`), the
receiver side (:func:`receive`) and one link's packet on a real network.

The rollout, the plug-in layer (``channel.layer``) and every deployed agent (``deploy``) call
these functions and no others, so a new mode, code or rule is written here once. Links are laid
out by sender slot, ``(..., K, K-1, ...)``, and which exist is a ``live`` mask
(``channel.routing``: the layout, ``Routing``, ``live_links``).

Dither. Link i -> j at step t of an episode with channel key ``key`` draws its dither from
``dither_key(key, t, i, j)`` (docs/spec.md section 1), so a receiver regenerates it alone:
:func:`dither_links` draws the dither of any set of links, steps and episodes in one vectorised
call (:func:`link_dither`: every step of a batch; :func:`step_dither`: one step).

Missing packets. :func:`receive` applies the one rule for a packet that did not arrive (lost,
late, or garbled): the null message (all-null symbols, rebuilt with the link's dither) or, with
``on_drop = "last"``, the link's last good reconstruction (zeros before the first).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from sparsecomm.channel.codes import Code, PacketError, decode, encode, payload_bits, wire_bits
from sparsecomm.channel.config import ChannelConfig
from sparsecomm.channel.ecc import decode as ecc_decode
from sparsecomm.channel.ecc import encode as ecc_encode
from sparsecomm.channel.ecc import wire_bits as ecc_bits
from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.frames import (
    decode_frame,
    encode_frame,
    frame_bits,
    frame_bits_of,
    link_bits,
)
from sparsecomm.channel.noise import ON_DROP
from sparsecomm.channel.permuted import packet_bits as permuted_bits
from sparsecomm.channel.quantizer import (
    MAX_AGENTS,
    MAX_STEPS,
    dither,
    dither_key,
    quantize_dithered,
)
from sparsecomm.channel.routing import others

# -- dither ---------------------------------------------------------------------------------


def key_batch_shape(key: jax.Array) -> tuple[int, ...]:
    """The batch shape of a key array, typed (``jax.random.key``) or raw uint32."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key.shape
    if key.dtype != jnp.uint32 or key.ndim < 1:
        raise ValueError(f"key must be a PRNG key (typed or raw uint32), got {key.dtype}")
    return key.shape[:-1]


def over_links(fn, key: jax.Array, t, sender, recipient, *arrays, per_entry: bool = False):
    """``fn(dither_key(key, t, i, j), *link_arrays)`` for every link i -> j of every batch
    entry, in one flat ``vmap`` (nested ones compile ~3x slower).

    ``key``: one key, or keys of batch shape ``kb``; ``t``: steps whose shape broadcasts with
    ``kb`` into the batch shape ``B``; ``sender``, ``recipient``: integer arrays (may be traced)
    of one link shape ``L``, or with ``per_entry`` each batch entry's own links, ``(*B, *L)``
    (a routed team's live links, ``sparsecomm.scaling.nearest_senders``); each of ``arrays`` is
    ``(*B, *L, ...)``. Returns ``(*B, *L, ...)``.
    """
    kb = key_batch_shape(key)
    t = jnp.asarray(t)
    batch = tuple(np.broadcast_shapes(kb, t.shape))
    sender, recipient = jnp.asarray(sender), jnp.asarray(recipient)
    links = tuple(np.broadcast_shapes(sender.shape, recipient.shape))
    if per_entry:
        links = links[len(batch) :]
    n, m = math.prod(batch), math.prod(links)
    i = jnp.broadcast_to(sender, (*batch, *links)).reshape(n * m)
    j = jnp.broadcast_to(recipient, (*batch, *links)).reshape(n * m)
    steps = jnp.repeat(jnp.broadcast_to(t, batch).reshape(n), m)
    flat = [a.reshape(n * m, *a.shape[len(batch) + len(links) :]) for a in arrays]
    if kb:  # one key per batch entry, broadcast to each of its links
        tail = key.shape[len(kb) :]  # (2,) for a raw uint32 key, () for a typed one
        key = jnp.broadcast_to(key, (*batch, *tail)).reshape(*batch, 1, *tail)
        key = jnp.broadcast_to(key, (*batch, m, *tail)).reshape(n * m, *tail)
        key_axis = 0
    else:
        key_axis = None

    def one_link(k, tt, ii, jj, *xs):
        return fn(dither_key(k, tt, ii, jj), *xs)

    out = jax.vmap(one_link, (key_axis, 0, 0, 0, *([0] * len(flat))))(key, steps, i, j, *flat)
    return out.reshape(*batch, *links, *out.shape[1:])


def dither_links(
    key: jax.Array, t, sender, recipient, num_elements: int, per_entry: bool = False
) -> jax.Array:
    """The dither of links ``sender -> recipient`` at steps ``t``: ``(*B, *L, C)`` with ``B``
    the batch of ``key`` and ``t``, ``L`` that of ``sender`` and ``recipient``
    (:func:`over_links`); each link's C values drawn from ``dither_key(key, t, i, j)``."""
    draw = lambda k: dither(k, (num_elements,))  # noqa: E731
    return over_links(draw, key, t, sender, recipient, per_entry=per_entry)


def listed_dither(cfg: ChannelConfig, keys: jax.Array, t, senders: jax.Array):
    """The dither of a routed team's live links listed by recipient at step ``t``: ``senders``
    (B, K, k) (:func:`sparsecomm.scaling.nearest_senders`) -> (B, K, k, C'), each link's values
    those :func:`step_dither` draws for it. ``None`` unless the channel quantizes."""
    if not cfg.quantizes:
        return None
    recipients = jnp.broadcast_to(jnp.arange(senders.shape[-2])[:, None], senders.shape)
    return dither_links(keys, t, senders, recipients, cfg.signal_elements, per_entry=True)


def _check_dither_range(num_steps: int, num_agents: int) -> None:
    if num_steps > MAX_STEPS or num_agents > MAX_AGENTS:
        raise ValueError(
            f"the dither keys support max_steps <= {MAX_STEPS} and num_agents <= {MAX_AGENTS}, got "
            f"{num_steps} and {num_agents}"
        )


def step_dither(cfg: ChannelConfig, keys: jax.Array, t, num_agents: int):
    """The dither of every link of a batch at step ``t``: (B, K, K-1, C') by sender slot,
    ``None`` unless the channel quantizes. Link i -> j of episode b uses ``dither_key(keys[b],
    t, i, j)``."""
    if not cfg.quantizes:
        return None
    senders, recipients = np.arange(num_agents)[:, None], others(num_agents)
    return dither_links(keys, t, senders, recipients, cfg.signal_elements)


def link_dither(cfg: ChannelConfig, keys: jax.Array, num_steps: int, num_agents: int):
    """:func:`step_dither` of every step, (T, B, K, K-1, C'), in one vectorised draw (``C' =
    cfg.signal_elements``: the link's gate draws its own)."""
    if not cfg.quantizes:
        return None
    _check_dither_range(num_steps, num_agents)
    senders, recipients = np.arange(num_agents)[:, None], others(num_agents)
    steps = jnp.arange(num_steps)[:, None]
    return dither_links(keys, steps, senders, recipients, cfg.signal_elements)


# -- the sender side ------------------------------------------------------------------------


class Sent(NamedTuple):
    """What one step's links carried and cost. Link axes ``(..., K, K-1)`` by sender slot; a
    deployed agent's is its own row, ``(1, K-1)``. Every field is 0 on a link not ``live``."""

    symbols: jax.Array
    """(..., K, K-1, C) int32: the symbols sent (0, the null, for ``off`` and ``continuous``)."""
    z_hat: jax.Array
    """(..., K, K-1, C) float32: each link's reconstruction; for a quantizing channel its value
    is ``(m - u) / levels`` and its gradient with respect to the link's ``z`` the identity."""
    penalty: jax.Array
    """(..., K, K-1) float32: each link's differentiable bit penalty, summed over elements."""
    payload_bits: jax.Array
    """(..., K, K-1) float32: each link's payload bits (the paper's count, ``channel.payload_bits``
    under the config's code)."""
    wire_bits: jax.Array
    """(..., K, K-1) float32: each link's share of its sender's frame on the wire
    (``channel.frames``; 0: silent): the bits the link adds to the frame's body, plus an equal
    share, among the sender's speaking links, of the recipient map, the padding, the check and
    error correction. Summed over a sender's links it is ``8 * len(encode_sender(...))`` on the
    host. A ``fitted`` code's links send their own packets (``8 * len(encode_link(...))``)."""
    log_prob: jax.Array
    """(..., K) float32: log-probability of each sender's symbols (``samples_symbols``; else 0)."""
    live: jax.Array | None
    """(..., K, K-1) bool: the links that existed (``None``: all of them)."""
    speak: jax.Array | None = None
    """(..., K, K-1) float32, with ``link_gate``: 1 where the link speaks (its gate opened and
    one of its symbols is not null: ``wire_bits > 0``), else 0, with the straight-through
    gradient of its gate's probability ``g``; ``z_hat`` is then the message the
    link would carry, and :func:`receive` mixes it with what a silent link delivers. ``None``:
    no gate."""
    frame_bits: jax.Array | None = None
    """(..., K, K-1) float32: the bits of the datagram that carries each link on a network of
    unicast links, its sender's whole frame where the link speaks (0: silent); what noise on
    the wire acts on. ``None``: ``wire_bits`` (a link's own packet)."""


def news_gate(cfg: ChannelConfig, z: jax.Array, held: jax.Array) -> jax.Array:
    """Event-triggered links (``ChannelConfig.news_margin``): each link's gate opened also by
    how far what it would say is from what its recipient holds.

    Args:
      cfg: the channel (``link_gate``, ``hold``; a ``news_margin``, else ``z`` is returned).
      z: (..., L, C + 1) signals of L links, the gate last (:func:`transmit`'s ``z``).
      held: (..., L, C) the last message each link delivered (``Sent.z_hat`` of the last step
        it spoke, zeros before the first); no gradient flows into it.

    Returns:
      ``z`` with each gate ``max(g, clip((d - m) / m, 0, 1))``, ``d = max_k |z_k - held_k|``.
    """
    if cfg.news_margin is None:
        return z
    margin = cfg.news_margin
    d = jnp.abs(z[..., :-1] - jax.lax.stop_gradient(held)).max(-1)
    news = jnp.clip((d - margin) / margin, 0.0, 1.0)
    return z.at[..., -1].set(jnp.maximum(z[..., -1], news))


def last_delivered(sent: Sent, held: jax.Array) -> jax.Array:
    """What each link has delivered by the end of this step, as its sender knows it: the
    message of a link that spoke (``Sent.wire_bits > 0``: ``Sent.z_hat``), else ``held``, the
    last one before (zeros before the first); no gradient. :func:`news_gate`'s ``held`` at the
    next step, and what ``AgentConfig.reads_sent`` reads back. (..., L, C)."""
    return jax.lax.stop_gradient(jnp.where((sent.wire_bits > 0)[..., None], sent.z_hat, held))


def transmit(
    cfg: ChannelConfig,
    z: jax.Array,
    u=None,
    keys=None,
    t=None,
    prev=None,
    *,
    live=None,
    code: Code | FittedCode | None = None,
    senders=None,
) -> Sent:
    """The sender side: put every link's signal on the channel, in any mode, and count its cost.

    Args:
      cfg: the channel.
      z: (..., K, K-1, C') signals in [0, 1] by sender slot (``C' = cfg.signal_elements``:
        with ``link_gate`` the link's gate last).
      u: (..., K, K-1, C') their dither (:func:`link_dither`); a quantizing channel needs it.
      keys: (...) the episodes' channel keys, and ``t`` the step: a channel that samples its
        symbols draws them with ``dither_key(keys, t, i, j)``.
      prev: (..., K, K-1, C) each link's symbols at the previous step (``Sent.symbols``; a
        fitted code's packets depend on them; default all nulls).
      live: (..., K, K-1) bool, the links that exist (:func:`live_links`); the others send
        z = 0 (the null symbol, no gradient) and cost and deliver nothing. Default: all.
      code: count bits in this code instead of ``cfg.code_obj`` (the plug-in layer's).
      senders: (..., K, k) int, a routed team's live links **listed by recipient** (link
        ``senders[..., j, r] -> j``; ``sparsecomm.scaling.nearest_senders``): then every link
        array is (..., K, k, ...) in that order, each sender's frame is summed over the links
        it has in the list, and ``cfg.lists_links`` must hold. Default: the sender-slot layout.

    Returns:
      :class:`Sent`.
    """
    if senders is not None and not cfg.lists_links:
        raise ValueError(
            "transmit(senders=...) needs a channel whose links keep no state and whose costs "
            "are the links' own (ChannelConfig.lists_links)"
        )
    code = cfg.code_obj if code is None else code
    speak = None
    if live is not None:
        z = jnp.where(live[..., None], z, 0.0)
    no_log_prob = jnp.zeros(z.shape[:-2], jnp.float32)
    if not cfg.speaks:
        return _silence(z, no_log_prob, live)
    if cfg.sends_values:
        m, z_hat, log_prob = jnp.zeros(z.shape, jnp.int32), z, no_log_prob
        payload, wire, frame, penalty = _value_bits(cfg, z, code, senders)
    else:
        if cfg.samples_symbols:
            if keys is None or t is None:
                raise ValueError("ChannelConfig.mode 'reinforced' needs the episodes' keys and t")
            m, z_hat, log_prob = _sample_symbols(cfg, keys, t, z)
        else:
            z, m, z_hat, penalty, speak = _quantize_links(cfg, z, u, live, code)
            log_prob = no_log_prob
        payload, wire, frame = _symbol_bits(cfg, m, code, prev, senders)
        if cfg.samples_symbols:
            penalty = cfg.link_penalty(z, code, live)
    if live is not None:
        z_hat = jnp.where(live[..., None], z_hat, 0.0)
        payload, wire, penalty = (jnp.where(live, x, 0.0) for x in (payload, wire, penalty))
        speak = None if speak is None else jnp.where(live, speak, 0.0)
    return Sent(m.astype(jnp.int32), z_hat, penalty, payload, wire, log_prob, live, speak, frame)


def _silence(z: jax.Array, no_log_prob: jax.Array, live) -> Sent:
    """What the links of a channel that does not speak (``off``) carry: null symbols, zero
    reconstructions, and no penalty, bits or log-probability (``no_log_prob``: zeros)."""
    zeros = jnp.zeros(z.shape[:-1], jnp.float32)
    return Sent(
        jnp.zeros(z.shape, jnp.int32),
        jnp.zeros_like(z),
        zeros,
        zeros,
        zeros,
        no_log_prob,
        live,
    )


def _value_bits(cfg: ChannelConfig, z: jax.Array, code: Code, senders=None):
    """The cost of links that send their values (``continuous``): 32 payload bits per float32
    element, the wire and frame bits of the frames that carry them (:func:`_framed_bits`), and
    no penalty. Returns ``(payload, wire, frame, penalty)``, each (..., K, K-1)."""
    lead = z.shape[:-1]
    payload = jnp.full(lead, 32.0 * z.shape[-1])
    wire, frame = _framed_bits(cfg, z, code, senders)
    penalty = jnp.zeros(lead, jnp.float32)
    return payload, wire, frame, penalty


def _quantize_links(cfg: ChannelConfig, z: jax.Array, u, live, code):
    """The paper's links (``discrete``): each link's penalty (:func:`price`, on the signals
    with their gate), then its symbols and reconstruction by dithered quantization
    (``quantize_dithered``). With ``link_gate`` the last element of ``z`` and ``u`` is the
    link's gate: it opens with probability ``g`` (its own dither), a closed link's symbols are
    all null, and ``speak`` is 1 where the link sends something (an open gate and a symbol not
    null), with the straight-through gradient of ``g``.

    Returns:
      ``(z, m, z_hat, penalty, speak)``: ``z`` the signals without the gate, ``speak`` None
      without ``link_gate``.
    """
    if u is None:
        raise ValueError("ChannelConfig.mode 'discrete' needs the links' dither u")
    speak = None
    penalty = price(cfg, z, live, code)
    if cfg.link_gate:  # the last element opens the link: 1 with probability g
        z, g, u, u_gate = z[..., :-1], z[..., -1], u[..., :-1], u[..., -1]
        opens = jnp.clip(jnp.floor(g + u_gate + 0.5), 0.0, 1.0)
    m, z_hat = quantize_dithered(z, u, cfg.levels)
    if cfg.link_gate:  # a closed link sends nothing: every element null
        m = jnp.where(opens[..., None] > 0, m, 0)
        # and a link speaks when it sends something: an open gate whose symbols are
        # all null sends no packet either (on a network it is silence)
        speak = g + jax.lax.stop_gradient(opens * (m != 0).any(-1) - g)
    return z, m, z_hat, penalty, speak


def _symbol_bits(cfg: ChannelConfig, m: jax.Array, code, prev, senders=None):
    """The cost of links that send symbols ``m`` (..., K, K-1, C): each link's payload bits
    (``payload_bits`` of ``code``, summed over elements), its wire bits and the frame bits of
    the datagram that carries it (``Sent.frame_bits``, None where links send their own
    packets). A ``permuted`` code sends every link's C codewords whatever they say; a fitted
    code's links send their own packets (``prev``: their symbols at the previous step); the
    others are framed per sender (:func:`_framed_bits`). Returns ``(payload, wire, frame)``."""
    payload = payload_bits(m, code).sum(-1).astype(jnp.float32)
    frame = None
    if cfg.code == "permuted":  # every link sends its C codewords, whatever they say
        wire = jnp.full(payload.shape, float(permuted_bits(m.shape[-1], cfg.levels)))
    elif isinstance(code, FittedCode):  # a fitted code's links send their own packets
        wire = ecc_bits(wire_bits(m, code, prev=prev), cfg.ecc).astype(jnp.float32)
    else:
        wire, frame = _framed_bits(cfg, m, code, senders)
    return payload, wire, frame


def price(cfg: ChannelConfig, z: jax.Array, live=None, code=None) -> jax.Array:
    """The differentiable cost of each link of signals ``z`` (..., K, K-1, C'), the penalty
    :func:`transmit` reports (``ChannelConfig.link_penalty`` of the links that exist, ``live``
    (..., K, K-1) bool or None: all): (..., K, K-1)."""
    if live is None:
        return cfg.link_penalty(z, code)
    z = jnp.where(live[..., None], z, 0.0)
    return jnp.where(live, cfg.link_penalty(z, code, live), 0.0)


def _framed_bits(cfg: ChannelConfig, m: jax.Array, code: Code, senders=None):
    """Each link's share of its sender's frame and the frame each speaking link's datagram
    carries (``Sent.wire_bits``, ``Sent.frame_bits``), from symbols (or float32 values) ``m``
    (..., K, K-1, C) by sender slot, or (..., K, k, C) listed by recipient with ``senders``
    (``transmit``): exactly the frames ``encode_sender`` writes."""
    body = link_bits(m, code)  # (..., K, L) int32
    if senders is None:  # each row is one sender's links
        frame = frame_bits(m, code, cfg.check_bits)
        total, count = body.sum(-1), (body > 0).sum(-1)
    else:  # sum each sender's listed links, then hand every link its sender's sums
        k = m.shape[-3]
        owner = jax.nn.one_hot(senders, k, dtype=jnp.int32)  # (..., K, k, K senders)
        total = jnp.einsum("...jr,...jrs->...s", body, owner)
        count = jnp.einsum("...jr,...jrs->...s", (body > 0).astype(jnp.int32), owner)
        frame = frame_bits_of(total, count > 0, k - 1, cfg.check_bits)
    frame = ecc_bits(frame, cfg.ecc).astype(jnp.float32)
    if senders is None:  # (..., K) -> (..., K, 1): over the row's links
        frame, total, count = frame[..., None], total[..., None], count[..., None]
    else:  # (..., K) by sender -> (..., K, k): each listed link's sender's
        flat = senders.reshape(*senders.shape[:-2], -1)
        frame, total, count = (
            jnp.take_along_axis(x, flat, -1).reshape(senders.shape) for x in (frame, total, count)
        )
    body = body.astype(jnp.float32)
    speaking = body > 0
    overhead = (frame - total) / jnp.maximum(count, 1)
    share = jnp.where(speaking, body + overhead, 0.0)
    return share, jnp.where(speaking, frame, 0.0)


def _sample_symbols(cfg: ChannelConfig, keys: jax.Array, t, z: jax.Array):
    """Reinforced communication learning: symbols are actions.

    Each element's symbol is sampled as m ~ Binomial(levels, z) (the number of ``levels``
    uniforms below z, drawn with the link's key ``dither_key(keys[b], t, i, j)``): full support
    on {0, ..., levels}, mean ``levels * z``. The receiver gets ``stop_gradient(m / levels)``,
    so no gradient crosses the channel; the sender learns from the log-probability of what it
    sent (z clipped to [1e-6, 1 - 1e-6] there), (..., K), summed over its recipients and
    elements. ``z`` is (..., K, K-1, C): every sender's row.
    """
    k = z.shape[-3]
    z_sample = jax.lax.stop_gradient(z)

    def one_link(key, z_link):
        u = jax.random.uniform(key, (*z_link.shape, cfg.levels))
        return (u < z_link[..., None]).sum(-1)

    senders, recipients = np.arange(k)[:, None], others(k)
    m = over_links(one_link, keys, jnp.asarray(t), senders, recipients, z_sample)
    n, mf = float(cfg.levels), m.astype(jnp.float32)
    zc = jnp.clip(z, 1e-6, 1.0 - 1e-6)
    log_comb = gammaln(n + 1.0) - gammaln(mf + 1.0) - gammaln(n - mf + 1.0)
    log_prob = (log_comb + mf * jnp.log(zc) + (n - mf) * jnp.log1p(-zc)).sum((-2, -1))
    return m, jax.lax.stop_gradient(mf / n), log_prob


# -- the receiver side ----------------------------------------------------------------------


class Received(NamedTuple):
    """What a receiver made of one step's links, in the layout it gave :func:`receive`."""

    z_hat: jax.Array
    """(..., C) float32: each link's message as the recipient's actor reads it."""
    last: jax.Array | None
    """(..., C) float32: each link's last good reconstruction after this step (``None`` when
    :func:`receive` was given none)."""
    news: jax.Array | None = None
    """(...) float32, under ``on_silence = "hold"``: 1 where this step's message is news (the
    link spoke and its packet arrived), 0 where it is held. ``None`` otherwise."""


def null_message(cfg: ChannelConfig, u, like: jax.Array) -> jax.Array:
    """What a recipient makes of the null message (every symbol 0), shaped like ``like``: on a
    quantizing channel the null symbols rebuilt with the link's dither, ``-u / levels``;
    otherwise 0. No gradient."""
    if cfg.quantizes and u is not None:
        return jax.lax.stop_gradient(-u / cfg.levels)
    return jnp.zeros(like.shape, jnp.float32)


def receive(
    cfg: ChannelConfig,
    message: jax.Array,
    u=None,
    *,
    ok=None,
    last=None,
    on_drop: str = "null",
    live=None,
    speak=None,
    silent=None,
) -> Received:
    """The receiver side: what each recipient reads of the links that reached it.

    Args:
      cfg: the channel.
      message: (..., C) per link, what arrived: integer **symbols** (decoded packets), rebuilt
        here as ``(m - u) / levels`` on a quantizing channel and ``m / levels`` on one that
        samples its symbols; or a **float** array, already the reconstruction (a
        ``continuous`` channel's values, or ``Sent.z_hat`` in a simulation, whose gradient it
        keeps). A channel that does not speak delivers 0.
      u: (..., C) each link's dither (:func:`dither_links`; a gate's is ignored), for a
        quantizing channel.
      ok: (...) bool, the links whose packet arrived; default all. A missing one is the null
        message (:func:`null_message`) or, with ``on_drop = "last"`` or ``cfg.holds``, ``last``.
      last: (..., C) each link's last good reconstruction (zeros before the first), needed with
        ``on_drop = "last"`` and ``cfg.holds``.
      on_drop: ``"null"`` or ``"last"`` (``channel.noise.ON_DROP``).
      live: (...) bool, the links that exist: the others deliver 0. Default: all.
      speak: (...) float, ``Sent.speak`` of a gated channel: a closed link delivers what a
        silent one does, mixed with the straight-through gradient of its gate.
      silent: (...) bool, the links that sent nothing (``Sent.wire_bits == 0``, or no packet
        on a real network); under ``cfg.holds`` they deliver ``last``.

    Returns:
      :class:`Received`: the messages, each link's updated last good reconstruction, and under
      ``cfg.holds`` which messages are news.
    """
    if on_drop not in ON_DROP:
        raise ValueError(f"on_drop must be one of {ON_DROP}, got {on_drop!r}")
    if last is None and (cfg.holds or (on_drop == "last" and ok is not None)):
        raise ValueError("receive with on_drop 'last' or on_silence 'hold' needs `last`")
    message = jnp.asarray(message)
    u = None if u is None else u[..., : message.shape[-1]]
    if not cfg.speaks:
        got = jnp.zeros(message.shape, jnp.float32)
    elif jnp.issubdtype(message.dtype, jnp.integer):  # symbols: rebuild them
        m = message.astype(jnp.float32)
        got = (m - u) / cfg.levels if cfg.quantizes else m / cfg.levels
    else:
        got = message
    spoke = None  # (...) bool: the link sent something
    if speak is not None:  # a closed gate: what a silent link delivers
        base = last if cfg.holds else null_message(cfg, u, got)
        spoke = speak > 0
        # exactly the message or the base (as a real receiver rebuilds them), with the gate's
        # straight-through gradient: the message it would carry minus what silence delivers
        through = (speak - jax.lax.stop_gradient(speak))[..., None] * (got - base)
        got = jnp.where(spoke[..., None], got, base) + through
    elif silent is not None:
        spoke = ~silent
        if cfg.holds:
            got = jnp.where(spoke[..., None], got, last)
    news = spoke if ok is None else (ok if spoke is None else ok & spoke)
    if ok is not None:
        instead = last if on_drop == "last" or cfg.holds else null_message(cfg, u, got)
        got = jnp.where(ok[..., None], got, instead)
    if cfg.holds:  # the last message the link did send, and that arrived
        last = got if news is None else jnp.where(news[..., None], got, last)
    elif last is not None and ok is not None:  # the last packet that arrived
        last = jnp.where(ok[..., None], got, last)
    if live is not None:
        got = jnp.where(live[..., None], got, 0.0)
    held = None
    if cfg.holds:
        held = jnp.ones(got.shape[:-1], jnp.float32) if news is None else news.astype(jnp.float32)
    return Received(got, last, held)


# -- one sender's frame on a real network --------------------------------------------------


def encode_sender(cfg: ChannelConfig, symbols: np.ndarray, signal: np.ndarray) -> bytes:
    """One sender's frame at one step, exactly as the channel counts it (``channel.frames``;
    ``b""``: all its links silent; error correction applied).

    Args:
      cfg: the channel (a framed one: ``cfg.deployable``).
      symbols: (L, C) int, the symbols of the sender's L links by recipient slot
        (``Sent.symbols``).
      signal: (L, C') float32, their signals (``StepOut.signal``): a channel that sends values
        sends the first C; the others ignore them.

    Returns:
      The frame's bytes; ``8 * len`` is its links' ``Sent.wire_bits`` summed.
    """
    if not cfg.speaks:
        return b""
    if cfg.sends_values:
        message = np.asarray(signal, np.float32)[..., : cfg.num_elements]
    else:
        message = np.asarray(symbols)
    frame = encode_frame(message, cfg.code_obj, check_bits=cfg.check_bits)
    if frame and cfg.ecc != "none":
        frame = ecc_encode(frame, cfg.ecc)
    return frame


def decode_sender(cfg: ChannelConfig, data: bytes, num_links: int) -> np.ndarray:
    """The (L, C) messages of one sender's frame (symbols, or floats for a channel that sends
    values; ``b""``: all null). Raises ``channel.PacketError`` for anything that is not a frame
    of this channel with ``num_links`` links."""
    if data and cfg.ecc != "none":
        try:
            data = ecc_decode(data, cfg.ecc)
        except ValueError as e:
            raise PacketError(str(e)) from None
        if not data:  # too short to hold a protected frame; silence is sent as nothing
            raise PacketError("an ecc-protected frame too short to hold a frame")
    return decode_frame(data, cfg.code_obj, num_links, cfg.num_elements, check_bits=cfg.check_bits)


# -- one link's packet on a real network ----------------------------------------------------


def encode_link(cfg: ChannelConfig, symbols: np.ndarray, signal: np.ndarray, prev) -> bytes:
    """One link's packet, exactly as the channel frames it (``b""``: silence; error correction
    applied): the symbols, or the float32 signal of a channel that sends values; nothing on a
    channel that does not speak. ``prev``: the link's symbols at the previous step."""
    if not cfg.speaks:
        return b""
    message = np.asarray(signal, np.float32) if cfg.sends_values else symbols
    packet = encode(message, cfg.code_obj, prev=prev)
    if packet and cfg.ecc != "none":
        packet = ecc_encode(packet, cfg.ecc)
    return packet


def decode_link(cfg: ChannelConfig, packet: bytes, prev) -> np.ndarray:
    """The message of one link's packet (symbols, or floats for a channel that sends values).
    Raises ``channel.PacketError`` for anything that is not a packet of this channel."""
    shape = (cfg.num_elements,)
    if packet and cfg.ecc != "none":
        try:
            packet = ecc_decode(packet, cfg.ecc)
        except ValueError as e:
            raise PacketError(str(e)) from None
        if not packet:  # too short to hold a protected packet; silence is sent as b""
            raise PacketError("an ecc-protected packet too short to hold a packet")
    return decode(packet, cfg.code_obj, shape, prev=prev)
