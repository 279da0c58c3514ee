"""Noise between senders and receivers inside a compiled rollout (``ChannelConfig.noise``).

:class:`LossyLinks` draws which of a step's packets are lost (``noise.lost_packets``: erasure,
and any flipped bit failing the CRC-32), holds what is late in a delay line, and under
``code = "permuted"`` corrupts symbols instead of losing packets (``channel.permuted``). What a
receiver then makes of a missing packet is :func:`sparsecomm.channel.links.receive`'s one rule,
applied by the caller with the ``ok`` flags returned here (and the links' last messages, which
the caller keeps).

Its keys come from ``fold_in(key, 7)``, outside the rollout's six splits of the batch key, so a
clean channel keeps every other draw, and results, bit for bit.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from sparsecomm.channel.config import ChannelConfig
from sparsecomm.channel.links import Sent
from sparsecomm.channel.noise import initial_bad, lost_packets
from sparsecomm.channel.permuted import corrupt, gradient_scale


class LinkState(NamedTuple):
    """What the noisy links carry from one step to the next, links ``(B, K, K-1)`` by sender
    slot and ``D = noise.delay``."""

    bad: jax.Array
    """(B, K, K-1) bool: each link's Gilbert-Elliott burst state."""
    queue: jax.Array
    """(B, D, K, K-1, C) float32: what was sent in the last D steps, oldest first."""
    queue_ok: jax.Array
    """(B, D, K, K-1) bool: whether each of those packets survived."""


class LossyLinks:
    """The noise of a batch of ``num_envs`` episodes of ``num_agents`` agents and ``num_steps``
    steps, drawn from the batch ``key``."""

    def __init__(self, cfg: ChannelConfig, key, num_envs: int, num_agents: int, num_steps: int):
        self.cfg, self.noise = cfg, cfg.noise
        k_bad, k_steps = jax.random.split(jax.random.fold_in(key, 7))
        self.step_keys = jax.random.split(k_steps, num_steps)
        links = (num_envs, num_agents, num_agents - 1)
        c, d = cfg.num_elements, self.noise.delay
        self.init = LinkState(
            bad=initial_bad(k_bad, self.noise, links),
            queue=jnp.zeros((num_envs, d, *links[1:], c), jnp.float32),
            queue_ok=jnp.zeros((num_envs, d, *links[1:]), bool),
        )

    def step(self, key, sent: Sent, u, state: LinkState):
        """One step's packets through the noise: ``(arrived (B, K, K-1, C), ok (B, K, K-1),
        state, lost (B,))``: what reaches the receivers now (the reconstructions sent
        ``delay`` steps ago), whether each packet did, and the number of packets lost."""
        scrambles = self.cfg.code == "permuted"
        if scrambles:  # flips corrupt symbols instead of losing packets
            key, k_symbols = jax.random.split(key)
        carried = sent.wire_bits if sent.frame_bits is None else sent.frame_bits
        lost, bad = lost_packets(
            key, self.noise, carried, state.bad, self.cfg.ecc, flips_lose=not scrambles
        )
        now = self._corrupt(k_symbols, sent, u, state.bad) if scrambles else sent.z_hat
        arrived, ok = now, ~lost
        state = state._replace(bad=bad)
        if self.noise.delay:  # what arrives now was sent ``delay`` steps ago
            arrived, ok = state.queue[:, 0], state.queue_ok[:, 0]
            state = state._replace(
                queue=jnp.concatenate([state.queue[:, 1:], now[:, None]], 1),
                queue_ok=jnp.concatenate([state.queue_ok[:, 1:], ~lost[:, None]], 1),
            )
        return arrived, ok, state, lost.sum((-2, -1)).astype(jnp.float32)

    def _corrupt(self, key, sent: Sent, u, bad):
        """The reconstructions of the symbols that cross the permuted channel
        (``channel.permuted``), with the gradient of their expectation, ``alpha`` times the
        sent message's."""
        cfg, noise = self.cfg, self.noise
        if noise.burst:  # each link's state sets the flip rate of all its elements
            p01 = p10 = jnp.where(bad, noise.burst_flip_bad, noise.burst_flip_good)[..., None]
        else:
            p01, p10 = noise.flip_rates
        r = corrupt(key, sent.symbols, cfg.levels, p01, p10)
        z_hat = r / cfg.levels if u is None else (r - u) / cfg.levels
        slope = gradient_scale(cfg.levels, noise) * sent.z_hat
        return slope + jax.lax.stop_gradient(z_hat - slope)
