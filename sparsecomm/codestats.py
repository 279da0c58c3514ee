"""What a trained team's messages carry, and a code fitted to them (docs/channel.md).

:func:`link_symbols` plays a team's episodes and returns every link's symbol sequence;
:func:`entropies` estimates their entropy (marginal and given the previous step's message, per
element and per link); :func:`measure` counts, on held-out episodes, the bits of every code
against those entropies; :func:`fit_code` (``sparsecomm fit-code``) fits a
:class:`~sparsecomm.channel.fitted.FittedCode` to a run's team and writes it as JSON, for
``--config.channel.code fitted --config.channel.code-file``.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np

from sparsecomm import channel
from sparsecomm.channel.fitted import MAX_GROUP, FittedCode, fit, previous
from sparsecomm.configs import MAX_SEED
from sparsecomm.errors import RunError
from sparsecomm.rollout import rollout
from sparsecomm.runfolder import (
    at_least,
    at_most,
    check_index,
    check_output,
    default_output,
    load_run,
    read_config,
)

FIT_SEED_OFFSET = 2_000_003
"""Fitting episodes use ``config.seed + FIT_SEED_OFFSET + args.seed``: disjoint from training
and from ``sparsecomm eval``'s episodes."""


@dataclasses.dataclass
class FitCode:
    """Fit a code to one trained team's messages and write it as JSON (``sparsecomm fit-code``)."""

    run: Path
    """Folder of a ``sparsecomm train``/``imitate`` run or of an exported team."""
    index: int = 0
    """Which run of the sweep (lambda-major, then budget, then seed)."""
    episodes: int = 2000
    """Episodes whose symbols the code is fitted to. ours: 2000 (on the small task ~60k
    non-silent link-steps; the code's bits on held-out episodes change by < 1% from 1000)."""
    seed: int = 0
    """Seed of the fitting episodes (offset from the run's, so they are not training's), in
    [0, :data:`~sparsecomm.configs.MAX_SEED`] (the PRNG's 32 bits)."""
    group: int = 5
    """Elements per presence group (``FittedCode.group``), in [1, min(elements per message,
    ``channel.fitted.MAX_GROUP`` = 8)]. ours: 5 (2 groups of 32 patterns for the paper's 10
    elements; docs/channel.md compares 1, 2, 5 and 10)."""
    alpha: float = 0.5
    """Smoothing count added to every cell (``FittedCode.alpha``), finite and > 0. ours."""
    out: Path | None = None
    """JSON file to write, a writable file path, not a folder (default: ``<run>/code.json``)."""

    def __post_init__(self):
        at_least(self, index=0, episodes=1, group=1, seed=0)
        at_most(self, "channel.fitted.MAX_GROUP", group=MAX_GROUP)
        at_most(self, "configs.MAX_SEED: the PRNG keeps 32 bits", seed=MAX_SEED)
        alpha = self.alpha
        number = isinstance(alpha, int | float) and not isinstance(alpha, bool)
        if not (number and math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"FitCode.alpha must be a finite number > 0, got {alpha!r}")
        check_output(self, folder=False)


def link_symbols(trainer, channel_cfg, params, key, episodes: int, batch: int = 512):
    """Every link's symbols over ``episodes`` episodes of one team: ``(links, valid)`` with
    links (episodes * K * (K-1), T, C) int64 (episode-major, then sender, then slot) and valid
    (same leading axes, T)."""
    play = jax.jit(
        lambda p, k, n: rollout(trainer.team, trainer.env, channel_cfg, p, k, n, keep_symbols=True),
        static_argnums=2,
    )
    links, valid = [], []
    for i, start in enumerate(range(0, episodes, batch)):
        n = min(batch, episodes - start)
        traj = play(params, jax.random.fold_in(key, i), n)
        m = np.asarray(traj.aside.symbols, np.int64)  # (T, B, K, K-1, C)
        t, b, k, r, c = m.shape
        links.append(m.transpose(1, 2, 3, 0, 4).reshape(b * k * r, t, c))
        valid.append(np.repeat(np.asarray(traj.valid).T, k * r, axis=0))
    return np.concatenate(links), np.concatenate(valid)


def _h(counts) -> float:
    c = np.asarray(counts, np.float64)
    p = c[c > 0] / c.sum()
    return float(-(p * np.log2(p)).sum())


def _cond(x: np.ndarray, y: np.ndarray) -> float:
    """Plug-in ``H(Y | X)`` of paired integer rows (x, y: (N,) or (N, D))."""
    x, y = x.reshape(len(x), -1), y.reshape(len(y), -1)
    joint = np.unique(np.concatenate([x, y], 1), axis=0, return_counts=True)[1]
    return _h(joint) - _h(np.unique(x, axis=0, return_counts=True)[1])


def entropies(links: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """Plug-in entropies of the links' messages, in bits per link-step.

    ``element``: sum over elements of each element's marginal entropy; ``element_given_prev``:
    the same given that element's previous symbol (an upper bound on the link's entropy given
    its previous message, exact when elements are independent chains; 16 x 16 cells per element,
    well estimated); ``link`` and ``link_given_prev``: the whole message as one symbol (plug-in
    on a huge alphabet: biased low when messages rarely repeat, reported with
    ``distinct_messages``).
    """
    cur, prev = links[valid], previous(links)[valid]
    c = cur.shape[1]
    return {
        "element": sum(_h(np.unique(cur[:, k], return_counts=True)[1]) for k in range(c)),
        "element_given_prev": sum(_cond(prev[:, k], cur[:, k]) for k in range(c)),
        "link": _h(np.unique(cur, axis=0, return_counts=True)[1]),
        "link_given_prev": _cond(prev, cur),
        "distinct_messages": float(len(np.unique(cur, axis=0))),
        "link_steps": float(len(cur)),
    }


def _old_wire(m: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """The former wire format (docs/channel.md): every element framed as Elias-gamma
    of m + 1 (2 L(m) + 1 bits, a null 1 bit), as logged (no padding, no CRC) and as the
    packet (padded to a byte, CRC-16)."""
    lengths = 2 * np.floor(np.log2(m + 1)).astype(np.int64) + 1
    logged = lengths.sum(-1)
    return logged, 8 * ((logged + 7) // 8) + 16


def _range_coder_bits(code: FittedCode, cur: np.ndarray, prev: np.ndarray) -> float | None:
    """Mean bits per link-step of the same model coded per packet with constriction's range
    coder (32-bit words) instead of Huffman, or None when constriction is not installed."""
    try:
        import constriction
    except ImportError:
        return None
    t = code._tables
    pat = np.asarray(code.pattern_counts, np.float64) + code.alpha
    sym = np.asarray(code.symbol_counts, np.float64) + code.alpha
    total = 0
    for m, p in zip(cur, prev, strict=True):
        if not m.any():
            continue
        enc = constriction.stream.queue.RangeEncoder()
        for g, (elems, q, pq) in enumerate(
            zip(t["groups"], code._patterns(m != 0), code._patterns(p != 0), strict=True)
        ):
            probs = pat[g, pq, : 1 << len(elems)]
            model = constriction.stream.model.Categorical(probs / probs.sum(), perfect=False)
            enc.encode(np.array([q], np.int32), model)
        for k in np.flatnonzero(m):
            probs = sym[k, p[k]]
            model = constriction.stream.model.Categorical(probs / probs.sum(), perfect=False)
            enc.encode(np.array([m[k] - 1], np.int32), model)
        total += 32 * len(enc.get_compressed())
    return total / len(cur)


def measure(code: FittedCode, links: np.ndarray, valid: np.ndarray, levels: int) -> dict:
    """Bits per link-step of every code on held-out ``links`` (not the ones ``code`` was fitted
    to), beside their entropies (:func:`entropies`)."""
    prev = previous(links)
    cur, pr = links[valid], prev[valid]
    old_logged, old_packet = _old_wire(cur, levels)
    model = code.ideal_bits(cur, pr)
    row = {
        "payload": float(np.asarray(channel.payload_bits(cur, "paper")).sum(-1).mean()),
        "wire_old_logged": float(old_logged.mean()),
        "wire_old_packet": float(old_packet.mean()),
        "wire_silence_free": float(np.asarray(channel.wire_bits(cur, "paper")).mean()),
        "fitted_code_bits": float(np.asarray(code.code_bits(cur, pr)).mean()),
        "fitted_model_bits": float(model.mean()),
        "wire_fitted": float(np.asarray(channel.wire_bits(cur, code, prev=pr)).mean()),
        "wire_fitted_no_crc": float(
            np.asarray(channel.wire_bits(cur, code, prev=pr, crc=False)).mean()
        ),
        "silent_links": float((cur == 0).all(-1).mean()),
        **{f"H_{k}": v for k, v in entropies(links, valid).items()},
    }
    ranged = _range_coder_bits(code, cur, pr)
    if ranged is not None:
        row["fitted_range_coder_bits"] = ranged
    return row


def fit_code(args: FitCode) -> Path:
    """Fit a code to run ``args.index`` of ``args.run`` and write it (``sparsecomm fit-code``)."""
    out = default_output(args, Path(args.run) / "code.json")
    elements = read_config(args.run).channel.num_elements  # metadata only, before any work
    if args.group > elements:
        raise RunError(
            f"FitCode.group must be in [1, {min(elements, MAX_GROUP)}] (a run of {elements} "
            f"elements per message), got {args.group}"
        )
    config, trainer, runs, actor = load_run(args.run)
    check_index(args, runs)
    params = jax.tree.map(lambda x: x[args.index], actor)
    key = jax.random.key(config.seed + FIT_SEED_OFFSET + args.seed)
    links, valid = link_symbols(trainer, config.channel, params, key, args.episodes)
    code = fit(links, valid, levels=config.channel.levels, group=args.group, alpha=args.alpha)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(code.to_json())
    busy = valid & (links != 0).any(-1)
    print(f"fitted to {int(busy.sum())} non-silent link-steps of {args.episodes} episodes -> {out}")
    return out
