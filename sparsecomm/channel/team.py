"""A team's channel, built once from its config (:func:`build`).

:class:`TeamChannel` holds the link rules of a team: a link's gate (``link_gate``), what a silent
link delivers (``on_silence``), news that opens a gate (``news_margin``) and what a missing packet
becomes (``NoiseConfig.on_drop``). It owns the one state a team's links carry from step to step
(:class:`LinkState`), answers once how wide each actor's inbox is, and runs one step of the links
(:meth:`TeamChannel.exchange`: news, the sender side, the wire, the receiver side, the inboxes).
The rollout, a team expert (``imitation.team_expert``) and every deployed agent (``deploy.core``,
its own row: :meth:`TeamChannel.agent_send`, :meth:`TeamChannel.agent_receive`) step their links
through it, so a new link rule is written in ``channel/`` alone: no module outside this package
reads the rules' fields.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from sparsecomm.channel.config import ChannelConfig
from sparsecomm.channel.links import (
    Received,
    Sent,
    last_delivered,
    news_gate,
    receive,
    transmit,
)
from sparsecomm.channel.noise import ON_DROP
from sparsecomm.channel.routing import deliver, inbox


class LinkState(NamedTuple):
    """What a team's links carry from one step to the next. Leading axes ``(..., K, L)``: the
    senders and their L links by slot (``L = K - 1``, or a routed team's k listed links); a
    deployed agent's share is one row ``(L, C)``: its own links' ``prev`` and ``own``, and the
    ``last`` of the links it receives (by sender, ``channel.others``)."""

    prev: jax.Array
    """(..., L, C) int32: each link's symbols at the previous step (a fitted code reads them)."""
    last: Any = None
    """(..., K-1, C) float32: each link's last good message at its recipient (zeros before
    the first), where a rule reads it (:attr:`TeamChannel.keeps_last`); else None."""
    own: Any = None
    """(..., K-1, C) float32: what each link last delivered, as its sender knows it (zeros
    before), where a rule reads it (:attr:`TeamChannel.keeps_own`); else None."""


class Exchange(NamedTuple):
    """One step of a team's links (:meth:`TeamChannel.exchange`)."""

    sent: Sent  # the sender side, by sender slot (B, K, K-1, C) or listed (B, K, k, C)
    got: Received  # the receiver side, in the same layout
    msgs: jax.Array  # (B, K, width) each recipient's inbox for the next step
    state: LinkState  # the links' state for the next step
    wire: Any  # what ``wire`` returned beside the packets (None without it)
    z: jax.Array  # the signals sent, after news opened gates: what ``channel.price`` prices


@dataclasses.dataclass(frozen=True)
class TeamChannel:
    """The channel of a team of ``num_agents`` (:func:`build`).

    ``reads_sent``: each actor's inbox ends with what its own links last delivered
    (``AgentConfig.reads_sent``). ``lossy``: packets can be lost on the wire (a noisy channel in
    a rollout, or a real network). ``on_drop``: what a missing packet becomes (``null`` or
    ``last``); default the config's ``noise.on_drop``.
    """

    cfg: ChannelConfig
    num_agents: int
    reads_sent: bool = False
    lossy: bool = False
    on_drop: str = ""

    def __post_init__(self):
        if not self.on_drop:
            object.__setattr__(self, "on_drop", self.cfg.noise.on_drop)
        if self.on_drop not in ON_DROP:
            raise ValueError(f"on_drop must be one of {ON_DROP}, got {self.on_drop!r}")
        if self.reads_sent and not self.cfg.holds:
            raise ValueError(
                "AgentConfig.reads_sent needs ChannelConfig.on_silence 'hold' (a held message "
                "to read back), got on_silence 'null'"
            )

    # -- what the team's networks see ---------------------------------------------------------

    @property
    def signal_elements(self) -> int:
        """Elements of each link's signal from the message head (C, and a gate)."""
        return self.cfg.signal_elements

    @property
    def gated(self) -> bool:
        """Each link's last signal element is its gate (``link_gate``)."""
        return self.cfg.link_gate

    @property
    def news_inputs(self) -> bool:
        """Each recipient also reads, per link, whether its message is news (``hold``)."""
        return self.cfg.holds

    def received_width(self, heard_links: int | None = None) -> int:
        """Inputs a recipient rebuilds from the links it hears (``heard_links``, default
        ``K - 1``): C per link, and its news flag under ``on_silence = "hold"``."""
        heard = self.num_agents - 1 if heard_links is None else heard_links
        return heard * (self.cfg.num_elements + int(self.cfg.holds))

    def inbox_width(self, heard_links: int | None = None) -> int:
        """Length of an actor's inbox: :meth:`received_width`, then with ``reads_sent`` the
        ``(K - 1) C`` messages its own links last delivered."""
        own = (self.num_agents - 1) * self.cfg.num_elements if self.reads_sent else 0
        return self.received_width(heard_links) + own

    # -- the link state -----------------------------------------------------------------------

    @property
    def keeps_last(self) -> bool:
        """Recipients keep each link's last good message: silence holds it, or a lossy wire
        delivers it for a missing packet (``on_drop = "last"``)."""
        return self.cfg.holds or (self.lossy and self.on_drop == "last")

    @property
    def keeps_own(self) -> bool:
        """Senders keep what each of their links last delivered: news reads it
        (``news_margin``) or each sender reads it back (``reads_sent``)."""
        return self.reads_sent or self.cfg.news_margin is not None

    def init(self, batch: tuple[int, ...], heard_links: int | None = None) -> LinkState:
        """The state of ``batch`` teams' links before the first step (``heard_links``: the k
        links each recipient is listed; default ``K - 1``)."""
        k, c = self.num_agents, self.cfg.num_elements
        heard = k - 1 if heard_links is None else heard_links
        links = jnp.zeros((*batch, k, k - 1, c), jnp.float32)
        return LinkState(
            prev=jnp.zeros((*batch, k, heard, c), jnp.int32),
            last=links if self.keeps_last else None,
            own=links if self.keeps_own else None,
        )

    def init_agent(self) -> LinkState:
        """A deployed agent's share of :meth:`init`, its own row: on a real network it keeps
        ``last`` and ``own`` whatever the rules (the unused one costs a few floats)."""
        c = self.cfg.num_elements
        links = jnp.zeros((self.num_agents - 1, c), jnp.float32)
        return LinkState(jnp.zeros((self.num_agents - 1, c), jnp.int32), links, links)

    # -- one step -----------------------------------------------------------------------------

    def exchange(
        self,
        state: LinkState,
        z: jax.Array,
        u,
        keys: jax.Array,
        t,
        *,
        live=None,
        senders=None,
        wire: Callable | None = None,
    ) -> Exchange:
        """One step of a team's links, as the rollout and a team expert both run it: a link
        with news opens its gate, the sender side, the wire, the receiver side, and the
        messages routed to their recipients for the next step.

        Args:
          state: the links' :class:`LinkState` (:meth:`init`, or the last step's).
          z: (B, K, K-1, C') the message heads' outputs by sender slot, or (B, K, k, C')
            listed by recipient with ``senders``.
          u: each link's dither, laid out as ``z``.
          keys: (B,) the episodes' channel keys; t: the step.
          live: (B, K, K-1) or (B, K, k) bool, the links that exist (None: all).
          senders: (B, K, k) int32 each recipient's listed senders
            (``scaling.nearest_senders``), or None for links by sender slot.
          wire: ``wire(sent) -> (arrived, ok, extra)``: the noise between the sides
            (``channel.lossy.LossyLinks.step``); None: every packet arrives as sent.
        """
        cfg, held = self.cfg, state.own
        if held is not None and senders is None:  # a link with news opens its gate
            z = news_gate(cfg, z, held)
        sent = transmit(cfg, z, u, keys, t, state.prev, live=live, senders=senders)
        arrived, ok, extra = sent.z_hat, None, None
        if wire is not None:
            arrived, ok, extra = wire(sent)
        got = receive(
            cfg,
            arrived,
            u,
            ok=ok,
            last=state.last,
            on_drop=self.on_drop,
            live=live,
            speak=sent.speak,
            silent=sent.wire_bits == 0 if cfg.holds and sent.speak is None else None,
        )
        batch = got.z_hat.shape[:2]
        if senders is not None:  # already by recipient: its k listed links
            msgs = got.z_hat.reshape(*batch, -1)
        else:
            msgs = deliver(got.z_hat)
        if got.news is not None:  # which messages are news, by recipient
            msgs = jnp.concatenate([msgs, inbox(got.news)], -1)
        own = None if held is None else last_delivered(sent, held)  # by sender
        if self.reads_sent:  # each sender reads it back
            msgs = jnp.concatenate([msgs, own.reshape(*batch, -1)], -1)
        return Exchange(sent, got, msgs, LinkState(sent.symbols, got.last, own), extra, z)

    # -- a deployed agent's own row -----------------------------------------------------------

    def agent_inbox(self, received: jax.Array, state: LinkState) -> jax.Array:
        """A deployed agent's inbox: what it rebuilt of the links it receives
        (:meth:`agent_receive`), then with ``reads_sent`` what its own links last delivered
        (as :meth:`exchange` appends it)."""
        if self.reads_sent:
            return jnp.concatenate([received, state.own.reshape(-1)])
        return received

    def agent_send(self, z: jax.Array, u, state: LinkState) -> tuple[Sent, jax.Array, LinkState]:
        """A deployed agent's sender side on its own links, as :meth:`exchange` runs it:
        ``z`` (K-1, C') its message head's signals, ``u`` their dither (1, K-1, C') or None.
        Returns ``(sent, signal, state)``: the links' :class:`Sent` (a batch of one), the
        signals after news opened gates, and ``state`` with ``prev`` and ``own`` updated."""
        signal = news_gate(self.cfg, z, state.own)
        sent = transmit(self.cfg, signal[None], u, prev=state.prev[None])
        own = last_delivered(sent, state.own[None])[0]
        return sent, signal, state._replace(prev=sent.symbols[0], own=own)

    def agent_receive(self, message, u, ok, silent, state: LinkState):
        """A deployed agent's receiver side: ``message`` (K-1, C) what arrived from each
        sender (symbols, or a ``continuous`` channel's values), ``u`` their dither or None,
        ``ok`` (K-1,) the links whose frame arrived or that sent nothing, ``silent`` (K-1,) the
        links that sent nothing. A gated channel hands the receiver the gate (0 where silent)
        and a holding one ``silent``, as :meth:`exchange` does. Returns ``(received, state)``:
        the :meth:`received_width` inputs its actor reads (the messages, then under ``hold``
        the news flags) and ``state`` with ``last`` updated."""
        said = {}
        if self.cfg.link_gate:
            said["speak"] = (~silent).astype(jnp.float32)
        elif self.cfg.holds:
            said["silent"] = silent
        got = receive(self.cfg, message, u, ok=ok, last=state.last, on_drop=self.on_drop, **said)
        received = got.z_hat.reshape(-1)
        if got.news is not None:  # which messages are news, after the messages
            received = jnp.concatenate([received, got.news])
        return received, state._replace(last=got.last)


def build(
    cfg: ChannelConfig,
    num_agents: int,
    *,
    reads_sent: bool = False,
    lossy: bool | None = None,
    on_drop: str = "",
) -> TeamChannel:
    """The channel ``cfg`` for a team of ``num_agents``: its link rules, the state they carry
    and the inbox they fill. ``reads_sent``: ``AgentConfig.reads_sent``; ``lossy``: packets can
    be lost (default: ``cfg``'s noise is not clean); ``on_drop``: what a missing packet becomes
    (default ``cfg.noise.on_drop``; a deployed agent's own choice)."""
    if lossy is None:
        lossy = cfg.speaks and not cfg.noise.clean
    return TeamChannel(cfg, num_agents, reads_sent, lossy, on_drop)
