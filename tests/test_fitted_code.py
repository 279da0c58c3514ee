"""The fitted code: exact round trips, wire bits equal to the packets, bits
near the entropy of a known source, clean errors for any bytes, and its use in a rollout."""

import dataclasses

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sparsecomm import channel
from sparsecomm.channel.fitted import (
    FittedCode,
    canonical_codes,
    fit,
    huffman_lengths,
    previous,
)
from sparsecomm.configs import ChannelConfig, RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.rl import make_train
from sparsecomm.rollout import rollout

C, LEVELS = 10, 15


def sticky_source(seed: int, links: int = 400, steps: int = 60) -> np.ndarray:
    """(links, steps, C) symbols like a trained team's: elements 0-3 mostly null, 4-9 mostly
    busy, each element keeping its symbol with probability 0.8, else redrawn from a skewed
    law (null with the element's probability, else 1 + a geometric number)."""
    rng = np.random.default_rng(seed)
    null_p = np.array([0.95, 0.9, 0.9, 0.8, 0.3, 0.3, 0.2, 0.2, 0.1, 0.1])

    def draw(shape):
        busy = rng.random(shape) > null_p
        return np.where(busy, np.minimum(rng.geometric(0.35, shape), LEVELS), 0)

    out = np.zeros((links, steps, C), np.int64)
    out[:, 0] = draw((links, C))
    for t in range(1, steps):
        keep = rng.random((links, C)) < 0.8
        out[:, t] = np.where(keep, out[:, t - 1], draw((links, C)))
    return out


@pytest.fixture(scope="module")
def code() -> FittedCode:
    return fit(sticky_source(0), levels=LEVELS)


def test_huffman_lengths_are_optimal_and_prefix_free():
    lengths = huffman_lengths([5, 2, 1, 1])
    assert lengths.tolist() == [1, 2, 3, 3]
    assert huffman_lengths([7]).tolist() == [0]
    codes = canonical_codes(lengths)
    words = [format(int(c), f"0{n}b") for c, n in zip(codes, lengths, strict=True)]
    assert all(not b.startswith(a) for a in words for b in words if a is not b)
    with pytest.raises(ValueError):
        huffman_lengths([1, 0])


def test_round_trip_and_wire_bits_equal_the_packets(code):
    m = sticky_source(1, links=20)
    prev = previous(m)
    wire = np.asarray(channel.wire_bits(m, code, prev=prev))
    for i in range(m.shape[0]):
        for t in range(m.shape[1]):
            packet = channel.encode(m[i, t], code, prev=prev[i, t])
            assert 8 * len(packet) == wire[i, t]
            back = channel.decode(packet, code, (C,), prev=prev[i, t])
            np.testing.assert_array_equal(back, m[i, t])
    assert channel.wire_bits(np.zeros(C, int), code) == 0
    assert channel.encode(np.zeros(C, int), code, prev=m[0, 5]) == b""


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, LEVELS), min_size=C, max_size=C),
    st.lists(st.integers(0, LEVELS), min_size=C, max_size=C),
)
def test_any_message_round_trips_even_unseen_when_fitting(code, m, prev):
    packet = channel.encode(m, code, prev=prev)
    assert 8 * len(packet) == int(channel.wire_bits(np.array(m), code, prev=np.array(prev)))
    np.testing.assert_array_equal(channel.decode(packet, code, (C,), prev=prev), m)


def test_a_receiver_with_another_previous_message_or_code_refuses_the_packet(code):
    m = np.array([0, 0, 0, 0, 3, 1, 1, 2, 0, 1])
    prev = np.array([0, 0, 0, 0, 3, 1, 1, 2, 0, 2])
    packet = channel.encode(m, code, prev=prev)
    with pytest.raises(channel.PacketError, match="CRC-32"):
        channel.decode(packet, code, (C,), prev=np.zeros(C, int))
    other = fit(sticky_source(5), levels=LEVELS)
    with pytest.raises(channel.PacketError, match="CRC-32"):
        channel.decode(packet, other, (C,), prev=prev)


def test_code_bits_approach_the_entropy_rate_of_the_source(code):
    """The source's elements are independent Markov chains, so its entropy given the previous
    message is the sum of the elements' conditional entropies (plug-in, 16 x 16 cells each). On
    fresh links the fitted code's codeword bits stay within 1.4x of it (Huffman spends at least
    a bit per coded group and symbol), and far below the paper code's framing."""
    m = sticky_source(2, links=2000)
    prev = previous(m)
    code_bits = np.asarray(code.code_bits(m, prev), np.float64).mean()

    def cond_entropy(x, y):  # H(Y | X), plug-in
        joint = np.unique(np.stack([x, y], -1), axis=0, return_counts=True)[1]
        marg = np.unique(x, return_counts=True)[1]
        h = lambda c: -(c / c.sum() * np.log2(c / c.sum())).sum()  # noqa: E731
        return h(joint) - h(marg)

    cur, pr = m.reshape(-1, C), prev.reshape(-1, C)
    entropy = sum(cond_entropy(pr[:, k], cur[:, k]) for k in range(C))
    paper = np.asarray(channel.wire_bits(m, "paper", crc=False), np.float64).mean()
    assert code_bits <= 1.4 * entropy, (code_bits, entropy)  # measured 1.35x
    assert code_bits < 0.7 * paper, (code_bits, paper)


def test_json_round_trip_and_bad_files(code, tmp_path):
    again = FittedCode.from_json(code.to_json())
    assert again == code and hash(again) == hash(code)
    for text, match in [
        ("not json", "not JSON"),
        ('{"format": "x"}', "not a sparsecomm.fitted_code"),
        ('{"format": "sparsecomm.fitted_code", "version": 1}', "missing or malformed"),
    ]:
        with pytest.raises(ValueError, match=match):
            FittedCode.from_json(text)
    d = code.to_dict()
    d["symbol_counts"] = d["symbol_counts"][:3]
    with pytest.raises(ValueError, match="symbol_counts must have shape"):
        FittedCode.from_json(__import__("json").dumps(d))
    with pytest.raises(ValueError, match="FittedCode.alpha"):
        dataclasses.replace(code, alpha=0.0)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40), st.lists(st.integers(0, LEVELS), min_size=C, max_size=C))
def test_decoding_arbitrary_bytes_gives_a_message_or_packet_error(code, data, prev):
    for crc in (True, False):
        try:
            out = channel.decode(data, code, (C,), prev=prev, crc=crc)
        except channel.PacketError:
            continue
        assert out.shape == (C,) and out.min() >= 0 and out.max() <= LEVELS
        assert channel.encode(out, code, prev=prev, crc=crc) == data  # canonical


def test_channel_config_checks_the_code_file(code, tmp_path):
    with pytest.raises(ValueError, match="ChannelConfig.code_file"):
        ChannelConfig(code="fitted")
    with pytest.raises(ValueError, match="ChannelConfig.code_file"):
        ChannelConfig(code="fitted", code_file=str(tmp_path / "missing.json"))
    path = tmp_path / "code.json"
    path.write_text(code.to_json())
    with pytest.raises(ValueError, match="levels 7 and 10 elements"):
        ChannelConfig(code="fitted", code_file=str(path), levels=7)
    assert ChannelConfig(code="fitted", code_file=str(path)).code_obj == code


def test_rollout_wire_bits_are_the_fitted_packets_of_every_link(tmp_path, fast_compile):
    """A team's rollout under a code fitted to its own symbols logs, per step, exactly the
    bytes that encoding each link given its previous message writes."""
    env = NavConfig(num_agents=3, max_steps=12)
    paper = RLConfig(env=env, num_envs=8)
    learner = make_train(paper)
    params = learner.init(jax.random.key(0), 0.0, float("nan")).params["actor"]

    def play(cfg, key):
        return rollout(learner.team, learner.env, cfg, params, key, 8, keep_symbols=True)

    traj = play(paper.channel, jax.random.key(1))
    links = np.asarray(traj.aside.symbols).transpose(1, 2, 3, 0, 4).reshape(-1, 12, C)
    fitted = fit(links, np.repeat(np.asarray(traj.valid).T, 6, axis=0), levels=LEVELS)
    path = tmp_path / "code.json"
    path.write_text(fitted.to_json())
    cfg = dataclasses.replace(paper.channel, code="fitted", code_file=str(path))
    traj = play(cfg, jax.random.key(2))
    m = np.asarray(traj.aside.symbols)
    wire = np.asarray(traj.wire_bits)
    assert np.any(m != 0)
    for t in range(m.shape[0]):
        for b in range(m.shape[1]):
            prev = m[t - 1, b] if t else np.zeros_like(m[0, b])
            total = sum(
                8 * len(channel.encode(m[t, b, i, r], fitted, prev=prev[i, r]))
                for i in range(3)
                for r in range(2)
            )
            assert wire[t, b] == total
    # payload bits stay the paper's count
    np.testing.assert_array_equal(
        np.asarray(traj.payload_bits), np.asarray(channel.payload_bits(m, "paper")).sum((2, 3, 4))
    )


def test_fit_code_command_writes_a_code_the_channel_accepts(tmp_path, fast_compile):
    from sparsecomm.cli import main
    from sparsecomm.runfolder import PRETRAINED

    out = tmp_path / "code.json"
    main(["fit-code", "--run", str(PRETRAINED), "--episodes", "16", "--out", str(out)])
    cfg = ChannelConfig(code="fitted", code_file=str(out))
    code = cfg.code_obj
    assert (code.levels, code.elements, code.group) == (LEVELS, C, 5)
    assert np.asarray(code.pattern_counts).sum() > 0  # fitted to the team's busy links
    with pytest.raises(SystemExit):
        main(["fit-code", "--run", str(PRETRAINED), "--episodes", "0"])


# -- a learned code: the paper's code with symbols ranked by frequency -----


def test_frequency_remap_gives_the_most_frequent_symbols_the_shortest_codewords():
    counts = np.zeros((2, LEVELS))
    counts[0, [6, 7, 8]] = [50, 40, 30]  # symbols 7, 8, 9
    counts[1] = np.arange(LEVELS)  # symbol 15 most frequent
    remap = channel.frequency_remap(counts)
    assert remap[0][7] == 1 and remap[0][8] == 2 and remap[0][9] == 3 and remap[0][0] == 0
    assert remap[1][15] == 1 and remap[1][14] == 2 and remap[1][1] == LEVELS
    code = channel.Code("paper", LEVELS, remap)
    m = np.array([[7, 0], [9, 1]])
    # codewords 1 and 2 take 1 bit, 3 takes 2, 15 takes 4
    np.testing.assert_array_equal(np.asarray(channel.payload_bits(m, code)), [[1, 0], [2, 4]])
    with pytest.raises(ValueError, match=r"Code.remap\[0\] must be a permutation"):
        channel.Code("paper", LEVELS, ((1, 0, *range(2, LEVELS + 1)),))
    with pytest.raises(ValueError, match="for the paper code only"):
        channel.Code("fixed", LEVELS, remap)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, LEVELS), min_size=C, max_size=C), st.integers(0, 2**31))
def test_remapped_code_round_trips_and_counts_its_packets(m, seed):
    rng = np.random.default_rng(seed)
    code = channel.Code("paper", LEVELS, channel.frequency_remap(rng.random((C, LEVELS))))
    packet = channel.encode(m, code)
    assert 8 * len(packet) == int(channel.wire_bits(np.array(m), code))
    np.testing.assert_array_equal(channel.decode(packet, code, (C,)), m)


def test_expected_bits_is_the_mean_codeword_length_under_the_dither_and_its_slope():
    rng = np.random.default_rng(0)
    code = channel.Code("paper", LEVELS, channel.frequency_remap(rng.random((C, LEVELS))))
    lengths = code.lengths()
    z = jax.random.uniform(jax.random.key(1), (C,))
    draws = 40_000
    m, _ = jax.vmap(lambda k: channel.quantize(k, z, LEVELS))(
        jax.random.split(jax.random.key(2), draws)
    )
    mc = np.asarray(channel.payload_bits(m, code), np.float64)
    exact = np.asarray(channel.expected_bits(z, LEVELS, lengths))
    se = mc.std(0) / np.sqrt(draws) + 1e-9
    assert np.all(np.abs(mc.mean(0) - exact) < 5 * se + 1e-6), (mc.mean(0), exact)
    grad = np.asarray(jax.grad(lambda z: channel.expected_bits(z, LEVELS, lengths).sum())(z))
    lo = np.floor(LEVELS * np.asarray(z)).astype(int)
    k = np.arange(C)
    np.testing.assert_allclose(grad, LEVELS * (lengths[k, lo + 1] - lengths[k, lo]), atol=1e-4)
    # for the paper's own code, log2(levels z + 1) bounds it from above
    paper = np.tile(np.floor(np.log2(np.arange(LEVELS + 1) + 1)), (C, 1))
    bound = np.asarray(channel.bit_penalty(z, LEVELS))
    assert np.all(np.asarray(channel.expected_bits(z, LEVELS, paper)) <= bound + 1e-6)


def test_remapped_channel_prices_and_counts_the_remapped_lengths(code, tmp_path):
    path = tmp_path / "code.json"
    path.write_text(code.to_json())
    cfg = ChannelConfig(code="remapped", code_file=str(path))
    learned = cfg.code_obj
    counts = np.asarray(code.symbol_counts).sum(1)
    assert learned.remap == channel.frequency_remap(counts)
    z = jax.random.uniform(jax.random.key(0), (4, 3, 2, C))
    u = channel.dither(jax.random.key(1), z.shape)
    sent = channel.transmit(cfg, z, u)
    m = np.asarray(sent.symbols)
    np.testing.assert_array_equal(
        np.asarray(sent.payload_bits).sum((1, 2)),
        np.asarray(channel.payload_bits(m, learned)).sum((1, 2, 3)),
    )
    expected = np.asarray(channel.expected_bits(z, 15, learned.lengths())).sum((1, 2, 3))
    np.testing.assert_allclose(np.asarray(sent.penalty).sum((1, 2)), expected, rtol=1e-5)
    assert cfg.max_bits_per_step(3) == ChannelConfig().max_bits_per_step(3)


def test_training_can_start_from_another_runs_parameters(tmp_path, fast_compile):
    from sparsecomm.errors import RunError
    from sparsecomm.experiment import Train, train
    from sparsecomm.runfolder import learner_for, load_params
    from sparsecomm.sweep import SweepSpec, run_sweep

    tiny = RLConfig(env=NavConfig(num_agents=3, max_steps=8), num_envs=4, num_updates=2)
    quiet = dict(chunk=1, tensorboard=False, eval_episodes=4, gif=False, progress=False)
    train(Train(config=tiny, out=tmp_path / "a", **quiet))
    first = load_params(tmp_path / "a")
    again = dataclasses.replace(tiny, num_updates=0)
    sweep = run_sweep(
        learner_for(again), SweepSpec(2, (0.0,), (None,)), tmp_path / "b", progress=False,
        tensorboard=False, start_params=first, start_from="a:0",
    )  # fmt: skip
    for i in range(2):  # every run of the new sweep starts from run 0 of the old one
        run = jax.tree.map(lambda x, i=i: np.asarray(x[i]), sweep.state.params)
        jax.tree.map(np.testing.assert_array_equal, run, first)
    other = dataclasses.replace(again, agent=dataclasses.replace(again.agent, hidden=8))
    with pytest.raises(RunError, match="actor network has other shapes"):
        train(Train(config=other, out=tmp_path / "c", init_from=tmp_path / "a", **quiet))
