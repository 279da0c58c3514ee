"""Decentralised execution (issue 19): the datagram format, the fault layer, the config checks,
and real deployments: a world process and one process per agent over UDP on loopback."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from sparsecomm import channel
from sparsecomm.configs import RLConfig, to_dict
from sparsecomm.deploy import core, wire
from sparsecomm.deploy.args import Deploy
from sparsecomm.deploy.faults import Deadlines, Faults, inject
from sparsecomm.deploy.launcher import deploy, kill_plan
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.errors import RunError
from sparsecomm.experiment import Eval, evaluate
from sparsecomm.jsonfile import write_json
from sparsecomm.learner import make_team
from sparsecomm.runfolder import PRETRAINED
from sparsecomm.sweep import Run

# -- the datagram ---------------------------------------------------------------------------


def test_datagram_round_trip_and_header_size():
    packet = channel.encode(np.array([0, 3, 0, 15, 1, 0, 0, 0, 0, 2]), "paper")
    data = wire.pack(wire.MSG, 2, 0, 123456, 4095, packet)
    assert len(data) == wire.HEADER_BYTES + len(packet) and wire.HEADER_BYTES == 13
    dg = wire.parse(data)
    assert dg == wire.Datagram(wire.MSG, 2, 0, 123456, 4095, packet)
    silence = wire.parse(wire.pack(wire.MSG, 0, 1, 7, 3))  # silence: an empty payload
    assert silence.payload == b"" and silence.kind == wire.MSG
    with pytest.raises(ValueError, match="step"):
        wire.pack(wire.MSG, 0, 1, 0, 70000)
    with pytest.raises(ValueError, match="sender"):
        wire.pack(wire.MSG, 256, 1, 0, 0)


def test_parse_never_raises_and_refuses_garbage():
    rng = np.random.default_rng(0)
    good = wire.pack(wire.MSG, 1, 2, 5, 9, b"\x80\x12\x34\x56\x78\x9a")
    accepted = 0
    for n in range(3000):
        if n % 2:
            data = rng.bytes(int(rng.integers(0, 40)))
        else:  # the good datagram with 1-3 bits flipped: the CRC-16 refuses it
            bits = np.unpackbits(np.frombuffer(good, np.uint8))
            bits[rng.choice(bits.size, int(rng.integers(1, 4)), replace=False)] ^= 1
            data = np.packbits(bits).tobytes()
        accepted += wire.parse(data) is not None
    assert accepted == 0
    assert wire.parse(None) is None and wire.parse(b"SC") is None


def test_decoders_never_crash_on_garbage_payloads():
    """A datagram with a good header and a garbage payload: the channel's decoder refuses it
    with PacketError (a ValueError), whatever the bytes."""
    rng = np.random.default_rng(1)
    for cfg in (
        channel.ChannelConfig(),
        channel.ChannelConfig(code="fixed"),
        channel.ChannelConfig(mode="continuous"),
        channel.ChannelConfig(ecc="hamming74"),
    ):
        for _ in range(300):
            payload = rng.bytes(int(rng.integers(1, 30)))
            try:
                channel.decode_link(cfg, payload, None)
            except channel.PacketError:
                pass


def test_addresses():
    assert wire.parse_address("10.0.0.2:9001") == ("10.0.0.2", 9001)
    for bad in ("10.0.0.2", ":9", "host:99999", "host:x"):
        with pytest.raises(ValueError, match="host:port"):
            wire.parse_address(bad)


# -- faults and configs ---------------------------------------------------------------------


def test_faults_are_seeded_and_do_what_they_say():
    dg = wire.pack(wire.MSG, 0, 1, 3, 4, b"\x01\x02")
    assert inject(Faults(), dg, 3, 4, 0, 1) == [(0.0, dg)]
    assert inject(Faults(loss=1.0), dg, 3, 4, 0, 1) == []
    assert [d for _, d in inject(Faults(duplicate=1.0), dg, 3, 4, 0, 1)] == [dg, dg]
    held = inject(Faults(reorder=1.0, reorder_delay=0.05), dg, 3, 4, 0, 1)
    assert len(held) == 1 and 0 <= held[0][0] <= 0.05
    junk = inject(Faults(garbage=1.0), dg, 3, 4, 0, 1)
    assert len(junk) == 2 and wire.parse(junk[1][1]) is None
    faults = Faults(loss=0.2, duplicate=0.1, reorder=0.1, garbage=0.01, seed=5)
    fates = [inject(faults, dg, b, t, 0, 1) for b in range(20) for t in range(50)]
    assert fates == [inject(faults, dg, b, t, 0, 1) for b in range(20) for t in range(50)]
    lost = np.mean([all(d != dg for _, d in f) for f in fates])
    assert 0.15 < lost < 0.25
    plan = kill_plan(0, 10, 3, 1, 8)
    assert plan == kill_plan(0, 10, 3, 1, 8) and all(1 <= p[0][0] <= 8 for p in plan.values())


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"loss": -0.1}, "Deploy.loss"),
        ({"garbage": 1.5}, "Deploy.garbage"),
        ({"duplicate": float("nan")}, "Deploy.duplicate"),
        ({"episodes": 0}, "Deploy.episodes"),
        ({"index": (-1,)}, "Deploy.index"),
        ({"kills_per_episode": -1}, "Deploy.kills_per_episode"),
        ({"on_drop": "zero"}, "Deploy.on_drop"),
        ({"message_deadline": 0.0}, "Deploy.message_deadline"),
        ({"action_deadline": 0.1}, "Deploy.action_deadline"),
        ({"run": Path("/nonexistent/run")}, "Deploy.run"),
    ],
)
def test_deploy_refuses_bad_input(changes, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        Deploy(**changes)


def test_deadlines_and_faults_checks():
    with pytest.raises(ValueError, match=r"Faults\.reorder_delay"):
        Faults(reorder_delay=-1.0)
    with pytest.raises(ValueError, match=r"Deadlines\.idle"):
        Deadlines(idle=1.0)


@pytest.mark.slow
def test_dither_is_regenerated_from_the_shared_key():
    """What each side draws alone equals what the rollout draws for the whole batch."""
    cfg, k, steps = channel.ChannelConfig(), 3, 5
    keys = jax.random.split(jax.random.key(4), 2)
    batch = jax.jit(lambda keys: channel.link_dither(cfg, keys, steps, k))(keys)
    batch = np.asarray(batch)  # (T, B, K, K-1, C)
    for i in range(k):
        for t in range(steps):
            mine = channel.dither_links(keys[1], t, i, channel.others(k)[i], cfg.num_elements)
            np.testing.assert_array_equal(np.asarray(mine), batch[t, 1, i])


def test_a_missing_packet_is_the_null_message_or_the_last_one():
    """As the simulator: a link not heard by the deadline is the all-null message rebuilt with
    that step's dither (``-u / levels``), or with on_drop last the link's last message."""
    cfg, k = channel.ChannelConfig(), 3
    key = jax.random.key(2)
    symbols = np.array([[3] * 10, [15] * 10], np.int32)
    last = np.full((2, 10), 0.25, np.float32)
    ok = np.array([True, False])
    msgs, kept = core.receive(cfg, k, "null")(key, 4, 1, symbols, ok, last)
    assert msgs.shape == (20,)
    heard = np.asarray(msgs).reshape(2, 10)
    u = [channel.dither(channel.dither_key(key, 4, s, 1), (10,)) for s in (0, 2)]
    np.testing.assert_allclose(heard[0], (3 - u[0]) / 15, rtol=1e-6)
    np.testing.assert_allclose(heard[1], -u[1] / 15, rtol=1e-6)  # the null message
    np.testing.assert_array_equal(kept, np.stack([heard[0], last[1]]))  # the last good ones
    msgs, kept = core.receive(cfg, k, "last")(key, 4, 1, symbols, ok, last)
    heard = np.asarray(msgs).reshape(2, 10)
    np.testing.assert_array_equal(heard[1], last[1])
    np.testing.assert_array_equal(kept, heard)


# -- real deployments -----------------------------------------------------------------------


def _team(
    folder: Path, num_agents: int = 3, max_steps: int = 10, radius: float = 0.45, channel_cfg=None
) -> Path:
    """An exported team of untrained actors: enough to test that deploy plays eval's episodes
    (their messages are busy, the goals close enough that some episodes succeed)."""
    env = NavConfig(
        num_agents=num_agents,
        max_steps=max_steps,
        success_radius=radius,
        arena_half_width=0.5,
        position_limit=0.75,
    )
    config = RLConfig(env=env, seed=11)
    if channel_cfg is not None:
        config = dataclasses.replace(config, channel=channel_cfg)
    _, team = make_team(config)
    shapes = jax.eval_shape(team.init, jax.random.key(0))["actor"]  # traced, not compiled
    rng = np.random.default_rng(3)
    actor = jax.tree.map(lambda s: rng.normal(0, 0.4, s.shape).astype(np.float32), shapes)
    folder.mkdir(parents=True)
    meta = {"kind": "train", "config": to_dict(config), "run": Run(0, 0.0, None)._asdict()}
    write_json(folder / "team.json", meta)
    (folder / "actor.msgpack").write_bytes(serialization.to_bytes(actor))
    return folder


def test_three_agent_processes_play_evals_episodes(tmp_path):
    """No faults: 3 agent processes and a world play the episodes `sparsecomm eval` plays for
    the same run (the simulation of the same draws), episode for episode: same success,
    length and bits."""
    team = _team(tmp_path / "team")
    episodes = 6
    report = deploy(Deploy(run=team, episodes=episodes, out=tmp_path / "deploy"))
    (row,) = report["runs"]
    sim = row["simulation"]
    assert row["episodes"] == episodes and row["restarts"] == 0
    assert sim["identical_episodes"] == episodes, sim["different_episodes"]
    for name in ("success_rate", "episode_length", "bits_per_step", "wire_bits_per_step"):
        assert row[name] == pytest.approx(sim[name], rel=1e-12), name
    # what crossed the wire: exactly the library's packets, plus a 13-byte header each
    assert row["packet_bits_per_step"] == pytest.approx(row["wire_bits_per_step"])
    header = row["datagram_bits_per_step"] - row["packet_bits_per_step"]
    assert header == pytest.approx(row["header_bits_per_step"]) == 6 * 8 * 13
    assert row["missing_messages_per_step"] == 0 and row["missing_actions_per_step"] == 0
    low, high = row["ci"]["bits_per_step"]
    assert low <= row["bits_per_step"] <= high
    saved = json.loads((tmp_path / "deploy" / "deploy.json").read_text())
    assert saved["runs"][0]["bits_per_step"] == row["bits_per_step"]
    links = (tmp_path / "deploy" / "run_0" / "links.csv").read_text().splitlines()
    assert len(links) - 1 == 6 * round(row["episode_length"] * episodes)  # per link and step


@pytest.mark.slow
def test_deploy_matches_sparsecomm_eval(tmp_path):
    """The figures of ``sparsecomm eval`` itself (runs vmapped, as the command does) for the
    same run and episode count: equal to deploy's."""
    team = _team(tmp_path / "team")
    (row,) = deploy(Deploy(run=team, episodes=8, out=tmp_path / "deploy"))["runs"]
    ev = evaluate(Eval(run=team, episodes=8, out=tmp_path / "eval.json"))["runs"][0]
    assert row["simulation"]["identical_episodes"] == 8
    assert row["success_rate"] == pytest.approx(ev["success_rate"], abs=1e-6)
    assert row["episode_length"] == pytest.approx(ev["episode_length"], rel=1e-6)
    assert row["bits_per_step"] == pytest.approx(ev["bits_per_step"], rel=1e-5)
    assert row["wire_bits_per_step"] == pytest.approx(ev["wire_bits_per_step"], rel=1e-5)


@pytest.mark.slow
def test_a_team_with_link_gates_deployed_plays_evals_episodes(tmp_path):
    """Gated links (``ChannelConfig.link_gate``): a closed link's symbols are all null on the
    wire and in the simulation alike, so deploy still plays eval's episodes exactly."""
    team = _team(tmp_path / "team", channel_cfg=channel.ChannelConfig(link_gate=True))
    (row,) = deploy(Deploy(run=team, episodes=4, out=tmp_path / "deploy"))["runs"]
    sim = row["simulation"]
    assert sim["identical_episodes"] == 4, sim["different_episodes"]
    assert row["wire_bits_per_step"] == pytest.approx(sim["wire_bits_per_step"], rel=1e-12)
    assert 0 < row["packet_bits_per_step"] < row["datagram_bits_per_step"]


@pytest.mark.slow
def test_faults_and_restarts_are_survived(tmp_path):
    """20% loss, 1% garbage, duplicates, reordering and one agent killed per episode: every
    episode finishes, every killed agent is restarted and rejoins."""
    team = _team(tmp_path / "team", num_agents=2, max_steps=12, radius=0.05)
    args = Deploy(
        run=team,
        episodes=3,
        out=tmp_path / "deploy",
        loss=0.2,
        garbage=0.01,
        duplicate=0.05,
        reorder=0.05,
        kills_per_episode=1,
        kill_window=3,
        action_deadline=1.0,
    )
    (row,) = deploy(args)["runs"]
    assert row["episodes"] == 3
    assert row["kills"] >= 1 and row["restarts"] >= row["kills"]
    assert row["rejoins"] >= 1 and row["missing_actions_per_step"] > 0
    assert row["missing_messages_per_step"] > 0


@pytest.mark.slow
def test_ctrl_c_leaves_no_orphan(tmp_path):
    team = _team(tmp_path / "team", num_agents=2, max_steps=64)
    out = tmp_path / "deploy"
    cmd = [sys.executable, "-m", "sparsecomm.cli", "deploy", "--run", str(team)]
    cmd += ["--episodes", "500", "--out", str(out), "--no-reference"]
    launcher = subprocess.Popen(cmd)
    try:
        until = time.monotonic() + 120
        while time.monotonic() < until and not (out / "run_0" / "episodes.jsonl").exists():
            time.sleep(0.5)
        children = _children(launcher.pid)
        assert len(children) == 3  # the world and two agents
        launcher.send_signal(signal.SIGINT)
        assert launcher.wait(30) != 0
    finally:
        if launcher.poll() is None:
            launcher.kill()
    time.sleep(0.5)
    assert not [pid for pid in children if _alive(pid)]


def _children(pid: int) -> list[int]:
    text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    return [int(x) for x in text.split()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_deploy_refuses_an_index_out_of_range(tmp_path):
    with pytest.raises(RunError, match=r"Deploy\.index must be in \[0, 0\]"):
        deploy(Deploy(run=PRETRAINED, index=(1,), out=tmp_path / "deploy"))
    with pytest.raises(RunError, match=r"Deploy\.run must be a run folder"):
        deploy(Deploy(run=tmp_path, out=tmp_path / "deploy"))
