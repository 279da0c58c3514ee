"""``sparsecomm deploy``: start the world and one process per agent, keep them alive, report.

For each run index: export the team (weights only) into the output folder, make the team's
secret (``wire.write_secret``, in a private temporary folder removed at the end: the processes
get its path, never the secret on a command line), pick free UDP ports on ``Deploy.host``,
start ``python -m sparsecomm.deploy.world`` and one ``python -m
sparsecomm.deploy.agent`` per agent (each in its own POSIX session, so a Ctrl-C reaches the launcher
alone; each asks Linux for SIGTERM when its parent dies, ``wire.die_with_parent``), then
supervise them:

* the world reports every step to the launcher's monitor socket; with ``kills_per_episode`` the
  launcher SIGKILLs the scheduled agent at the scheduled step (``kill_plan``, seeded);
* an agent process that exits before the world has played every episode (the world's sealed
  ``done``), whatever its exit code, is started again at once (its recurrent state starts from
  zero: it rejoins at the step the world is at; ``sparsecomm.deploy.agent``); one that keeps
  dying fails the run;
* nothing waits without a deadline: the world that reports no step for
  ``Deadlines.startup + Deadlines.action`` seconds is stopped and the run refused;
* on return, error, Ctrl-C or SIGTERM every child is stopped (SIGTERM, then SIGKILL after 3 s)
  and reaped: no orphan; the simulation thread is joined before the launcher exits, so its exit
  status is 0, 2 (a ``RunError``: the cause printed) or 130 (interrupted), never a signal.

Then it reads the world's ``episodes.jsonl``, computes eval's metrics with 95% bootstrap CIs
over episodes (``sparsecomm.stats``), and, with ``reference``, plays the same episodes in
simulation (``rollout``, the run's ``sparsecomm eval`` draws) to set the two side by side,
episode for episode.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sparsecomm.deploy import wire
from sparsecomm.deploy.faults import Deadlines, Faults
from sparsecomm.deploy.report import CI_METRICS, read_episodes, summarize
from sparsecomm.errors import RunError
from sparsecomm.stats import bootstrap_ci


def kill_plan(seed: int, episodes: int, num_agents: int, kills: int, window: int) -> dict:
    """``{episode: [(step, agent), ...]}``: which agent the launcher kills at which step (uniform
    in [1, window]) of each episode, ``kills`` per episode (a kill scheduled after the episode
    ended does not happen). Seeded: the same plan for the same arguments."""
    plan = {}
    for b in range(episodes if kills else 0):
        rng = np.random.default_rng([seed, b, 7919])
        steps = rng.integers(1, window + 1, size=kills)
        agents = rng.integers(0, num_agents, size=kills)
        plan[b] = sorted(zip(steps.tolist(), agents.tolist(), strict=True))
    return plan


class Processes:
    """The children of one deployment; ``close`` stops and reaps every one."""

    def __init__(self, logs: Path):
        self.logs = logs
        self.logs.mkdir(parents=True, exist_ok=True)
        self.all: list[subprocess.Popen] = []

    def start(self, name: str, cmd: list[str]) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "ab")
        log.write(f"--- start {time.strftime('%H:%M:%S')}: {' '.join(cmd)}\n".encode())
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        self.all.append(proc)
        return proc

    def wait_ready(self, name: str, proc: subprocess.Popen, deadline: float) -> bool:
        """Wait until the process ``name`` logs that it is ready, dies, or ``deadline``
        seconds pass (True: ready)."""
        until = time.monotonic() + deadline
        while time.monotonic() < until and proc.poll() is None:
            if ": ready " in self.tail(name, 3):
                return True
            time.sleep(0.05)
        return False

    def close(self, grace: float = 3.0) -> None:
        alive = [p for p in self.all if p.poll() is None]
        for p in alive:
            with contextlib.suppress(ProcessLookupError):
                p.terminate()
        until = time.monotonic() + grace
        for p in alive:
            try:
                p.wait(max(until - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    p.kill()
                p.wait(5)

    def tail(self, name: str, lines: int = 15) -> str:
        path = self.logs / f"{name}.log"
        if not path.exists():
            return ""
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


def _flags(prefix: str, obj) -> list[str]:
    out = []
    for field in dataclasses.fields(obj):
        out += [f"--{prefix}.{field.name.replace('_', '-')}", str(getattr(obj, field.name))]
    return out


def play(
    team: Path,
    out: Path,
    seed: int,
    episodes: int,
    num_agents: int,
    *,
    host: str = "127.0.0.1",
    faults: Faults | None = None,
    deadlines: Deadlines | None = None,
    on_drop: str = "null",
    greedy: bool = False,
    kills_per_episode: int = 0,
    kill_window: int = 8,
    kill_seed: int = 0,
    peer=None,
) -> dict:
    """Play one deployment of the exported ``team``; ``{"episodes": [...], "kills", "restarts",
    "wall_s", "peer"}``. Raises ``RunError`` when the world fails or stalls.

    ``peer``: a hostile peer (``Deploy.forgeries_per_second``, ``Deploy.replay``), called with
    ``{name: ((host, port), recipient id)}`` for the world, each agent (``agent_<i>``) and the
    launcher's monitor before the processes start; it returns an object whose ``go()`` the
    launcher calls when the world reports its first step (the drill is of the play; a flood
    during start-up only delays it) and whose ``stop()`` returns what it did (``"peer"`` of the
    result), e.g. a ``hostile.Flood`` or a ``replay.Replay``; ``None``: no peer."""
    faults = Faults() if faults is None else faults
    deadlines = Deadlines() if deadlines is None else deadlines
    k = num_agents
    private = Path(tempfile.mkdtemp(prefix="sparsecomm-deploy-"))  # mode 0700, removed below
    net = _open_network(host, k, private)
    world_cmd, agent_cmd = _commands(
        team, out, seed, episodes, net, faults, deadlines, on_drop=on_drop, greedy=greedy
    )
    plan = kill_plan(kill_seed, episodes, k, kills_per_episode, kill_window)
    shutil.rmtree(out / "logs", ignore_errors=True)
    procs = Processes(out / "logs")
    (out / "episodes.jsonl").unlink(missing_ok=True)
    start = time.monotonic()
    max_restarts = kills_per_episode * episodes + 3 * k
    watch = _Supervisor(procs, agent_cmd, net, plan, start, deadlines, max_restarts)
    peer_did = None
    # Ctrl-C and SIGTERM stop every process. SIGINT is set here too, not left to Python: a
    # launcher started in the background of a script inherits SIGINT ignored, and Python then
    # installs no handler of its own.
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        # a peer starts first: a replaying one captures the team's start-up hellos too
        watch.hostile = None if peer is None else peer(_targets(net))
        world = procs.start("world", world_cmd)
        watch.start_team(k)
        watch.until_world_exits(world)
        watch.wait_for_agents()
    finally:
        if watch.hostile is not None:
            peer_did = watch.hostile.stop()
        procs.close()
        net.monitor.close()
        shutil.rmtree(private, ignore_errors=True)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return {
        "episodes": read_episodes(out),
        "kills": watch.kills,
        "restarts": watch.restarts,
        "wall_s": time.monotonic() - start,
        "peer": peer_did,
    }


class _Network(NamedTuple):
    """Where the processes of one deployment listen, and the secret their datagrams are sealed
    with."""

    secret: Path
    """The team's secret file, in the launcher's private folder (``wire.write_secret``)."""
    auth: wire.Auth
    """Seals and checks datagrams under that secret."""
    world: str
    """The world's address, ``host:port``."""
    agents: list[str]
    """Each agent's address, ``host:port``, in id order."""
    monitor: socket.socket
    """The launcher's monitor socket, where the world reports its steps."""
    monitor_addr: str
    """Its address, ``host:port``."""


def _open_network(host: str, num_agents: int, private: Path) -> _Network:
    """A new deployment's :class:`_Network` on ``host``: the team's secret written into
    ``private``, a free UDP port for the world and for each agent, and the monitor socket bound
    to one more."""
    secret = wire.write_secret(private / "team.key")
    auth = wire.Auth(wire.read_secret(secret))
    ports = wire.free_ports(host, num_agents + 1)
    world_addr = f"{host}:{ports[0]}"
    agents = [f"{host}:{p}" for p in ports[1:]]
    monitor = wire.udp_socket((host, 0))
    monitor_addr = f"{host}:{monitor.getsockname()[1]}"
    return _Network(secret, auth, world_addr, agents, monitor, monitor_addr)


def _commands(team, out, seed, episodes, net: _Network, faults, deadlines, *, on_drop, greedy):
    """The command lines of a deployment's processes: the world's, and a function of ``i`` that
    gives agent ``i``'s (each ``python -m``, with the team, batch seed, episodes, compilation
    cache under ``out`` and secret file in common)."""
    py = [sys.executable, "-m"]
    common = ["--team", str(team), "--seed", str(seed), "--episodes", str(episodes)]
    common += ["--jax-cache", str(out / "jax_cache"), "--secret-file", str(net.secret)]
    world_cmd = [
        *py,
        "sparsecomm.deploy.world",
        *common,
        "--agents",
        *net.agents,
        "--listen",
        net.world,
        "--monitor",
        net.monitor_addr,
        "--out",
        str(out),
        *_flags("deadlines", deadlines),
    ]

    def agent_cmd(i: int) -> list[str]:
        return [
            *py,
            "sparsecomm.deploy.agent",
            *common,
            "--agent",
            str(i),
            "--peers",
            *net.agents,
            "--world",
            net.world,
            "--on-drop",
            on_drop,
            "--greedy" if greedy else "--no-greedy",
            *_flags("faults", faults),
            *_flags("deadlines", deadlines),
        ]

    return world_cmd, agent_cmd


def _targets(net: _Network) -> dict:
    """What a hostile peer may forge datagrams to: ``{name: ((host, port), recipient id)}`` for
    the world, each agent (``agent_<i>``) and the launcher's monitor."""
    targets = {"world": (wire.parse_address(net.world), wire.WORLD)}
    targets |= {f"agent_{i}": (wire.parse_address(a), i) for i, a in enumerate(net.agents)}
    targets["launcher"] = (wire.parse_address(net.monitor_addr), wire.WORLD)
    return targets


class _Supervisor:
    """The launcher's watch over one deployment's agent processes while the world plays.

    It reads the world's steps on the monitor socket, lets the hostile peer (``hostile``) loose
    at the first, kills agents as ``plan`` (:func:`kill_plan`) says, starts again at once an
    agent that exits before the world is done (``max_restarts`` times in all, then the run
    fails), and refuses a world that reports no step for ``Deadlines.startup +
    Deadlines.action`` seconds. ``kills`` and ``restarts`` list what happened (restarts timed
    in seconds from ``start``, monotonic).
    """

    def __init__(
        self,
        procs: Processes,
        agent_cmd,
        net: _Network,
        plan: dict,
        start: float,
        deadlines: Deadlines,
        max_restarts: int,
    ):
        self.procs, self.agent_cmd, self.net, self.plan = procs, agent_cmd, net, plan
        self.start, self.deadlines, self.max_restarts = start, deadlines, max_restarts
        self.team: list[subprocess.Popen] = []
        self.hostile = None
        self.kills: list[dict] = []
        self.restarts: list[dict] = []

    def start_team(self, num_agents: int) -> None:
        """Start every agent process: agent 0 first, the others once it is ready (or
        ``Deadlines.startup`` seconds passed)."""
        self.team = [self.procs.start("agent_0", self.agent_cmd(0))]
        # The others start once agent 0 has compiled: they then load its programs from the
        # shared compilation cache instead of compiling them again on the same cores.
        self.procs.wait_ready("agent_0", self.team[0], self.deadlines.startup)
        self.team += [
            self.procs.start(f"agent_{i}", self.agent_cmd(i)) for i in range(1, num_agents)
        ]

    def until_world_exits(self, world: subprocess.Popen) -> None:
        """Supervise until the world exits; ``RunError`` (with a log's tail) when an agent
        keeps dying, the world stalls, or it exits with an error."""
        self.progress = time.monotonic()
        self.done = False  # the world said it played every episode
        self.last_step = (-1, -1)  # the latest (episode, step) the world reported
        self.let_loose = False
        stall = self.deadlines.startup + self.deadlines.action
        while world.poll() is None:
            self._read_monitor()
            now = time.monotonic()
            self._restart_exited(world, now)
            if now - self.progress > stall:
                raise RunError(
                    f"the world reported no step for {stall:.0f} s (Deadlines.startup + "
                    "Deadlines.action); its log:\n" + self.procs.tail("world")
                )
        if world.returncode != 0:
            raise RunError(
                f"the world exited with {world.returncode}; its log:\n" + self.procs.tail("world")
            )

    def _read_monitor(self) -> None:
        """Every datagram waiting on the monitor socket (a flood must not hold the world's step
        or done behind it; the first waited for up to 50 ms): note ``done`` and each new step,
        let the peer loose at the first, and kill the agents ``plan`` schedules at that step."""
        for dg in _monitor_datagrams(self.net.monitor, self.net.auth):
            self.done |= dg.kind == wire.DONE
            # Progress is a step later than the last one seen: a replayed (sealed, real)
            # step datagram must not hide a stalled world, nor trigger a kill twice.
            if dg.kind != wire.STEP or (dg.episode, dg.step) <= self.last_step:
                continue
            self.progress, self.last_step = time.monotonic(), (dg.episode, dg.step)
            if self.hostile is not None and not self.let_loose:  # the team plays: let it loose
                self.hostile.go()
                self.let_loose = True
            for step, agent in self.plan.get(dg.episode, []):
                if step == dg.step and self.team[agent].poll() is None:
                    self.team[agent].kill()
                    self.kills.append({"episode": dg.episode, "step": step, "agent": agent})

    def _restart_exited(self, world: subprocess.Popen, now: float) -> None:
        """Start again every agent process that exited, whatever its exit code, while the world
        still plays and has not said it is done (``now``: the time of the check, monotonic)."""
        for i, p in enumerate(self.team):  # an exit before the world is done: restart
            if p.poll() is not None and not self.done and world.poll() is None:
                if len(self.restarts) >= self.max_restarts:
                    raise RunError(
                        f"agent {i} keeps dying ({len(self.restarts)} restarts); its log:\n"
                        + self.procs.tail(f"agent_{i}")
                    )
                self.restarts.append({"agent": i, "exit": p.returncode, "at_s": now - self.start})
                self.team[i] = self.procs.start(f"agent_{i}", self.agent_cmd(i))

    def wait_for_agents(self) -> None:
        """Give the agents, told bye by the world, 5 s in all to exit."""
        until = time.monotonic() + 5.0  # the agents were told bye
        for p in self.team:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(until - time.monotonic(), 0.01))


def _monitor_datagrams(monitor, auth: wire.Auth, most: int = 4096) -> list[wire.Datagram]:
    """The world's sealed datagrams waiting on the launcher's ``monitor`` socket (at most
    ``most``; the first waited for up to 50 ms); anything else is dropped."""
    found = []
    monitor.settimeout(0.05)
    for _ in range(most):
        try:
            dg = auth.parse(monitor.recv(wire.MAX_DATAGRAM))
        except (TimeoutError, BlockingIOError, ConnectionError):
            break
        monitor.settimeout(0.0)
        if dg is not None and dg.sender == wire.WORLD and dg.recipient == wire.WORLD:
            found.append(dg)
    return found


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


class Background:
    """``fn(*args)`` in a daemon thread (a Ctrl-C does not wait for it); ``result()`` joins it
    and returns its value or raises its exception."""

    def __init__(self, fn, *args):
        self.value, self.error = None, None
        self.thread = threading.Thread(target=self._run, args=(fn, args), daemon=True)
        self.thread.start()

    def _run(self, fn, args):
        try:
            self.value = fn(*args)
        except BaseException as e:  # re-raised in the caller's thread by result()
            self.error = e

    def result(self):
        self.thread.join()
        if self.error is not None:
            raise self.error
        return self.value


def reference(env, team, channel, params, seed: int, episodes: int, greedy: bool) -> dict:
    """The same episodes played in simulation (``rollout`` with the batch key of ``sparsecomm
    eval``) over ``channel`` (``ChannelConfig``): per-episode success, length, payload and
    wire bits, datagrams (speaking links) and the frame bits they carry."""
    import jax

    from sparsecomm.deploy.core import batch_key
    from sparsecomm.rollout import rollout

    traj = jax.jit(lambda p, k: rollout(team, env, channel, p, k, episodes, greedy=greedy))(
        params, batch_key(seed)
    )
    valid = np.asarray(traj.valid)
    return {
        "success": np.asarray(traj.success).any(0),
        "length": valid.sum(0),
        "payload_bits": (np.asarray(traj.payload_bits) * valid).sum(0),
        "sim_wire_bits": (np.asarray(traj.wire_bits) * valid).sum(0),
        "datagrams": (np.asarray(traj.speaking) * valid).sum(0),
        "datagram_bits": (np.asarray(traj.datagram_bits) * valid).sum(0),
    }


def compare(episodes: list[dict], ref: dict) -> dict:
    """The simulation's figures of the same episodes, and how many episodes are identical
    (success, length, payload bits, wire bits, datagrams and the bits they carry all
    equal)."""
    steps = ref["length"].sum()
    same = [
        bool(e["success"]) == bool(ref["success"][b])
        and e["length"] == int(ref["length"][b])
        and e["payload_bits"] == round(float(ref["payload_bits"][b]))
        and e["sim_wire_bits"] == round(float(ref["sim_wire_bits"][b]))
        and e.get("datagrams") == round(float(ref["datagrams"][b]))
        and _carried(e) == round(float(ref["datagram_bits"][b]))
        for b, e in enumerate(episodes)
    ]
    return {
        "success_rate": float(ref["success"].mean()),
        "episode_length": float(ref["length"].mean()),
        "bits_per_step": float(ref["payload_bits"].sum() / steps),
        "wire_bits_per_step": float(ref["sim_wire_bits"].sum() / steps),
        "datagrams_per_step": float(ref["datagrams"].sum() / steps),
        "datagram_bits_per_step": float(ref["datagram_bits"].sum() / steps),
        "identical_episodes": int(sum(same)),
        "different_episodes": [b for b, s in enumerate(same) if not s],
    }


def _carried(episode: dict) -> int:
    """The frame bits an episode's MSG datagrams carried (their bytes less their headers)."""
    datagrams = episode.get("datagrams", 0)
    return 8 * (episode.get("datagram_bytes", 0) - wire.HEADER_BYTES * datagrams)


def deploy(args) -> dict:
    """Run ``sparsecomm deploy`` (:class:`sparsecomm.deploy.args.Deploy`); writes
    ``<out>/deploy.json``. On Ctrl-C or SIGTERM every process is stopped and it exits with
    status 130."""
    try:
        return _deploy(args)
    except KeyboardInterrupt:
        print("deploy: interrupted; every process stopped", file=sys.stderr)
        raise SystemExit(130) from None


def _deploy(args) -> dict:
    """:func:`deploy` without its Ctrl-C handling: every run of ``Deploy.index`` exported,
    played and printed, then the report, per run and per (lambda, budget) group, written."""
    import jax

    from sparsecomm import runfolder
    from sparsecomm.channel import NoiseConfig
    from sparsecomm.deploy.core import with_channel

    source, out, config, env, team_net, runs, actor = _load_source(args)
    k = config.env.num_agents
    faults, deadlines = args.faults(), args.deadlines()
    results = []
    for r in args.index:
        seed = config.seed + runfolder.EVAL_SEED_OFFSET + r
        note = f"deployed from {source}, index {r}"
        team = runfolder.write_team(out / f"team_{r}", config, runs, actor, r, note)
        print(f"deploy: run {r} ({k} agent processes + world), {args.episodes} episodes")
        simulated = None
        if args.reference:  # compiled and played in a thread while the processes start up
            noise = NoiseConfig(erasure=args.loss, on_drop=args.on_drop)
            params = jax.tree.map(lambda x, r=r: x[r], actor)
            channel = with_channel(config, noise=noise).channel
            simulated = Background(
                reference, env, team_net, channel, params, seed, args.episodes, args.greedy
            )
        played = _play_run(args, team, out / f"run_{r}", seed, k, faults, deadlines, env, simulated)
        row = _run_row(r, runs[r], seed, played, simulated)
        results.append(row)
        _print_row(row)
    by_group = _by_group(results, runs, args.index)
    report = {
        "episodes_per_run": args.episodes,
        "greedy": args.greedy,
        "faults": dataclasses.asdict(faults),
        "kills_per_episode": args.kills_per_episode,
        "on_drop": args.on_drop,
        "deadlines": dataclasses.asdict(deadlines),
        "header_bytes": wire.HEADER_BYTES,
        "udp_ip_bytes": wire.UDP_IP_BYTES,
        "runs": results,
        "by_group": by_group,
    }
    from sparsecomm.jsonfile import write_json

    write_json(out / "deploy.json", report)
    print(f"-> {out / 'deploy.json'}")
    return report


def _load_source(args):
    """The run folder or exported team ``Deploy.run`` names (default: the pretrained team),
    the output folder (``Deploy.out``, default ``<source>/deploy``) and what
    ``runfolder.load_actors`` reads of it; ``RunError`` when it is neither, when an index of
    ``Deploy.index`` is not one of its runs, or when its channel cannot be deployed."""
    from sparsecomm import runfolder
    from sparsecomm.deploy.core import check_deployable
    from sparsecomm.errors import CheckpointError

    source = runfolder.PRETRAINED if args.run is None else Path(args.run)
    out = args.out or (Path("runs/pretrained") if args.run is None else source) / "deploy"
    problem = runfolder.output_problem(out, folder=True)
    if problem:  # a given --out was checked while parsing
        raise RunError(f"Deploy.out (default: {out}) {problem}")
    try:
        runs = runfolder.runs_of(source)
    except (OSError, KeyError, TypeError, ValueError, CheckpointError) as e:
        raise RunError(f"Deploy.run must be a run folder or an exported team: {e}") from None
    for r in args.index:
        if not 0 <= r < len(runs):
            raise RunError(
                f"Deploy.index must be in [0, {len(runs) - 1}] (the runs of {source}), got {r}"
            )
    config, env, team_net, runs, actor = runfolder.load_actors(source)
    try:
        check_deployable(config)
    except ValueError as e:
        raise RunError(str(e)) from None
    return source, out, config, env, team_net, runs, actor


def _play_run(args, team, out, seed, k, faults, deadlines, env, simulated) -> dict:
    """:func:`play` of one exported run with ``Deploy``'s settings (``args``). On any exception
    the simulation playing beside it (``simulated``, or None) is let finish first: an
    interpreter that exits while XLA runs in another thread dies of SIGABRT, and the exit
    status must be the error's."""
    try:
        return play(
            team,
            out,
            seed,
            args.episodes,
            k,
            host=args.host,
            faults=faults,
            deadlines=deadlines,
            on_drop=args.on_drop,
            greedy=args.greedy,
            kills_per_episode=args.kills_per_episode,
            kill_window=args.kill_window,
            kill_seed=args.fault_seed,
            peer=_peer(args, env),
        )
    except BaseException:
        if simulated is not None:
            simulated.thread.join()
        raise


def _run_row(r: int, run, seed: int, played: dict, simulated) -> dict:
    """The report's row of run ``r`` (``run``: its entry of the run folder): eval's metrics
    over the episodes ``played`` with their 95% CIs, kills, restarts and wall-clock seconds,
    the forged datagrams of a hostile peer, and beside the simulation of the same episodes
    (:func:`compare`; ``simulated``: its :class:`Background`, or None)."""
    means, cis = summarize(played["episodes"])
    row = {
        "index": r,
        **run._asdict(),
        "seed_key": seed,
        "episodes": len(played["episodes"]),
        **means,
        "ci": cis,
        "kills": len(played["kills"]),
        "restarts": len(played["restarts"]),
        "wall_clock_s": played["wall_s"],
    }
    if played["peer"] is not None:
        row.update(played["peer"])  # forgeries_sent, replays
    if simulated is not None:
        row["simulation"] = compare(played["episodes"], simulated.result())
    return row


def _by_group(results: list[dict], runs, index) -> dict:
    """Each (lambda, budget) group's mean and 95% bootstrap CI over its deployed runs (the
    ``results`` rows), of eval's CI metrics and the network's, in the order of ``index``."""
    by_group = {}
    for group in dict.fromkeys(runs[r].group for r in index):
        rows = [row for row in results if runs[row["index"]].group == group]
        by_group[group] = {
            name: dict(
                zip(
                    ("mean", "ci_low", "ci_high"),
                    bootstrap_ci([row[name] for row in rows]),
                    strict=True,
                )
            )
            for name in (
                *CI_METRICS,
                "frame_bits_per_step",
                "datagram_bits_per_step",
                "datagrams_per_step",
                "missing_messages_per_step",
            )
        }
    return by_group


class _Peers:
    """Several hostile peers as one (``play``'s ``peer``): ``go`` and ``stop`` each;
    ``stop()`` returns ``{name: what it did}``."""

    def __init__(self, peers: dict):
        self.peers = peers

    def go(self) -> None:
        for peer in self.peers.values():
            peer.go()

    def stop(self) -> dict:
        return {name: peer.stop() for name, peer in self.peers.items()}


def _peer(args, env):
    """The hostile peers of ``Deploy.forgeries_per_second`` (``forgeries_sent``) and
    ``Deploy.replay`` (``replays``), as one; ``None``: none."""
    if not (args.forgeries_per_second > 0 or args.replay):
        return None

    def start(targets):
        peers = {}
        try:
            if args.replay:  # first: it captures the team's start-up hellos too
                from sparsecomm.deploy.replay import Replay

                peers["replays"] = Replay(targets, seed=args.fault_seed)
            if args.forgeries_per_second > 0:
                from sparsecomm.deploy.hostile import Flood

                peers["forgeries_sent"] = Flood(
                    targets,
                    num_agents=env.num_agents,
                    episodes=args.episodes,
                    steps=env.max_steps,
                    obs_dim=env.obs_dim,
                    rate=args.forgeries_per_second,
                    seed=args.fault_seed,
                )
        except BaseException:
            _Peers(peers).stop()
            raise
        return _Peers(peers)

    return start


def _print_row(row: dict) -> None:
    ci = row["ci"]
    line = (
        f"  run {row['index']}: success {row['success_rate']:.3f} "
        f"[{ci['success_rate'][0]:.3f}, {ci['success_rate'][1]:.3f}], "
        f"length {row['episode_length']:.1f}, bits/step {row['bits_per_step']:.1f} payload, "
        f"{row['frame_bits_per_step']:.1f} frame, {row['network_bits_per_step']:.1f} network "
        f"({row['network_datagrams_per_step']:.2f} datagrams), "
        f"{row['missing_messages_per_step']:.3f} lost; "
        f"{row['restarts']} restarts"
    )
    if "forgeries_sent" in row:
        line += (
            f"\n    forged datagrams sent {sum(row['forgeries_sent'].values())}, dropped by the "
            f"agents {row['garbage_dropped']} and the world {row['world_dropped']}"
        )
    if "replays" in row:
        line += (
            f"\n    replayed datagrams sent {sum(row['replays']['sent'].values())}; dropped as "
            f"duplicates {row['duplicates_dropped']} + {row['world_duplicates_dropped']} "
            f"(world), stale {row['stale_dropped']}, for another process "
            f"{row['foreign_dropped']}, misaddressed {row['garbage_dropped']} + "
            f"{row['world_dropped']} (world); hellos ignored {row['hellos_ignored']}"
        )
    if "simulation" in row:
        sim = row["simulation"]
        line += (
            f"\n    simulation of the same episodes: success {sim['success_rate']:.3f}, length "
            f"{sim['episode_length']:.1f}, bits/step {sim['bits_per_step']:.1f}; identical "
            f"episodes {sim['identical_episodes']}/{row['episodes']}"
        )
    print(line)
