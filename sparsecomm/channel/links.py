"""The channel as it is used between agents: its configuration, routing and one ``transmit``.

Every agent i sends one signal ``z^{i->j}`` of ``num_elements`` elements to every other agent j
at every step. A batch of links is laid out by sender, ``(B, K, K-1, C)``: sender i's slot r
goes to recipient ``others(K)[i, r]`` (the other agents in increasing order). :func:`transmit`
sends a batch of links through the channel in any mode and counts what it cost; :func:`deliver`
routes the reconstructions to their recipients, ``(B, K, (K-1) C)``.

The dither of link i -> j at step t of an episode with channel key ``key`` is drawn from
``dither_key(key, t, i, j)`` (docs/spec.md section 1), so the receiver can regenerate it alone:
:func:`link_dither` draws every step's dither of a batch at once (one large draw instead of
many small ones inside the time loop).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from sparsecomm.channel.codes import CODE_NAMES, Code, frequency_remap, payload_bits, wire_bits
from sparsecomm.channel.ecc import ECC_NAMES
from sparsecomm.channel.ecc import wire_bits as ecc_bits
from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.noise import NoiseConfig
from sparsecomm.channel.penalty import code_penalty
from sparsecomm.channel.permuted import packet_bits as permuted_bits
from sparsecomm.channel.quantizer import (
    MAX_AGENTS,
    MAX_STEPS,
    check_levels,
    dither,
    dither_key,
    quantize_dithered,
)

CHANNEL_MODES = ("discrete", "continuous", "off", "reinforced")
CHANNEL_CODES = (*CODE_NAMES[:2], "fitted", "remapped", "permuted")


@dataclasses.dataclass(frozen=True)
class ChannelConfig:
    """The message channel between agents (docs/spec.md sections 1-3)."""

    mode: str = "discrete"
    """``discrete``: dithered quantization, the paper's method. ``continuous``: real-valued
    messages sent as float32 (a baseline, 32 bits per element). ``off``: no communication
    (messages are zeros, 0 bits; a baseline). ``reinforced``: reinforced communication learning
    (RCL, a baseline): each element's symbol is sampled as an action, m ~ Binomial(levels, z),
    the receiver gets m / levels with no gradient through the channel, and the senders learn by
    policy gradient on the log-probability of the symbols sent, with ``bit_cost`` per bit."""
    levels: int = 15
    """|M|, symbols per element are {0, ..., levels}. SPEC section 1."""
    num_elements: int = 10
    """C, elements of the signal z each agent sends to each recipient per step. Paper: 10."""
    code: str = "paper"
    """Code used to count payload bits (and frame them on the wire) for the ``discrete`` and
    ``reinforced`` modes:
    ``paper`` (the paper's variable-length code, Elias-gamma framing), ``fixed`` (fixed-width,
    a baseline), ``fitted`` (a code fitted to a trained team's symbols, read from
    ``code_file``: payload bits and the penalty stay the paper's, wire bits are the fitted
    code's packets; ``sparsecomm.channel.fitted``) or ``remapped`` (a learned code: the paper's
    code with each element's symbols ranked by how often the team of ``code_file`` sends them,
    the most frequent getting the shortest codeword; payload bits and the penalty, the exact
    expected codeword bits, price the remapped lengths; ``Code.remap``). SPEC section 2."""
    code_file: str = ""
    """``code = fitted`` or ``remapped`` only: the JSON file of a fitted code (``sparsecomm
    fit-code``). A fitted code's SHA-256 fingerprint is checked by every packet's CRC."""
    noise: NoiseConfig = NoiseConfig()
    """Noise on every link's packets (``sparsecomm.channel.noise``): bit flips, erasure, bursts,
    delay; a packet with a flipped bit fails its CRC-32 and is lost, and the receiver uses the
    null message or its last good one (``noise.on_drop``). Applied in training and evaluation
    alike (``sparsecomm eval --noise.*`` evaluates a team under other noise). ours: none."""
    ecc: str = "none"
    """Error correction on every packet (``sparsecomm.channel.ecc``): ``none``, or
    ``hamming74`` (each 4 bits of a packet sent as 7, correcting one flipped bit per block; the
    redundancy, 1.75x plus padding, is counted in the wire bits). ours: ``none``."""
    bit_cost: float = 0.0
    """``reinforced`` mode only: reward subtracted from agent i at step t per payload bit it
    sends (paper reward units, scaled by ``reward_scale`` like the task reward; not included in
    the logged group reward). Neither the paper nor SPEC gives a value; ours: 0 (no cost), and
    ``sparsecomm reproduce`` uses 0.001, the price per bit that the surrogate penalty sets at
    lambda = 0.001 (lambda is in the same units, see ``sparsecomm.rl``)."""

    def __post_init__(self):
        if self.mode not in CHANNEL_MODES:
            raise _bad("mode", self.mode, f"one of {CHANNEL_MODES}")
        check_levels(self.levels, "ChannelConfig.levels")
        if not isinstance(self.num_elements, int) or self.num_elements < 1:
            raise _bad("num_elements", self.num_elements, "an integer >= 1")
        if self.code not in CHANNEL_CODES:
            raise _bad("code", self.code, f"one of {CHANNEL_CODES}")
        if (self.code in ("fitted", "remapped")) != bool(self.code_file):
            raise _bad(
                "code_file",
                self.code_file,
                "a fitted code's JSON file exactly when code is 'fitted' or 'remapped'",
            )
        if self.code_file:
            fitted = load_code(self.code_file)
            if (fitted.levels, fitted.elements) != (self.levels, self.num_elements):
                raise _bad(
                    "code_file",
                    self.code_file,
                    f"a code for levels {self.levels} and {self.num_elements} elements (it has "
                    f"levels {fitted.levels} and {fitted.elements} elements)",
                )
        if self.ecc not in ECC_NAMES:
            raise _bad("ecc", self.ecc, f"one of {ECC_NAMES}")
        if self.code == "permuted" and self.mode not in ("discrete", "reinforced"):
            raise _bad("code", self.code, f"not 'permuted' in mode {self.mode!r} (no symbols)")
        if self.code == "permuted" and self.ecc != "none":
            raise _bad("ecc", self.ecc, "'none' with code 'permuted' (its flips corrupt symbols)")
        if not (self.bit_cost >= 0 and self.bit_cost < float("inf")):
            raise _bad("bit_cost", self.bit_cost, "finite and >= 0")

    @property
    def code_obj(self) -> Code | FittedCode:
        if self.mode == "continuous":
            return Code("float32", self.levels)
        if self.code == "fitted":
            return load_code(self.code_file)
        if self.code == "permuted":
            return Code("paper", self.levels)  # payload: the paper's count
        if self.code == "remapped":
            counts = np.asarray(load_code(self.code_file).symbol_counts).sum(1)
            return Code("paper", self.levels, frequency_remap(counts))
        return Code(self.code, self.levels)

    def penalty(self, z: jax.Array) -> jax.Array:
        """The differentiable bit cost of each element of signals ``z`` (..., C): the paper's
        ``log2(levels z + 1)``, or for a learned (``remapped``) code the exact expected bits
        of its codewords (``channel.expected_bits``)."""
        return code_penalty(z, self.levels, self.code_obj)

    def max_bits_per_step(self, num_agents: int) -> int:
        """The most payload bits a team of ``num_agents`` can send in one step: every element of
        every link at the code's longest codeword."""
        code = self.code_obj
        if code.name == "fitted":
            code = Code("paper", self.levels)  # payload: the paper's count
        per_element = code.max_paper_length if code.name == "paper" else code.fixed_width
        return num_agents * (num_agents - 1) * self.num_elements * per_element


@functools.lru_cache(maxsize=8)
def _load_code(path: str, mtime_ns: int, size: int) -> FittedCode:
    return FittedCode.from_json(Path(path).read_text())


def load_code(path: str) -> FittedCode:
    """The fitted code in the JSON file ``path`` (read once while the file is unchanged)."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise _bad("code_file", path, f"a readable fitted-code JSON file ({e.strerror})") from None
    try:
        return _load_code(str(path), st.st_mtime_ns, st.st_size)
    except ValueError as e:
        raise _bad("code_file", path, f"a valid fitted-code JSON file ({e})") from None


def _bad(name: str, value, allowed: str) -> ValueError:
    return ValueError(f"ChannelConfig.{name} must be {allowed}, got {value!r}")


def others(num_agents: int) -> np.ndarray:
    """(K, K-1): row i lists the other agents in increasing order. Read by sender, it is the
    recipient of sender i's slot r; read by receiver, the sender of receiver j's s-th link."""
    k = num_agents
    return np.array([[j for j in range(k) if j != i] for i in range(k)]).reshape(k, k - 1)


def link_tables(num_agents: int) -> tuple[np.ndarray, np.ndarray]:
    """Static routing tables ``(sender, slot)``, each (K, K-1): receiver j's s-th incoming link
    comes from ``sender[j, s]``, which wrote it into its output slot ``slot[j, s]``."""
    sender = others(num_agents)
    receiver = np.arange(num_agents)[:, None]
    return sender, np.where(receiver > sender, receiver - 1, receiver)


def deliver(z_hat: jax.Array) -> jax.Array:
    """Route decoded links to their recipients: (B, K, K-1, C) by sender -> (B, K, (K-1) C),
    receiver j's row holding the messages of the other agents in increasing order."""
    b, k, _, c = z_hat.shape
    sender, slot = link_tables(k)
    return z_hat[:, sender, slot].reshape(b, k, (k - 1) * c)


def step_dither(cfg: ChannelConfig, keys: jax.Array, t, num_agents: int):
    """The dither of every link of a batch at step ``t``: (B, K, K-1, C), ``None`` unless the
    channel quantizes. Link i -> j of episode b uses ``dither_key(keys[b], t, i, j)``."""
    if cfg.mode != "discrete":
        return None

    def one_link(key, i, j):
        return dither(dither_key(key, t, i, j), (cfg.num_elements,))

    links = jax.vmap(jax.vmap(one_link, (None, None, 0)), (None, 0, 0))
    senders, recv = jnp.arange(num_agents), jnp.asarray(others(num_agents))
    return jax.vmap(lambda key: links(key, senders, recv))(keys)


def link_dither(cfg: ChannelConfig, keys: jax.Array, num_steps: int, num_agents: int):
    """:func:`step_dither` of every step, (T, B, K, K-1, C), in one vectorised draw."""
    if cfg.mode != "discrete":
        return None
    if num_steps > MAX_STEPS or num_agents > MAX_AGENTS:
        raise ValueError(
            f"the dither keys support max_steps <= {MAX_STEPS} and num_agents <= {MAX_AGENTS}, got "
            f"{num_steps} and {num_agents}"
        )
    return jax.vmap(lambda t: step_dither(cfg, keys, t, num_agents))(jnp.arange(num_steps))


class Sent(NamedTuple):
    """What one step's links cost and delivered, for a batch of B episodes."""

    z_hat: jax.Array  # (B, K, K-1, C) the reconstructions the recipients decode
    penalty: jax.Array  # (B,) the differentiable bit penalty, summed over links and elements
    payload: jax.Array  # (B,) payload bits sent by the team (the paper's count)
    wire: jax.Array  # (B,) bits on the wire: every link's packet, framing and CRC included
    link: jax.Array  # (B, K, K-1) payload bits of each link, by sender and slot
    log_prob: jax.Array  # (B, K) log-prob of each sender's symbols ("reinforced"; else 0)
    symbols: jax.Array  # (B, K, K-1, C) int32 symbols sent (0, the null, for "off"/"continuous")
    link_wire: jax.Array  # (B, K, K-1) wire bits of each link's packet (0: silent)


def transmit(cfg: ChannelConfig, z: jax.Array, u=None, keys=None, t=None, prev=None) -> Sent:
    """Send every link of a batch through the channel, in any mode.

    ``z`` (B, K, K-1, C) the signals in [0, 1]; ``u`` (B, K, K-1, C) their dither
    (:func:`link_dither`; the ``discrete`` mode needs it); ``keys`` (B,) the episodes' channel
    keys and ``t`` the step (the ``reinforced`` mode samples its symbols with them); ``prev``
    (B, K, K-1, C) each link's symbols at the previous step (``Sent.symbols``; a fitted code's
    wire bits depend on them; default all nulls).
    """
    b, k, r, c = z.shape
    zeros_b = jnp.zeros((b,), jnp.float32)
    no_log_prob = jnp.zeros((b, k), jnp.float32)
    if cfg.mode == "off":
        z0 = jnp.zeros_like(z)
        link = jnp.zeros((b, k, r), jnp.float32)
        m0 = jnp.zeros(z.shape, jnp.int32)
        return Sent(z0, zeros_b, zeros_b, zeros_b, link, no_log_prob, m0, link)
    if cfg.mode == "continuous":
        link = jnp.full((b, k, r), 32.0 * c)
        total = jnp.full((b,), 32.0 * c * k * r)
        per_link = ecc_bits(wire_bits(z, cfg.code_obj), cfg.ecc).astype(jnp.float32)
        m0 = jnp.zeros(z.shape, jnp.int32)
        return Sent(z, zeros_b, total, per_link.sum((-2, -1)), link, no_log_prob, m0, per_link)
    if cfg.mode == "reinforced":
        if keys is None or t is None:
            raise ValueError("ChannelConfig.mode 'reinforced' needs the episodes' keys and t")
        m, z_hat, log_prob = _sample_symbols(cfg, keys, t, z)
    else:
        if u is None:
            raise ValueError("ChannelConfig.mode 'discrete' needs the links' dither u")
        m, z_hat = quantize_dithered(z, u, cfg.levels)
        log_prob = no_log_prob
    code = cfg.code_obj
    link = payload_bits(m, code).sum(-1).astype(jnp.float32)
    if cfg.code == "permuted":  # every link sends its C codewords, whatever they say
        per_link = jnp.full(link.shape, float(permuted_bits(c, cfg.levels)))
    else:
        per_link = ecc_bits(wire_bits(m, code, prev=prev), cfg.ecc).astype(jnp.float32)
    penalty = cfg.penalty(z).sum((-3, -2, -1))
    wire = per_link.sum((-2, -1))
    return Sent(
        z_hat, penalty, link.sum((-2, -1)), wire, link, log_prob, m.astype(jnp.int32), per_link
    )


def _sample_symbols(cfg: ChannelConfig, keys: jax.Array, t, z: jax.Array):
    """Reinforced communication learning: symbols are actions.

    Each element's symbol is sampled as m ~ Binomial(levels, z) (the number of ``levels``
    uniforms below z, drawn with the link's key ``dither_key(keys[b], t, i, j)``): full support
    on {0, ..., levels}, mean ``levels * z``. The receiver gets ``stop_gradient(m / levels)``,
    so no gradient crosses the channel; the sender learns from the log-probability of what it
    sent (z clipped to [1e-6, 1 - 1e-6] there), (B, K), summed over its recipients and elements.
    """
    k = z.shape[1]
    z_sample = jax.lax.stop_gradient(z)

    def one_link(key, i, j, z_link):
        u = jax.random.uniform(dither_key(key, t, i, j), (*z_link.shape, cfg.levels))
        return (u < z_link[..., None]).sum(-1)

    per_link = jax.vmap(jax.vmap(one_link, (None, None, 0, 0)), (None, 0, 0, 0))
    m = jax.vmap(per_link, (0, None, None, 0))(
        keys, jnp.arange(k), jnp.asarray(others(k)), z_sample
    )
    n, mf = float(cfg.levels), m.astype(jnp.float32)
    zc = jnp.clip(z, 1e-6, 1.0 - 1e-6)
    log_comb = gammaln(n + 1.0) - gammaln(mf + 1.0) - gammaln(n - mf + 1.0)
    log_prob = (log_comb + mf * jnp.log(zc) + (n - mf) * jnp.log1p(-zc)).sum((-2, -1))
    return m, jax.lax.stop_gradient(mf / n), log_prob
