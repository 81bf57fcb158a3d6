"""Strict JSON: every file and line MineTwin writes parses in any JSON reader.

Python's ``json`` writes bare ``NaN`` and ``Infinity`` by default, which
JavaScript's ``JSON.parse`` and most other parsers refuse. Here a non-finite
number is written as ``null`` (a value that does not exist), numpy scalars and
arrays as numbers and lists, and ``allow_nan=False`` makes any miss an error.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def plain(value):
    """``value`` with numpy types as Python ones and non-finite floats as None."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "f":  # one pass over the array, not one call per element
            rows = value.astype(object)
            rows[~np.isfinite(value)] = None
            return rows.tolist()
        return value.tolist() if value.dtype.kind in "biu" else plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def dumps(value, **options) -> str:
    """``json.dumps`` of ``plain(value)`` with ``allow_nan=False``."""
    return json.dumps(plain(value), allow_nan=False, **options)


def write(path, value, *, indent: int | None = 2, sort_keys: bool = False) -> Path:
    """Write ``value`` as strict JSON (and a final newline) to ``path``; returns the path."""
    path = Path(path)
    path.write_text(dumps(value, indent=indent, sort_keys=sort_keys) + "\n")
    return path
