"""The channel of SPEC sections 1-3: quantizer statistics, gradient, penalty bound, codes and
wire format."""

import hashlib
import itertools
import math
import zlib

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
    np.testing.assert_array_equal(channel.payload_bits(m, "fixed"), 4)
    np.testing.assert_array_equal(channel.payload_bits(m, channel.Code("float32")), 32)
    assert channel.Code("fixed", 16).fixed_width == 5 and channel.Code("fixed", 1).fixed_width == 1
    # Wire bits of 16 one-element links: symbol 0 sends nothing; otherwise a 1-bit bitmap and
    # the codeword (paper 2 L bits: 2, 4, 6 or 8; fixed 4 bits), padded to a byte, + CRC-32.
    one = m[:, None]
    np.testing.assert_array_equal(channel.wire_bits(one, "paper"), [0] + [8 + 32] * 14 + [16 + 32])
    np.testing.assert_array_equal(channel.wire_bits(one, "fixed"), [0] + [8 + 32] * 15)
    np.testing.assert_array_equal(channel.wire_bits(one, "paper", crc=False), [0] + [8] * 14 + [16])
    # One link of the 16 elements: 16-bit bitmap + 2 * 38 codeword bits = 92 -> 12 bytes + CRC;
    # float32: 2 bitmap bytes, 15 floats (0.0 is null) of 4 bytes, + CRC.
    assert int(channel.wire_bits(m, "paper")) == 8 * 12 + 32 == 8 * len(channel.encode(m))
    assert int(channel.wire_bits(m, "fixed")) == 8 * 10 + 32 == 8 * len(channel.encode(m, "fixed"))
    floats = m.astype(jnp.float32)
    assert int(channel.wire_bits(floats, "float32")) == 8 * (2 + 60 + 4)
    assert 8 * len(channel.encode(floats, "float32")) == 8 * (2 + 60 + 4)
    # A scalar is a link of one element.
    assert int(channel.wire_bits(jnp.int32(3), "paper")) == 40 and channel.wire_bits(0) == 0


def test_paper_codewords_are_shortlex():
    # After the presence bit and the length in unary (L - 1 zeros, a one): the paper codeword.
    words = []
    for m in range(1, 8):
        bits = np.unpackbits(np.frombuffer(channel.encode([m], "paper", crc=False), np.uint8))
        length = int(channel.paper_length(m))
        assert bits[0] == 1 and not bits[1:length].any() and bits[length] == 1
        words.append("".join(map(str, bits[length + 1 : 2 * length + 1])))
    assert words == ["0", "1", "00", "01", "10", "11", "000"]


def _links(rng, shape, code: channel.Code, null_share=None):
    """Random links (last axis C) with a random share of null elements per link; some links all
    null."""
    share = rng.random((*shape[:-1], 1)) if null_share is None else null_share
    present = rng.random(shape) >= share
    if code.name == "float32":
        values = rng.standard_normal(shape).astype(np.float32)
        values[values == 0] = 1.0
        return np.where(present, values, np.float32(0.0))
    return np.where(present, rng.integers(1, code.levels + 1, shape), 0)


@pytest.mark.parametrize("name", channel.CODE_NAMES)
@pytest.mark.parametrize("levels", [1, 15, 1000])
def test_round_trips_are_exact_including_silent_links(name, levels):
    rng = np.random.default_rng(levels)
    code = channel.Code(name, levels)
    links = _links(rng, (400, 10), code)
    links[:40] = 0  # all-null links
    links[40:60] = _links(rng, (20, 10), code, null_share=0.0)  # no null element
    for link in links:
        packet = channel.encode(link, code)
        assert (packet == b"") == (not link.any())
        out = channel.decode(packet, code, link.shape)
        assert out.shape == link.shape
        np.testing.assert_array_equal(
            out.view(np.uint32) if name == "float32" else out,
            (link.view(np.uint32) if name == "float32" else link),
        )


@pytest.mark.parametrize("name", channel.CODE_NAMES)
def test_silence_is_free(name):
    code = channel.Code(name)
    zeros = np.zeros((3, 10), np.float32 if name == "float32" else np.int64)
    assert channel.encode(zeros[0], code) == b"" and channel.packet_bits(zeros, code) == 0
    np.testing.assert_array_equal(channel.wire_bits(zeros, code), [0, 0, 0])
    np.testing.assert_array_equal(jax.jit(lambda m: channel.wire_bits(m, code))(zeros), 0)
    out = channel.decode(b"", code, (3, 10))
    assert out.shape == (3, 10) and out.dtype == zeros.dtype and not out.any()
    # -0.0 is not the null float: its bits are sent (the round trip is bitwise).
    if name == "float32":
        neg = np.array([0.0, -0.0], np.float32)
        packet = channel.encode(neg, code)
        assert 8 * len(packet) == int(channel.wire_bits(neg, code)) == 8 * (1 + 4 + 4)
        np.testing.assert_array_equal(
            channel.decode(packet, code, (2,)).view(np.uint32), [0, 1 << 31]
        )


@pytest.mark.parametrize("name", channel.CODE_NAMES)
@pytest.mark.parametrize("crc", [True, False])
def test_wire_bits_are_the_packet_sizes(name, crc):
    """jnp (under jit, vmap) against the bytes encode writes, link by link, many nulls."""
    rng = np.random.default_rng(7)
    code = channel.Code(name)
    for c in (1, 7, 8, 10, 17):
        m = _links(rng, (6, 3, 2, c), code)
        m[rng.random(m.shape) < 0.5] = 0  # many nulls
        bits = jax.jit(jax.vmap(lambda x: channel.wire_bits(x, code, crc=crc)))(jnp.asarray(m))
        assert bits.shape == (6, 3, 2) and bits.dtype == jnp.int32
        sizes = [
            [[8 * len(channel.encode(link, code, crc=crc)) for link in r] for r in b] for b in m
        ]
        np.testing.assert_array_equal(bits, sizes)


@pytest.mark.parametrize("mode", ["discrete", "continuous"])
def test_transmit_counts_every_senders_frame(mode):
    cfg = channel.ChannelConfig(mode=mode, num_elements=10)
    b, k = 4, 3
    z = jax.random.uniform(jax.random.key(0), (b, k, k - 1, 10))
    z = jnp.where(jax.random.uniform(jax.random.key(1), z.shape) < 0.8, 0.0, z)  # sparse
    z = z.at[0, 0, 0].set(0.0)  # one silent link
    keys = jax.random.split(jax.random.key(2), b)
    u = channel.link_dither(cfg, keys, 1, k)
    sent = channel.transmit(cfg, z, None if u is None else u[0], keys, 0)
    if mode == "discrete":
        m = np.asarray(channel.quantize_dithered(z, u[0], cfg.levels)[0])
        assert not m[0, 0, 0].any() and (m == 0).mean() > 0.5
    else:
        m = np.asarray(z)
    frames = [[channel.encode_sender(cfg, row, row) for row in ep] for ep in m]
    sizes = [[8 * len(f) for f in ep] for ep in frames]
    np.testing.assert_array_equal(sent.wire_bits.sum(-1), sizes)
    # each speaking link's datagram carries its sender's whole frame; a silent one nothing
    speaking = np.asarray(sent.wire_bits) > 0
    assert not speaking[0, 0, 0] and speaking.mean() > 0.5
    np.testing.assert_array_equal(
        sent.frame_bits, np.where(speaking, np.asarray(sent.wire_bits).sum(-1, keepdims=True), 0)
    )
    for ep, row in zip(frames, m, strict=True):  # and the frames decode to what was sent
        for f, links in zip(ep, row, strict=True):
            np.testing.assert_array_equal(channel.decode_sender(cfg, f, k - 1), links)


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
    assert int(channel.wire_bits(m, code, crc=crc)) == 8 * len(data)


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
    m[data.draw(st.integers(0, m.size - 1))] = data.draw(st.integers(1, 15))  # not silent
    packet = bytearray(channel.encode(m, name))
    cut = data.draw(st.integers(1, len(packet) - 1))
    with pytest.raises(channel.PacketError, match="truncated|corrupted"):
        channel.decode(bytes(packet[:cut]), name, m.shape)
    with pytest.raises(channel.PacketError, match="corrupted"):
        channel.decode(bytes(packet) + b"\x00", name, m.shape)
    with pytest.raises(channel.PacketError):
        channel.decode(bytes(packet) + bytes(packet), name, m.shape)
    with pytest.raises(channel.PacketError, match="corrupted"):  # another agreed size
        channel.decode(bytes(packet), name, (m.size + 1,))
    bit = data.draw(st.integers(0, 8 * len(packet) - 1))
    packet[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(channel.PacketError, match="corrupted"):
        channel.decode(bytes(packet), name, m.shape)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 15), min_size=1, max_size=40), st.data())
def test_truncated_or_extended_packets_raise_even_without_checksum(values, data):
    m = np.array(values, np.int64)
    m[-1] = 15  # not silent; the last byte holds codeword bits
    for name in ("paper", "fixed", "float32"):
        packet = channel.encode(m, name, crc=False)
        cut = data.draw(st.integers(1, len(packet) - 1)) if len(packet) > 1 else 0
        if cut:
            with pytest.raises(channel.PacketError, match="truncated"):
                channel.decode(packet[:cut], name, m.shape, crc=False)
        with pytest.raises(channel.PacketError, match="trailing|too long"):
            channel.decode(packet + b"\x00", name, m.shape, crc=False)


@pytest.mark.parametrize("name", channel.CODE_NAMES)
@pytest.mark.parametrize(
    "shape", [(10**12,), (2**31, 2**31), (channel.MAX_ELEMENTS + 1,), (10**6,), "just over"]
)
def test_huge_claimed_shape_is_a_clean_error_without_allocating(name, shape):
    import tracemalloc

    packet = channel.encode(np.arange(10) % 3, name)
    if shape == "just over":  # one element more than the packet's bits could flag present
        shape = (8 * len(packet) + 1,)
    tracemalloc.start()
    try:
        for data in (packet, b""):
            if data == b"" and math.prod(shape) <= channel.MAX_ELEMENTS:
                continue  # silence: all zeros, of a shape it may allocate
            with pytest.raises(channel.PacketError, match="claimed shape|corrupted"):
                channel.decode(data, name, shape)
            with pytest.raises(channel.PacketError, match="claimed shape"):
                channel.decode(data, name, shape, crc=False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20


@pytest.mark.parametrize("shape", [(-1,), (2, -3), "ab", 1.5, [[1, 2]], None])
def test_bad_shapes_raise_packet_error(shape):
    with pytest.raises(channel.PacketError, match="shape"):
        channel.decode(b"", "paper", shape)


@settings(max_examples=300, deadline=None)
def _spec_identity(code: channel.Code) -> bytes:
    """A code's identity as the format says (written here from the spec, not from the module):
    the name's length and the name, ``n`` and levels in ``n`` bytes, the remap's rows (4 bytes)
    and its entries (``n`` bytes each), all big-endian."""
    n = max(1, (code.levels.bit_length() + 7) // 8)
    out = bytes([len(code.name)]) + code.name.encode() + bytes([n]) + code.levels.to_bytes(n, "big")
    out += len(code.remap).to_bytes(4, "big")
    return out + b"".join(x.to_bytes(n, "big") for row in code.remap for x in row)


def _spec_crc(code: channel.Code, count: int, body: bytes) -> bytes:
    """A packet's CRC-32 as the format says: over C (4 bytes), the fingerprint, the body."""
    header = count.to_bytes(4, "big") + hashlib.sha256(_spec_identity(code)).digest()[:4]
    return zlib.crc32(header + body).to_bytes(4, "big")


def test_code_identity_is_the_documented_layout():
    assert channel.Code("paper", 15).identity == b"\x05paper\x01\x0f\x00\x00\x00\x00"
    assert channel.Code("paper", 15).fingerprint == bytes.fromhex("ab9794b9")  # docs/channel.md
    assert channel.Code("float32", 256).identity == b"\x07float32\x02\x01\x00" + bytes(4)
    remap = ((0, 2, 1), (0, 1, 2))
    assert channel.Code("paper", 2, remap).identity == (
        b"\x05paper\x01\x02\x00\x00\x00\x02" + bytes([0, 2, 1, 0, 1, 2])
    )
    rng = np.random.default_rng(3)
    codes = [channel.Code(name, levels) for name in channel.CODE_NAMES for levels in (1, 7, 15)]
    codes += [channel.Code("paper", 300), channel.Code("fixed", 1 << 40)]
    codes += [channel.Code("paper", 15, channel.frequency_remap(rng.random((4, 15))))]
    for code in codes:
        assert code.identity == _spec_identity(code)
        assert code.fingerprint == hashlib.sha256(code.identity).digest()[:4]
        m = _links(rng, (4,), code, null_share=0.3)
        if m.any():
            packet = channel.encode(m, code)
            assert packet[-4:] == _spec_crc(code, 4, packet[:-4])
    assert len({c.identity for c in codes}) == len({c.fingerprint for c in codes}) == len(codes)


def same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype == np.float32:
        a, b = a.view(np.uint32), np.asarray(b, np.float32).view(np.uint32)
    return a.shape == b.shape and np.array_equal(a, b)


def _agreements():
    """(code, C) agreements for the mismatch test: every code at several levels, with and
    without a remap, several element counts (some whose packets have the same sizes), and a
    fitted code."""
    rng = np.random.default_rng(11)
    remap = channel.frequency_remap(rng.integers(0, 100, (10, LEVELS)))
    remap2 = channel.frequency_remap(rng.integers(0, 100, (10, LEVELS)))
    source = np.where(rng.random((40, 30, 10)) < 0.3, rng.integers(1, LEVELS + 1, (40, 30, 10)), 0)
    out = [(channel.Code(name, levels), 10) for name in channel.CODE_NAMES for levels in (7, 8, 15)]
    out += [(channel.Code("paper", LEVELS, remap), 10), (channel.Code("paper", LEVELS, remap2), 10)]
    out += [(channel.Code(name, LEVELS), c) for name in channel.CODE_NAMES for c in (9, 12)]
    out += [(channel.Code("paper", 1), 10), (channel.Code("fixed", 1), 10)]
    out += [(channel.fit(source, levels=LEVELS), 10)]
    return out


def test_a_receiver_with_another_agreement_refuses_every_packet():
    """Every ordered pair of distinct agreements (code, C): packets of random valid messages
    under one, decoded under the other, are all refused (the code's fingerprint and C are in the
    CRC's implicit header), while the sender's own agreement decodes them exactly."""
    agreements = _agreements()
    assert len(set(agreements)) == len(agreements)
    rng = np.random.default_rng(12)
    silent = {}
    sizes = {}
    for i, (code, c) in enumerate(agreements):
        kind = code if isinstance(code, channel.Code) else channel.Code("paper", LEVELS)
        links = _links(rng, (120, c), kind, null_share=rng.random((120, 1)) * 0.9)
        packets = [channel.encode(m, code) for m in links if m.any()]
        for m, p in zip((m for m in links if m.any()), packets, strict=True):
            assert same_bits(channel.decode(p, code, (c,)), m)
        sizes[i] = {len(p) for p in packets}
        for j, (other, d) in enumerate(agreements):
            if j == i:
                continue
            for p in packets:
                try:
                    channel.decode(p, other, (d,))
                except channel.PacketError:
                    continue
                silent[i, j] = silent.get((i, j), 0) + 1
    assert silent == {}
    # The test means something: many pairs share packet sizes, so only the check tells them apart.
    shared = sum(bool(sizes[i] & sizes[j]) for i in sizes for j in sizes if i != j)
    assert shared > len(agreements) ** 2 // 2


@given(
    st.binary(max_size=48),
    st.sampled_from(channel.CODE_NAMES),
    st.integers(1, 300),
    st.lists(st.integers(0, 12), max_size=3),
    st.booleans(),
    st.booleans(),
)
def test_decoding_arbitrary_bytes_gives_the_shape_or_packet_error(
    data, name, levels, shape, crc, checksummed
):
    """Any bytes: a result of the claimed shape (that re-encodes to the same bytes: one packet
    per message) or PacketError, nothing else. ``checksummed`` appends a valid CRC-32 so that
    the parser behind it is exercised too."""
    code = channel.Code(name, levels)
    shape = tuple(shape)
    if crc and checksummed:
        count = int(np.prod(shape, dtype=np.int64))
        data += _spec_crc(code, count, data)
    try:
        out = channel.decode(data, code, shape, crc=crc)
    except channel.PacketError:
        return
    assert out.shape == shape
    assert channel.encode(out, code, crc=crc) == data


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
    with pytest.raises(channel.PacketError, match="data must be bytes"):
        channel.decode("abc", "paper", (1,))


def test_inside_jit_out_of_range_z_is_clipped_not_checked():
    quantize = jax.jit(channel.quantize, static_argnums=2)
    m, _ = quantize(jax.random.key(0), jnp.array([-2.0, 3.0]), 15)
    np.testing.assert_array_equal(m, [0, 15])


@pytest.mark.parametrize("name", ["paper", "fixed"])
@pytest.mark.parametrize(
    "links, check_bits, scale, gated",
    [(1, 32, 0.02, False), (1, 8, 0.08, True), (3, 16, 0.08, True), (2, 0, 1.0, False)],
)
def test_expected_frame_bits_match_the_encoders_mean_frame(name, links, check_bits, scale, gated):
    """The differentiable price of speaking is the exact mean of the real frames' bits."""
    levels, c, n = 15, 10, 4000
    code = channel.Code(name, levels)
    rng = np.random.default_rng(int(scale * 100) + links)
    z = rng.uniform(0, scale, (links, c)).astype(np.float32) * (rng.random((links, c)) < 0.6)
    g = rng.uniform(0.2, 0.9, links).astype(np.float32) if gated else None
    u = np.asarray(jax.random.uniform(jax.random.key(1), (n, links, c), minval=-0.5, maxval=0.5))
    m = np.clip(np.floor(levels * z + u + 0.5), 0, levels).astype(np.int64)
    if gated:  # a closed gate: every element null
        m *= (rng.random((n, links)) < g)[..., None]
    bits = np.array([8 * len(channel.encode_frame(f, code, check_bits=check_bits)) for f in m])
    expect = float(
        channel.expected_frame_bits(
            jnp.asarray(z), levels, code.wire_lengths(c), check_bits, None if g is None else g
        )
    )
    se = max(bits.std() / np.sqrt(n), 1e-6)
    assert abs(bits.mean() - expect) < 4 * se + 1e-4, (bits.mean(), expect, se)


def test_expected_frame_bits_equal_the_exact_sum_over_every_outcome():
    """Enumerating the 2^C symbol outcomes of one link gives the same expectation, to float
    precision, with and without a gate."""
    levels, c = 15, 6
    code = channel.Code("paper", levels)
    table = code.wire_lengths(c)
    z = np.asarray([0.01, 0.05, 0.2, 0.0, 0.6, 0.03])
    x = levels * z
    lo, f = np.floor(x).astype(int), x - np.floor(x)
    exact = 0.0
    for up in itertools.product([0, 1], repeat=c):
        p = np.prod(np.where(up, f, 1 - f))
        exact += p * 8 * len(channel.encode_frame((lo + np.asarray(up))[None], code, check_bits=16))
    got = channel.expected_frame_bits(jnp.asarray(z[None], jnp.float32), levels, table, 16)
    np.testing.assert_allclose(float(got), exact, rtol=1e-5)
    gated = channel.expected_frame_bits(jnp.asarray(z[None], jnp.float32), levels, table, 16, [0.3])
    np.testing.assert_allclose(float(gated), 0.3 * exact, rtol=1e-5)


def test_expected_frame_bits_gradient_matches_finite_differences_where_smooth():
    levels, c = 15, 4
    table = channel.Code("paper", levels).wire_lengths(c)
    z = jnp.asarray([[0.01, 0.03, 0.0, 0.05]])  # below 1 / levels: every element may be null
    f = lambda z: channel.expected_frame_bits(z, levels, table)  # noqa: E731
    grad = np.asarray(jax.grad(f)(z))[0]
    h = 1e-3
    for k in range(c):
        step = jnp.zeros((1, c)).at[0, k].set(h)
        fd = (float(f(z + step)) - float(f(jnp.maximum(z - step, 0.0)))) / (2 * h if k != 2 else h)
        assert abs(grad[k] - fd) < 1e-2 * max(1.0, abs(fd)), (k, grad[k], fd)
    assert grad.min() > 0  # speaking costs more the likelier it is
    # the cliff: once one element is surely not null, the others' chance of silence is gone
    cliff = np.asarray(jax.grad(f)(z.at[0, 0].set(0.5)))[0]
    assert cliff[1] < grad[1]
    # a gate's gradient is smooth: the frame's bits grow with the chance the link opens
    zg = jnp.asarray([[0.5, 0.3, 0.0, 0.1], [0.2, 0.0, 0.0, 0.4]])
    fg = lambda g: channel.expected_frame_bits(zg, levels, table, 8, g)  # noqa: E731
    g = jnp.asarray([0.3, 0.6])
    dg = np.asarray(jax.grad(fg)(g))
    for j in range(2):
        step = jnp.zeros(2).at[j].set(1e-3)
        fd = (float(fg(g + step)) - float(fg(g - step))) / 2e-3
        assert abs(dg[j] - fd) < 1e-2 * max(1.0, abs(fd)), (j, dg[j], fd)
    assert dg.min() > 0


@pytest.mark.parametrize("name", ["paper", "fixed"])
def test_expected_frame_bits_gradient_is_the_exact_sums(name):
    """Value and gradient against the sum over every outcome of two gated links of three
    elements (4 x 2^6 outcomes, each weighed by its probability, differentiated by JAX), where
    the written-out gradient's products meet exact zeros: steps up at exactly one half, gates
    exactly 0 and 1, links sure to be null or sure to speak."""
    levels, c = 16, 3  # 16 z = 0.5 exactly for z = 1/32
    code = channel.Code(name, levels)
    table = code.wire_lengths(c)
    z = jnp.asarray(
        [
            [[1 / 32, 1 / 32, 3 / 32], [0.0, 0.2, 1 / 32]],
            [[1 / 32, 1 / 32, 1 / 32], [0.0, 0.0, 0.0]],
            [[0.3, 0.01, 0.5], [0.07, 1 / 32, 1.0]],
        ],
        jnp.float32,
    )
    g = jnp.asarray([[1.0, 0.4], [0.0, 1.0], [0.7, 1.0]], jnp.float32)
    x = np.asarray(levels * z)
    lo = np.floor(x).astype(int)
    outcomes = list(itertools.product([0, 1], repeat=2 * c + 2))
    bits = np.zeros((len(z), len(outcomes)), np.float32)
    for i, j in itertools.product(range(len(z)), range(len(outcomes))):
        up, opens = np.reshape(outcomes[j][: 2 * c], (2, c)), np.asarray(outcomes[j][2 * c :])
        m = np.minimum(lo[i] + up, levels) * opens[:, None]
        bits[i, j] = 8 * len(channel.encode_frame(m, code, check_bits=8))
    pick = jnp.asarray(outcomes, jnp.float32)  # (outcomes, 2 C + 2)

    def exact(z, g):
        f = (levels * z - lo).reshape(len(z), 1, 2 * c)
        p_up = jnp.where(pick[:, : 2 * c] > 0, f, 1.0 - f).prod(-1)
        gg = g[:, None, :]
        p_open = jnp.where(pick[:, 2 * c :] > 0, gg, 1.0 - gg).prod(-1)
        return (p_up * p_open * bits).sum(-1)

    def priced(z, g):
        return channel.expected_frame_bits(z, levels, table, 8, g)

    np.testing.assert_allclose(priced(z, g), exact(z, g), rtol=1e-5, atol=1e-5)
    for argnum in (0, 1):
        want = jax.grad(lambda *a: exact(*a).sum(), argnum)(z, g)
        got = jax.grad(lambda *a: priced(*a).sum(), argnum)(z, g)
        assert np.isfinite(np.asarray(got)).all()
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


def test_a_link_gate_opens_with_its_probability_and_a_closed_link_sends_nothing():
    cfg = channel.ChannelConfig(link_gate=True, prices="wire")
    b, k, c = 2000, 3, cfg.num_elements
    z = jax.random.uniform(jax.random.key(0), (b, k, k - 1, c + 1))
    g = jnp.asarray([0.1, 0.5, 0.9])[None, :, None]  # sender i's gate, on both its links
    z = z.at[..., -1].set(jnp.broadcast_to(g, (b, k, k - 1)))
    u = channel.dither(jax.random.key(1), z.shape)
    sent = channel.transmit(cfg, z, u)
    opened = np.asarray(sent.speak) > 0
    for i, p in enumerate([0.1, 0.5, 0.9]):
        rate = opened[:, i].mean()
        assert abs(rate - p) < 4 * np.sqrt(p * (1 - p) / opened[:, i].size), (i, rate)
    closed = ~opened
    assert not np.asarray(sent.symbols)[closed].any()  # every element null
    assert (
        not np.asarray(sent.wire_bits)[closed].any()
        and not np.asarray(sent.payload_bits)[closed].any()
    )
    # the penalty is each sender's expected frame bits given its gates, shared by its links
    table = cfg.code_obj.wire_lengths(c)

    def frame(z):
        return channel.expected_frame_bits(z[..., :-1], cfg.levels, table, 32, z[..., -1])

    np.testing.assert_allclose(sent.penalty.sum(-1), frame(z), rtol=1e-5)
    np.testing.assert_allclose(sent.penalty[..., 0], sent.penalty[..., 1], rtol=1e-6)
    grad = jax.grad(lambda z: channel.transmit(cfg, z, u).penalty.sum())(z)
    np.testing.assert_allclose(grad, jax.grad(lambda z: frame(z).sum())(z), rtol=1e-5)
    assert float(grad[..., -1].min()) > 0  # opening a gate always costs
    # straight-through: what a receiver reads moves with the gate by the message it would carry
    null = -u[..., :-1] / cfg.levels
    got = channel.receive(cfg, sent.z_hat, u, speak=sent.speak).z_hat
    np.testing.assert_allclose(np.asarray(got)[closed], np.asarray(null)[closed], atol=1e-7)
    np.testing.assert_allclose(np.asarray(got)[opened], np.asarray(sent.z_hat)[opened], atol=1e-7)
    d = jax.grad(lambda g: channel.receive(cfg, sent.z_hat, u, speak=sent.speak + g).z_hat.sum())(
        jnp.zeros_like(sent.speak)
    )
    np.testing.assert_allclose(d, (sent.z_hat - null).sum(-1), rtol=1e-4, atol=1e-5)


def test_a_held_link_delivers_its_last_message_and_says_it_is_not_news():
    cfg = channel.ChannelConfig(on_silence="hold", num_elements=2)
    last = jnp.asarray([[0.3, 0.4], [0.0, 0.0], [0.7, 0.1]])
    m = jnp.asarray([[5, 6], [0, 0], [2, 0]], jnp.int32)
    u = jnp.full((3, 2), 0.25)
    silent = jnp.asarray([False, True, False])
    ok = jnp.asarray([True, True, False])  # link 2's packet lost: held too, not news
    got = channel.receive(cfg, m, u, ok=ok, last=last, silent=silent)
    np.testing.assert_allclose(got.z_hat[0], (m[0] - 0.25) / 15, rtol=1e-6)
    np.testing.assert_array_equal(got.z_hat[1:], last[1:])
    np.testing.assert_array_equal(got.news, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(got.last[1:], last[1:])
    np.testing.assert_allclose(got.last[0], got.z_hat[0])
    with pytest.raises(ValueError, match="last"):
        channel.receive(cfg, m, u, silent=silent)
    # and the paper's rule: a silent link is the null message, always news
    paper = channel.ChannelConfig(num_elements=2)
    assert channel.receive(paper, m, u, silent=silent).news is None


def test_a_link_with_news_opens_its_gate():
    """``news_margin``: the gate is ``max(g, clip((d - m) / m, 0, 1))``, ``d`` the largest gap
    between what the link would say and what its recipient holds; the gradient of the news
    reaches the signal, never the held message."""
    cfg = channel.ChannelConfig(link_gate=True, on_silence="hold", num_elements=2, news_margin=0.1)
    held = jnp.asarray([[0.5, 0.5]] * 4)
    z = jnp.asarray(
        [[0.5, 0.5, 0.3], [0.55, 0.5, 0.3], [0.5, 0.65, 0.3], [0.9, 0.1, 0.0]]
    )  # gaps 0, 0.05, 0.15, 0.4
    out = channel.news_gate(cfg, z, held)
    np.testing.assert_allclose(out[:, -1], [0.3, 0.3, 0.5, 1.0], rtol=1e-6)
    np.testing.assert_array_equal(out[:, :-1], z[:, :-1])  # the message itself is untouched
    assert channel.news_gate(channel.ChannelConfig(link_gate=True), z, held) is z
    grad_z, grad_held = jax.grad(
        lambda z, h: channel.news_gate(cfg, z, h)[:, -1].sum(), argnums=(0, 1)
    )(z, held)
    np.testing.assert_allclose(grad_z[2], [0.0, 10.0, 0.0], rtol=1e-5)  # (d - m) / m: 1 / m
    np.testing.assert_array_equal(grad_z[0], [0.0, 0.0, 1.0])  # the head's gate decides
    assert not np.asarray(grad_held).any()
    for bad in (
        {"news_margin": 0.1},  # no gate, no hold
        {"news_margin": 0.1, "link_gate": True},  # no hold
        {"news_margin": 0.0, "link_gate": True, "on_silence": "hold"},
        {"news_margin": 1.5, "link_gate": True, "on_silence": "hold"},
    ):
        with pytest.raises(ValueError, match="ChannelConfig.news_margin"):
            channel.ChannelConfig(**bad)


def test_in_a_rollout_every_link_with_news_speaks():
    """An untrained team (gates open half the time) on the small task: with ``news_margin``
    every link speaks at the first step, where its recipient holds nothing and its signal is
    news; without it about half do, and with it fewer speak later than at the first step."""
    import dataclasses

    from sparsecomm.configs import PRESETS
    from sparsecomm.learner import make_team
    from sparsecomm.rollout import rollout

    config = PRESETS["silent"]["train"]
    speaking = {}
    for margin in (None, 0.1):
        cfg = dataclasses.replace(config.channel, news_margin=margin)
        env, team = make_team(dataclasses.replace(config, channel=cfg))
        params = team.init(jax.random.key(0))["actor"]
        traj = rollout(team, env, cfg, params, jax.random.key(1), 200)
        steps = np.asarray(traj.valid)
        speaking[margin] = (
            np.asarray(traj.speaking)[0].mean() / 2,
            (np.asarray(traj.speaking)[1:][steps[1:]].mean() / 2),
        )
    first, later = speaking[0.1]
    assert first == 1.0 and speaking[None][0] < 0.7  # gates open half the time, news always
    assert later < first


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("prices", "bytes", "ChannelConfig.prices"),
        ("on_silence", "repeat", "ChannelConfig.on_silence"),
        ("link_gate", 1, "ChannelConfig.link_gate"),
    ],
)
def test_bad_silence_and_price_fields_are_refused_by_name(field, value, match):
    with pytest.raises(ValueError, match=match):
        channel.ChannelConfig(**{field: value})


def test_wire_prices_and_gates_need_the_discrete_channel():
    with pytest.raises(ValueError, match="ChannelConfig.prices"):
        channel.ChannelConfig(mode="continuous", prices="wire")
    with pytest.raises(ValueError, match="ChannelConfig.prices"):
        channel.ChannelConfig(prices="wire", ecc="hamming74")
    with pytest.raises(ValueError, match="ChannelConfig.link_gate"):
        channel.ChannelConfig(mode="reinforced", link_gate=True)
    with pytest.raises(ValueError, match="ChannelConfig.on_silence"):
        channel.ChannelConfig(on_silence="hold", noise=channel.NoiseConfig(delay=1))
    assert channel.ChannelConfig(on_silence="hold").deployable
    wire = channel.ChannelConfig(prices="wire")
    assert wire.counted_metric == "wire_bits_per_step"
    loudest = np.full((2, 10), 15)  # both links of a sender, every element's longest codeword
    assert wire.max_bits_per_step(3) == 3 * 8 * len(channel.encode_frame(loudest, "paper"))


def test_a_senders_wire_price_is_shared_by_the_links_that_exist():
    cfg = channel.ChannelConfig(prices="wire", link_gate=True)
    z = jax.random.uniform(jax.random.key(3), (5, 4, 3, cfg.signal_elements))
    live = jax.random.uniform(jax.random.key(4), (5, 4, 3)) < 0.6
    u = channel.dither(jax.random.key(5), z.shape)
    sent = channel.transmit(cfg, z, u, live=live)
    zl = jnp.where(live[..., None], z, 0.0)
    table = cfg.code_obj.wire_lengths(cfg.num_elements)
    frame = channel.expected_frame_bits(zl[..., :-1], cfg.levels, table, 32, zl[..., -1])
    np.testing.assert_allclose(sent.penalty.sum(-1), frame, rtol=1e-5, atol=1e-6)
    assert not np.asarray(sent.penalty)[~np.asarray(live)].any()
    count = np.maximum(np.asarray(live).sum(-1, keepdims=True), 1)
    share = np.where(np.asarray(live), np.asarray(frame)[..., None] / count, 0.0)
    np.testing.assert_allclose(sent.penalty, share, rtol=1e-5, atol=1e-6)
