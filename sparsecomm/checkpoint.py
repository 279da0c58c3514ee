"""Checkpoints without pickle: msgpack for arrays (``flax.serialization``), JSON for configs.

A checkpoint folder holds ``state.msgpack`` (the batched train state of every run of a sweep) and
``config.json`` (the configuration and the sweep axes). Loading executes no code from the file.
Writes are atomic (temporary file, then rename), so a run killed mid-write keeps the previous
checkpoint.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
from flax import serialization

from sparsecomm.sharding import is_key, is_primary, raw_keys, to_host


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save(folder: str | os.PathLike, state, meta: dict) -> None:
    """Save a pytree ``state`` (PRNG keys stored as their raw data) and JSON ``meta``.

    Under ``jax.distributed`` every process must call it (the state is gathered); process 0
    writes.
    """
    raw = to_host(state)
    if not is_primary():
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _atomic_write(folder / "state.msgpack", serialization.to_bytes(raw))
    _atomic_write(folder / "config.json", json.dumps(meta, indent=2).encode())


def load_meta(folder: str | os.PathLike) -> dict:
    path = Path(folder) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint in {folder} (missing {path.name})")
    return json.loads(path.read_text())


def load(folder: str | os.PathLike, template):
    """Restore a state saved by :func:`save` into the structure of ``template``."""
    path = Path(folder) / "state.msgpack"
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint in {folder} (missing {path.name})")
    raw_template = raw_keys(template)
    raw = serialization.from_bytes(raw_template, path.read_bytes())
    return jax.tree.map(
        lambda t, r: jax.random.wrap_key_data(r) if is_key(t) else jax.numpy.asarray(r),
        template,
        raw,
    )


def exists(folder: str | os.PathLike) -> bool:
    return (Path(folder) / "state.msgpack").exists()
