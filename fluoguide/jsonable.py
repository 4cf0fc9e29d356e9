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


def read_json(path, expect=dict, field=None):
    """Parse the JSON file ``path``; FluoInputError naming the file, line and column.

    Parameters
    ----------
    path : str or Path
    expect : type or tuple of types, optional
        The type the top-level value must have (``dict`` by default; None for any).
    field : str, optional
        The option or field the file came from (``--calibration``), for the message.
    """
    from pathlib import Path

    from fluoguide.errors import FluoInputError

    path = Path(path)
    if not path.is_file():
        raise FluoInputError("file not found" if not path.exists() else "not a regular file",
                             file=path, field=field)
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text)
    except UnicodeDecodeError:
        raise FluoInputError("not UTF-8 text", file=path, field=field) from None
    except json.JSONDecodeError as exc:
        raise FluoInputError(f"not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})",
                             file=path, field=field) from None
    except RecursionError:
        raise FluoInputError("JSON nested too deeply", file=path, field=field) from None
    except OSError as exc:
        raise FluoInputError(f"cannot read ({exc.strerror})", file=path, field=field) from None
    if expect is not None and not isinstance(data, expect):
        want = expect.__name__ if isinstance(expect, type) else "/".join(t.__name__ for t in expect)
        raise FluoInputError(f"expected a JSON {'object' if expect is dict else want}, "
                             f"got {type(data).__name__}", file=path, field=field)
    return data
