"""Draw episodes of the navigation task with PIL and save them as GIFs.

Frame layout (square, ``size`` pixels a side, 640 by default):

* a header bar with the step number (``step t / max_steps``) and the episode status (green once
  the team has succeeded);
* the arena: the white square is where goals and starts are drawn from, the grey band around it the
  margin up to ``position_limit``; the view is zoomed to the arena and as much of the margin as the
  episode uses (:func:`fit_view_limit`). Each agent is a disc of its own colour with its index
  written in it; its goal is a tinted ring of radius ``success_radius`` (the distance that counts
  as "at the goal") of the same colour, with a cross at the centre;
* with ``link_bits``, the messages of the step. Every directed link ``i -> j`` is drawn on its own
  line, offset from the segment between the two agents to the left of the direction of travel (on
  screen), so ``i -> j`` and ``j -> i`` run on opposite sides of the segment. A link that carries
  bits is a line in the sender's colour, with an arrowhead at the recipient, whose width and colour
  saturation grow with the bits (relative to the busiest link of the episode), labelled with the bit
  count in a box on the same side, a third of the way from the sender. A silent link (0 bits) is a
  thin dashed light-grey line with no label. Labels are placed by :func:`link_label_boxes`, which
  never lets two labels overlap;
* a footer with the caption (the team's bits this step and the episode total so far) and a legend.

Command line (writes a GIF of one oracle episode)::

    python -m sparsecomm.envs.render --policy oracle --out docs/oracle.gif --seed 0
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Literal

import jax
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from sparsecomm.envs.navigation import NavConfig, NavState
from sparsecomm.envs.oracle import center_actions, oracle_actions, scripted_episode

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

DEFAULT_SIZE = 640
"""Default frame width and height in pixels."""

SILENT_COLOUR = (170, 170, 170)
"""Colour of the dashed line of a link that carries no bits at a step."""

Box = tuple[float, float, float, float]
"""An axis-aligned pixel box ``(x0, y0, x1, y1)``."""

_LABEL_FRACTIONS = (1 / 3, 0.25, 0.42, 0.5, 0.17, 0.58)
_LABEL_STEPS_OUT = (0.0, 0.5, 1.0, 2.0, 3.0)


def _mix(colour: tuple[int, int, int], weight_white: float) -> tuple[int, int, int]:
    """``colour`` blended with white (``weight_white`` in [0, 1])."""
    w = min(1.0, max(0.0, weight_white))
    return tuple(int(round(c + (255 - c) * w)) for c in colour)


@dataclasses.dataclass(frozen=True)
class FrameLayout:
    """Pixel geometry of a frame of :func:`render_frames` (see :func:`frame_layout`)."""

    size: int
    """Frame width and height."""
    header: int
    """Height of the header bar (rows ``[0, header)``)."""
    footer: int
    """Height of the footer (rows ``[size - footer, size)``)."""
    view_limit: float
    """World half-width drawn: the view is the square ``[-view_limit, view_limit]^2``."""
    scale: float
    """Pixels per world unit."""
    x0: float
    """Pixel column of world ``x = -view_limit``."""
    y0: float
    """Pixel row of world ``y = +view_limit``."""
    unit: float
    """Length unit of strokes, fonts and offsets (``size / 640``)."""

    @property
    def arena_box(self) -> Box:
        """Pixel box of the drawn world square ``[-view_limit, view_limit]^2``."""
        side = 2 * self.view_limit * self.scale
        return (self.x0, self.y0, self.x0 + side, self.y0 + side)

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """World points ``(..., 2)`` (x right, y up) to pixels (x right, y down)."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack(
            [
                self.x0 + (xy[..., 0] + self.view_limit) * self.scale,
                self.y0 + (self.view_limit - xy[..., 1]) * self.scale,
            ],
            axis=-1,
        )

    @property
    def agent_radius(self) -> float:
        return max(3.0, 0.07 * self.scale)

    @property
    def link_offset(self) -> float:
        """Distance of a link's line from the segment between its two agents."""
        return max(2.0, 0.5 * self.max_link_width + 2.5 * self.unit)

    @property
    def max_link_width(self) -> float:
        return max(3.0, 9.0 * self.unit)

    def link_width(self, bits: float, max_bits: float) -> int:
        """Line width of a link carrying ``bits`` (> 0); the busiest one carries ``max_bits``."""
        frac = min(1.0, max(0.0, bits / max(max_bits, 1e-12)))
        return max(2, int(round(max(2.0, 2.0 * self.unit) + frac * (self.max_link_width - 2.0))))


def fit_view_limit(pos: np.ndarray, goals: np.ndarray, config: NavConfig) -> float:
    """Half-width of the view of an episode: the arena with a small margin, widened to show every
    position and goal of ``pos`` / ``goals`` (any shape ``(..., 2)``), at most ``position_limit``.

    A team that stays in the arena is drawn as large as the frame allows; the grey band of the
    margin up to ``position_limit`` shows only as far as agents go into it.
    """
    reach = max(float(np.abs(np.asarray(pos)).max()), float(np.abs(np.asarray(goals)).max()))
    view = max(1.1 * config.arena_half_width, reach + 0.1)
    return float(min(config.position_limit, view))


def frame_layout(
    config: NavConfig, size: int = DEFAULT_SIZE, view_limit: float | None = None
) -> FrameLayout:
    """Geometry of a ``size`` x ``size`` frame: header, footer, world-to-pixel map.

    ``view_limit``: world half-width drawn (:func:`fit_view_limit`; ``position_limit`` if None).
    """
    size = int(size)
    unit = size / 640
    header = max(10, int(round(size / 17)))
    footer = max(12, int(round(size / 9)))
    side = max(4, min(size - 4, size - header - footer - 4))
    lim = float(config.position_limit if view_limit is None else view_limit)
    return FrameLayout(
        size=size,
        header=header,
        footer=footer,
        view_limit=lim,
        scale=side / (2 * lim),
        x0=(size - side) / 2,
        y0=header + 2,
        unit=unit,
    )


def link_normal(p_from: np.ndarray, p_to: np.ndarray, i: int = 0, j: int = 1) -> np.ndarray:
    """Unit normal to the left (on screen, y down) of the direction ``p_from -> p_to``.

    It flips with the direction, so ``i -> j`` and ``j -> i`` get opposite sides. When the two
    points coincide, the direction is taken as +x for ``i < j`` and -x otherwise.
    """
    d = np.asarray(p_to, dtype=np.float64) - np.asarray(p_from, dtype=np.float64)
    norm = float(np.hypot(d[0], d[1]))
    if norm < 1e-9:
        d, norm = np.array([1.0 if i < j else -1.0, 0.0]), 1.0
    return np.array([d[1], -d[0]]) / norm


def link_line(
    p_from: np.ndarray,
    p_to: np.ndarray,
    offset: float,
    trim_from: float = 0.0,
    trim_to: float = 0.0,
    i: int = 0,
    j: int = 1,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Pixel end points of the line of link ``i -> j``: the segment ``p_from -> p_to`` shifted by
    ``offset`` along :func:`link_normal` and shortened by ``trim_from`` / ``trim_to`` at its ends
    (to stay clear of the agent discs); ``None`` when nothing is left of it."""
    p_from = np.asarray(p_from, dtype=np.float64)
    p_to = np.asarray(p_to, dtype=np.float64)
    d = p_to - p_from
    length = float(np.hypot(d[0], d[1]))
    if length <= trim_from + trim_to + 1.0:
        return None
    u = d / length
    shift = link_normal(p_from, p_to, i, j) * offset
    return p_from + u * trim_from + shift, p_to - u * trim_to + shift


def boxes_intersect(a: Box, b: Box, gap: float = 0.0) -> bool:
    """Whether two boxes overlap or come closer than ``gap``."""
    return not (
        a[2] + gap <= b[0] or b[2] + gap <= a[0] or a[3] + gap <= b[1] or b[3] + gap <= a[1]
    )


def link_label_boxes(
    pos_px: np.ndarray,
    links: Sequence[tuple[int, int]],
    label_sizes: Sequence[tuple[float, float]],
    clearance: float,
    bounds: Box | None = None,
    obstacles: Sequence[Box] = (),
    gap: float = 2.0,
) -> list[Box]:
    """Place one label box per directed link so that no two labels intersect (pure geometry).

    ``pos_px``: ``(K, 2)`` agent pixel positions; ``links``: the ``(i, j)`` pairs to label;
    ``label_sizes``: ``(width, height)`` of each label; ``clearance``: distance from the segment
    ``i - j`` that the label keeps (the link's line lies within it). A label goes on its link's
    side (:func:`link_normal`, so ``i -> j`` and ``j -> i`` face each other across the segment) a
    third of the way from the sender. If that spot meets a placed label or an ``obstacle`` (agent
    discs, goals) or leaves ``bounds``, the next of a few spots along and away from the link is
    tried, then a spiral around the first spot. Labels are kept at least ``gap`` apart from each
    other in every case; only if the spiral finds no room (many more labels than fit) are
    ``obstacles`` and ``bounds`` given up.
    """
    pos_px = np.asarray(pos_px, dtype=np.float64)
    placed: list[Box] = []
    for (i, j), (w, h) in zip(links, label_sizes, strict=True):
        w, h = float(w), float(h)
        p0 = pos_px[i]
        d = pos_px[j] - p0
        n = link_normal(pos_px[i], pos_px[j], i, j)
        half_n = 0.5 * (abs(n[0]) * w + abs(n[1]) * h)

        def box_at(c: np.ndarray, w=w, h=h) -> Box:
            return (c[0] - w / 2, c[1] - h / 2, c[0] + w / 2, c[1] + h / 2)

        def free(b: Box, strict: bool) -> bool:
            if any(boxes_intersect(b, o, gap) for o in placed):
                return False
            if not strict:
                return True
            if bounds is not None and not (
                bounds[0] <= b[0] and b[2] <= bounds[2] and bounds[1] <= b[1] and b[3] <= bounds[3]
            ):
                return False
            return not any(boxes_intersect(b, o) for o in obstacles)

        candidates = [
            p0 + f * d + n * (clearance + half_n + out * h)
            for out in _LABEL_STEPS_OUT
            for f in _LABEL_FRACTIONS
        ]
        nominal = candidates[0]
        chosen = next((box_at(c) for c in candidates if free(box_at(c), True)), None)
        if chosen is None:
            reach = 2.0 * max(w, h) * (len(links) + len(obstacles) + 2)
            if bounds is not None:
                reach = max(reach, float(np.hypot(bounds[2] - bounds[0], bounds[3] - bounds[1])))
            angles = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
            ring = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
            for strict in (True, False):
                for r in np.arange(0.5 * h, reach + h, 0.5 * h):
                    chosen = next(
                        (box_at(c) for c in nominal + r * ring if free(box_at(c), strict)), None
                    )
                    if chosen is not None:
                        break
                if chosen is not None:
                    break
        placed.append(box_at(nominal) if chosen is None else chosen)
    return placed


def link_colour(sender_colour: tuple[int, int, int], bits: float, max_bits: float) -> tuple:
    """Colour of a link carrying ``bits`` (> 0): the sender's colour, paler for fewer bits."""
    frac = min(1.0, max(0.0, bits / max(max_bits, 1e-12)))
    return _mix(sender_colour, 0.5 * (1.0 - frac))


def format_bits(bits: float) -> str:
    """Bit count as a short label: integers as such, others with 3 significant digits."""
    bits = float(bits)
    return str(int(bits)) if bits.is_integer() and abs(bits) < 1e6 else f"{bits:.3g}"


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


def _font(size: float) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size=max(7, int(round(size))))


def _dashed_line(draw, a, b, fill, width: int, dash: float, gap: float) -> None:
    d = b - a
    length = float(np.hypot(d[0], d[1]))
    if length <= 0:
        return
    u = d / length
    s = 0.0
    while s < length:
        e = min(length, s + dash)
        draw.line([tuple(a + u * s), tuple(a + u * e)], fill=fill, width=width)
        s += dash + gap


def _arrow(draw, a, b, fill, width: int, unit: float) -> None:
    d = b - a
    length = float(np.hypot(d[0], d[1]))
    if length <= 0:
        return
    u = d / length
    n = np.array([u[1], -u[0]])
    head = min(0.6 * length, width + 8.0 * unit + 2.0)
    half = 0.5 * width + 3.0 * unit + 1.0
    base = b - u * head
    draw.line([tuple(a), tuple(base + u * 1.0)], fill=fill, width=width)
    draw.polygon([tuple(b), tuple(base + n * half), tuple(base - n * half)], fill=fill)


def _goal_marker(draw, xy, colour, r_goal: float, unit: float) -> None:
    gx, gy = xy
    ring = max(1, int(round(2.0 * unit)))
    draw.ellipse(
        [gx - r_goal, gy - r_goal, gx + r_goal, gy + r_goal],
        fill=_mix(colour, 0.82),
        outline=colour,
        width=ring,
    )
    c = max(2.0, 0.55 * r_goal)
    draw.line([gx - c, gy - c, gx + c, gy + c], fill=colour, width=ring)
    draw.line([gx - c, gy + c, gx + c, gy - c], fill=colour, width=ring)


def _agent_disc(draw, xy, colour, r: float, index: int | None, font, unit: float) -> None:
    x, y = xy
    draw.ellipse(
        [x - r, y - r, x + r, y + r],
        fill=colour,
        outline=(0, 0, 0),
        width=max(1, int(round(1.5 * unit))),
    )
    if index is not None:
        draw.text((x, y), str(index), fill=(255, 255, 255), font=font, anchor="mm")


def _legend(draw, layout: FrameLayout, config: NavConfig, k: int, with_links: bool, font) -> None:
    """Draw the static legend row at the bottom of the footer."""
    u = layout.unit
    y = layout.size - 0.28 * layout.footer
    x = 8.0 * u + 2
    r = max(3.0, 8.0 * u)
    right = layout.size - 4
    pad = 14.0 * u

    def text(s: str) -> None:
        nonlocal x
        if x + draw.textlength(s, font=font) <= right:
            draw.text((x, y), s, fill=(40, 40, 40), font=font, anchor="lm")
        x += draw.textlength(s, font=font) + pad

    for i in range(min(k, 8)):
        if x + 2 * r > right:
            return
        _agent_disc(draw, (x + r, y), AGENT_COLOURS[i % len(AGENT_COLOURS)], r, None, font, u)
        x += 2 * r + 3 * u
    x += 3 * u
    text("agents")
    if x + 2 * r > right:
        return
    _goal_marker(draw, (x + r, y), (90, 90, 90), r, u)
    x += 2 * r + 4 * u
    text(f"goals (radius {config.success_radius:g})")
    if not with_links:
        return
    seg = 34.0 * u
    if x + seg > right:
        return
    _arrow(draw, np.array([x, y]), np.array([x + seg, y]), AGENT_COLOURS[0], max(2, int(5 * u)), u)
    x += seg + 4 * u
    text("bits i->j")
    if x + seg > right:
        return
    width = max(1, int(round(1.5 * u)))
    a, b = np.array([x, y]), np.array([x + seg, y])
    _dashed_line(draw, a, b, SILENT_COLOUR, width, 7 * u + 1, 5 * u + 1)
    x += seg + 4 * u
    text("silent")


def render_frames(
    states_sequence: NavState | Sequence[NavState],
    config: NavConfig,
    link_bits: np.ndarray | None = None,
    size: int = DEFAULT_SIZE,
) -> list[np.ndarray]:
    """Draw one ``(size, size, 3)`` uint8 RGB frame per state (layout: module docstring).

    ``states_sequence``: a list of :class:`NavState` or one state with a leading time axis (T).
    ``link_bits``: optional ``(T, K, K)`` payload bits sent ``i -> j`` (``[t, i, j]``), drawn on
    frame ``t``; a ``(T - 1, K, K)`` array is padded with a zero last step (the terminal state
    sends nothing). The diagonal is ignored. Line widths and colours are relative to the largest
    entry of the episode.
    """
    s = _stack_states(states_sequence)
    num_frames, k = s["pos"].shape[:2]
    link_bits = _episode_link_bits(link_bits, num_frames, k)
    layout = frame_layout(config, size, fit_view_limit(s["pos"], s["goals"], config))
    pens = _Pens.of(layout, config, link_bits)
    background = _background(pens, config, k, with_links=link_bits is not None)
    frames = []
    cum_bits = 0.0
    for t in range(num_frames):
        bits = None if link_bits is None else link_bits[t]
        cum_bits += 0.0 if bits is None else float(bits.sum())
        frames.append(_draw_frame(background.copy(), pens, config, s, t, bits, cum_bits))
    return frames


def _draw_frame(img, pens: _Pens, config: NavConfig, s: dict, t: int, bits, cum_bits) -> np.ndarray:
    """Frame ``t`` drawn on ``img`` (a copy of the background): goals, links, agents, the links'
    labels, header and caption. ``bits``: the step's (K, K) link bits, or None; ``cum_bits``:
    the team's bits up to and including this step."""
    draw = ImageDraw.Draw(img)
    layout = pens.layout
    pos = layout.to_px(s["pos"][t])
    goals = layout.to_px(s["goals"][t])
    for i, goal in enumerate(goals):
        _goal_marker(draw, goal, _agent_colour(i), pens.r_goal, layout.unit)
    labels = [] if bits is None else _draw_links(draw, pens, pos, bits)
    for i, xy in enumerate(pos):
        _agent_disc(draw, xy, _agent_colour(i), pens.r_agent, i, pens.agent_font, layout.unit)
    if labels:
        _draw_labels(draw, pens, pos, goals, labels)
    _draw_header(draw, pens, config, s, t)
    caption = f"step {int(s['time'][t])}"
    if bits is not None:
        caption += (
            f"   team bits this step: {format_bits(float(bits.sum()))}"
            f"   episode total: {format_bits(cum_bits)}"
        )
    _draw_caption(draw, pens, caption)
    return np.asarray(img, dtype=np.uint8)


def _agent_colour(i: int) -> tuple[int, int, int]:
    return AGENT_COLOURS[i % len(AGENT_COLOURS)]


def _episode_link_bits(link_bits, num_frames: int, k: int) -> np.ndarray | None:
    """``render_frames``'s ``link_bits`` checked, padded to ``num_frames`` steps and with the
    diagonal zeroed (None stays None)."""
    if link_bits is None:
        return None
    link_bits = np.asarray(link_bits, dtype=np.float64)
    if link_bits.ndim != 3 or link_bits.shape[1:] != (k, k):
        raise ValueError(f"link_bits must have shape (T, {k}, {k}), got {link_bits.shape}")
    if link_bits.shape[0] == num_frames - 1:
        link_bits = np.concatenate([link_bits, np.zeros((1, k, k))])
    if link_bits.shape[0] != num_frames:
        raise ValueError(f"link_bits has {link_bits.shape[0]} steps for {num_frames} states")
    return link_bits * (1 - np.eye(k))[None]


@dataclasses.dataclass(frozen=True)
class _Pens:
    """What every frame of one episode is drawn with: its layout, fonts and stroke sizes."""

    layout: FrameLayout
    head_font: ImageFont.FreeTypeFont | ImageFont.ImageFont
    caption_font: ImageFont.FreeTypeFont | ImageFont.ImageFont
    legend_font: ImageFont.FreeTypeFont | ImageFont.ImageFont
    label_font: ImageFont.FreeTypeFont | ImageFont.ImageFont
    agent_font: ImageFont.FreeTypeFont | ImageFont.ImageFont | None
    """None when the discs are too small to hold their index."""
    r_agent: float
    r_goal: float
    offset: float
    """Distance of a link's line from the segment between its agents."""
    clearance: float
    """Distance from that segment that a label keeps."""
    trim_from: float
    trim_to: float
    silent_width: int
    label_pad: float
    label_h: float
    max_bits: float
    """The busiest link's bits in the episode (1 without links)."""
    bounds: Box
    """Where labels may go: the frame between header and footer."""
    label_w: dict[str, float] = dataclasses.field(default_factory=dict)
    """Width of each label text drawn so far (a cache)."""

    @property
    def footer_top(self) -> float:
        return self.layout.size - self.layout.footer

    @classmethod
    def of(cls, layout: FrameLayout, config: NavConfig, link_bits: np.ndarray | None) -> _Pens:
        u = layout.unit
        label_font = _font(max(17.0 * u, 8))
        r_agent = layout.agent_radius
        offset = layout.link_offset
        label_pad = max(1.0, 3.0 * u)
        digits = label_font.getbbox("0123456789", anchor="mm")
        return cls(
            layout=layout,
            head_font=_font(0.5 * layout.header),
            caption_font=_font(0.26 * layout.footer),
            legend_font=_font(0.2 * layout.footer),
            label_font=label_font,
            agent_font=_font(1.15 * r_agent) if r_agent >= 6 else None,
            r_agent=r_agent,
            r_goal=config.success_radius * layout.scale,
            offset=offset,
            clearance=offset + 0.5 * layout.max_link_width + 1.0 * u,
            trim_from=r_agent + 2.0 * u,
            trim_to=r_agent + 3.0 * u,
            silent_width=max(1, int(round(1.5 * u))),
            label_pad=label_pad,
            label_h=digits[3] - digits[1] + 2 * label_pad,
            max_bits=max(1e-12, float(link_bits.max())) if link_bits is not None else 1.0,
            bounds=(2.0, layout.header + 2.0, layout.size - 2.0, layout.size - layout.footer - 2.0),
        )


def _background(pens: _Pens, config: NavConfig, k: int, with_links: bool) -> Image.Image:
    """The static part of every frame: margin band, arena, footer bar and legend."""
    layout, u = pens.layout, pens.layout.unit
    size = layout.size
    background = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(background)
    a = config.arena_half_width
    world = layout.to_px(np.array([[-a, a], [a, -a]]))
    draw.rectangle(layout.arena_box, fill=(228, 228, 228))
    draw.rectangle(
        [tuple(world[0]), tuple(world[1])],
        fill=(255, 255, 255),
        outline=(120, 120, 120),
        width=max(1, int(round(u))),
    )
    footer_top = pens.footer_top
    draw.rectangle([0, footer_top, size, size], fill=(245, 245, 245))
    draw.line([0, footer_top, size, footer_top], fill=(200, 200, 200), width=1)
    _legend(draw, layout, config, k, with_links, pens.legend_font)
    return background


def _draw_links(draw, pens: _Pens, pos: np.ndarray, bits: np.ndarray) -> list:
    """Draw one step's links (``bits`` (K, K)): silent ones dashed, then the others as arrows,
    busiest last so they are on top where lines cross. Returns the labels to place, one
    ``((i, j), text)`` per link that carries bits."""
    u = pens.layout.unit
    k = len(pos)
    labels = []
    active = []
    for i in range(k):
        for j in range(k):
            if i == j:
                continue
            line = link_line(pos[i], pos[j], pens.offset, pens.trim_from, pens.trim_to, i, j)
            if bits[i, j] > 0:
                active.append((i, j, line))
                labels.append(((i, j), format_bits(bits[i, j])))
            elif line is not None:
                _dashed_line(draw, *line, SILENT_COLOUR, pens.silent_width, 7 * u + 1, 5 * u + 1)
    for i, j, line in sorted(active, key=lambda x: bits[x[0], x[1]]):
        if line is None:
            continue
        _arrow(
            draw,
            *line,
            link_colour(_agent_colour(i), bits[i, j], pens.max_bits),
            pens.layout.link_width(bits[i, j], pens.max_bits),
            u,
        )
    return labels


def _draw_labels(draw, pens: _Pens, pos: np.ndarray, goals: np.ndarray, labels: list) -> None:
    """Draw each link's bit count in a box placed by :func:`link_label_boxes`, with a leader
    line back to its link when the box had to move far from it."""
    u = pens.layout.unit
    sizes = []
    for _, text in labels:
        if text not in pens.label_w:
            box = pens.label_font.getbbox(text, anchor="mm")
            pens.label_w[text] = box[2] - box[0] + 2 * pens.label_pad
        sizes.append((pens.label_w[text], pens.label_h))
    r = pens.r_agent
    obstacles = [
        (x - r - 2, y - r - 2, x + r + 2, y + r + 2) for x, y in np.concatenate([pos, goals])
    ]
    links = [ij for ij, _ in labels]
    boxes = link_label_boxes(pos, links, sizes, pens.clearance, pens.bounds, obstacles)
    for ((i, j), text), box in zip(labels, boxes, strict=True):
        colour = _agent_colour(i)
        centre = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
        anchor = pos[i] + (pos[j] - pos[i]) / 3 + link_normal(pos[i], pos[j], i, j) * pens.offset
        if np.hypot(*(centre - anchor)) > pens.clearance + 2.5 * pens.label_h:
            draw.line([tuple(centre), tuple(anchor)], fill=_mix(colour, 0.4), width=1)
        draw.rectangle(box, fill=(255, 255, 255), outline=colour, width=max(1, int(u)))
        ink = tuple(int(0.8 * c) for c in colour)
        draw.text(tuple(centre), text, fill=ink, font=pens.label_font, anchor="mm")


def _draw_header(draw, pens: _Pens, config: NavConfig, s: dict, t: int) -> None:
    """The header bar of step ``t``: the step number and the team's status (green on success)."""
    layout, u = pens.layout, pens.layout.unit
    size = layout.size
    k = s["pos"].shape[1]
    success = bool(s["success"][t])
    at_goal = int((np.hypot(*(s["pos"][t] - s["goals"][t]).T) < config.success_radius).sum())
    draw.rectangle([0, 0, size, layout.header], fill=(30, 110, 30) if success else (40, 40, 40))
    hy = layout.header / 2
    draw.text(
        (6 * u + 2, hy),
        f"step {int(s['time'][t])} / {config.max_steps}",
        fill=(255, 255, 255),
        font=pens.head_font,
        anchor="lm",
    )
    status = "SUCCESS: all agents at their goals" if success else f"{at_goal}/{k} at goal"
    draw.text(
        (size - 6 * u - 2, hy), status, fill=(255, 255, 255), font=pens.head_font, anchor="rm"
    )


def _draw_caption(draw, pens: _Pens, caption: str) -> None:
    """The caption line of the footer."""
    layout, u = pens.layout, pens.layout.unit
    draw.text(
        (8 * u + 2, pens.footer_top + 0.3 * layout.footer),
        caption,
        fill=(20, 20, 20),
        font=pens.caption_font,
        anchor="lm",
    )


def write_gif(
    path: str | Path, frames: Sequence[np.ndarray], fps: float = 10.0, hold_last: float = 1.0
) -> Path:
    """Write RGB frames to an infinitely looping GIF; returns the path.

    The last frame is shown for ``hold_last`` seconds (at least one frame period). All frames share
    one 255-colour palette taken from a sample of them (no dithering), which keeps the colours
    steady between frames and the writing fast (a few seconds for 256 frames of 640 x 640).
    """
    if len(frames) == 0:
        raise ValueError("no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = [np.ascontiguousarray(np.asarray(f, dtype=np.uint8)[..., :3]) for f in frames]
    sample = np.concatenate(arrays[:: max(1, len(arrays) // 8)] + [arrays[-1]], axis=0)
    palette = Image.fromarray(sample).quantize(
        colors=255, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE
    )
    images = [
        Image.fromarray(a).quantize(palette=palette, dither=Image.Dither.NONE) for a in arrays
    ]
    period = 1000.0 / fps
    images[0].save(
        path,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=[period] * (len(images) - 1) + [max(period, 1000.0 * hold_last)],
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
    states = scripted_episode(key, config, policy_fn, keep_states=True)[3]
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
    size: int = DEFAULT_SIZE
    """Frame width and height in pixels."""
    fps: float = 10.0
    """GIF frames per second (of kept frames)."""
    stride: int = 1
    """Keep every stride-th frame (the last frame is always kept)."""
    env: NavConfig = dataclasses.field(default_factory=NavConfig)
    """Environment configuration."""


def main(args: RenderArgs) -> Path:
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
