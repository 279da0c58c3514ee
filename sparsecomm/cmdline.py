"""Checks of what a command receives before it is parsed or JAX starts: an empty value of a
path flag (``Path('')`` reads as the current folder) and the host device count that
``JAX_NUM_CPU_DEVICES`` or ``XLA_FLAGS`` sets (JAX reads them as it is imported and XLA as its
CPU backend starts; a bad value is a traceback or a fatal error there). Imports no JAX, so
:func:`sparsecomm.cli.script` runs these checks before anything imports it."""

from __future__ import annotations

import dataclasses
import os
import typing
from collections.abc import Mapping
from pathlib import Path

DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"
"""The XLA flag (in ``XLA_FLAGS``) that sets the number of CPU devices."""


def _positive_integer(text: str) -> bool:
    text = text.strip()
    return text.isascii() and text.isdigit() and int(text) > 0


def check_device_counts(environ: Mapping[str, str] = os.environ) -> None:
    """Refuse a ``JAX_NUM_CPU_DEVICES`` or an ``XLA_FLAGS`` device count (``DEVICE_COUNT_FLAG``)
    that is not a positive integer, with a ``ValueError`` naming the variable."""
    value = environ.get("JAX_NUM_CPU_DEVICES")
    if value is not None and not _positive_integer(value):
        raise ValueError(
            f"JAX_NUM_CPU_DEVICES must be a positive integer (the number of CPU devices), "
            f"got {value!r}"
        )
    for flag in environ.get("XLA_FLAGS", "").split():
        name, eq, count = flag.partition("=")
        if name == DEVICE_COUNT_FLAG and not (eq and _positive_integer(count)):
            raise ValueError(
                f"XLA_FLAGS: {DEVICE_COUNT_FLAG} must be a positive integer (the number of CPU "
                f"devices, as {DEVICE_COUNT_FLAG}=N), got {flag!r}"
            )


def path_flags(cls) -> dict[str, str]:
    """The flags of ``cls``'s fields typed ``Path`` (or ``Path | None``), by flag
    (``--out``: ``out``)."""
    hints = typing.get_type_hints(cls)
    return {
        "--" + f.name.replace("_", "-"): f.name
        for f in dataclasses.fields(cls)
        if Path in (hints[f.name], *typing.get_args(hints[f.name]))
    }


def refuse_empty_paths(cls, argv: list[str]) -> None:
    """Refuse an empty value for a path flag of ``cls`` in ``argv`` (``--out ''``, ``--run=``)
    with a ``ValueError`` naming the field: the parser would read it as the current folder
    (``Path('')`` is ``.``)."""
    paths = path_flags(cls)
    for i, arg in enumerate(argv):
        flag, eq, value = arg.partition("=")
        empty = value == "" if eq else i + 1 < len(argv) and argv[i + 1] == ""
        if flag in paths and empty:
            raise ValueError(f"{cls.__name__}.{paths[flag]} must be a path, got ''")
