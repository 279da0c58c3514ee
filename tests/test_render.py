"""Tests of the PIL renderer, GIF writer and render CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
import pytest

from sparsecomm.envs import NavConfig, oracle_actions, record_episode
from sparsecomm.envs.render import AGENT_COLOURS, render_frames, trim_episode, write_gif

CFG = NavConfig()
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def episode():
    states, dones = record_episode(jax.random.PRNGKey(0), CFG, oracle_actions)
    return trim_episode(states, dones)


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


def test_write_gif_roundtrip(episode, tmp_path):
    frames = render_frames(episode, CFG, size=64)
    path = write_gif(tmp_path / "sub" / "ep.gif", frames, fps=20)
    back = iio.imread(path)
    assert back.shape[0] == len(frames) and back.shape[1:3] == (64, 64)


def test_cli_writes_gif(tmp_path, fast_compile):
    out = tmp_path / "oracle.gif"
    cmd = [sys.executable, "-m", "sparsecomm.envs.render", "--policy", "oracle"]
    cmd += ["--out", str(out), "--seed", "0", "--size", "96", "--stride", "2"]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "success=True" in result.stdout
    frames = iio.imread(out)
    assert frames.shape[1:3] == (96, 96) and frames.shape[0] >= 2
