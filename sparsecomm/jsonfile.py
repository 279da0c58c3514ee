"""Results files as strict JSON: no NaN or infinity ever reaches one.

JSON has no NaN. :func:`write_json` writes a non-finite number as ``null`` and, when the
document is an object, lists where and why under ``"nulls"`` (``{"runs[0].bits_per_step": "not
finite (nan)"}``), so a reader never mistakes a missing value for a measured one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def finite(data, nulls: dict | None = None, where: str = ""):
    """``data`` with every non-finite number replaced by ``None`` (recorded in ``nulls``)."""
    if isinstance(data, dict):
        return {k: finite(v, nulls, f"{where}.{k}" if where else str(k)) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [finite(v, nulls, f"{where}[{i}]") for i, v in enumerate(data)]
    if isinstance(data, float | np.floating) and not math.isfinite(data):
        if nulls is not None:
            nulls[where] = f"not finite ({float(data)})"
        return None
    if isinstance(data, np.generic):
        return data.item()
    return data


def write_json(path: str | Path, data) -> Path:
    """Write ``data`` as strict JSON (see the module docstring)."""
    nulls: dict = {}
    data = finite(data, nulls)
    if nulls and isinstance(data, dict):
        data = {**data, "nulls": nulls}
    path = Path(path)
    path.write_text(json.dumps(data, indent=2, allow_nan=False))
    return path


def read_json(path: str | Path) -> dict | None:
    """The JSON document at ``path``, or None when there is no file."""
    path = Path(path)
    return json.loads(path.read_text()) if path.exists() else None
