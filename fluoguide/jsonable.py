"""JSON text of results: numpy types converted, NaN and inf written as null."""

from __future__ import annotations

import json

import numpy as np


def to_jsonable(obj):
    """Plain Python of ``obj``: dicts, lists, numbers; NaN/inf become ``None``."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None  # JSON has no NaN/inf; null says "not defined"
    return obj


def dumps(result, indent=2):
    """JSON text of a result dict (numpy types converted, NaN/inf -> null)."""
    return json.dumps(to_jsonable(result), indent=indent, allow_nan=False)
