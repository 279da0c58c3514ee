"""Tests of the PIL renderer, GIF writer and render CLI."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sparsecomm.envs import NavConfig, oracle_actions, record_episode
from sparsecomm.envs.navigation import NavState
from sparsecomm.envs.render import (
    AGENT_COLOURS,
    DEFAULT_SIZE,
    SILENT_COLOUR,
    RenderArgs,
    boxes_intersect,
    fit_view_limit,
    format_bits,
    frame_layout,
    link_colour,
    link_label_boxes,
    link_line,
    link_normal,
    render_frames,
    trim_episode,
    write_gif,
)

CFG = NavConfig()
ROOT = Path(__file__).resolve().parents[1]
ALL_LINKS = [(i, j) for i in range(3) for j in range(3) if i != j]


@pytest.fixture(scope="module")
def raw_episode():
    """All ``max_steps + 1`` states of an oracle episode (it goes on after its success)."""
    return record_episode(jax.random.PRNGKey(0), CFG, oracle_actions)


@pytest.fixture(scope="module")
def episode(raw_episode):
    return trim_episode(*raw_episode)


def _state(pos, goals) -> NavState:
    """One hand-placed state (K = 3)."""
    return NavState(
        pos=jnp.asarray(pos, dtype=jnp.float32),
        vel=jnp.zeros((3, 2), jnp.float32),
        goals=jnp.asarray(goals, dtype=jnp.float32),
        time=jnp.asarray(7, jnp.int32),
        done=jnp.asarray(False),
        success=jnp.asarray(False),
        parked=jnp.zeros(3, bool),
    )


def test_trim_stops_at_first_done(episode):
    done = np.asarray(episode.done)
    assert done[-1] and not done[:-1].any()
    assert bool(episode.success[-1])


def test_frames_shape_dtype_and_content(episode):
    frames = render_frames(episode, CFG, size=128)
    assert len(frames) == len(episode.time)
    assert all(f.shape == (128, 128, 3) and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[-1])
    # Each agent's colour is on the first frame (its disc and its goal marker).
    for colour in AGENT_COLOURS[:3]:
        assert np.any(np.all(frames[0] == colour, axis=-1)), colour
    # A list of single states works the same way.
    states = [jax.tree.map(lambda x, t=t: x[t], episode) for t in range(2)]
    np.testing.assert_array_equal(render_frames(states, CFG, size=128)[1], frames[1])


def test_default_frames_are_at_least_512_px(episode):
    first = jax.tree.map(lambda x: x[:2], episode)
    frames = render_frames(first, CFG)
    assert min(frames[0].shape[:2]) >= 512 and frames[0].shape == (DEFAULT_SIZE, DEFAULT_SIZE, 3)
    bits = np.full((2, 3, 3), 4.0)
    assert min(render_frames(first, CFG, link_bits=bits)[0].shape[:2]) >= 512
    assert RenderArgs().size >= 512


def test_link_bits_are_drawn(episode):
    t_steps = len(episode.time)
    bits = np.zeros((t_steps, 3, 3))
    bits[0, 0, 1] = 12
    bits[0, 2, 0] = 3
    plain = render_frames(episode, CFG, size=192)
    linked = render_frames(episode, CFG, link_bits=bits, size=192)
    assert not np.array_equal(plain[0], linked[0])  # lines, labels and header differ
    # A (T - 1)-step array is padded with a silent last step.
    short = render_frames(episode, CFG, link_bits=bits[:-1], size=192)
    np.testing.assert_array_equal(short[0], linked[0])
    with pytest.raises(ValueError, match="link_bits"):
        render_frames(episode, CFG, link_bits=np.zeros((t_steps, 2, 2)))


def _along(frame: np.ndarray, line: tuple[np.ndarray, np.ndarray], n: int = 60) -> np.ndarray:
    """Pixels sampled on the middle half of a line (away from discs and arrowheads)."""
    a, b = line
    pts = a + np.linspace(0.25, 0.75, n)[:, None] * (b - a)
    xy = np.round(pts).astype(int)
    return frame[xy[:, 1], xy[:, 0]]


def _is(pixels: np.ndarray, colour) -> np.ndarray:
    return np.all(pixels == np.asarray(colour), axis=-1)


def test_silent_link_is_drawn_differently_from_a_link_with_bits():
    state = _state([[-0.6, -0.5], [0.6, -0.5], [0.0, 0.6]], [[0.7, 0.7], [-0.7, 0.6], [0.0, -0.8]])
    busy = np.full((1, 3, 3), 8.0)
    quiet = busy.copy()
    quiet[0, 0, 1] = 0.0  # 0 -> 1 is silent; 1 -> 0 (same segment, other side) still carries 8
    f_busy = render_frames([state], CFG, link_bits=busy)[0]
    f_quiet = render_frames([state], CFG, link_bits=quiet)[0]
    pos = np.asarray(state.pos)
    layout = frame_layout(CFG, DEFAULT_SIZE, fit_view_limit(pos, np.asarray(state.goals), CFG))
    px = layout.to_px(pos)
    line_01 = link_line(px[0], px[1], layout.link_offset, i=0, j=1)
    line_10 = link_line(px[1], px[0], layout.link_offset, i=1, j=0)
    drawn = link_colour(AGENT_COLOURS[0], 8.0, 8.0)
    # With bits: a solid line in the sender's colour.
    assert _is(_along(f_busy, line_01), drawn).mean() > 0.9
    # Silent: no trace of that colour; light-grey dashes (with gaps) instead.
    silent = _along(f_quiet, line_01)
    assert not _is(silent, drawn).any()
    assert 0.3 < _is(silent, SILENT_COLOUR).mean() < 1.0
    assert (_is(silent, SILENT_COLOUR) | _is(silent, (255, 255, 255))).mean() > 0.9
    # The reverse link on the other side of the segment is drawn with bits in both frames.
    other = link_colour(AGENT_COLOURS[1], 8.0, 8.0)
    for frame in (f_busy, f_quiet):
        assert _is(_along(frame, line_10), other).mean() > 0.9
    # A link's width grows with its bits.
    assert layout.link_width(1.0, 64.0) < layout.link_width(16.0, 64.0) < layout.link_width(64, 64)


def test_link_directions_lie_on_opposite_sides():
    p, q = np.array([100.0, 200.0]), np.array([300.0, 120.0])
    np.testing.assert_allclose(link_normal(p, q), -link_normal(q, p))
    np.testing.assert_allclose(np.linalg.norm(link_normal(p, q)), 1.0)
    # Coincident agents still get opposite sides.
    np.testing.assert_allclose(link_normal(p, p, 0, 1), -link_normal(p, p, 1, 0))
    a, b = link_line(p, q, 6.0, 10.0, 12.0)
    np.testing.assert_allclose(np.dot(a - p, link_normal(p, q)), 6.0)
    np.testing.assert_allclose(np.linalg.norm(b - a), np.linalg.norm(q - p) - 22.0)
    assert link_line(p, p + 5.0, 6.0, 10.0, 12.0) is None


def _assert_disjoint(boxes, gap=0.0):
    for a, b in itertools.combinations(boxes, 2):
        assert not boxes_intersect(a, b, gap), (a, b)


@pytest.mark.parametrize("seed", range(4))
def test_labels_of_all_six_links_never_overlap(seed):
    rng = np.random.default_rng(seed)
    bounds = (0.0, 40.0, 640.0, 570.0)
    for trial in range(100):
        pos = rng.uniform([40, 80], [600, 530], size=(3, 2))
        if trial % 4 == 1:  # two agents close together
            pos[1] = pos[0] + rng.normal(0, 8, 2)
        if trial % 4 == 2:  # three agents nearly on a line
            pos[2] = pos[0] + rng.uniform(0.2, 0.8) * (pos[1] - pos[0])
        if trial % 4 == 3:  # all in one spot
            pos[:] = pos[0]
        sizes = [(rng.uniform(16, 48), 22.0) for _ in ALL_LINKS]
        obstacles = [(x - 14, y - 14, x + 14, y + 14) for x, y in pos]
        boxes = link_label_boxes(pos, ALL_LINKS, sizes, 12.0, bounds, obstacles)
        assert len(boxes) == 6
        _assert_disjoint(boxes, gap=1.0)
        for box, (w, h) in zip(boxes, sizes, strict=True):
            np.testing.assert_allclose([box[2] - box[0], box[3] - box[1]], [w, h])


def test_labels_sit_on_their_own_side_near_the_sender():
    pos = np.array([[100.0, 400.0], [500.0, 400.0], [300.0, 100.0]])
    sizes = [(30.0, 20.0)] * 6
    boxes = dict(zip(ALL_LINKS, link_label_boxes(pos, ALL_LINKS, sizes, 10.0), strict=True))
    for (i, j), box in boxes.items():
        centre = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
        rel = centre - pos[i]
        d = pos[j] - pos[i]
        side = np.dot(rel, link_normal(pos[i], pos[j], i, j))
        along = np.dot(rel, d) / np.dot(d, d)
        assert side > 10.0 + 9.0, (i, j, side)  # clear of the segment and of the link's line
        assert 0.15 < along < 0.6, (i, j, along)  # nearer the sender than the recipient
    # i -> j and j -> i face each other across the segment.
    assert boxes[(0, 1)][3] < 400 < boxes[(1, 0)][1] or boxes[(1, 0)][3] < 400 < boxes[(0, 1)][1]


def test_crowded_labels_still_never_overlap():
    rng = np.random.default_rng(0)
    pos = rng.uniform(300, 340, size=(5, 2))
    links = [(i, j) for i in range(5) for j in range(5) if i != j]
    boxes = link_label_boxes(pos, links, [(34.0, 20.0)] * len(links), 8.0, (0, 0, 640, 640))
    _assert_disjoint(boxes, gap=1.0)


def test_format_bits():
    assert format_bits(12.0) == "12" and format_bits(0.5) == "0.5" and format_bits(1 / 3) == "0.333"


def test_view_zooms_to_the_arena_and_widens_for_the_margin():
    assert fit_view_limit(np.zeros((3, 2)), np.full((3, 2), 0.5), CFG) == pytest.approx(1.1)
    assert fit_view_limit(np.full((3, 2), 1.3), np.zeros((3, 2)), CFG) == pytest.approx(1.4)
    assert fit_view_limit(np.full((3, 2), 1.5), np.zeros((3, 2)), CFG) == CFG.position_limit


def test_write_gif_roundtrip(episode, tmp_path):
    frames = render_frames(episode, CFG, size=64)
    path = write_gif(tmp_path / "sub" / "ep.gif", frames, fps=20)
    back = iio.imread(path)
    assert back.shape[0] == len(frames) and back.shape[1:3] == (64, 64)


def test_full_episode_gif_at_default_size(raw_episode, tmp_path):
    states, _ = raw_episode
    n = len(np.asarray(states.time))
    assert n == CFG.max_steps + 1
    bits = np.random.default_rng(0).choice([0.0, 0.0, 2.0, 8.0, 32.0], size=(n - 1, 3, 3))
    t0 = time.perf_counter()
    frames = render_frames(states, CFG, link_bits=bits)
    path = write_gif(tmp_path / "team.gif", frames, fps=12)
    elapsed = time.perf_counter() - t0
    back = iio.imread(path)
    assert back.shape == (n, DEFAULT_SIZE, DEFAULT_SIZE, 3)
    # One shared palette without dithering: the frames come back close to what was drawn.
    assert np.abs(back[10].astype(int) - frames[10]).mean() < 4.0
    assert elapsed < 60.0, elapsed  # a few seconds on a free core; lenient for shared machines


def test_cli_writes_gif(tmp_path, fast_compile):
    out = tmp_path / "oracle.gif"
    cmd = [sys.executable, "-m", "sparsecomm.envs.render", "--policy", "oracle"]
    cmd += ["--out", str(out), "--seed", "0", "--size", "96", "--stride", "2"]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "success=True" in result.stdout
    frames = iio.imread(out)
    assert frames.shape[1:3] == (96, 96) and frames.shape[0] >= 2
