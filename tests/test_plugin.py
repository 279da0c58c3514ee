"""The plug-in layer (``sparsecomm/channel/layer.py``) and its tutorial (docs/plugin.md).

``python tests/test_plugin.py`` runs the tutorial in the repository root: it prints the table of
docs/plugin.md and rewrites ``docs/results/plugin/plugin.png``.
"""

import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm import channel

DOC = Path(__file__).resolve().parent.parent / "docs" / "plugin.md"
K, C, LEVELS = 4, 3, 15
RING = channel.Routing.from_neighbours([[1], [2], [3], [0]])  # 0 -> 1 -> 2 -> 3 -> 0
SPARSE = channel.Routing.from_neighbours([[1, 2], [0], [], [0, 2]])  # agent 2 says nothing


def _signals(seed=0, shape=(K, K, C)):
    return jax.random.uniform(jax.random.key(seed), shape)


@pytest.fixture(autouse=True)
def _quick_compile(request):
    """Compile with most XLA optimisations off (conftest's ``fast_compile``), except for the
    tutorial, whose 600 training steps need them: these tests compile far more than they run."""
    if request.node.name == "test_tutorial_runs":
        yield
    else:
        request.getfixturevalue("fast_compile")
        yield


def tutorial_code() -> str:
    """The ```python blocks of docs/plugin.md, in order, as one program."""
    blocks = re.findall(r"^```python\n(.*?)^```", DOC.read_text(), flags=re.M | re.S)
    assert len(blocks) >= 5
    return "\n\n".join(blocks)


@pytest.mark.slow  # trains four small teams: a learning test (CI runs the slow set too)
def test_tutorial_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the figure goes to tmp_path/docs/results/plugin
    scope = {"__name__": "plugin_tutorial"}
    exec(compile(tutorial_code(), str(DOC), "exec"), scope)
    results = scope["results"]
    assert results[0.0]["accuracy"] > 0.99
    assert results[0.01]["accuracy"] > 0.99
    bits = [results[lam]["payload bits"] for lam in (0.0, 0.003, 0.01, 0.03)]
    assert bits == sorted(bits, reverse=True)  # bits fall as a bit's price rises
    assert (tmp_path / "docs/results/plugin/plugin.png").stat().st_size > 0


@pytest.mark.parametrize("routing", [RING, SPARSE, channel.Routing.all_to_all(K)])
def test_each_link_is_channel_quantize_exactly(routing):
    key, t, z = jax.random.key(7), 11, _signals()
    msgs = channel.send(key, z, routing, t=t, levels=LEVELS)
    quantize = jax.jit(channel.quantize, static_argnums=2)  # send is one compiled program
    for i in range(K):
        for j in range(K):
            if routing.mask[i, j]:
                m, z_hat = quantize(channel.dither_key(key, t, i, j), z[i, j], LEVELS)
                eager_m, eager_z_hat = channel.quantize(
                    channel.dither_key(key, t, i, j), z[i, j], LEVELS
                )
                np.testing.assert_array_equal(msgs.symbols[i, j], eager_m)
                np.testing.assert_allclose(msgs.z_hat[i, j], eager_z_hat, rtol=1e-6)
                np.testing.assert_array_equal(msgs.symbols[i, j], m)
                np.testing.assert_array_equal(msgs.z_hat[i, j], z_hat)
                np.testing.assert_array_equal(msgs.inbox[j, i], z_hat)
                pen = channel.bit_penalty(z[i, j], LEVELS).sum()
                np.testing.assert_allclose(msgs.penalty[i, j], pen, rtol=1e-6)
                assert msgs.payload_bits[i, j] == channel.payload_bits(m).sum()
                assert (msgs.wire_bits[i, j] > 0) == bool(np.asarray(m).any())
            else:
                assert not msgs.mask[i, j]
        # a sender's links share its one frame: their wire bits add up to its bytes exactly
        row = np.asarray(msgs.symbols)[i, channel.others(K)[i]]  # (K-1, C) by recipient slot
        frame = channel.encode_frame(row, "paper")
        assert float(msgs.wire_bits[i].sum()) == 8 * len(frame)


def test_missing_links_send_nothing_and_cost_nothing():
    z = jnp.ones((K, K, C))  # the loudest signal everywhere, self-links included
    msgs = channel.send(jax.random.key(0), z, SPARSE, t=0)
    off = ~SPARSE.mask
    assert (np.asarray(msgs.symbols)[off] == 0).all()
    assert (np.asarray(msgs.z_hat)[off] == 0).all()
    assert (np.asarray(msgs.inbox).swapaxes(0, 1)[off] == 0).all()
    for field in (msgs.penalty, msgs.payload_bits, msgs.wire_bits):
        assert (np.asarray(field)[off] == 0).all()
    on = SPARSE.mask
    assert (np.asarray(msgs.symbols)[on] == LEVELS).all()  # z = 1 sends the top symbol
    assert (np.asarray(msgs.wire_bits)[on] > 0).all()
    # The entries of missing links are ignored, even outside [0, 1].
    garbage = jnp.where(jnp.asarray(off)[..., None], 7.0, z)
    again = channel.send(jax.random.key(0), garbage, SPARSE, t=0)
    np.testing.assert_array_equal(again.symbols, msgs.symbols)


@pytest.mark.parametrize("routing", [RING, SPARSE])
def test_gradients_flow_only_along_links_that_exist(routing):
    key, z = jax.random.key(1), _signals(2)
    jac = jax.jit(jax.jacrev(lambda z: channel.send(key, z, routing, t=3).inbox))(z)
    jac = np.asarray(jac)  # (recipient j, sender i, c, z's sender i', recipient j', c')
    eye = np.eye(C)
    for j in range(K):
        for i in range(K):
            block = jac[j, i]  # d inbox[j, i] / d z
            if routing.mask[i, j]:
                np.testing.assert_array_equal(block[:, i, j], eye)  # identity on its own link
                block = block.copy()
                block[:, i, j] = 0
            # d inbox[j] / d z[i]: zero where i -> j does not exist; from no other link ever.
            assert (block == 0).all(), (i, j)
    pen = jax.jit(jax.grad(lambda z: channel.send(key, z, routing, t=3).penalty.sum()))(z)
    assert (np.asarray(pen)[~routing.mask] == 0).all()
    assert (np.asarray(pen)[routing.mask] > 0).all()


def test_gradients_with_broadcast_signals():
    key, z = jax.random.key(1), _signals(3, (K, C))
    jac = jax.jit(jax.jacrev(lambda z: channel.send(key, z, SPARSE, t=0, broadcast=True).inbox))
    jac = np.asarray(jac(z))  # (j, i, c, i', c')
    for j in range(K):
        for i in range(K):
            for i2 in range(K):
                want = np.eye(C) if (i2 == i and SPARSE.mask[i, j]) else np.zeros((C, C))
                np.testing.assert_array_equal(jac[j, i, :, i2], want)


def test_receiver_loss_reaches_only_senders_it_hears_from():
    """End to end: from each receiver's loss to each sender's parameters (a gate included)."""
    key = jax.random.key(4)
    obs = jax.random.normal(jax.random.key(5), (K, 6))
    weights = 0.3 * jax.random.normal(jax.random.key(6), (K, 6, K * C))  # one head per agent

    def receiver_losses(weights):
        head = jnp.einsum("ko,kom->km", obs, weights).reshape(K, K, C)
        msgs = channel.send(key, head, RING, t=2, gate="sigmoid")
        return (msgs.inbox**2).sum((-2, -1))  # (K,) one loss per receiver

    grads = np.asarray(jax.jit(jax.jacrev(receiver_losses))(weights))  # (j, i, 6, K C)
    for j in range(K):
        for i in range(K):
            g = grads[j, i]
            if RING.mask[i, j]:
                assert np.abs(g).max() > 0
            else:
                assert (g == 0).all(), (i, j)


def _same(a, b):
    """Equal: exactly for symbols, bits and masks; floats up to rounding (XLA fuses jit and
    eager code differently)."""
    a, b = np.asarray(a), np.asarray(b)
    if np.issubdtype(a.dtype, np.floating):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    else:
        np.testing.assert_array_equal(a, b)


def test_batches_vmap_jit_and_traced_masks_agree():
    batch = (2, 3)
    z = _signals(8, (*batch, K, K, C))
    keys = jax.random.split(jax.random.key(9), 6).reshape(batch)
    t = jnp.arange(6).reshape(batch)
    batched = channel.send(keys, z, SPARSE, t=t)  # one compiled program, called eagerly
    mapped = jax.jit(jax.vmap(jax.vmap(lambda k, z, t: channel.send(k, z, SPARSE, t=t))))
    mapped = mapped(keys, z, t)
    mask = jnp.broadcast_to(jnp.asarray(SPARSE.mask), (*batch, K, K))
    traced = jax.jit(lambda k, z, t, m: channel.send(k, z, m, t=t))(keys, z, t, mask)
    one = channel.send(keys[1, 2], z[1, 2], SPARSE, t=5)
    for a, b, c in zip(batched, mapped, traced, strict=True):
        if a is None:  # news: only with ``last``
            assert b is None and c is None
            continue
        _same(a, b)
        _same(a, c)
    for a, b in zip(batched, one, strict=True):
        if a is not None:
            _same(a[1, 2], b)
    # Raw uint32 keys, and one key shared by the batch.
    raw = jax.random.key_data(keys)
    np.testing.assert_array_equal(channel.send(raw, z, SPARSE, t=t).symbols, batched.symbols)
    shared = channel.send(keys[0, 0], z, SPARSE, t=0)
    np.testing.assert_array_equal(shared.symbols[0, 0], batched.symbols[0, 0])
    # A traced mask's diagonal is ignored.
    full = jnp.ones((K, K), bool)
    np.testing.assert_array_equal(
        channel.send(keys[0, 0], z[0, 0], full, t=0).symbols,
        channel.send(keys[0, 0], z[0, 0], channel.Routing.all_to_all(K), t=0).symbols,
    )


def test_inbox_mean_averages_over_senders():
    msgs = channel.send(jax.random.key(2), _signals(4), SPARSE, t=1)
    for j in range(K):
        senders = SPARSE.senders(j)
        want = np.mean([msgs.z_hat[i, j] for i in senders], 0) if senders else np.zeros(C)
        np.testing.assert_allclose(msgs.inbox_mean[j], want, atol=1e-7)


def test_reconstruct_from_symbols_alone():
    key, z = jax.random.key(3), _signals(5, (2, K, K, C))
    keys = jax.random.split(key, 2)
    msgs = channel.send(keys, z, RING, t=9)
    inbox = channel.reconstruct(keys, msgs.symbols, RING, t=9)
    np.testing.assert_allclose(inbox, msgs.inbox, atol=1e-6)
    wrong_step = channel.reconstruct(keys, msgs.symbols, RING, t=10)
    assert np.abs(np.asarray(wrong_step - msgs.inbox)).max() > 1e-3


def test_codes_and_a_learned_code():
    z = _signals(6)
    fixed = channel.send(jax.random.key(0), z, RING, t=0, code="fixed")
    assert (np.asarray(fixed.payload_bits)[RING.mask] == C * 4).all()
    remap = channel.frequency_remap(np.arange(LEVELS * C).reshape(C, LEVELS))
    code = channel.Code("paper", LEVELS, remap)
    learned = channel.send(jax.random.key(0), z, RING, t=0, code=code)
    expect = channel.expected_bits(z, LEVELS, code.lengths()).sum(-1)
    np.testing.assert_allclose(np.asarray(learned.penalty)[RING.mask], expect[RING.mask], 1e-6)


def test_routing_tables():
    r = channel.Routing.all_to_all(3)
    assert r.num_links == 6 and r.senders(0) == [1, 2] and r.recipients(2) == [0, 1]
    assert SPARSE.senders(2) == [0, 3] and SPARSE.recipients(2) == []
    assert channel.Routing.from_mask(SPARSE.mask) == SPARSE
    assert hash(RING) == hash(channel.Routing.from_neighbours([[1], [2], [3], [0]]))
    assert channel.Routing.all_to_all(1).num_links == 0


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: channel.Routing.all_to_all(0), "num_agents must be an integer in"),
        (lambda: channel.Routing.all_to_all(2.0), "num_agents must be an integer in"),
        (lambda: channel.Routing.from_neighbours([[1], [5]]), r"neighbours\[1\] must hold"),
        (lambda: channel.Routing.from_neighbours([[0], []]), "must not hold 0 itself"),
        (lambda: channel.Routing.from_neighbours([[1, 1], []]), "twice"),
        (lambda: channel.Routing.from_mask(np.ones((2, 3), bool)), "square"),
        (lambda: channel.Routing.from_mask(np.zeros((2, 2))), "boolean"),
        (lambda: channel.Routing.from_mask(np.ones((2, 2), bool)), "False diagonal"),
        (lambda: channel.send(jax.random.key(0), _signals(), RING, t=0, levels=0), "levels"),
        (lambda: channel.send(jax.random.key(0), _signals(), RING, t=4096), r"t must be .*4096"),
        (lambda: channel.send(jax.random.key(0), _signals(), RING, t=-1), r"t must be"),
        (lambda: channel.send(jax.random.key(0), _signals(), RING, t=0.5), r"t must be"),
        (lambda: channel.send(jax.random.key(0), 2 * _signals(), RING, t=0), r"\[0, 1\]"),
        (lambda: channel.send(jax.random.key(0), _signals(0, (K, 2, C)), RING, t=0), "z must"),
        (lambda: channel.send(jax.random.key(0), _signals(0, (3, 3, C)), RING, t=0), "routing"),
        (
            lambda: channel.send(jax.random.key(0), _signals(), np.ones((K, K)), t=0),
            "routing must be",
        ),
        (
            lambda: channel.send(jax.random.split(jax.random.key(0), 3), _signals(), RING, t=0),
            "key must be",
        ),
        (lambda: channel.send(jax.random.key(0), _signals(), RING, t=0, gate="relu"), "gate"),
        (
            lambda: channel.reconstruct(jax.random.key(0), jnp.full((K, K, C), 16), RING, t=0),
            r"symbols must lie in \[0, 15\]",
        ),
    ],
)
def test_bad_input_is_a_value_error(build, match):
    with pytest.raises(ValueError, match=match):
        build()


if __name__ == "__main__":
    import os
    import time

    os.chdir(DOC.parent.parent)
    start = time.perf_counter()
    exec(compile(tutorial_code(), str(DOC), "exec"), {"__name__": "plugin_tutorial"})
    print(f"tutorial: {time.perf_counter() - start:.1f} s", file=sys.stderr)


def test_with_the_last_inbox_a_silent_link_holds_its_last_message():
    """``last`` (the previous inbox): a link that sends nothing delivers its last message and
    is flagged as not news, in ``send`` and ``reconstruct`` alike (the channel's hold rule)."""
    key = jax.random.key(3)
    z = _signals(4, (K, K, C))
    z = z.at[0, 1].set(0.0).at[2, 0].set(0.0)  # links 0 -> 1 and 2 -> 0 fall silent
    last = jax.random.uniform(jax.random.key(5), (K, K, C))
    msgs = channel.send(key, z, RING, t=2, last=last)
    plain = channel.send(key, z, RING, t=2)
    mask = np.asarray(RING.mask)
    silent = ~np.asarray(plain.symbols != 0).any(-1) & mask  # (sender, recipient)
    assert silent[0, 1] or silent[2, 0]
    inbox, news = np.asarray(msgs.inbox), np.asarray(msgs.news)
    for i, j in zip(*np.nonzero(mask), strict=True):
        if silent[i, j]:
            np.testing.assert_array_equal(inbox[j, i], np.asarray(last)[j, i])
            assert news[j, i] == 0.0
        else:
            np.testing.assert_array_equal(inbox[j, i], np.asarray(plain.inbox)[j, i])
            assert news[j, i] == 1.0
    assert not news[~mask.T].any() and not inbox[~mask.T].any()
    again = channel.reconstruct(key, msgs.symbols, RING, t=2, last=last)
    np.testing.assert_allclose(again, msgs.inbox, atol=1e-6)
    assert plain.news is None
    with pytest.raises(ValueError, match="last"):
        channel.send(key, z, RING, t=2, last=last[0])
