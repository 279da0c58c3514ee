"""Noise on the wire (channel/noise.py): each model's empirical rates match its parameters, no
noise changes nothing, and the receiver never accepts a wrong message.

Statistical checks use fixed seeds and a tolerance of 5 standard errors (a false failure has
probability ~6e-7 per check if the seed were redrawn); where steps are correlated (the burst
channel) the standard error is inflated by the chain's autocorrelation, as noted there.
"""

import re

import numpy as np
import pytest

from sparsecomm import channel
from sparsecomm.channel.noise import NoiseConfig, NoisyLink, flip_bits

LEVELS = 15
SHAPE = (10,)


def _bits(packets) -> np.ndarray:
    return np.unpackbits(np.frombuffer(b"".join(packets), np.uint8))


def _run(config: NoiseConfig, packets, seed=0) -> list:
    link = NoisyLink(config, np.random.default_rng(seed))
    return [link.send(p) for p in packets]


def _random_packets(n: int, size: int, seed: int) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [rng.bytes(size) for _ in range(n)]


def test_symmetric_flips_match_p():
    p = 0.05
    sent = _random_packets(4000, 32, seed=1)
    got = _run(NoiseConfig(flip=p), sent, seed=2)
    assert [len(g) for g in got] == [len(s) for s in sent]
    flipped = _bits(sent) ^ _bits(got)
    se = np.sqrt(p * (1 - p) / flipped.size)  # independent bits: binomial
    assert abs(flipped.mean() - p) < 5 * se


def test_asymmetric_flips_match_each_direction():
    p01, p10 = 0.1, 0.05  # AAAI 2020's rates
    sent = _random_packets(4000, 32, seed=3)
    before, after = _bits(sent), _bits(_run(NoiseConfig(flip_01=p01, flip_10=p10), sent, seed=4))
    for bit, p in ((0, p01), (1, p10)):
        rate = (after[before == bit] != bit).mean()
        se = np.sqrt(p * (1 - p) / (before == bit).sum())
        assert abs(rate - p) < 5 * se, bit


def test_flip_bits_extremes_and_no_draw_at_zero():
    rng = np.random.default_rng(0)
    data = bytes([0b10100101, 0xFF, 0x00])
    assert flip_bits(data, rng, 1.0, 1.0) == bytes(b ^ 0xFF for b in data)
    assert flip_bits(data, rng, 1.0, 0.0) == b"\xff\xff\xff"
    assert flip_bits(data, rng, 0.0, 1.0) == b"\x00\x00\x00"
    state = rng.bit_generator.state
    assert flip_bits(data, rng, 0.0, 0.0) == data and flip_bits(b"", rng, 0.5, 0.5) == b""
    assert rng.bit_generator.state == state


def test_erasure_rate_and_silence_is_never_lost():
    q = 0.2
    sent = _random_packets(10_000, 8, seed=5)
    sent[::5] = [b""] * len(sent[::5])  # every fifth step silent
    got = _run(NoiseConfig(erasure=q), sent, seed=6)
    lost = np.array([g is None for g, s in zip(got, sent, strict=True) if s])
    assert all(g == b"" for g, s in zip(got, sent, strict=True) if not s)
    assert all(g == s for g, s in zip(got, sent, strict=True) if g is not None)
    se = np.sqrt(q * (1 - q) / lost.size)
    assert abs(lost.mean() - q) < 5 * se


def test_gilbert_elliott_share_flip_rate_and_bursts():
    # Faster-mixing than the defaults so that 20,000 steps pin the rates down: autocorrelation
    # rho = 1 - g2b - b2g = 0.75 between steps, so the standard error of a mean over steps is
    # the independent one times sqrt((1 + rho) / (1 - rho)) = sqrt(7) (exact for a function
    # of the state; conservative for the flip rate, whose within-state noise is independent).
    g2b, b2g, f_good, f_bad = 0.05, 0.2, 0.001, 0.3
    cfg = NoiseConfig(
        burst=True,
        burst_good_to_bad=g2b,
        burst_bad_to_good=b2g,
        burst_flip_good=f_good,
        burst_flip_bad=f_bad,
    )
    share = g2b / (g2b + b2g)
    assert cfg.burst_bad_share == pytest.approx(share)
    inflation = np.sqrt((1 + 0.75) / (1 - 0.75))
    n, size = 20_000, 16
    sent = _random_packets(n, size, seed=7)
    sent[::4] = [b""] * len(sent[::4])  # silent steps move the chain too
    link = NoisyLink(cfg, np.random.default_rng(8))
    bad, got = [], []
    for packet in sent:
        bad.append(link.bad)
        got.append(link.send(packet))
    bad = np.array(bad)
    assert abs(bad.mean() - share) < 5 * inflation * np.sqrt(share * (1 - share) / n)

    # Per-bit flip rate over the packets sent: the stationary mixture of the two states.
    on = np.array([bool(s) for s in sent])
    flips = np.array(
        [(_bits([s]) ^ _bits([g])).mean() if s else 0.0 for s, g in zip(sent, got, strict=True)]
    )
    mixture = share * f_bad + (1 - share) * f_good
    spread = share * (1 - share) * (f_bad - f_good) ** 2 * inflation**2 + mixture / (8 * size)
    assert abs(flips[on].mean() - mixture) < 5 * np.sqrt(spread / on.sum())

    # Bursts: a corrupted packet is followed by another far more often than packets are
    # corrupted (expected ~0.61 against ~0.30 here; standard errors ~0.02).
    corrupt = flips > 0
    pairs = on[:-1] & on[1:]
    marginal = corrupt[on].mean()
    after_corrupt = corrupt[1:][pairs & corrupt[:-1]].mean()
    assert after_corrupt > marginal + 0.15, (after_corrupt, marginal)


def test_burst_defaults_and_silent_steps():
    cfg = NoiseConfig(burst=True)
    assert cfg.burst_bad_share == pytest.approx(1 / 11) and not cfg.clean
    link = NoisyLink(cfg, np.random.default_rng(0))
    # Silence passes unchanged while the chain moves: over 2,000 silent steps it visits both.
    states = set()
    for _ in range(2000):
        states.add(link.bad)
        assert link.send(b"") == b""
    assert states == {False, True}


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_delay_is_exact(delay):
    sent = [bytes([t]) * (t % 3) for t in range(1, 21)]  # some silent (b"")
    got = _run(NoiseConfig(delay=delay), sent)
    assert got[:delay] == [None] * delay
    assert got[delay:] == sent[: len(sent) - delay]


def test_no_noise_is_bit_identical():
    cfg = NoiseConfig()
    assert cfg.clean and NoiseConfig(on_drop="last").clean
    assert NoiseConfig(burst=True, burst_flip_bad=0.0).clean
    assert not NoiseConfig(delay=1).clean and not NoiseConfig(erasure=0.01).clean
    rng = np.random.default_rng(9)
    messages = rng.integers(0, LEVELS + 1, (500, *SHAPE)) * (rng.random((500, 1)) < 0.8)
    link_rng = np.random.default_rng(10)
    state = link_rng.bit_generator.state
    link = NoisyLink(cfg, link_rng)
    for m in messages:
        packet = channel.encode(m, "paper")
        assert link.send(packet) == packet
        assert np.array_equal(channel.decode(packet, "paper", SHAPE), m)
    assert link_rng.bit_generator.state == state  # a clean link draws nothing


@pytest.mark.parametrize("p", [0.05, 0.005])
def test_decoding_under_flips_never_accepts_a_wrong_message(p):
    rng = np.random.default_rng(11)
    n = 1500
    messages = rng.integers(0, LEVELS + 1, (n, *SHAPE)) * (rng.random((n, 1)) < 0.9)
    link = NoisyLink(NoiseConfig(flip=p), np.random.default_rng(12))
    cfg = channel.ChannelConfig(num_elements=SHAPE[0])
    failed, expected = [], []
    for m in messages:
        packet = channel.encode(m, "paper")
        try:  # accepted: exactly what was sent (a corrupted packet fails the CRC-32)
            message, ok = channel.decode_link(cfg, link.send(packet), None), True
            np.testing.assert_array_equal(message, m)
            assert message.dtype == np.int64 and message.shape == SHAPE
        except channel.PacketError:
            ok = False
        failed.append(not ok)
        expected.append(1 - (1 - p) ** (8 * len(packet)))  # any flipped bit fails
    expected = np.array(expected)
    se = np.sqrt((expected * (1 - expected)).sum()) / n  # independent, unequal Bernoullis
    assert abs(np.mean(failed) - expected.mean()) < 5 * se


def test_a_missing_packet_is_the_null_message_or_the_last_good_one():
    """The channel's one rule (``channel.receive``), the same in training and in deploy."""
    import jax.numpy as jnp

    cfg = channel.ChannelConfig(num_elements=SHAPE[0])
    m = jnp.asarray(np.stack([np.arange(10) % 4] * 2), jnp.int32)  # two links' symbols
    u = jnp.asarray(np.random.default_rng(0).uniform(-0.5, 0.5, m.shape), jnp.float32)
    ok = jnp.array([True, False])
    last = jnp.full(m.shape, 0.25)
    got = channel.receive(cfg, m, u, ok=ok)  # default on_drop: the null message
    np.testing.assert_allclose(got.z_hat[0], (m[0] - u[0]) / LEVELS, rtol=1e-6)
    np.testing.assert_allclose(got.z_hat[1], -u[1] / LEVELS, rtol=1e-6)
    assert got.last is None
    got = channel.receive(cfg, m, u, ok=ok, last=last, on_drop="last")
    np.testing.assert_array_equal(got.z_hat[1], last[1])
    np.testing.assert_array_equal(got.last, got.z_hat)  # the good one is the new last
    values = channel.ChannelConfig(mode="continuous", num_elements=SHAPE[0])
    got = channel.receive(values, jnp.full(m.shape, 0.5), ok=ok)
    assert float(got.z_hat[0].min()) == 0.5 and not got.z_hat[1].any()  # null: zeros
    live = jnp.array([False, True])
    assert not channel.receive(cfg, m, u, live=live).z_hat[0].any()  # no link, nothing
    with pytest.raises(ValueError, match="on_drop"):
        channel.receive(cfg, m, u, ok=ok, on_drop="zero")
    with pytest.raises(ValueError, match="last"):
        channel.receive(cfg, m, u, ok=ok, on_drop="last")
    with pytest.raises(channel.PacketError):
        channel.decode_link(values, b"\x00\x01", None)  # malformed
    assert not channel.decode_link(values, b"", None).any()  # silence is a message


@pytest.mark.parametrize(
    "field, kwargs",
    [
        ("flip", {"flip": -0.1}),
        ("flip_01", {"flip_01": 1.5}),
        ("flip_10", {"flip_10": float("nan")}),
        ("erasure", {"erasure": "0.1"}),
        ("burst_good_to_bad", {"burst_good_to_bad": 2}),
        ("burst_bad_to_good", {"burst_bad_to_good": -1}),
        ("burst_flip_good", {"burst_flip_good": 1.01}),
        ("burst_flip_bad", {"burst_flip_bad": True}),
        ("burst", {"burst": "yes"}),
        ("delay", {"delay": -1}),
        ("delay", {"delay": 1.5}),
        ("delay", {"delay": True}),
        ("on_drop", {"on_drop": "zero"}),
        ("flip", {"flip": 0.1, "flip_01": 0.1}),
        ("burst", {"burst": True, "flip_10": 0.1}),
    ],
)
def test_bad_configs_name_the_field(field, kwargs):
    with pytest.raises(ValueError, match=rf"NoiseConfig\.{re.escape(field)}\b"):
        NoiseConfig(**kwargs)


def test_good_configs_are_accepted_and_hashable():
    configs = {
        NoiseConfig(flip_01=0.1, flip_10=0.05),
        NoiseConfig(delay=np.int64(2), erasure=1, on_drop="last"),
        NoiseConfig(burst=True, burst_good_to_bad=0, burst_bad_to_good=0),
    }
    assert len(configs) == 3
    assert NoiseConfig(flip=0.2).flip_rates == (0.2, 0.2)


# -- under jit: the packets a rollout's receivers lose --------------------------------------


def test_lost_packets_under_jit_match_erasure_flips_and_bursts():
    import jax
    import jax.numpy as jnp

    from sparsecomm.channel.noise import initial_bad, lost_packets

    n = 200_000
    w = jnp.where(jnp.arange(n) % 4 == 0, 0.0, 40.0)  # a quarter silent: never lost
    busy = np.asarray(w) > 0
    for cfg, p in [
        (NoiseConfig(erasure=0.2), 0.2),
        (NoiseConfig(flip=0.01), 1 - 0.99**40),
        (NoiseConfig(erasure=0.1, flip=0.01), 1 - 0.9 * 0.99**40),
    ]:
        lost, _ = lost_packets(jax.random.key(0), cfg, w, jnp.zeros(n, bool))
        lost = np.asarray(lost)
        assert not lost[~busy].any()
        rate, se = lost[busy].mean(), np.sqrt(p * (1 - p) / busy.sum())
        assert abs(rate - p) < 5 * se, (cfg, rate, p)
    # bursts: the bad share stays at its stationary value, and losses come in runs
    cfg = NoiseConfig(burst=True, burst_good_to_bad=0.05, burst_bad_to_good=0.2)
    bad = initial_bad(jax.random.key(1), cfg, (20_000,))
    step = jax.jit(lambda k, b: lost_packets(k, cfg, jnp.full(b.shape, 40.0), b))
    shares, losses = [], []
    for t in range(40):
        lost, bad = step(jax.random.key(100 + t), bad)
        shares.append(float(bad.mean()))
        losses.append(np.asarray(lost))
    assert abs(np.mean(shares) - 0.2) < 0.01  # 0.05 / (0.05 + 0.2)
    losses = np.array(losses)
    after_loss = losses[1:][losses[:-1]].mean()
    assert after_loss > losses.mean() + 0.2, (after_loss, losses.mean())


def test_rollout_under_erasure_loses_its_share_of_packets_and_delays_exactly(fast_compile):
    import dataclasses

    import jax

    from sparsecomm.configs import RLConfig
    from sparsecomm.envs.navigation import NavConfig
    from sparsecomm.rl import make_train
    from sparsecomm.rollout import rollout

    cfg = RLConfig(env=NavConfig(max_steps=16), num_envs=64)
    learner = make_train(cfg)
    params = learner.init(jax.random.key(0), 0.0).params["actor"]

    def play(noise, **kw):
        ch = dataclasses.replace(cfg.channel, noise=noise)
        return rollout(learner.team, learner.env, ch, params, jax.random.key(1), 64, **kw)

    clean = play(NoiseConfig(), keep_symbols=True)
    busy = (np.asarray(clean.aside.symbols) != 0).any(-1).sum((2, 3))  # (T, B) packets sent
    noisy = play(NoiseConfig(erasure=0.25), keep_symbols=True)
    # the senders' first step is the same (nothing received yet), later steps differ
    np.testing.assert_array_equal(noisy.aside.symbols[0], clean.aside.symbols[0])
    lost = np.asarray(noisy.aside.lost)
    sent = (np.asarray(noisy.aside.symbols) != 0).any(-1).sum((2, 3))
    valid = np.asarray(noisy.valid)
    rate = lost[valid].sum() / sent[valid].sum()
    se = np.sqrt(0.25 * 0.75 / sent[valid].sum())
    assert busy[valid].sum() > 1000 and abs(rate - 0.25) < 5 * se, rate
    assert clean.aside.lost is None
    everything = play(NoiseConfig(erasure=1.0), keep_symbols=True)
    sent_all = (np.asarray(everything.aside.symbols) != 0).any(-1).sum((2, 3))
    assert sent_all.sum() > 0
    np.testing.assert_array_equal(np.asarray(everything.aside.lost), sent_all)  # every packet lost


def test_delay_line_delivers_what_was_sent_d_steps_before_and_null_until_then():
    import jax
    import jax.numpy as jnp

    from sparsecomm.channel import ChannelConfig

    cfg = ChannelConfig(num_elements=2, noise=NoiseConfig(delay=2, on_drop="null"))
    wire = channel.lossy.LossyLinks(cfg, jax.random.key(0), 1, 3, 5)
    state = wire.init
    sent_z = [jnp.full((1, 3, 2, 2), 0.1 * (t + 1)) for t in range(5)]
    for t in range(5):
        u = jnp.full((1, 3, 2, 2), 0.25)
        bits = jnp.full((1, 3, 2), 24.0)
        sent = channel.Sent(None, sent_z[t], None, bits, bits, None, None)
        arrived, ok, state, lost = wire.step(wire.step_keys[t], sent, u, state)
        got = channel.receive(cfg, arrived, u, ok=ok).z_hat
        want = sent_z[t - 2] if t >= 2 else -u / cfg.levels  # null: all-null symbols
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6)
        assert float(lost.sum()) == 0


def test_eval_command_can_evaluate_a_team_under_other_noise(tmp_path, fast_compile):
    import json

    from sparsecomm.cli import main
    from sparsecomm.runfolder import PRETRAINED

    out = tmp_path / "eval.json"
    args = ["eval", "--run", str(PRETRAINED), "--episodes", "16", "--out", str(out)]
    main([*args, "--no-own-noise", "--noise.erasure", "1.0"])
    lost = json.loads(out.read_text())["by_group"]["budget=16/0"]
    lost = lost["channel/packets_lost_per_step"]["mean"]
    assert lost > 1.5  # two links, nearly always speaking: every packet lost
    main(args)
    assert (
        "channel/packets_lost_per_step"
        not in json.loads(out.read_text())["by_group"]["budget=16/0"]
    )


# -- error correction ------------------------------------------------------------------------


def test_hamming_corrects_one_flip_per_block_and_counts_its_bits():
    from sparsecomm.channel import ecc

    rng = np.random.default_rng(3)
    for n in range(1, 20):
        packet = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        sent = ecc.encode(packet)
        assert 8 * len(sent) == int(ecc.wire_bits(8 * n, "hamming74"))
        assert int(ecc.data_bits(8 * len(sent), "hamming74")) == 8 * n
        assert ecc.decode(sent) == packet
        bits = np.unpackbits(np.frombuffer(sent, np.uint8))
        for block in range(2 * n):  # one flip in every block at once: all corrected
            bits[7 * block + rng.integers(7)] ^= 1
        assert ecc.decode(np.packbits(bits).tobytes()) == packet
    assert ecc.encode(b"") == b"" and int(ecc.wire_bits(0, "hamming74")) == 0
    with pytest.raises(ValueError, match="ecc must be one of"):
        ecc.encode(b"x", "turbo")


def test_hamming_packets_survive_flips_as_the_block_law_says_and_never_decode_wrong():
    import jax
    import jax.numpy as jnp

    from sparsecomm.channel import ecc
    from sparsecomm.channel.noise import lost_packets

    p, n = 0.02, 3000
    cfg = channel.ChannelConfig(num_elements=SHAPE[0], ecc="hamming74")
    link = NoisyLink(NoiseConfig(flip=p), np.random.default_rng(4))
    rng = np.random.default_rng(5)
    ok, expect = [], []
    for _ in range(n):
        m = np.where(rng.random(10) < 0.5, rng.integers(1, LEVELS + 1, 10), 0)
        packet = channel.encode(m, "paper")
        if not packet:
            continue
        try:
            got, fine = channel.decode_link(cfg, link.send(ecc.encode(packet)), None), True
            assert (got == m).all()  # accepted only when right
        except channel.PacketError:
            fine = False
        ok.append(fine)
        expect.append(ecc.block_survival(p) ** (2 * len(packet)))
    rate, want = np.mean(ok), np.mean(expect)
    assert abs(rate - want) < 5 * np.sqrt(want * (1 - want) / len(ok)), (rate, want)
    # without the code the same packets would mostly be lost: (1 - p)^W
    assert want > np.mean([(1 - p) ** (8 * len(channel.encode(np.ones(10, int))))]) + 0.3
    # the jit law agrees with the host's
    w = jnp.full((200_000,), float(ecc.wire_bits(8 * 7, "hamming74")))
    lost, _ = lost_packets(jax.random.key(0), NoiseConfig(flip=p), w, w < 0, "hamming74")
    survive = ecc.block_survival(p) ** 14
    assert abs(1 - float(lost.mean()) - survive) < 5 * np.sqrt(survive * (1 - survive) / w.size)


def test_channel_with_hamming_counts_the_redundancy_in_its_wire_bits():
    import jax

    from sparsecomm.channel import ChannelConfig, ecc

    z = jax.random.uniform(jax.random.key(0), (4, 3, 2, 10)) * (
        jax.random.uniform(jax.random.key(1), (4, 3, 2, 10)) < 0.3
    )
    u = channel.dither(jax.random.key(2), z.shape)
    plain = channel.transmit(ChannelConfig(), z, u)
    coded = channel.transmit(ChannelConfig(ecc="hamming74"), z, u)
    frames = np.asarray(plain.wire_bits).sum(-1)  # each sender's frame
    np.testing.assert_allclose(coded.wire_bits.sum(-1), ecc.wire_bits(frames, "hamming74"))
    m = np.asarray(coded.symbols)
    for i in np.ndindex(m.shape[:2]):
        frame = ecc.encode(channel.encode_frame(m[i], "paper"))
        assert 8 * len(frame) == coded.wire_bits[i].sum()
        assert channel.encode_sender(ChannelConfig(ecc="hamming74"), m[i], m[i]) == frame
    with pytest.raises(ValueError, match="ChannelConfig.ecc"):
        ChannelConfig(ecc="turbo")
