"""One JSON convention for every file calib writes: numpy scalars/arrays and paths become JSON values,
NaN/inf become ``null`` (JSON has no NaN), and keys starting with ``_`` (in-memory only) can be dropped."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def jsonable(obj, drop_private=False):
    """``obj`` with numpy types converted and non-finite floats made None, at any depth.

    drop_private : also drop dict keys that start with ``_`` (arrays kept in memory for plots)."""
    if isinstance(obj, dict):
        return {str(k) if isinstance(k, Path) else k: jsonable(v, drop_private) for k, v in obj.items()
                if not (drop_private and str(k).startswith("_"))}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, drop_private) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fiu" and (obj.dtype.kind != "f" or np.isfinite(obj).all()):
            return obj.tolist()   # numbers only, all finite: Python ints/floats already (no walk per element)
        return jsonable(obj.tolist(), drop_private)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def dumps_json(obj, drop_private=False, **kw):
    """``json.dumps`` of :func:`jsonable` (``obj``); NaN written as null, never as the invalid ``NaN``."""
    return json.dumps(jsonable(obj, drop_private), allow_nan=False, **kw)
