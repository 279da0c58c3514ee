"""Where code ran: the machine and software, the code's git commit and source digest (read by
the benchmarks, the scripts and the paper's pipelines)."""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
from pathlib import Path

import jax
import jaxlib

PACKAGE = Path(__file__).parent
"""The ``sparsecomm`` package folder: its sources are digested, its git repository asked."""


def hardware() -> dict:
    """The machine and software this process runs on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    dev = jax.devices()[0]
    return {
        "cpu": cpu,
        "cpu_cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "device": str(dev),
        "device_kind": dev.device_kind,
        "devices": len(jax.devices()),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "python": platform.python_version(),
        "os": platform.platform(),
    }


def source_digest() -> str:
    """SHA-256 (first 16 hex digits) of the package's Python sources, in path order: names the
    code that ran even where the git metadata is missing or stale."""
    h = hashlib.sha256()
    for path in sorted(PACKAGE.rglob("*.py")):
        h.update(path.relative_to(PACKAGE).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:16]


def git_commit() -> str | None:
    """The short commit of the code, with ``+changes`` if tracked files differ from it."""

    def git(*args: str) -> str:
        out = subprocess.run(
            ["git", *args], capture_output=True, text=True, cwd=PACKAGE, timeout=10
        )
        return out.stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        if commit and git("status", "--porcelain", "--untracked-files=no"):
            commit += "+changes"
        return commit or None
    except (OSError, subprocess.SubprocessError):
        return None
