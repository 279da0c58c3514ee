"""The permuted symbol channel (Freed et al., AAAI 2020): corruption independent of the message,
its rate and gradient scale, the host codec, and the channel in a rollout."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from sparsecomm import channel
from sparsecomm.channel import ChannelConfig, NoiseConfig, permuted
from sparsecomm.channel.noise import flip_bits

N = 400_000  # symbols per statistical test


def _sent_and_received(levels, p01, p10, permute=True, seed=0, law=False):
    """Uniform symbols through the bit-level mechanism (``simulate``) or its law (``corrupt``)."""
    k_m, k_c = jax.random.split(jax.random.PRNGKey(seed))
    m = jax.random.randint(k_m, (N,), 0, levels + 1)
    if law:
        r = permuted.corrupt(k_c, m, levels, p01, p10)
    else:
        r = permuted.simulate(k_c, m, levels, p01, p10, permute=permute)
    return np.asarray(m), np.asarray(r)


def _error_by_symbol_p(m, r, levels):
    """p-value of the chi-square test that the error rate is the same for every sent symbol."""
    table = np.array(
        [[np.sum((m == s) & (r == s)), np.sum((m == s) & (r != s))] for s in range(levels + 1)]
    )
    return stats.chi2_contingency(table)[1]


@pytest.mark.parametrize("levels", [15, 14])
def test_error_is_independent_of_the_message(levels):
    # AAAI 2020's asymmetric flips: 0 -> 1 at 0.1, 1 -> 0 at 0.05
    m, r = _sent_and_received(levels, 0.1, 0.05)
    assert _error_by_symbol_p(m, r, levels) > 1e-3
    eps = permuted.symbol_error_rate(levels, 0.1, 0.05)
    assert abs((r != m).mean() - eps) < 5 * np.sqrt(eps * (1 - eps) / N)
    # given an error, every other symbol is equally likely: the offset r - m is uniform
    wrong = r != m
    offsets = np.bincount((r[wrong] - m[wrong]) % (levels + 1), minlength=levels + 1)[1:]
    assert stats.chisquare(offsets).pvalue > 1e-3


@pytest.mark.parametrize("levels", [15, 14])
def test_the_rollouts_sampler_draws_the_mechanisms_law(levels):
    a = _sent_and_received(levels, 0.1, 0.05, seed=1)
    b = _sent_and_received(levels, 0.1, 0.05, seed=2, law=True)
    n = levels + 1
    tables = [np.bincount(m * n + (r - m) % n, minlength=n * n) for m, r in (a, b)]
    assert stats.chi2_contingency(np.array(tables))[1] > 1e-3  # same joint law of (m, offset)
    eps = permuted.symbol_error_rate(levels, 0.1, 0.05)
    assert abs((b[1] != b[0]).mean() - eps) < 5 * np.sqrt(eps * (1 - eps) / N)


def test_without_the_permutation_the_error_depends_on_the_message():
    m, r = _sent_and_received(15, 0.1, 0.05, permute=False)
    assert _error_by_symbol_p(m, r, 15) < 1e-12
    # 0000 has four bits that flip at 0.1, 1111 four at 0.05
    assert (r != m)[m == 0].mean() > (r != m)[m == 15].mean() + 0.1


def test_gradient_scale_is_the_slope_of_the_expected_symbol():
    m, r = _sent_and_received(15, 0.05, 0.05, seed=3)
    slope = np.polyfit(m, r, 1)[0]
    alpha = permuted.gradient_scale(15, NoiseConfig(flip=0.05))
    assert abs(slope - alpha) < 0.01
    assert permuted.gradient_scale(15, NoiseConfig()) == 1.0


def test_host_codec_round_trips_and_never_crashes():
    rng = np.random.default_rng(0)
    key = jax.random.PRNGKey(5)
    for levels, c in [(15, 10), (14, 7), (1, 3)]:
        size = permuted.packet_bits(c, levels) // 8
        for _ in range(20):
            m = rng.integers(0, levels + 1, c)
            packet = permuted.encode(m, key, levels)
            assert len(packet) == size
            np.testing.assert_array_equal(permuted.decode(packet, key, levels, c), m)
        for _ in range(200):  # any bytes of the right length decode to valid symbols
            got = permuted.decode(rng.bytes(size), key, levels, c)
            assert got.shape == (c,) and got.min() >= 0 and got.max() <= levels
        for n in (0, size - 1, size + 1):
            with pytest.raises(channel.PacketError):
                permuted.decode(rng.bytes(n), key, levels, c)
    with pytest.raises(ValueError, match="symbols must lie"):
        permuted.encode(np.array([16]), key, 15)


def test_host_flips_corrupt_symbols_at_the_predicted_rate():
    # real bytes through the host's bit flips: the same law as under jit
    rng = np.random.default_rng(1)
    p, c, errors, total = 0.05, 10, 0, 0
    for i in range(1500):
        key = jax.random.PRNGKey(i)
        m = rng.integers(0, 16, c)
        got = permuted.decode(flip_bits(permuted.encode(m, key, 15), rng, p, p), key, 15, c)
        errors, total = errors + int((got != m).sum()), total + c
    eps = permuted.symbol_error_rate(15, p, p)
    assert abs(errors / total - eps) < 5 * np.sqrt(eps * (1 - eps) / total)


def test_config_refuses_what_the_channel_cannot_do():
    with pytest.raises(ValueError, match="ChannelConfig.ecc"):
        ChannelConfig(code="permuted", ecc="hamming74")
    with pytest.raises(ValueError, match="ChannelConfig.code"):
        ChannelConfig(code="permuted", mode="continuous")


def test_the_rollout_wire_corrupts_symbols_and_passes_alpha():
    noise = NoiseConfig(flip=0.05)
    cfg = ChannelConfig(code="permuted", noise=noise)
    b, k, c = 512, 3, cfg.num_elements
    key = jax.random.PRNGKey(0)
    z = jax.random.uniform(key, (b, k, k - 1, c))
    u = channel.dither(jax.random.PRNGKey(1), z.shape)
    wire = channel.lossy.LossyLinks(cfg, key, b, k, 1)

    def received(z):
        sent = channel.transmit(cfg, z, u)
        got, _, _, lost = wire.step(wire.step_keys[0], sent, u, wire.init)
        return got, (sent, lost)

    got, (sent, lost) = jax.jit(received)(z)
    assert float(lost.sum()) == 0  # flips lose no packet: there is no CRC to fail
    np.testing.assert_array_equal(sent.wire_bits, 40.0)  # 10 codewords of 4 bits, always sent
    r = np.rint(np.asarray(got) * cfg.levels + np.asarray(u)).astype(int)
    eps = permuted.symbol_error_rate(15, 0.05, 0.05)
    wrong = (r != np.asarray(sent.symbols)).mean()
    assert abs(wrong - eps) < 5 * np.sqrt(eps * (1 - eps) / r.size)
    grad = jax.jit(jax.grad(lambda z: received(z)[0].sum()))(z)
    np.testing.assert_allclose(grad, permuted.gradient_scale(15, noise), rtol=1e-6)


def test_clean_permuted_channel_delivers_the_paper_channel_messages():
    paper, perm = ChannelConfig(), ChannelConfig(code="permuted")
    z = jax.random.uniform(jax.random.PRNGKey(2), (4, 3, 2, 10))
    u = channel.dither(jax.random.PRNGKey(3), z.shape)
    a, b = channel.transmit(paper, z, u), channel.transmit(perm, z, u)
    for field in ("z_hat", "penalty", "payload_bits", "symbols"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(b.wire_bits.sum((-2, -1)), 6 * 40.0)
    assert dataclasses.replace(perm, noise=NoiseConfig(flip=0.01)).code_obj.name == "paper"
    assert jnp.all(a.wire_bits[a.payload_bits == 0] == 0)  # the paper code's silence is free
