"""Checkpoints that cannot lie: msgpack for arrays (``flax.serialization``), JSON for configs.

A checkpoint folder holds ``state.msgpack`` (the batched train state of every run of a sweep)
and ``config.json`` (the configuration, the sweep axes, the SHA-256 of ``state.msgpack``, and
the SHA-256 of ``config.json``'s own other fields).
Loading executes no code from the files.

A save writes a whole new folder beside the old one (``<name>.new``: both files, each fsynced),
then swaps it in by renames (``<name>`` -> ``<name>.old``, ``<name>.new`` -> ``<name>``, then the
old one is removed). A run killed at any moment therefore leaves either the previous checkpoint
or the new one, whole; :func:`load_meta` and :func:`load` find whichever survived. A file that
was changed, truncated or removed afterwards is refused with a :class:`CheckpointError` naming
it, never loaded as if it were right.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import jax
import numpy as np
from flax import serialization

from sparsecomm.errors import CheckpointError
from sparsecomm.sharding import is_key, is_primary, raw_keys, to_host

STATE, META = "state.msgpack", "config.json"


def _write(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _sync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save(folder: str | os.PathLike, state, meta: dict) -> None:
    """Save a pytree ``state`` (PRNG keys stored as their raw data) and JSON ``meta``.

    Under ``jax.distributed`` every process must call it (the state is gathered); process 0
    writes.
    """
    raw = to_host(state)
    if not is_primary():
        return
    folder = Path(folder)
    new, old = folder.with_name(folder.name + ".new"), folder.with_name(folder.name + ".old")
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir(parents=True)
    data = serialization.to_bytes(raw)
    _write(new / STATE, data)
    meta = {**meta, "state_sha256": hashlib.sha256(data).hexdigest()}
    meta["meta_sha256"] = _meta_digest(meta)
    _write(new / META, json.dumps(meta, indent=2).encode())
    _sync_dir(new)
    if folder.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(folder, old)
    os.replace(new, folder)
    _sync_dir(folder.parent)
    shutil.rmtree(old, ignore_errors=True)


def _meta_digest(meta: dict) -> str:
    """SHA-256 of the metadata itself (every field but this digest, keys sorted)."""
    rest = {k: v for k, v in meta.items() if k != "meta_sha256"}
    return hashlib.sha256(json.dumps(rest, sort_keys=True).encode()).hexdigest()


def _current(folder: str | os.PathLike) -> Path:
    """The folder holding the checkpoint: ``folder``, or ``folder.old`` when a save was
    interrupted between its two renames."""
    folder = Path(folder)
    old = folder.with_name(folder.name + ".old")
    if not folder.exists() and old.exists():
        return old
    return folder


def exists(folder: str | os.PathLike) -> bool:
    """A checkpoint folder is there (whole or not: loading it says which)."""
    return _current(folder).exists()


def meta_file(folder: str | os.PathLike) -> Path:
    """The checkpoint's ``config.json`` (in ``folder``, or ``folder.old`` after an interrupted
    save): the file a refusal of its metadata names."""
    return _current(folder) / META


def _read(folder: str | os.PathLike, name: str) -> tuple[Path, bytes]:
    """The bytes of one checkpoint file; missing or unreadable (a folder in its place, no
    permission, an I/O error: any ``OSError``) is a ``CheckpointError`` naming it."""
    path = _current(folder) / name
    try:
        if not path.exists():
            raise CheckpointError(f"checkpoint {folder} is incomplete: {path} is missing")
        return path, path.read_bytes()
    except OSError as e:
        reason = e.strerror or type(e).__name__
        raise CheckpointError(f"checkpoint file {path} cannot be read ({reason})") from None


def load_meta(folder: str | os.PathLike) -> dict:
    """The JSON metadata of a checkpoint (``CheckpointError`` if missing or unreadable)."""
    path, data = _read(folder, META)
    try:
        meta = json.loads(data.decode())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"checkpoint file {path} is damaged (not valid JSON: {e})") from None
    if not isinstance(meta, dict) or "state_sha256" not in meta or "meta_sha256" not in meta:
        raise CheckpointError(
            f"checkpoint file {path} has no digests (damaged, or written by an older "
            "sparsecomm that did not record them)"
        )
    if _meta_digest(meta) != meta["meta_sha256"]:
        raise CheckpointError(
            f"checkpoint file {path} is damaged: its SHA-256 differs from the one recorded when "
            "it was saved"
        )
    return meta


ADDED_FIELDS = {("budget", "held"): ("budget", "log_weight")}
"""State fields added after checkpoints were first written: a checkpoint without one takes its
value from the named field (``held``, the bit-budget controller's last good price, the
bounded relief of docs/budget.md, starts at the current price)."""


def _upgrade(state: dict) -> dict:
    for (part, field), (src_part, src) in ADDED_FIELDS.items():
        sub = state.get(part) if isinstance(state, dict) else None
        if isinstance(sub, dict) and field not in sub and src in state.get(src_part, {}):
            sub[field] = state[src_part][src]
    return state


def load(folder: str | os.PathLike, template):
    """Restore a state saved by :func:`save` into the structure of ``template``, after checking
    the SHA-256 of ``state.msgpack`` against the one recorded at save time."""
    meta = load_meta(folder)
    path, data = _read(folder, STATE)
    if hashlib.sha256(data).hexdigest() != meta["state_sha256"]:
        raise CheckpointError(
            f"checkpoint file {path} is damaged: its SHA-256 differs from the one recorded when "
            f"it was saved ({len(data)} bytes now)"
        )
    raw_template = raw_keys(template)
    try:
        raw = serialization.from_state_dict(
            raw_template, _upgrade(serialization.msgpack_restore(data))
        )
        _check_shapes(raw_template, raw, path)
        return jax.tree.map(
            lambda t, r: jax.random.wrap_key_data(r) if is_key(t) else jax.numpy.asarray(r),
            template,
            raw,
        )
    except (ValueError, TypeError, KeyError) as e:
        raise CheckpointError(
            f"checkpoint file {path} does not hold this run's state ({type(e).__name__}: {e})"
        ) from None


def _check_shapes(template, raw, path: Path) -> None:
    """Refuse arrays whose shapes are not the template's (``from_state_dict`` does not look):
    a leading (run) axis of another length means that ``config.json``'s sweep (its seeds, lams
    and budgets) is not the one the state was saved from."""
    leaves = jax.tree_util.tree_leaves_with_path(template)
    for (where, t), r in zip(leaves, jax.tree.leaves(raw), strict=True):
        want, got = tuple(np.shape(t)), tuple(np.shape(r))
        if want[:1] != got[:1]:
            raise CheckpointError(
                f"checkpoint file {path} holds {got[0] if got else 0} run(s), but {META}'s "
                f"sweep (seeds x lams x budgets) has {want[0] if want else 0}"
            )
        if want != got:
            raise CheckpointError(
                f"checkpoint file {path} does not hold this run's state: "
                f"{jax.tree_util.keystr(where)} has shape {got}, this run's is {want}"
            )
