"""JSON for the commands' ``--json`` output and the daemon's replies: strict JSON (``allow_nan=False``)."""
from __future__ import annotations

import numpy as np


def json_safe(obj):
    """``obj`` with non-finite floats as None and numpy scalars as Python numbers, recursively
    through dicts (keys as str), lists and tuples."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
