"""Draw episodes of the navigation task with PIL and save them as GIFs.

Each frame shows the arena (white square; the grey band around it is the margin up to
``position_limit``), every agent as a coloured disc, its goal as a cross of the same colour inside a
ring of radius ``success_radius``, and optionally the messages of that step: a line from sender to
recipient whose width and opacity grow with the payload bits, labelled with the bit count near the
sender. A header gives the step, whether the episode has succeeded and the bits of the step (and
the running total).

Command line (writes a GIF of one oracle episode)::

    python -m sparsecomm.envs.render --policy oracle --out docs/oracle.gif --seed 0
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Literal

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from sparsecomm.envs.navigation import NavConfig, NavigationEnv, NavState

AGENT_COLOURS = [
    (31, 119, 180),
    (214, 39, 40),
    (44, 160, 44),
    (148, 103, 189),
    (255, 127, 14),
    (23, 190, 207),
    (227, 119, 194),
    (140, 86, 75),
]
"""Agent colours (cycled for K > 8)."""


def _stack_states(states_sequence: NavState | Sequence[NavState]) -> dict[str, np.ndarray]:
    """NumPy arrays with a leading time axis from a stacked state or a list of states."""
    if isinstance(states_sequence, NavState):
        stacked = states_sequence
        if np.ndim(stacked.time) == 0:
            stacked = jax.tree.map(lambda x: np.asarray(x)[None], stacked)
    else:
        if len(states_sequence) == 0:
            raise ValueError("states_sequence is empty")
        stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *states_sequence)
    out = {f.name: np.asarray(getattr(stacked, f.name)) for f in dataclasses.fields(NavState)}
    if out["pos"].ndim != 3:
        raise ValueError(f"expected states with pos of shape (T, K, 2), got {out['pos'].shape}")
    return out


def trim_episode(states: NavState, dones: jax.Array) -> NavState:
    """Keep the states up to and including the first done one (all of them if none is done)."""
    dones = np.asarray(dones)
    last = int(np.argmax(dones)) if dones.any() else len(dones) - 1
    return jax.tree.map(lambda x: np.asarray(x)[: last + 1], states)


def render_frames(
    states_sequence: NavState | Sequence[NavState],
    config: NavConfig,
    link_bits: np.ndarray | None = None,
    size: int = 256,
) -> list[np.ndarray]:
    """Draw one ``(size, size, 3)`` uint8 RGB frame per state.

    ``states_sequence``: a list of :class:`NavState` or one state with a leading time axis (T).
    ``link_bits``: optional ``(T, K, K)`` payload bits sent ``i -> j`` (``[t, i, j]``), drawn on
    frame ``t``; a ``(T - 1, K, K)`` array is padded with a zero last step (the terminal state
    sends nothing). The diagonal is ignored.
    """
    s = _stack_states(states_sequence)
    num_frames, k = s["pos"].shape[:2]
    if link_bits is not None:
        link_bits = np.asarray(link_bits, dtype=np.float64)
        if link_bits.ndim != 3 or link_bits.shape[1:] != (k, k):
            raise ValueError(f"link_bits must have shape (T, {k}, {k}), got {link_bits.shape}")
        if link_bits.shape[0] == num_frames - 1:
            link_bits = np.concatenate([link_bits, np.zeros((1, k, k))])
        if link_bits.shape[0] != num_frames:
            raise ValueError(f"link_bits has {link_bits.shape[0]} steps for {num_frames} states")
        link_bits = link_bits * (1 - np.eye(k))[None]
    size = int(size)
    header = max(14, size // 14)
    font = ImageFont.load_default(size=max(8, int(0.62 * header)))
    small = ImageFont.load_default(size=max(7, size // 28))
    lim = config.position_limit
    scale = (size - header - 2) / (2 * lim)

    def px(xy: np.ndarray) -> tuple[float, float]:
        # World (x right, y up) to pixels (x right, y down), below the header.
        return (
            1 + header / 2 + (float(xy[0]) + lim) * scale,
            header + 1 + (lim - float(xy[1])) * scale,
        )

    a = config.arena_half_width
    r_goal = config.success_radius * scale
    r_agent = max(3.0, 0.05 * scale)
    cum_bits = 0.0
    frames = []
    for t in range(num_frames):
        img = Image.new("RGB", (size, size), (255, 255, 255))
        draw = ImageDraw.Draw(img)
        draw.rectangle([px((-lim, lim)), px((lim, -lim))], fill=(232, 232, 232))
        draw.rectangle([px((-a, a)), px((a, -a))], fill=(255, 255, 255), outline=(90, 90, 90))

        pos, goals = s["pos"][t], s["goals"][t]
        for i in range(k):
            colour = AGENT_COLOURS[i % len(AGENT_COLOURS)]
            gx, gy = px(goals[i])
            draw.ellipse([gx - r_goal, gy - r_goal, gx + r_goal, gy + r_goal], outline=colour)
            c = max(3.0, 0.6 * r_goal)
            draw.line([gx - c, gy - c, gx + c, gy + c], fill=colour, width=2)
            draw.line([gx - c, gy + c, gx + c, gy - c], fill=colour, width=2)

        step_bits = 0.0
        if link_bits is not None:
            bits = link_bits[t]
            step_bits = float(bits.sum())
            max_bits = max(1.0, float(link_bits.max()))
            overlay = Image.new("RGBA", (size, size), (0, 0, 0, 0))
            odraw = ImageDraw.Draw(overlay)
            labels = []
            for i in range(k):
                for j in range(k):
                    if i == j or bits[i, j] <= 0:
                        continue
                    p0, p1 = np.array(px(pos[i])), np.array(px(pos[j]))
                    d = p1 - p0
                    n = np.array([-d[1], d[0]]) / max(1e-9, float(np.hypot(*d)))
                    # Offset each direction to its own side so i->j and j->i do not overlap.
                    off = n * max(2.0, size / 128)
                    frac = bits[i, j] / max_bits
                    width = int(round(1 + 5 * frac))
                    alpha = int(round(70 + 160 * frac))
                    colour = AGENT_COLOURS[i % len(AGENT_COLOURS)]
                    odraw.line(
                        [tuple(p0 + off), tuple(p1 + off)], fill=(*colour, alpha), width=width
                    )
                    labels.append((tuple(p0 + 0.3 * d + 3 * off), f"{bits[i, j]:g}", colour))
            img = Image.alpha_composite(img.convert("RGBA"), overlay).convert("RGB")
            draw = ImageDraw.Draw(img)
            for xy, text, colour in labels:
                draw.text(xy, text, fill=colour, font=small, anchor="mm")
        cum_bits += step_bits

        for i in range(k):
            colour = AGENT_COLOURS[i % len(AGENT_COLOURS)]
            x, y = px(pos[i])
            draw.ellipse(
                [x - r_agent, y - r_agent, x + r_agent, y + r_agent],
                fill=colour,
                outline=(0, 0, 0),
            )

        success = bool(s["success"][t])
        text = f"t={int(s['time'][t])}  {'success' if success else 'searching'}"
        if link_bits is not None:
            text += f"  bits {step_bits:g}  total {cum_bits:g}"
        draw.rectangle([0, 0, size, header], fill=(40, 40, 40) if not success else (30, 110, 30))
        draw.text((4, header / 2), text, fill=(255, 255, 255), font=font, anchor="lm")
        frames.append(np.asarray(img, dtype=np.uint8))
    return frames


def write_gif(
    path: str | Path, frames: Sequence[np.ndarray], fps: float = 10.0, hold_last: float = 1.0
) -> Path:
    """Write RGB frames to an infinitely looping GIF with imageio; returns the path.

    The last frame is shown for ``hold_last`` seconds (at least one frame period).
    """
    if len(frames) == 0:
        raise ValueError("no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(
        path,
        np.stack([np.asarray(f, dtype=np.uint8) for f in frames]),
        extension=".gif",
        duration=[1000.0 / fps] * (len(frames) - 1) + [max(1000.0 / fps, 1000.0 * hold_last)],
        loop=0,
    )
    return path


@partial(jax.jit, static_argnums=(1, 2))
def record_episode(key: jax.Array, config: NavConfig, policy_fn) -> tuple[NavState, jax.Array]:
    """Run one episode of ``policy_fn(state, config) -> (K,) int32`` and keep every state.

    Returns the stacked states ``(max_steps + 1, ...)`` (the reset state first) and ``dones``
    ``(max_steps + 1,)``; pass them to :func:`trim_episode` to stop at the end of the episode.
    Uses the same keys as episode ``e`` of ``run_policy_episodes`` when given
    ``jax.random.split(key, num_episodes)[e]``.
    """
    env = NavigationEnv(config)
    key_reset, key_steps = jax.random.split(key)
    _, state = env.reset(key_reset)

    def body(state, step_key):
        _, next_state, _, _, _ = env.step(step_key, state, policy_fn(state, config))
        return next_state, next_state

    _, states = jax.lax.scan(body, state, jax.random.split(key_steps, config.max_steps))
    states = jax.tree.map(lambda x0, xs: jnp.concatenate([x0[None], xs]), state, states)
    return states, states.done


@dataclasses.dataclass
class RenderArgs:
    """Record one episode of a scripted policy and save it as a GIF."""

    policy: Literal["oracle", "center"] = "oracle"
    """Scripted policy: the centralised oracle or the no-communication centre policy."""
    out: Path = Path("docs/oracle.gif")
    """Output GIF path."""
    seed: int = 0
    """Episode seed (jax.random.PRNGKey(seed))."""
    size: int = 256
    """Frame width and height in pixels."""
    fps: float = 10.0
    """GIF frames per second (of kept frames)."""
    stride: int = 1
    """Keep every stride-th frame (the last frame is always kept)."""
    env: NavConfig = dataclasses.field(default_factory=NavConfig)
    """Environment configuration."""


def main(args: RenderArgs) -> Path:
    from sparsecomm.envs.oracle import center_actions, oracle_actions

    policy = {"oracle": oracle_actions, "center": center_actions}[args.policy]
    states, dones = record_episode(jax.random.PRNGKey(args.seed), args.env, policy)
    states = trim_episode(states, dones)
    frames = render_frames(states, args.env, size=args.size)
    keep = list(range(0, len(frames), max(1, args.stride)))
    if keep[-1] != len(frames) - 1:
        keep.append(len(frames) - 1)
    path = write_gif(args.out, [frames[i] for i in keep], fps=args.fps)
    success = bool(np.asarray(states.success)[-1])
    print(
        f"wrote {path} ({len(keep)} frames, {path.stat().st_size / 1024:.0f} KiB): "
        f"{args.policy} episode of {len(frames) - 1} steps, success={success}"
    )
    return path


if __name__ == "__main__":
    import tyro

    main(tyro.cli(RenderArgs))
