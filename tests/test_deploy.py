"""Decentralised execution: the datagram format, the fault layer, the config checks,
and real deployments: a world process and one process per agent over UDP on loopback."""

import dataclasses
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from sparsecomm import channel
from sparsecomm.configs import AgentConfig, RLConfig, to_dict
from sparsecomm.deploy import core, wire
from sparsecomm.deploy.args import Deploy
from sparsecomm.deploy.faults import Deadlines, Faults, inject
from sparsecomm.deploy.launcher import deploy, kill_plan
from sparsecomm.deploy.report import read_episodes
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.errors import RunError
from sparsecomm.experiment import Eval, evaluate
from sparsecomm.jsonfile import write_json
from sparsecomm.learner import make_team
from sparsecomm.runfolder import PRETRAINED
from sparsecomm.sweep import Run

# -- the datagram ---------------------------------------------------------------------------

AUTH = wire.Auth(bytes(range(32)))
"""A team secret for the tests that make datagrams by hand."""
HEAD = wire.HEADER_BYTES
"""19: a datagram's header and MAC."""


def test_datagram_round_trip_and_header_size():
    packet = channel.encode(np.array([0, 3, 0, 15, 1, 0, 0, 0, 0, 2]), "paper")
    data = AUTH.pack(wire.MSG, 2, 0, 123456, 4095, packet)
    assert len(data) == wire.HEADER_BYTES + len(packet) and wire.HEADER_BYTES == 19
    dg = AUTH.parse(data)
    assert dg == wire.Datagram(wire.MSG, 2, 0, 123456, 4095, packet)
    empty = AUTH.parse(AUTH.pack(wire.MSG, 0, 1, 7, 3))  # an open gate with null symbols
    assert empty.payload == b"" and empty.kind == wire.MSG
    with pytest.raises(ValueError, match="step"):
        AUTH.pack(wire.MSG, 0, 1, 0, 70000)
    with pytest.raises(ValueError, match="sender"):
        AUTH.pack(wire.MSG, 256, 1, 0, 0)
    with pytest.raises(ValueError, match="at least 16 bytes"):
        wire.Auth(b"short")


def test_parse_never_raises_and_refuses_garbage_and_forgeries():
    """Random bytes, a sealed datagram with 1-3 bits flipped (in its fields, MAC or payload),
    and datagrams sealed under another secret (any kind, any fields): none is accepted."""
    rng = np.random.default_rng(0)
    good = AUTH.pack(wire.MSG, 1, 2, 5, 9, b"\x80\x12\x34\x56\x78\x9a")
    stranger = wire.Auth(bytes(range(1, 33)))
    accepted = 0
    for n in range(3000):
        if n % 3 == 0:
            data = rng.bytes(int(rng.integers(0, 40)))
        elif n % 3 == 1:
            bits = np.unpackbits(np.frombuffer(good, np.uint8))
            bits[rng.choice(bits.size, int(rng.integers(1, 4)), replace=False)] ^= 1
            data = np.packbits(bits).tobytes()
        else:
            kind = int(rng.choice(list(wire.KINDS)))
            fields = rng.integers(0, 256, 2).tolist() + rng.integers(0, 1000, 2).tolist()
            data = stranger.pack(kind, *fields, rng.bytes(int(rng.integers(0, 30))))
        accepted += AUTH.parse(data) is not None
    assert accepted == 0
    assert AUTH.parse(None) is None and AUTH.parse(b"SC") is None
    old = b"SC\x11" + bytes(10) + b"\x01"  # version 1 (a CRC-16 where the MAC is)
    assert AUTH.parse(old + bytes(wire.HEADER_BYTES - len(old))) is None
    # version 2 (hellos with the process id, answered every time), sealed with the secret
    head = wire.FIELDS.pack(wire.MAGIC, 2 << 4 | wire.HELLO, 0, wire.WORLD, 0, 0)
    payload = (1234).to_bytes(4, "big")
    assert AUTH.parse(head + AUTH._mac(head, payload) + payload) is None


def test_reports_and_hellos_have_a_fixed_layout_and_a_parser_that_never_raises():
    report = wire.Report(
        action=3,
        rejoined=True,
        sim_wire=120,
        frame=120,
        missing=1,
        dup=0,
        stale=2,
        foreign=5,
        bad=2**32 - 1,
        no_map=0,
        payload=(17, 0),
        spoke=(1, 0),
        datagram=(34, 0),
        sent=(68, 0),
        sent_n=(2, 0),
    )
    data = wire.pack_report(report)
    assert len(data) == wire.report_bytes(2) == 35 + 2 * 12
    assert wire.parse_report(data, 2) == report
    assert wire.parse_report(data, 1) is None and wire.parse_report(data + b"\0", 2) is None
    assert wire.parse_report(data[:-1], 2) is None and wire.parse_report(None, 2) is None
    flag = bytearray(data)
    flag[2] = 2  # rejoined is 0 or 1
    assert wire.parse_report(bytes(flag), 2) is None
    rng = np.random.default_rng(2)
    for _ in range(2000):  # whatever the bytes: a report or None, never an exception
        junk = rng.bytes(int(rng.choice([wire.report_bytes(2), int(rng.integers(0, 80))])))
        got = wire.parse_report(junk, 2)
        assert got is None or (len(got.spoke) == 2 and set(got.spoke) <= {0, 1})
        assert wire.parse_hello(junk) in (None, junk)
        assert wire.parse_hello(junk) is None or len(junk) == wire.NONCE_BYTES
    for bad in (b"null", b"[]", b'{"a": 1e999}'):  # the JSON payloads that crashed the world
        assert wire.parse_report(bad, 2) is None


def test_secret_files(tmp_path):
    path = wire.write_secret(tmp_path / "team.key")
    assert os.stat(path).st_mode & 0o777 == 0o600
    secret = wire.read_secret(path)
    assert len(secret) == wire.SECRET_BYTES and secret != wire.read_secret(
        wire.write_secret(tmp_path / "other.key")
    )
    with pytest.raises(FileExistsError):
        wire.write_secret(path)
    for name, text, mode, match in (
        ("open.key", "ab" * 32, 0o644, "chmod 600"),
        ("short.key", "ab" * 8, 0o600, "at least 32 hex digits"),
        ("text.key", "not hex at all!", 0o600, "hex digits only"),
    ):
        bad = tmp_path / name
        bad.write_text(text)
        bad.chmod(mode)
        with pytest.raises(ValueError, match=f"AgentArgs.secret_file .*{match}"):
            wire.read_secret(bad, "AgentArgs.secret_file")
    with pytest.raises(ValueError, match="not a regular file"):
        wire.read_secret(tmp_path, "x")
    with pytest.raises(ValueError, match="cannot be read"):
        wire.read_secret(tmp_path / "missing.key", "x")


@pytest.mark.parametrize(
    "cfg",
    [
        channel.ChannelConfig(),
        channel.ChannelConfig(code="fixed"),
        channel.ChannelConfig(mode="continuous"),
        channel.ChannelConfig(ecc="hamming74"),
        channel.ChannelConfig(link_gate=True, on_silence="hold", check_bits=8),
        channel.ChannelConfig(check_bits=0),
    ],
)
def test_frame_decoder_never_crashes_on_garbage_payloads(cfg):
    """A datagram with a good header and a garbage payload: the channel's frame decoder refuses
    it with PacketError (a ValueError) or, past a short check by chance, returns symbols in
    range; it raises nothing else, whatever the bytes, and a real frame with bits flipped is
    refused at least as often as its check promises."""
    rng = np.random.default_rng(1)
    for links in (1, 2, 4):
        for _ in range(300):
            payload = rng.bytes(int(rng.integers(1, 40)))
            try:
                m = channel.decode_sender(cfg, payload, links)
            except channel.PacketError:
                continue
            assert m.shape == (links, cfg.num_elements)
            if cfg.sends_symbols:
                assert 0 <= m.min() and m.max() <= cfg.levels
    symbols = rng.integers(0, cfg.levels + 1, (2, cfg.num_elements))
    signal = rng.random((2, cfg.signal_elements)).astype(np.float32)
    frame = channel.encode_sender(cfg, symbols, signal)
    np.testing.assert_array_equal(
        channel.decode_sender(cfg, frame, 2),
        signal[:, : cfg.num_elements] if cfg.sends_values else symbols,
    )
    passed = 0
    for _ in range(400):
        bits = np.unpackbits(np.frombuffer(frame, np.uint8))
        bits[rng.choice(bits.size, int(rng.integers(1, 4)), replace=False)] ^= 1
        try:
            channel.decode_sender(cfg, np.packbits(bits).tobytes(), 2)
            passed += 1
        except channel.PacketError:
            pass
    if cfg.ecc != "none":  # Hamming(7,4) corrects single flips: they pass, as they should
        return
    if cfg.check_bits == 32:
        assert passed == 0
    elif cfg.check_bits == 8:
        assert passed < 20  # about 1 in 256 corrupted frames passes an 8-bit check


def test_addresses():
    assert wire.parse_address("10.0.0.2:9001") == ("10.0.0.2", 9001)
    for bad in ("10.0.0.2", ":9", "host:99999", "host:x"):
        with pytest.raises(ValueError, match="host:port"):
            wire.parse_address(bad)


# -- faults and configs ---------------------------------------------------------------------


def test_faults_are_seeded_and_do_what_they_say():
    dg = AUTH.pack(wire.MSG, 0, 1, 3, 4, b"\x01\x02")
    assert inject(Faults(), dg, 3, 4, 0, 1) == [(0.0, dg)]
    assert inject(Faults(loss=1.0), dg, 3, 4, 0, 1) == []
    assert [d for _, d in inject(Faults(duplicate=1.0), dg, 3, 4, 0, 1)] == [dg, dg]
    held = inject(Faults(reorder=1.0, reorder_delay=0.05), dg, 3, 4, 0, 1)
    assert len(held) == 1 and 0 <= held[0][0] <= 0.05
    junk = inject(Faults(garbage=1.0), dg, 3, 4, 0, 1)
    assert len(junk) == 2 and AUTH.parse(junk[1][1]) is None
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


def test_deploy_refuses_a_channel_it_cannot_carry_and_takes_hold():
    base = RLConfig(env=NavConfig(num_agents=2), seed=0)
    for cfg, field in (
        (channel.ChannelConfig(mode="reinforced"), "mode 'reinforced'"),
        (channel.ChannelConfig(levels=3, num_elements=2, code="fixed"), None),
        (channel.ChannelConfig(on_silence="hold", link_gate=True, check_bits=16), None),
    ):
        config = dataclasses.replace(base, channel=cfg)
        if field is None:
            core.check_deployable(config)
            continue
        with pytest.raises(ValueError, match=r"ChannelConfig\.mode one of .*" + field):
            core.check_deployable(config)


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
    silent = np.array([False, False])
    msgs, kept = core.receive(cfg, k, "null")(key, 4, 1, symbols, ok, silent, last)
    assert msgs.shape == (20,)
    heard = np.asarray(msgs).reshape(2, 10)
    u = [channel.dither(channel.dither_key(key, 4, s, 1), (10,)) for s in (0, 2)]
    np.testing.assert_allclose(heard[0], (3 - u[0]) / 15, rtol=1e-6)
    np.testing.assert_allclose(heard[1], -u[1] / 15, rtol=1e-6)  # the null message
    np.testing.assert_array_equal(kept, np.stack([heard[0], last[1]]))  # the last good ones
    msgs, kept = core.receive(cfg, k, "last")(key, 4, 1, symbols, ok, silent, last)
    heard = np.asarray(msgs).reshape(2, 10)
    np.testing.assert_array_equal(heard[1], last[1])
    np.testing.assert_array_equal(kept, heard)


# -- silence, frames and the heard map ------------------------------------------------------


def test_heard_map_round_trip_and_never_raises():
    for n in (0, 1, 2, 7, 8, 9, 254):
        heard = np.random.default_rng(n).random(n) < 0.5
        data = wire.pack_map(heard)
        assert len(data) == wire.map_bytes(n) == -(-n // 8)
        np.testing.assert_array_equal(wire.parse_map(data, n), heard)
    assert wire.pack_map([True, False, False, True]) == bytes([0b1001])  # bit s: slot s
    assert wire.parse_map(bytes([0b100]), 2) is None  # a padding bit set: no map
    assert wire.parse_map(b"\x01\x00", 2) is None  # another length: no map
    obs = np.arange(8, dtype=np.float32)
    nonce = wire.new_nonce()
    data = wire.pack_obs(nonce, obs, [True, False])
    assert len(data) == wire.NONCE_BYTES + 4 * 8 + 1 and wire.obs_nonce(data) == nonce
    got, values, heard = wire.parse_obs(data, 8, 2)
    np.testing.assert_array_equal(values, obs)
    assert got == nonce and heard.tolist() == [True, False]
    _, values, heard = wire.parse_obs(wire.pack_obs(nonce, obs), 8, 2)  # no map: wait for all
    assert heard is None and values.size == 8
    assert wire.parse_obs(data[wire.NONCE_BYTES :], 8, 2) == (None, None, None)  # no nonce
    with pytest.raises(ValueError, match="nonce must have 8 bytes"):
        wire.pack_obs(b"pid1", obs)
    rng = np.random.default_rng(2)
    for _ in range(2000):
        data = rng.bytes(int(rng.integers(0, 60)))
        got, values, heard = wire.parse_obs(data, 8, int(rng.integers(0, 20)))
        assert values is None or (values.shape == (8,) and got == data[: wire.NONCE_BYTES])
        assert wire.obs_nonce(data) in (None, data[: wire.NONCE_BYTES])
        wire.parse_map(data, int(rng.integers(0, 40)))
    assert wire.parse_obs(None, 8, 2) == (None, None, None) and wire.parse_map(None, 2) is None
    assert wire.obs_nonce(None) is None


def test_the_world_maps_what_each_sender_reported():
    from sparsecomm.deploy.world import heard_maps

    # sender 0 spoke to 1 (slot 0) only, sender 1 to nobody, sender 2's report is missing
    maps = heard_maps({0: [1, 0], 1: [0, 0]}, 3)
    assert maps[0] == [False, True]  # from 1: silent; from 2: no report, so wait for it
    assert maps[1] == [True, True]  # from 0: spoke; from 2: no report
    assert maps[2] == [False, False]  # from 0 (slot 1): silent; from 1: silent
    assert heard_maps({0: "junk", 1: None}, 2) == [[True], [True]]  # a bad report: wait
    assert [core.frame_slot(s, 2) for s in (0, 1, 3)] == [1, 1, 2]
    assert [int(channel.others(4)[s][core.frame_slot(s, 2)]) for s in (0, 1, 3)] == [2, 2, 2]
    with pytest.raises(ValueError, match="recipient must differ"):
        core.frame_slot(1, 1)


def test_a_held_link_is_the_channels_rule():
    """Under ``on_silence = "hold"`` the deployed receiver is ``channel.receive``: a silent link
    delivers its last message with news 0, a link that spoke and arrived its message with news
    1, a lost one its last message with news 0; the inbox is the messages, then the news."""
    cfg, k, c = channel.ChannelConfig(on_silence="hold"), 4, 10
    key = jax.random.key(5)
    message = np.array([[3] * c, [0] * c, [7] * c], np.int32)
    last = np.stack([np.full(c, v, np.float32) for v in (0.1, 0.2, 0.3)])
    silent = np.array([False, True, False])
    ok = np.array([True, True, False])  # link 2 spoke, and its frame was lost
    msgs, kept = core.receive(cfg, k, "null")(key, 6, 2, message, ok, silent, last)
    assert msgs.shape == (3 * c + 3,) == (core.inbox_size(cfg, k),)
    u = channel.dither_links(key, 6, channel.others(k)[2], 2, c)
    want = channel.receive(cfg, message, u, ok=ok, last=last, silent=silent)
    np.testing.assert_array_equal(msgs[: 3 * c], np.asarray(want.z_hat).reshape(-1))
    np.testing.assert_array_equal(msgs[3 * c :], [1.0, 0.0, 0.0])  # news: arrived only
    np.testing.assert_array_equal(kept, want.last)
    heard = np.asarray(msgs[: 3 * c]).reshape(3, c)
    np.testing.assert_allclose(heard[0], (3 - np.asarray(u[0])) / 15, rtol=1e-6)
    np.testing.assert_array_equal(heard[1:], last[1:])  # held: silent and lost alike
    np.testing.assert_array_equal(kept[1:], last[1:])
    # a gated channel hands the receiver the gate, as the rollout does: the same messages
    gated = channel.ChannelConfig(on_silence="hold", link_gate=True)
    msgs_g, kept_g = core.receive(gated, k, "null")(key, 6, 2, message, ok, silent, last)
    np.testing.assert_array_equal(msgs_g, msgs)
    np.testing.assert_array_equal(kept_g, kept)


def test_an_open_gate_saying_nothing_is_silence():
    """An open gate whose symbols are all null has no frame (0 wire bits): it is silent on the
    wire and in the rollout alike (``Sent.speak`` 0), so it sends no datagram, and under
    ``hold`` its receiver holds the last message (news 0) exactly as the rollout's
    ``channel.receive(..., speak=sent.speak)`` does; a link that says something speaks."""
    k, c = 3, 10
    key = jax.random.key(9)
    z = np.zeros((1, k - 1, c + 1), np.float32)
    z[0, :, -1] = 1.0  # both gates open for sure
    z[0, 1, 0] = 1.0  # link 1 says something, link 0 nothing
    for on_silence in ("hold", "null"):
        cfg = channel.ChannelConfig(link_gate=True, on_silence=on_silence)
        u = channel.dither_links(key, 2, 1, channel.others(k)[1], c + 1)[None]
        sent = channel.transmit(cfg, jax.numpy.asarray(z), u)
        assert sent.wire_bits[0, 0] == 0 and sent.wire_bits[0, 1] > 0
        assert core.link_speaks(sent)[0].tolist() == [False, True]
        np.testing.assert_array_equal(sent.speak[0], [0.0, 1.0])
        frame = channel.encode_sender(cfg, np.asarray(sent.symbols[0]), z[0])
        assert 8 * len(frame) == float(sent.wire_bits.sum())
        np.testing.assert_array_equal(channel.decode_sender(cfg, frame, k - 1), sent.symbols[0])
    # at agent 2, whose senders are 0 and 1: sender 1's frame row 1 (link 1 -> 2) said
    # something, sender 0 was silent to it
    cfg = channel.ChannelConfig(link_gate=True, on_silence="hold")
    last = np.full((k - 1, c), 0.5, np.float32)
    message = np.zeros((k - 1, c), np.int32)
    message[1] = np.asarray(sent.symbols[0, 1])
    silent = np.array([True, False])
    ok = np.ones(k - 1, bool)
    msgs, kept = core.receive(cfg, k, "null")(key, 2, 2, message, ok, silent, last)
    ud = channel.dither_links(key, 2, channel.others(k)[2], 2, c)
    want = channel.receive(cfg, message, ud, last=last, speak=jax.numpy.asarray([0.0, 1.0]))
    np.testing.assert_array_equal(msgs[: 2 * c], np.asarray(want.z_hat).reshape(-1))
    np.testing.assert_array_equal(msgs[:c], last[0])  # held
    np.testing.assert_array_equal(msgs[2 * c :], [0.0, 1.0])  # held, news
    np.testing.assert_array_equal(kept, want.last)


@pytest.mark.parametrize("reads_sent, news_margin", [(False, None), (True, None), (False, 0.1)])
def test_core_replays_the_rollout_of_a_gated_holding_team(tmp_path, reads_sent, news_margin):
    """A deployment without sockets: every agent steps with ``core.agent_step``, sends its frame
    (``channel.encode_sender``; none when silent), every receiver takes its row of each frame
    (``channel.decode_sender``), treats a sender that did not speak to it as silence and
    rebuilds with ``core.receive``. Under gates and ``hold`` it plays the rollout's episodes:
    the same symbols and actions at every step, the frames' bits the library's count; with
    ``reads_sent`` each sender reads back what its links last delivered, which is what their
    recipients hold, and with ``news_margin`` a link with news opens its gate."""
    from sparsecomm.rollout import rollout

    cfg = channel.ChannelConfig(link_gate=True, on_silence="hold", news_margin=news_margin)
    agent = AgentConfig(reads_sent=reads_sent)
    loaded = core.read_team(_team(tmp_path / "team", channel_cfg=cfg, agent_cfg=agent))
    env, team, k, n = loaded.env, loaded.team, loaded.env.num_agents, 3
    params = jax.tree.map(jax.numpy.asarray, loaded.actor)
    key = core.batch_key(7)
    traj = jax.jit(lambda p, key: rollout(team, env, cfg, p, key, n, keep_symbols=True))(
        params, key
    )
    reset, env_step = core.world_fns(env)
    reset_keys, env_keys = core.world_draws(key, n, env.config.max_steps)
    chan, gumbel = core.agent_draws(key, n, env.config.max_steps, k, env.num_actions)
    step_fn, receive_fn = core.agent_step(team, cfg, False), core.receive(cfg, k, "null")
    others, c = channel.others(k), cfg.num_elements
    counts = {"silent": 0, "held": 0, "spoke": 0, "steps": 0}
    for b in range(n):
        obs, state = reset(reset_keys[b])
        carry = [np.zeros(team.cfg.gru, np.float32)] * k
        msgs = [np.zeros(core.inbox_size(cfg, k), np.float32)] * k
        last = [np.zeros((k - 1, c), np.float32)] * k
        prev = [np.zeros((k - 1, c), np.int32)] * k
        delivered = [np.zeros((k - 1, c), np.float32)] * k
        ever = np.zeros((k, k - 1), bool)  # a link that spoke before: silence is then held
        for t in range(env.config.max_steps):
            if bool(state.done):
                break
            counts["steps"] += 1
            outs = [
                step_fn(
                    params,
                    i,
                    carry[i],
                    obs[i],
                    msgs[i],
                    gumbel[t, b, i],
                    t,
                    chan[b],
                    prev[i],
                    delivered[i],
                )
                for i in range(k)
            ]
            frames = []
            for i, out in enumerate(outs):
                np.testing.assert_array_equal(out.symbols, traj.aside.symbols[t, b, i])
                assert int(out.action) == int(traj.actions[t, b, i]), (b, t, i)
                frame = channel.encode_sender(cfg, np.asarray(out.symbols), np.asarray(out.signal))
                assert 8 * len(frame) == round(float(out.wire))
                frames.append(frame if np.asarray(out.spoke).any() else None)
            assert sum(8 * len(f or b"") for f in frames) == round(float(traj.wire_bits[t, b]))
            for j in range(k):
                message = np.zeros((k - 1, c), np.int32)
                silent = np.zeros(k - 1, bool)
                for r, s in enumerate(others[j]):
                    slot = core.frame_slot(int(s), j)
                    if not outs[s].spoke[slot]:
                        silent[r] = True  # nothing reached j from s
                        counts["silent"] += 1
                        counts["held"] += bool(ever[s, slot])
                        continue
                    counts["spoke"] += 1
                    ever[s, slot] = True
                    message[r] = channel.decode_sender(cfg, frames[s], k - 1)[slot]
                ok = np.ones(k - 1, bool)
                msgs[j], last[j] = receive_fn(chan[b], t, j, message, ok, silent, last[j])
            for j in range(k):  # what j holds from s is what s says its link delivered (to
                # float32 rounding: the sender's z + (z_hat - z), the receiver's z_hat)
                for r, s in enumerate(others[j]):
                    said = outs[s].delivered[core.frame_slot(s, j)]
                    np.testing.assert_allclose(said, last[j][r], rtol=0, atol=1e-6)
            carry = [out.carry for out in outs]
            delivered = [out.delivered for out in outs]
            prev = [np.asarray(out.symbols) for out in outs]
            actions = jax.numpy.asarray([int(out.action) for out in outs])
            obs, state, *_ = env_step(env_keys[t, b], state, actions)
    assert counts["steps"] == int(np.asarray(traj.valid).sum())
    assert counts["held"] > 0 and counts["spoke"] > 0, counts  # silences held, messages heard


def _drain(sock, seen: list, forward=None, wait: float = 0.02) -> None:
    """Every datagram waiting on ``sock``: parsed into ``seen`` (with its size), and sent on
    to ``forward``."""
    sock.settimeout(wait)
    while True:
        try:
            data, _ = sock.recvfrom(wire.MAX_DATAGRAM)
        except (TimeoutError, BlockingIOError):
            return
        seen.append((AUTH.parse(data), len(data)))
        if forward is not None:
            sock.sendto(data, forward)


@pytest.mark.parametrize("loss", [0.0, 0.3])
def test_silent_links_put_no_datagram_on_the_network(tmp_path, loss):
    """Three agents in this process, their peers' addresses pointing at taps that count every
    datagram the network carries before passing it on. A link that did not speak puts no
    datagram on the network; a speaking link one (its sender's frame); a frame that the heard
    map promised and the fault layer dropped is a loss at its receiver, a silence is not; an
    observation without a map makes the receiver wait for every sender and count each one not
    heard as missing."""
    from sparsecomm.deploy.agent import Agent, AgentArgs
    from sparsecomm.deploy.world import heard_maps

    cfg = channel.ChannelConfig(link_gate=True, on_silence="hold")
    team = _team(tmp_path / "team", channel_cfg=cfg)
    k, steps, host = 3, 8, "127.0.0.1"
    world = wire.udp_socket((host, 0))
    taps = [wire.udp_socket((host, 0)) for _ in range(k)]
    ports = wire.free_ports(host, k)
    agents = []
    try:
        for i in range(k):
            args = AgentArgs(
                team=team,
                agent=i,
                peers=tuple(f"{host}:{tap.getsockname()[1]}" for tap in taps),
                world=f"{host}:{world.getsockname()[1]}",
                seed=3,
                episodes=1,
                secret_file=_secret(tmp_path),
                listen=f"{host}:{ports[i]}",
                faults=Faults(loss=loss, seed=4),
                deadlines=Deadlines(message=0.05),
            )
            agents.append(Agent(args))
        rng = np.random.default_rng(0)
        seen, reports = [], {}
        spoke = {i: [False] * (k - 1) for i in range(k)}
        for t in range(steps + 1):
            for j, tap in enumerate(taps):  # the frames of step t - 1, on to their recipients
                _drain(tap, seen, (host, ports[j]))
            maps = heard_maps(spoke, k)
            spoke = {}
            for i, agent in enumerate(agents):
                heard = None if t == steps else maps[i]  # the last step: no map
                obs = rng.normal(size=agent.obs_dim).astype(np.float32)
                payload = wire.pack_obs(agent.nonce, obs, heard)
                data = AUTH.pack(wire.OBS, wire.WORLD, i, 0, t, payload)
                assert agent._act(AUTH.parse(data)) is None
                world.settimeout(5.0)
                dg = AUTH.parse(world.recvfrom(wire.MAX_DATAGRAM)[0])
                assert (dg.kind, dg.sender, dg.step) == (wire.ACT, i, t)
                reports[i, t] = wire.parse_report(dg.payload, k - 1)._asdict()
                spoke[i] = reports[i, t]["spoke"]
    finally:
        for sock in (world, *taps, *(a.sock for a in agents)):
            sock.close()
    carried = {}
    for dg, size in seen:
        assert dg is not None and dg.kind == wire.MSG
        carried.setdefault((dg.sender, dg.recipient, dg.step), []).append(size)
    silent = speaking = lost = 0
    for (i, t), report in reports.items():
        for r, j in enumerate(channel.others(k)[i]):
            sizes = carried.get((i, int(j), t), [])
            if t == steps:
                continue  # sent after the last drain
            if not report["spoke"][r]:
                assert sizes == [], (i, j, t)  # silence: nothing on the network
                silent += 1
                continue
            speaking += 1
            assert report["sent_n"][r] == len(sizes) and report["sent"][r] == sum(sizes)
            assert sizes in ([], [HEAD + report["frame"] // 8])  # the frame, once, or lost
            lost += not sizes
    assert silent > 0 and speaking > 0
    assert (lost > 0) == (loss > 0)
    for (j, t), report in reports.items():  # the receivers' losses: promised, not arrived
        if t == 0:
            continue
        senders = channel.others(k)[j]
        promised = [reports[s, t - 1]["spoke"][core.frame_slot(int(s), j)] for s in senders]
        arrived = [bool(carried.get((int(s), j, t - 1))) for s in senders]
        if t < steps:
            want = sum(p and not a for p, a in zip(promised, arrived, strict=True))
            assert report["missing"] == want and report["no_map"] == 0, (j, t)
        else:  # no map: every sender not heard is missing, silent ones included
            assert report["no_map"] == 1
            assert report["missing"] == sum(not a for a in arrived), (j, t)


# -- real deployments -----------------------------------------------------------------------


def _secret(folder: Path) -> Path:
    """A secret file holding :data:`AUTH`'s secret."""
    path = folder / "team.key"
    if not path.exists():
        path.write_text(bytes(range(32)).hex())
        path.chmod(0o600)
    return path


def _team(
    folder: Path,
    num_agents: int = 3,
    max_steps: int = 10,
    radius: float = 0.45,
    channel_cfg=None,
    agent_cfg=None,
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
    if agent_cfg is not None:
        config = dataclasses.replace(config, agent=agent_cfg)
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
    # what crossed the wire: exactly the library's frames, one per speaking sender, one copy
    # (and a 19-byte header and MAC) per speaking link, and nothing for a silent link
    assert row["frame_bits_per_step"] == pytest.approx(row["wire_bits_per_step"])
    assert row["datagrams_per_step"] == pytest.approx(row["speaking_links_per_step"])
    assert row["network_datagrams_per_step"] == pytest.approx(row["datagrams_per_step"])
    assert row["header_bits_per_step"] == pytest.approx(8 * HEAD * row["datagrams_per_step"])
    assert 0 < row["datagrams_per_step"] <= 6
    network = row["datagram_bits_per_step"] + 8 * (HEAD + 28) * row["datagrams_per_step"]
    assert row["network_bits_per_step"] == pytest.approx(network)
    # eval's count of the datagrams and the frames they carry
    assert row["datagrams_per_step"] == pytest.approx(sim["datagrams_per_step"], rel=1e-12)
    assert row["datagram_bits_per_step"] == pytest.approx(sim["datagram_bits_per_step"], rel=1e-12)
    assert row["map_bits_per_step"] == 3 * 8  # one byte per observation: 2 senders each
    assert row["missing_messages_per_step"] == 0 and row["missing_actions_per_step"] == 0
    assert row["steps_without_map"] == 0
    low, high = row["ci"]["bits_per_step"]
    assert low <= row["bits_per_step"] <= high
    saved = json.loads((tmp_path / "deploy" / "deploy.json").read_text())
    assert saved["runs"][0]["bits_per_step"] == row["bits_per_step"]
    _check_tables(tmp_path / "deploy" / "run_0", k=3, steps=round(row["episode_length"] * episodes))


def _check_tables(folder: Path, k: int, steps: int) -> tuple[list, list]:
    """links.csv (one row per link and step) and frames.csv (one per sender and step) agree:
    a speaking link's datagram is the header and its sender's frame, a silent link has none;
    returns their rows."""
    import csv

    with open(folder / "links.csv") as f:
        links = list(csv.DictReader(f))
    with open(folder / "frames.csv") as f:
        frames = list(csv.DictReader(f))
    assert len(links) == k * (k - 1) * steps and len(frames) == k * steps
    frame_of = {(r["episode"], r["step"], r["sender"]): r for r in frames}
    for r in links:
        frame = frame_of[(r["episode"], r["step"], r["sender"])]
        due = int(r["datagram_bytes"])
        assert due == (HEAD + int(frame["frame_bits"]) // 8 if r["spoke"] == "1" else 0), r
    for r in frames:
        assert int(r["frame_bits"]) == int(r["sim_wire_bits"]), r
    return links, frames


@pytest.mark.slow
def test_deploy_matches_sparsecomm_eval(tmp_path):
    """The figures of ``sparsecomm eval`` itself (runs vmapped, as the command does) for the
    same run and episode count: equal to deploy's."""
    team = _team(tmp_path / "team")
    (row,) = deploy(Deploy(run=team, episodes=8, out=tmp_path / "deploy"))["runs"]
    ev = evaluate(Eval(run=team, episodes=8, out=tmp_path / "eval.json"))["runs"][0]
    ev = {k.rpartition("/")[2]: v for k, v in ev.items()}  # deploy's flat names, eval's grouped
    assert row["simulation"]["identical_episodes"] == 8
    assert row["success_rate"] == pytest.approx(ev["success_rate"], abs=1e-6)
    assert row["episode_length"] == pytest.approx(ev["episode_length"], rel=1e-6)
    assert row["bits_per_step"] == pytest.approx(ev["bits_per_step"], rel=1e-5)
    assert row["wire_bits_per_step"] == pytest.approx(ev["wire_bits_per_step"], rel=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("on_silence, news_margin", [("null", None), ("hold", None), ("hold", 0.1)])
def test_a_team_with_link_gates_deployed_plays_evals_episodes(tmp_path, on_silence, news_margin):
    """Gated links (``ChannelConfig.link_gate``): a closed link sends no datagram, and its
    receiver, told so by the world's heard map, makes of it what the simulation does (the null
    message, or under ``on_silence = "hold"`` the link's last message with news 0), so deploy
    still plays eval's episodes exactly, and the network carries one datagram per speaking
    link; with ``news_margin`` each agent process opens its links on news as the rollout does."""
    cfg = channel.ChannelConfig(link_gate=True, on_silence=on_silence, news_margin=news_margin)
    team = _team(tmp_path / "team", channel_cfg=cfg)
    (row,) = deploy(Deploy(run=team, episodes=4, out=tmp_path / "deploy"))["runs"]
    sim = row["simulation"]
    assert sim["identical_episodes"] == 4, sim["different_episodes"]
    assert row["wire_bits_per_step"] == pytest.approx(sim["wire_bits_per_step"], rel=1e-12)
    assert row["frame_bits_per_step"] == pytest.approx(row["wire_bits_per_step"])
    assert row["datagrams_per_step"] == pytest.approx(sim["datagrams_per_step"], rel=1e-12)
    assert row["datagram_bits_per_step"] == pytest.approx(sim["datagram_bits_per_step"], rel=1e-12)
    # closed gates: fewer datagrams than links, and only those on the network
    assert 0 < row["network_datagrams_per_step"] == row["datagrams_per_step"] < 6
    assert row["missing_messages_per_step"] == 0
    steps = round(row["episode_length"] * 4)
    links, _ = _check_tables(tmp_path / "deploy" / "run_0", k=3, steps=steps)
    silent = [r for r in links if r["spoke"] == "0"]
    assert silent and all(r["sent_datagrams"] == "0" and r["sent_bytes"] == "0" for r in silent)


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
def test_a_gated_holding_team_survives_loss_and_counts_it(tmp_path):
    """10% of the frames' datagrams dropped: a gate + hold team still plays every episode, each
    dropped frame is a loss at its receiver (the heard map promised it), the network carries
    only the datagrams not dropped, and the report counts both."""
    cfg = channel.ChannelConfig(link_gate=True, on_silence="hold")
    team = _team(tmp_path / "team", max_steps=12, radius=0.05, channel_cfg=cfg)
    args = Deploy(run=team, episodes=4, out=tmp_path / "deploy", loss=0.1, fault_seed=2)
    (row,) = deploy(args)["runs"]
    assert row["episodes"] == 4 and row["missing_actions_per_step"] == 0
    steps = round(row["episode_length"] * 4)
    links, _ = _check_tables(tmp_path / "deploy" / "run_0", k=3, steps=steps)
    last = {e["episode"]: e["length"] - 1 for e in read_episodes(tmp_path / "deploy" / "run_0")}
    # dropped: due and not sent; those of an episode's last step are heard by nobody
    dropped = [r for r in links if r["datagram_bytes"] != "0" and r["sent_datagrams"] == "0"]
    heard = [r for r in dropped if int(r["step"]) < last[int(r["episode"])]]
    assert len(heard) > 0
    lost = round(row["missing_messages_per_step"] * steps)
    # every dropped frame is a loss at its receiver (a late one on a loaded machine would add)
    assert len(heard) <= lost <= len(heard) + 0.05 * row["datagrams_per_step"] * steps
    assert row["garbage_dropped"] == 0
    sent = sum(r["datagram_bytes"] != "0" for r in links) - len(dropped)
    assert round(row["network_datagrams_per_step"] * steps) == sent
    assert row["datagrams_per_step"] < 6  # silent links still send nothing
    assert row["network_bits_per_step"] < row["datagram_bits_per_step"] + 8 * (HEAD + 28) * 6


@pytest.mark.slow
def test_ctrl_c_leaves_no_orphan(tmp_path):
    team = _team(tmp_path / "team", num_agents=2, max_steps=64)
    out = tmp_path / "deploy"
    cmd = [sys.executable, "-m", "sparsecomm.cli", "deploy", "--run", str(team)]
    cmd += ["--episodes", "500", "--out", str(out), "--no-reference"]
    # Started with SIGINT ignored, as a background job of a script inherits it (an ignored
    # signal stays ignored across exec): the launcher must stop anyway.
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        launcher = subprocess.Popen(cmd)
    finally:
        signal.signal(signal.SIGINT, previous)
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


# -- a hostile peer -------------------------------------------------------------------------


def test_a_flood_of_forgeries_changes_no_action(tmp_path):
    """A peer without the secret floods the world, both agents and the launcher (10,000
    datagrams per second in all) with forged datagrams of every kind (random MACs, another
    secret's forged bye / hello / observation / action / frame, the version-1 JSON payloads that
    crashed the world, cut-short and oversized ones) while the team plays: every episode is
    eval's (same actions, messages and bits), no process dies, and the drops are counted."""
    team = _team(tmp_path / "team", num_agents=2, max_steps=12)
    args = Deploy(run=team, episodes=8, out=tmp_path / "deploy", forgeries_per_second=1e4)
    (row,) = deploy(args)["runs"]
    sim = row["simulation"]
    assert sim["identical_episodes"] == 8, sim["different_episodes"]
    assert row["restarts"] == 0 and row["missing_actions_per_step"] == 0
    sent = row["forgeries_sent"]
    assert set(sent) == {"world", "agent_0", "agent_1", "launcher"} and min(sent.values()) > 0
    assert row["garbage_dropped"] > 0 and row["world_dropped"] > 0


def _capture_refused() -> str:
    from sparsecomm.deploy.replay import can_capture

    return can_capture()


def test_a_replaying_peer_changes_no_episode(tmp_path):
    """A peer without the secret captures every datagram the team's processes send each other
    (hellos, observations, actions, frames, the world's steps) and sends copies of each at once,
    duplicated, reordered, late, to the wrong process, and old ones at random, under reordering:
    every episode is still eval's, nothing is reflected (no copied hello answered), no process
    dies, and each kind of copy is counted where it is dropped."""
    why = _capture_refused()
    if why:
        pytest.skip(f"a packet capture socket is needed (root or CAP_NET_RAW): {why}")
    team = _team(tmp_path / "team", num_agents=2, max_steps=12)
    args = Deploy(run=team, episodes=8, out=tmp_path / "deploy", reorder=0.5, replay=True)
    (row,) = deploy(args)["runs"]
    sim = row["simulation"]
    assert sim["identical_episodes"] == 8, sim["different_episodes"]
    assert row["restarts"] == 0 and row["missing_actions_per_step"] == 0
    captured, sent = row["replays"]["captured"], row["replays"]["sent"]
    assert all(captured[kind] > 0 for kind in ("hello", "obs", "act", "msg", "step"))
    assert all(sent[mode] > 0 for mode in ("once", "duplicated", "reordered", "wrong", "old"))
    assert row["hellos_answered"] == 0 and row["hellos_ignored"] > 0  # never reflected
    assert row["duplicates_dropped"] > 0 and row["world_duplicates_dropped"] > 0
    assert row["stale_dropped"] > 0 and row["late_actions"] == 0
    assert row["garbage_dropped"] > 0 and row["world_dropped"] > 0  # sent to the wrong process


def test_the_replaying_peer_reads_udp_packets_and_never_raises():
    from sparsecomm.deploy.replay import udp_of

    payload = b"SC" + bytes(30)
    udp = struct.pack("!HHHH", 5000, 6000, 8 + len(payload), 0) + payload
    head = bytes([0x45, 0]) + struct.pack("!H", 20 + len(udp)) + bytes(4) + bytes([64, 17])
    head += bytes(2) + bytes([127, 0, 0, 1]) + bytes([127, 0, 0, 2])
    got = udp_of(head + udp)
    assert got == (("127.0.0.1", 5000), ("127.0.0.2", 6000), payload)
    fragment = head[:6] + b"\x20\x00" + head[8:]  # more fragments follow: not whole
    assert udp_of(fragment + udp) is None
    assert udp_of(head[:9] + b"\x06" + head[10:] + udp) is None  # TCP
    rng = np.random.default_rng(5)
    for _ in range(3000):
        junk = bytearray(rng.bytes(int(rng.integers(0, 80))))
        if junk and rng.random() < 0.5:
            junk[0] = 0x45
        got = udp_of(bytes(junk))
        assert got is None or len(got) == 3


def test_deploy_refuses_a_replay_it_cannot_capture(monkeypatch):
    from sparsecomm.deploy import replay

    monkeypatch.setattr(replay, "can_capture", lambda: "Operation not permitted")
    with pytest.raises(ValueError, match=r"Deploy\.replay needs a packet capture socket"):
        Deploy(replay=True)


@pytest.mark.slow
def test_a_replaying_peer_under_kills_leaves_every_restart_rejoining(tmp_path):
    """Copies of every datagram, one agent killed per episode and 20% loss: each killed agent's
    successor acts only on observations its own hello asked for (those of its predecessor are
    dropped, ``foreign``), so it rejoins every time and sends no action for a step the world
    already played."""
    why = _capture_refused()
    if why:
        pytest.skip(f"a packet capture socket is needed (root or CAP_NET_RAW): {why}")
    team = _team(tmp_path / "team", num_agents=2, max_steps=12, radius=0.05)
    args = Deploy(
        run=team,
        episodes=3,
        out=tmp_path / "deploy",
        loss=0.2,
        reorder=0.5,
        kills_per_episode=1,
        kill_window=3,
        action_deadline=1.0,
        replay=True,
    )
    (row,) = deploy(args)["runs"]
    assert row["episodes"] == 3 and row["kills"] == 3
    assert row["restarts"] == row["kills"] == row["hellos_answered"] and row["rejoins"] >= 1
    assert row["late_actions"] == 0 and row["hellos_ignored"] > 0
    assert row["replays"]["sent"]["late"] > 0


def test_an_agent_drops_what_is_not_sealed_or_not_expected(tmp_path):
    """One agent in this process: a bye, an observation or a frame sealed under another secret
    is dropped (counted ``bad``); so is a sealed one from the wrong sender, for another
    recipient, or for an episode or step outside the batch; an observation already acted on,
    replayed, is stale, a copy of the one just acted on a duplicate (nothing sent back), one
    carrying another process's nonce foreign; only the world's sealed bye ends the agent."""
    from sparsecomm.deploy.agent import Agent, AgentArgs

    team = _team(tmp_path / "team", num_agents=2, max_steps=5)
    host = "127.0.0.1"
    world = wire.udp_socket((host, 0))
    ports = wire.free_ports(host, 2)
    args = AgentArgs(
        team=team,
        agent=0,
        peers=tuple(f"{host}:{p}" for p in ports),
        world=f"{host}:{world.getsockname()[1]}",
        seed=1,
        episodes=2,
        secret_file=_secret(tmp_path),
    )
    agent = Agent(args)
    try:
        stranger = wire.Auth(bytes(range(100, 132)))
        obs = wire.pack_obs(agent.nonce, np.zeros(agent.obs_dim, np.float32), [False])
        dropped = [
            stranger.pack(wire.BYE, wire.WORLD, 0, 0, 0),
            stranger.pack(wire.OBS, wire.WORLD, 0, 0, 0, obs),
            stranger.pack(wire.MSG, 1, 0, 0, 0, b"\x80\x00"),
            AUTH.pack(wire.BYE, 1, 0, 0, 0),  # a bye not from the world
            AUTH.pack(wire.OBS, 1, 0, 0, 0, obs),  # an observation not from the world
            AUTH.pack(wire.BYE, wire.WORLD, 1, 0, 0),  # for agent 1
            AUTH.pack(wire.OBS, wire.WORLD, 0, 2, 0, obs),  # episode outside the batch
            AUTH.pack(wire.MSG, 1, 0, 0, 5, b"\x80\x00"),  # step outside the episode
            AUTH.pack(wire.MSG, 0, 0, 0, 0, b"\x80\x00"),  # from myself
            AUTH.pack(wire.BYE, wire.WORLD, 0, 0, 0, b"x"),  # a bye with a payload
            b"SC\x15" + bytes(10) + b"\xff\xff",  # version 1 with a CRC-16
        ]
        for data in dropped:
            assert agent._handle(data) is None
        assert agent.counts["bad"] == len(dropped)
        first = AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 1, obs)
        assert agent._act(agent._handle(first)) is None
        world.settimeout(5.0)
        act = AUTH.parse(world.recvfrom(wire.MAX_DATAGRAM)[0])
        assert act.kind == wire.ACT and wire.parse_report(act.payload, 1).bad == len(dropped)
        assert agent._handle(AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 0, obs)) is None  # replayed
        assert agent.counts["stale"] == 1
        # a copy of the observation just acted on is a duplicate: nothing is sent back (a
        # replay is not reflected)
        assert agent._handle(first) is None and agent.counts["dup"] == 1
        world.settimeout(0.2)
        with pytest.raises(TimeoutError):
            world.recvfrom(wire.MAX_DATAGRAM)
        # while a step is in progress, a copy of its observation is a duplicate, not the world
        # moving on (it would end the wait for the step's frames); a newer one is news
        agent.acting = (0, 2)
        assert agent._handle(AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 2, obs)) is None
        assert agent.counts["dup"] == 2
        # an observation for another process of this agent (a predecessor's nonce): foreign
        other = wire.pack_obs(wire.new_nonce(), np.zeros(agent.obs_dim, np.float32), [False])
        assert agent._handle(AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 3, other)) is None
        assert agent._handle(AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 3, b"")) is None
        assert agent.counts["foreign"] == 2
        assert agent._handle(AUTH.pack(wire.OBS, wire.WORLD, 0, 0, 3, obs)).step == 3
        assert agent._handle(AUTH.pack(wire.BYE, wire.WORLD, 0, 0, 0)) == "bye"
    finally:
        world.close()
        agent.sock.close()


@pytest.mark.slow
def test_the_launcher_exits_2_when_the_world_dies(tmp_path):
    """The world killed mid-run: the launcher stops every process and exits 2 with the cause
    (before, it died of SIGABRT in 2 of 3 runs: its simulation thread was inside XLA)."""
    team = _team(tmp_path / "team", num_agents=2, max_steps=64)
    out = tmp_path / "deploy"
    cmd = [sys.executable, "-m", "sparsecomm.cli", "deploy", "--run", str(team)]
    cmd += ["--episodes", "500", "--out", str(out)]
    launcher = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        until = time.monotonic() + 120
        while time.monotonic() < until and not (out / "run_0" / "episodes.jsonl").exists():
            time.sleep(0.2)
        (world,) = [p for p in _children(launcher.pid) if b"deploy.world" in _cmdline(p)]
        os.kill(world, signal.SIGKILL)
        _, err = launcher.communicate(timeout=60)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert launcher.returncode == 2, err
    assert "the world exited with -9" in err and "Traceback" not in err


def _cmdline(pid: int) -> bytes:
    return Path(f"/proc/{pid}/cmdline").read_bytes()


def test_an_ipv6_host_is_refused_as_such():
    for host in ("::1", "[::1]", "fe80::1"):
        with pytest.raises(ValueError, match=r"Deploy\.host .*an IPv6 address: .*IPv4 only"):
            Deploy(host=host)
    with pytest.raises(ValueError, match=r"Deploy\.host .*without a port"):
        Deploy(host="localhost:9000")


@pytest.mark.parametrize("module", ["agent", "world"])
def test_an_empty_secret_file_is_reported_as_given(module, tmp_path):
    """``--secret-file ''`` is named as the empty value it is, not as the current folder."""
    cls = {"agent": "AgentArgs", "world": "WorldArgs"}[module]
    for flag in (["--secret-file", ""], ["--secret-file="]):
        done = subprocess.run(
            [sys.executable, "-m", f"sparsecomm.deploy.{module}", *flag],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp_path,
        )
        assert done.returncode == 2, done.stderr[-2000:]
        assert f"{cls}.secret_file must be a path, got ''" in done.stderr, done.stderr[-2000:]
        assert "'.'" not in done.stderr and "Traceback" not in done.stderr
    assert list(tmp_path.iterdir()) == []
