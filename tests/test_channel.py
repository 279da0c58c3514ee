"""The channel of SPEC sections 1-3: quantizer statistics, gradient, penalty bound, codes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from sparsecomm import channel

LEVELS = 15


def _sample(z, seed=0, levels=LEVELS):
    key = jax.random.key(seed)
    return jax.jit(channel.quantize, static_argnums=2)(key, jnp.asarray(z, jnp.float32), levels)


def test_reconstruction_error_is_uniform_and_independent_of_z():
    n = 200_000
    z = jax.random.uniform(jax.random.key(1), (n,))
    _, z_hat = _sample(z, seed=2)
    err = np.asarray(z_hat - z, np.float64)
    half = 1 / (2 * LEVELS)
    assert err.min() >= -half - 1e-6 and err.max() <= half + 1e-6
    uniform = stats.uniform(loc=-half, scale=2 * half).cdf
    assert stats.kstest(err, uniform).pvalue > 1e-3
    # Per z bin, the error has the same uniform law (Bonferroni over 10 bins).
    bins = np.minimum((np.asarray(z) * 10).astype(int), 9)
    for b in range(10):
        assert stats.kstest(err[bins == b], uniform).pvalue > 1e-3 / 10, b
    # Zero mean and uncorrelated with z (4 standard errors).
    assert abs(err.mean()) < 4 * err.std() / np.sqrt(n)
    assert abs(np.corrcoef(err, np.asarray(z))[0, 1]) < 4 / np.sqrt(n)


def test_error_uniform_at_fixed_z_including_ends():
    for zv in (0.0, 0.37, 1.0):
        _, z_hat = _sample(jnp.full((50_000,), zv), seed=3)
        err = np.asarray(z_hat, np.float64) - np.float32(zv)
        half = 1 / (2 * LEVELS)
        assert stats.kstest(err, stats.uniform(loc=-half, scale=2 * half).cdf).pvalue > 1e-3, zv


def test_expected_symbol_is_levels_times_z():
    n = 40_000
    for i, zv in enumerate(np.linspace(0, 1, 21)):
        m, _ = _sample(jnp.full((n,), zv), seed=10 + i)
        m = np.asarray(m, np.float64)
        se = max(m.std(), 1e-9) / np.sqrt(n)
        assert abs(m.mean() - LEVELS * np.float32(zv)) <= 4 * se + 1e-6, zv
        assert m.min() >= 0 and m.max() <= LEVELS


def test_zero_signal_is_always_the_null_message():
    m, _ = _sample(jnp.zeros((100_000,)), seed=5)
    assert int(jnp.abs(m).max()) == 0
    assert int(channel.payload_bits(m).sum()) == 0


def test_gradient_is_identity():
    z = jax.random.uniform(jax.random.key(0), (7, 10))
    w = jax.random.normal(jax.random.key(1), (7, 10))
    key = jax.random.key(2)
    g = jax.grad(lambda z: jnp.sum(channel.quantize(key, z, LEVELS)[1] * w))(z)
    np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_receiver_regenerates_dither_from_shared_key():
    base = jax.random.key(42)
    z = jax.random.uniform(jax.random.key(0), (10,))
    k = channel.dither_key(base, 17, 0, 2)
    m, z_hat = channel.quantize(k, z, LEVELS)
    np.testing.assert_array_equal(channel.dequantize(k, m, LEVELS), z_hat)
    # Each of time, sender and recipient changes the dither.
    u = channel.dither(k, (10,))
    for other in (
        channel.dither_key(base, 18, 0, 2),
        channel.dither_key(base, 17, 1, 2),
        channel.dither_key(base, 17, 0, 1),
    ):
        assert not np.array_equal(channel.dither(other, (10,)), u)
    # vmap over links gives the same keys as the scalar calls.
    ks = jax.vmap(channel.dither_key, (None, None, None, 0))(base, 17, 0, jnp.arange(3))
    np.testing.assert_array_equal(channel.dither(ks[2], (10,)), u)


def test_penalty_values_and_gradient():
    z = jnp.array([0.0, 1 / 15, 1.0])
    np.testing.assert_allclose(channel.bit_penalty(z, LEVELS), [0.0, 1.0, 4.0], atol=1e-6)
    g = jax.grad(lambda z: channel.bit_penalty(z, LEVELS).sum())(z)
    np.testing.assert_allclose(g, LEVELS / ((LEVELS * z + 1) * np.log(2)), rtol=1e-6)


@pytest.mark.parametrize("levels", [1, 3, 15, 100])
def test_penalty_bounds_mean_paper_code_length(levels):
    n = 20_000
    zs = jnp.linspace(0, 1, 101)
    keys = jax.random.split(jax.random.key(levels), zs.size)
    m, _ = jax.vmap(lambda k, z: channel.quantize(k, jnp.full((n,), z), levels))(keys, zs)
    bits = np.asarray(channel.payload_bits(m), np.float64)
    mean, se = bits.mean(1), bits.std(1) / np.sqrt(n)
    bound = np.asarray(channel.bit_penalty(zs, levels))
    assert np.all(mean <= bound + 4 * se + 1e-6)


def test_bit_counts_of_known_symbols():
    m = jnp.arange(16)
    expect = [0, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3, 3, 3, 4]
    np.testing.assert_array_equal(channel.payload_bits(m, "paper"), expect)
    np.testing.assert_array_equal(channel.wire_bits(m, "paper"), 2 * np.array(expect) + 1)
    np.testing.assert_array_equal(channel.payload_bits(m, "fixed"), 4)
    np.testing.assert_array_equal(channel.wire_bits(m, channel.Code("float32")), 32)
    assert channel.Code("fixed", 16).fixed_width == 5 and channel.Code("fixed", 1).fixed_width == 1
    # jit + vmap friendly, and consistent with the bytes actually produced.
    batch = jax.random.randint(jax.random.key(0), (4, 6, 10), 0, 16)
    jitted = jax.jit(jax.vmap(lambda x: channel.wire_bits(x, "paper").sum()))(batch)
    for row, bits in zip(np.asarray(batch), np.asarray(jitted), strict=True):
        body = len(channel.encode(row, "paper", crc=False))
        assert body == -(-int(bits) // 8)


def test_paper_codewords_are_shortlex():
    # After the Elias-gamma framing (L zeros, a one), the bits are the paper's codeword.
    words = []
    for m in range(1, 8):
        bits = np.unpackbits(np.frombuffer(channel.encode([m], "paper", crc=False), np.uint8))
        length = int(channel.paper_length(m))
        words.append("".join(map(str, bits[length + 1 : 2 * length + 1])))
    assert words == ["0", "1", "00", "01", "10", "11", "000"]


symbol_arrays = st.integers(1, 1000).flatmap(
    lambda levels: st.tuples(
        st.just(levels),
        st.lists(st.integers(0, levels), min_size=0, max_size=70),
    )
)


@settings(max_examples=150, deadline=None)
@given(symbol_arrays, st.sampled_from(["paper", "fixed"]), st.booleans())
def test_symbols_round_trip_through_bytes(args, name, crc):
    levels, values = args
    m = np.array(values, np.int64)
    code = channel.Code(name, levels)
    data = channel.encode(m, code, crc=crc)
    np.testing.assert_array_equal(channel.decode(data, code, m.shape, crc=crc), m)
    assert channel.packet_bits(m, code, crc=crc) == 8 * len(data)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(allow_nan=False, width=32), max_size=30))
def test_float32_round_trip_is_bitwise(values):
    x = np.array(values, np.float32)
    out = channel.decode(channel.encode(x, "float32"), "float32", x.shape)
    np.testing.assert_array_equal(out.view(np.uint32), x.view(np.uint32))


def test_round_trip_keeps_shape():
    m = np.asarray(jax.random.randint(jax.random.key(3), (3, 2, 10), 0, 16))
    np.testing.assert_array_equal(channel.decode(channel.encode(m), "paper", m.shape), m)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.integers(0, 15), min_size=1, max_size=40),
    st.sampled_from(["paper", "fixed", "float32"]),
    st.data(),
)
def test_corrupted_or_truncated_packets_raise(values, name, data):
    m = np.array(values, np.int64)
    packet = bytearray(channel.encode(m, name))
    cut = data.draw(st.integers(0, len(packet) - 1))
    with pytest.raises(ValueError):
        channel.decode(bytes(packet[:cut]), name, m.shape)
    with pytest.raises(ValueError):
        channel.decode(bytes(packet) + b"\x00", name, m.shape)
    bit = data.draw(st.integers(0, 8 * len(packet) - 1))
    packet[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(ValueError, match="corrupted|truncated|invalid|outside|trailing"):
        channel.decode(bytes(packet), name, m.shape)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 15), min_size=1, max_size=40), st.data())
def test_truncated_packets_raise_even_without_checksum(values, data):
    m = np.array(values, np.int64)
    for name in ("paper", "fixed"):
        packet = channel.encode(m, name, crc=False)
        cut = data.draw(st.integers(0, len(packet) - 1))
        with pytest.raises(ValueError, match="truncated"):
            channel.decode(packet[:cut], name, m.shape, crc=False)


@pytest.mark.parametrize("levels", [0, -3, 1.5, True, "15"])
def test_bad_levels(levels):
    with pytest.raises(ValueError, match="levels must be an integer >= 1"):
        channel.quantize(jax.random.key(0), jnp.zeros(3), levels)
    with pytest.raises(ValueError, match="levels"):
        channel.bit_penalty(jnp.zeros(3), levels)
    with pytest.raises(ValueError, match="levels"):
        channel.Code("paper", levels)


@pytest.mark.parametrize(
    "z, match",
    [
        (jnp.zeros((0,)), "non-empty"),
        (jnp.array([0.5, jnp.nan]), "finite"),
        (jnp.array([0.5, jnp.inf]), "finite"),
        (jnp.array([-0.1, 0.5]), r"\[0, 1\]"),
        (jnp.array([1.1]), r"\[0, 1\]"),
    ],
)
def test_bad_signal(z, match):
    with pytest.raises(ValueError, match="z must .*" + match):
        channel.quantize(jax.random.key(0), z, LEVELS)
    with pytest.raises(ValueError, match="z must"):
        channel.bit_penalty(z, LEVELS)


def test_bad_code_and_symbols():
    with pytest.raises(ValueError, match="code must be one of"):
        channel.encode([1, 2], "huffmann")
    with pytest.raises(ValueError, match=r"m must hold symbols in \[0, 15\]"):
        channel.encode([0, 16], "paper")
    with pytest.raises(ValueError, match=r"m must hold symbols in \[0, 15\]"):
        channel.encode([-1], "fixed")
    with pytest.raises(ValueError, match="integer symbols"):
        channel.encode([0.5], "paper")
    with pytest.raises(ValueError, match=r"m must hold symbols in \[0, 15\]"):
        channel.dequantize(jax.random.key(0), jnp.array([16]), LEVELS)
    with pytest.raises(ValueError, match="data must be bytes"):
        channel.decode("abc", "paper", (1,))


def test_inside_jit_out_of_range_z_is_clipped_not_checked():
    quantize = jax.jit(channel.quantize, static_argnums=2)
    m, _ = quantize(jax.random.key(0), jnp.array([-2.0, 3.0]), 15)
    np.testing.assert_array_equal(m, [0, 15])
