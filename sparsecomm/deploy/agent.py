"""One agent as its own process: ``python -m sparsecomm.deploy.agent --team T --agent I ...``.

It binds its UDP address, says hello to the world, and then, for every observation the world
sends for step ``t`` of episode ``b``:

1. reads the observation's heard map (``wire.parse_obs``): which of its senders spoke to it at
   step ``t - 1``; it waits for those senders' frames only, at most ``Deadlines.message`` from
   the observation's arrival; a promised frame still missing then is a **loss** (the null
   message, or the link's last one: ``on_drop``, and always under ``on_silence = "hold"``); a
   sender the map says was silent is silence at once (no datagram was sent). Without a map it
   waits for every sender until the deadline, and a sender not heard is a loss;
2. takes its own row of each frame (``channel.decode_sender``, ``core.frame_slot``) and rebuilds
   each message with the dither regenerated from ``dither_key(chan[b], t - 1, s, I)``
   (``core.receive``: the channel's receiver side, ``channel.receive``, news inputs included);
3. steps its actor (``core.agent_step``: ``Team.act``, the action rule, ``channel.transmit``);
4. when at least one of its links speaks, encodes its frame (``channel.encode_sender``) and sends
   one copy to each recipient whose link speaks, through the fault layer; a silent agent sends
   its peers nothing. Then it sends the world its action with what it sent (which links spoke,
   the frame's bits, the datagrams) and heard (frames missing, duplicates, stale and dropped
   datagrams), a ``wire.Report``.

Every datagram is sealed with the team's secret (``wire.Auth``); one that fails its MAC, or
whose sender, kind, episode or step is not one this agent expects (an observation or ``bye``
not from the world, a frame not from one of its senders, an episode or step outside the batch),
is dropped before its payload is read and counted (``bad``).

Each process draws a nonce (``wire.new_nonce``) and sends it in its hello; the world echoes
an agent's latest nonce first in every observation, and the agent drops every observation that
does not carry its own (``foreign``): a restarted agent acts only on the observation its own
hello asked for and those after it, never on its predecessor's or on replays of them. An
observation of step 0, or the first observation this process acts on, starts from a zero GRU
state: a restarted agent rejoins the episode where it is, with its recurrent state reset (and,
with ``on_drop = last`` or ``on_silence = hold``, no last messages), and without the frames of
the step before (sent before it said hello: each one promised is a loss). A copy of the observation
being acted on, or of the one just acted on, is dropped (``dup``; nothing is sent back, so a
replay is not reflected); an older one is dropped (``stale``). The agent exits on the world's
``bye`` (0; only a sealed ``bye`` from the world counts), after ``Deadlines.idle`` without a
word from the world (3), or on SIGINT/SIGTERM.
"""

from __future__ import annotations

import dataclasses
import heapq
import sys
import time
from pathlib import Path

import numpy as np

from sparsecomm.cmdline import refuse_empty_paths
from sparsecomm.deploy import wire
from sparsecomm.deploy.faults import Deadlines, Faults, inject

ON_DROP = ("null", "last")
_STARTED = time.monotonic()


@dataclasses.dataclass
class AgentArgs:
    """One agent process of a deployed team."""

    team: Path
    """Folder of the exported team (``sparsecomm export``; ``sparsecomm deploy`` writes one)."""
    agent: int
    """This agent's id, in [0, K - 1]."""
    peers: tuple[str, ...]
    """The address (host:port) of every agent, in id order, this one's included: where each
    agent listens. The same list on every host."""
    world: str
    """The world's address (host:port)."""
    seed: int
    """The batch seed: ``sparsecomm eval`` uses ``config.seed + 1000003 + run index``."""
    episodes: int
    """Episodes in the batch (the draws depend on it, as in ``sparsecomm eval --episodes``)."""
    secret_file: Path
    """File of the team's secret (hex; only its owner may read it: ``wire.read_secret``),
    under which every datagram is sealed and checked. ``sparsecomm deploy`` makes one per
    deployment; on separate hosts, copy the same file to each (docs/deploy.md)."""
    listen: str = ""
    """Address to bind (host:port); default: this agent's entry of ``peers``. On a host behind
    another interface, e.g. ``0.0.0.0:9001``."""
    greedy: bool = False
    """Take the most probable action instead of sampling."""
    on_drop: str = "null"
    """A packet missing at the deadline is the ``null`` message (the paper's "nothing sent") or
    the link's ``last`` good one (``NoiseConfig.on_drop``). Default: null."""
    faults: Faults = Faults()
    """Faults on this agent's outgoing packets."""
    jax_cache: str = ""
    """Folder of JAX's persistent compilation cache, shared by the team's processes (a
    restarted agent then starts without compiling); empty: none."""
    deadlines: Deadlines = Deadlines()
    """How long each wait lasts."""

    def __post_init__(self):
        if self.on_drop not in ON_DROP:
            raise ValueError(f"AgentArgs.on_drop must be one of {ON_DROP}, got {self.on_drop!r}")
        for name in ("agent", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"AgentArgs.{name} must be an integer >= 0, got {value!r}")
        if isinstance(self.episodes, bool) or not isinstance(self.episodes, int):
            raise ValueError(f"AgentArgs.episodes must be an integer >= 1, got {self.episodes!r}")
        if self.episodes < 1:
            raise ValueError(f"AgentArgs.episodes must be an integer >= 1, got {self.episodes!r}")
        if not 0 <= self.agent < len(self.peers):
            raise ValueError(
                f"AgentArgs.agent must be in [0, {len(self.peers) - 1}] (one per peer), got "
                f"{self.agent}"
            )
        for text in self.peers:
            wire.parse_address(text, "AgentArgs.peers")
        wire.parse_address(self.world, "AgentArgs.world")
        if self.listen:
            wire.parse_address(self.listen, "AgentArgs.listen")


class Outbox:
    """Datagrams waiting for their send time (reordered ones are held back)."""

    def __init__(self, sock):
        self.sock, self.heap, self.n = sock, [], 0

    def send(self, data: bytes, address, delay: float = 0.0) -> None:
        if delay <= 0:
            self._send(data, address)
        else:
            self.n += 1
            heapq.heappush(self.heap, (time.monotonic() + delay, self.n, data, address))

    def flush(self) -> float | None:
        """Send what is due; the time until the next one (``None``: nothing held)."""
        now = time.monotonic()
        while self.heap and self.heap[0][0] <= now:
            _, _, data, address = heapq.heappop(self.heap)
            self._send(data, address)
        return self.heap[0][0] - now if self.heap else None

    def _send(self, data, address) -> None:
        try:
            self.sock.sendto(data, address)
        except OSError:  # e.g. nobody listening yet (ICMP refused): the datagram is lost
            pass


class Agent:
    def __init__(self, args: AgentArgs):
        import jax
        import jax.numpy as jnp

        from sparsecomm import channel
        from sparsecomm.deploy import core

        self.auth = wire.Auth(wire.read_secret(args.secret_file, "AgentArgs.secret_file"))
        core.use_compile_cache(args.jax_cache)
        self.args, self.core, self.channel, self.jnp = args, core, channel, jnp
        loaded = core.read_team(args.team)
        self.cfg = loaded.config.channel
        k = loaded.env.num_agents
        if len(args.peers) != k:
            raise ValueError(f"AgentArgs.peers must list the team's {k} agents, got {args.peers}")
        self.k, self.i = k, args.agent
        self.senders = [int(s) for s in channel.others(k)[self.i]]  # whom I hear, slot order
        self.recipients = self.senders  # whom I send to, slot order (the same list)
        self.rows = [core.frame_slot(s, self.i) for s in self.senders]  # my row in their frames
        self.peers = [wire.parse_address(p) for p in args.peers]
        self.world = wire.parse_address(args.world)
        listen = wire.parse_address(args.listen) if args.listen else self.peers[self.i]
        self.sock = wire.udp_socket(listen)
        self.out = Outbox(self.sock)
        self.params = jax.tree.map(jnp.asarray, loaded.actor)
        self.obs_dim = loaded.env.obs_dim  # the task's (the world sends its observations)
        steps = self.steps = loaded.env.max_steps
        key = core.batch_key(args.seed)
        self.chan, gumbel = core.agent_draws(key, args.episodes, steps, k, loaded.env.num_actions)
        self.gumbel = np.asarray(gumbel[:, :, self.i])  # (T, N, A)
        step_fn = core.agent_step(loaded.team, self.cfg, args.greedy)
        receive_fn = core.receive(self.cfg, k, args.on_drop)
        self.step_fn = lambda params, *rest: step_fn(params, self.i, *rest)
        self.receive_fn = lambda key, t, *rest: receive_fn(key, t, self.i, *rest)
        c = self.cfg.num_elements
        self.c, self.h = c, loaded.team.cfg.gru
        self.inbox_size = core.inbox_size(self.cfg, k)
        self.inbox: dict[tuple[int, int, int], list[bytes]] = {}
        self.episode = -1
        self.last_act: tuple[int, int] | None = None  # the observation last acted on
        self.acting: tuple[int, int] | None = None  # the observation being acted on
        self.nonce = wire.new_nonce()  # this process's: the world echoes it in observations
        self.counts = {"dup": 0, "stale": 0, "foreign": 0, "bad": 0, "no_map": 0}
        self._reset_episode(-1)
        self._warm_up()

    def _reset_episode(self, episode: int) -> None:
        jnp = self.jnp
        self.episode, self.t = episode, -1
        self.carry = jnp.zeros((self.h,), jnp.float32)
        # my links' state (``channel.team.LinkState``, my row): my links' symbols at t - 1 and
        # what they last delivered, and the last good message of each link I receive
        self.links = self.channel.build(self.cfg, self.k, lossy=True).init_agent()

    def _warm_up(self) -> None:
        """Compile every jitted function before saying hello."""
        obs = np.zeros(self.obs_dim, np.float32)
        msgs = np.zeros(self.inbox_size, np.float32)
        self.step_fn(
            self.params,
            self.carry,
            obs,
            msgs,
            self.gumbel[0, 0],
            0,
            self.chan[0],
            self.links.prev,
            self.links.own,
        ).action.block_until_ready()
        ok = np.zeros(self.k - 1, bool)
        self.receive_fn(self.chan[0], 0, self._message_buffer(), ok, ~ok, self.links.last)

    def _message_buffer(self) -> np.ndarray:
        """Room for one step's K - 1 incoming messages: the floats of a channel that sends
        values, else symbols."""
        dtype = np.float32 if self.cfg.sends_values else np.int32
        return np.zeros((self.k - 1, self.c), dtype)

    # -- the loop ---------------------------------------------------------------------------

    def run(self) -> int:
        d = self.args.deadlines
        hello = self.auth.pack(wire.HELLO, self.i, wire.WORLD, 0, 0, self.nonce)
        start = time.monotonic()
        next_hello = 0.0
        obs = None
        while obs is None:  # hello until the world answers with an observation
            now = time.monotonic()
            if now - start > d.startup:
                print(f"agent {self.i}: no observation within {d.startup} s", file=sys.stderr)
                return 3
            if now >= next_hello:
                self.out.send(hello, self.world)
                next_hello = now + 0.5
            got = self._receive(min(next_hello, start + d.startup))
            if got == "bye":
                return 0
            obs = got if isinstance(got, wire.Datagram) else None
        heard = time.monotonic()
        while True:
            if obs is not None:
                result = self._act(obs)
                if result == "bye":
                    return 0
                heard = time.monotonic()
                obs = result if isinstance(result, wire.Datagram) else None
                continue
            got = self._receive(heard + d.idle)
            if got == "bye":
                return 0
            if not isinstance(got, wire.Datagram):
                if time.monotonic() - heard >= d.idle:
                    print(f"agent {self.i}: world silent for {d.idle} s", file=sys.stderr)
                    return 3
                continue
            obs = got

    def _receive(self, until: float):
        """Handle datagrams until an observation newer than the last handled arrives (returned),
        a peer's packet (``"msg"``), a ``bye`` (``"bye"``) or the time ``until`` (``None``)."""
        while True:
            due = self.out.flush()
            wait = until - time.monotonic()
            if due is not None:
                wait = min(wait, due)
            if wait <= 0 and due is None:
                return None
            self.sock.settimeout(max(wait, 1e-4))
            try:
                data, _ = self.sock.recvfrom(wire.MAX_DATAGRAM)
            except (TimeoutError, BlockingIOError):
                if time.monotonic() >= until:
                    return None
                continue
            except ConnectionError:  # ICMP port unreachable of an earlier send, on some OSes
                continue
            got = self._handle(data)
            if got is not None:
                return got

    def _handle(self, data: bytes):
        dg = self.auth.parse(data)
        in_batch = dg is not None and dg.episode < self.args.episodes and dg.step < self.steps
        if dg is None or dg.recipient != self.i or not in_batch:
            self.counts["bad"] += 1
            return None
        if dg.kind == wire.BYE and dg.sender == wire.WORLD and not dg.payload:
            return "bye"
        if dg.kind == wire.OBS and dg.sender == wire.WORLD:
            if wire.obs_nonce(dg.payload) != self.nonce:  # for another process of this agent
                self.counts["foreign"] += 1
                return None
            here = (dg.episode, dg.step)
            if here == self.acting or (self.last_act is not None and here == self.last_act):
                self.counts["dup"] += 1  # a copy of the observation in progress or just done
                return None
            if self.last_act is not None and here < self.last_act:
                self.counts["stale"] += 1  # an observation already acted on: a replay
                return None
            return dg
        if dg.kind == wire.MSG and dg.sender in self.senders:
            if (dg.episode, dg.step) < (self.episode, self.t):
                self.counts["stale"] += 1  # for a step already acted on
                return None
            got = self.inbox.setdefault((dg.episode, dg.step, dg.sender), [])
            if dg.payload in got:
                self.counts["dup"] += 1
            elif len(got) < 4:
                got.append(dg.payload)
            return "msg"
        self.counts["bad"] += 1
        return None

    def _decode(self, r: int, payload: bytes):
        """My row of sender slot ``r``'s frame ``payload`` (``None``: not a frame of this
        channel)."""
        try:
            frame = self.channel.decode_sender(self.cfg, payload, self.k - 1)
        except ValueError:  # channel.PacketError: garbage behind a good header
            self.counts["bad"] += 1
            return None
        return np.asarray(frame)[self.rows[r]]

    def _gather(self, episode: int, t: int, until: float, expect: np.ndarray):
        """My row of each ``expect``-ed sender's frame of step ``t`` (decoded), waiting until
        ``until`` at most; ``None`` for a sender not expected or not heard."""
        got = [None] * (self.k - 1)
        while True:
            for r, s in enumerate(self.senders):
                if got[r] is not None or not expect[r]:
                    continue
                for payload in self.inbox.pop((episode, t, s), []):
                    got[r] = self._decode(r, payload)
                    if got[r] is not None:
                        break
            if all(g is not None for g, e in zip(got, expect, strict=True) if e):
                return got, None
            event = self._receive(until)
            if event != "msg":  # the deadline, a bye, or the world moved on (act on this step
                return got, event  # first, then on the newer one)

    def _act(self, obs: wire.Datagram):
        """One step: gather, rebuild, act, send. Returns a newer observation that arrived
        meanwhile, ``"bye"`` (after acting), or ``None``."""
        b, t = obs.episode, obs.step
        arrived = time.monotonic()
        if b >= self.args.episodes or t >= self.gumbel.shape[0]:
            return None
        rejoined = False
        if b != self.episode or t == 0:
            rejoined = t > 0  # a restart, or an episode whose start we missed
            self._reset_episode(b)
        elif t <= self.t:
            return None
        _, values, heard = wire.parse_obs(obs.payload, self.obs_dim, self.k - 1)
        if values is None:
            self.counts["bad"] += 1
            return None
        self.acting = (b, t)  # from here a copy of this observation is a duplicate
        msgs, missing, newer = self._messages(b, t, heard, arrived, rejoined)
        self._prune(b, t)
        out = self.step_fn(
            self.params,
            self.carry,
            values,
            msgs,
            self.gumbel[t, b],
            t,
            self.chan[b],
            self.links.prev,
            self.links.own,
        )
        self.carry, self.t = out.carry, t
        symbols, signal = np.asarray(out.symbols), np.asarray(out.signal)
        spoke = np.asarray(out.spoke, bool)
        frame_bits, datagram, sent, sent_n = self._send_frame(b, t, symbols, signal, spoke)
        self.links = self.links._replace(prev=out.symbols, own=out.delivered)
        report = self._report(out, rejoined, frame_bits, missing, spoke, datagram, sent, sent_n)
        act = self.auth.pack(wire.ACT, self.i, wire.WORLD, b, t, wire.pack_report(report))
        self.last_act, self.acting = (b, t), None
        self.out.send(act, self.world)
        return newer

    def _messages(self, b: int, t: int, heard, arrived: float, rejoined: bool = False):
        """The inbox my actor reads at step ``t`` of episode ``b``: the messages of step
        ``t - 1`` rebuilt (``core.receive``) from my row of each sender's frame, waiting for the
        senders the observation's ``heard`` map promises (every sender without a map) until
        ``Deadlines.message`` after the observation ``arrived`` (monotonic seconds); zeros at
        step 0 or on a channel that does not speak. A process that ``rejoined`` mid-episode
        uses no frame of ``t - 1``: they were sent before it said hello (to its predecessor,
        or to a port nobody held yet), so whether one reached it is an accident of timing; each
        promised one is a loss.

        Returns:
          ``(msgs, missing, newer)``: the inbox, the number of promised frames still missing
          at the deadline (losses), and what :meth:`_gather` stopped for (a newer observation,
          ``"bye"``, or ``None``).
        """
        newer = None
        missing = 0
        if t == 0 or not self.cfg.speaks:  # nothing heard yet, or nothing ever sent
            msgs = np.zeros(self.inbox_size, np.float32)
        else:
            if heard is None:  # no map: wait for every sender; one not heard is a loss
                self.counts["no_map"] += 1
                expect = np.ones(self.k - 1, bool)
            else:
                expect = heard
            if rejoined:
                got = [None] * (self.k - 1)
            else:
                until = arrived + self.args.deadlines.message
                got, newer = self._gather(b, t - 1, until, expect)
            silent = ~expect  # the map says: nothing was sent
            ok = np.array([g is not None for g in got], bool) | silent
            missing = int((~ok).sum())
            message = self._message_buffer()
            for r, g in enumerate(got):
                if g is not None:
                    message[r] = g
            msgs, last = self.receive_fn(self.chan[b], t - 1, message, ok, silent, self.links.last)
            self.links = self.links._replace(last=last)
        return msgs, missing, newer

    def _send_frame(self, b: int, t: int, symbols, signal, spoke: np.ndarray):
        """Send my frame of step ``t`` of episode ``b`` (``channel.encode_sender`` of my links'
        ``symbols`` and ``signal``), one copy to each recipient whose link ``spoke``, through
        the fault layer (``faults.inject``); nothing when no link speaks.

        Returns:
          ``(frame_bits, datagram, sent, sent_n)``: the frame's bits (0: none), and per
          recipient slot the bytes of the datagram due (0: none) and the bytes and datagrams
          the fault layer sent for it.
        """
        n = self.k - 1
        datagram, sent, sent_n = [0] * n, [0] * n, [0] * n
        frame_bits = 0
        if self.cfg.speaks and spoke.any():  # one frame, one copy per speaking recipient
            frame = self.channel.encode_sender(self.cfg, symbols, signal)
            frame_bits = 8 * len(frame)
            for r, j in enumerate(self.recipients):
                if not spoke[r]:
                    continue
                dg = self.auth.pack(wire.MSG, self.i, j, b, t, frame)
                sends = inject(self.args.faults, dg, b, t, self.i, j)
                for delay, data in sends:
                    self.out.send(data, self.peers[j], delay)
                datagram[r], sent[r], sent_n[r] = len(dg), sum(len(d) for _, d in sends), len(sends)
        return frame_bits, datagram, sent, sent_n

    def _report(self, out, rejoined, frame_bits, missing, spoke, datagram, sent, sent_n):
        """This step's :class:`wire.Report` for the world: the action of the actor's ``out``
        and what I sent (the simulation's wire bits, the frame's, per link payload bits,
        ``spoke``, ``datagram``, ``sent``, ``sent_n``) and heard (``missing`` frames, and the
        datagrams counted since the last report, each count capped at 2**32 - 1; they then
        start again from 0)."""
        counts = {name: min(v, 2**32 - 1) for name, v in self.counts.items()}
        self.counts = dict.fromkeys(self.counts, 0)
        return wire.Report(
            action=int(out.action),
            rejoined=rejoined,
            sim_wire=round(float(out.wire)),
            frame=frame_bits,
            missing=missing,
            **counts,
            payload=tuple(int(x) for x in np.asarray(out.payload)),
            spoke=tuple(int(x) for x in spoke),
            datagram=tuple(datagram),
            sent=tuple(sent),
            sent_n=tuple(sent_n),
        )

    def _prune(self, episode: int, t: int) -> None:
        for key in [key for key in self.inbox if (key[0], key[1]) < (episode, t)]:
            del self.inbox[key]


def main(argv: list[str] | None = None) -> int:
    import tyro

    wire.die_with_parent()
    argv = sys.argv[1:] if argv is None else argv
    try:
        refuse_empty_paths(AgentArgs, argv)  # the parser would read '' as the current folder
        args = tyro.cli(AgentArgs, args=argv)
        agent = Agent(args)
        ready = time.monotonic() - _STARTED
        print(f"agent {args.agent}: ready {ready:.1f} s after start", flush=True)
    except ValueError as e:
        print(f"sparsecomm.deploy.agent: error: {e}", file=sys.stderr)
        return 2
    try:
        return agent.run()
    except KeyboardInterrupt:
        return 130
    finally:
        agent.sock.close()


if __name__ == "__main__":
    sys.exit(main())
