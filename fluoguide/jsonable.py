"""JSON text of results (numpy types converted, NaN and inf written as null), and
JSON read strictly: a key given twice in one object is refused.

Python's ``json`` (like most parsers) keeps the last of two equal keys without a
word, so ``{"n": 1.37, ..., "n": 2.9}`` changes the physics silently; every
reader of a user's JSON (files, a recording's log lines, MRML attributes) goes
through :func:`loads` or :func:`read_json`, which refuse it naming the file and
the path of keys (``regions.3.n``, ``cases[0].labels``).
"""

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


class _Marked(dict):
    """A parsed object that remembers the first key it saw twice."""

    duplicate = None


def _pairs_strict(pairs):
    d = dict(pairs)
    if len(d) != len(pairs):
        raise _DuplicateKey
    return d


def _pairs_marking(pairs):
    d = _Marked()
    for k, v in pairs:
        if k in d and d.duplicate is None:
            d.duplicate = k
        d[k] = v
    return d


class _DuplicateKey(Exception):
    pass


def _first_duplicate(data):
    """(path of keys, key) of the first object, in document order, that has a
    key twice (``data`` parsed with :func:`_pairs_marking`); iterative, so a
    deep document costs no recursion."""
    stack = [(data, "")]
    while stack:
        obj, path = stack.pop()
        if isinstance(obj, dict):
            if obj.duplicate is not None:
                return (f"{path}.{obj.duplicate}" if path else obj.duplicate), obj.duplicate
            stack.extend(reversed([(v, f"{path}.{k}" if path else k) for k, v in obj.items()]))
        elif isinstance(obj, list):
            stack.extend(reversed([(v, f"{path}[{i}]") for i, v in enumerate(obj)]))
    return "", None


def loads(text, file=None, field=None):
    """``json.loads(text)``, refusing a key given twice in one object.

    Parameters
    ----------
    text : str
        JSON text.
    file : str or Path, optional
        Where the text came from, for the message.
    field : str, optional
        What the text is (an option, ``line 7`` of a log, a node attribute),
        put before the path of keys in the message.

    Returns
    -------
    object
        The parsed value (objects are plain dicts).

    Raises
    ------
    FluoInputError
        On a duplicate key: the file, ``field: path.of.keys`` and the key.
    json.JSONDecodeError, RecursionError
        As ``json.loads`` (the caller words them for its file).
    """
    try:
        return json.loads(text, object_pairs_hook=_pairs_strict)
    except _DuplicateKey:
        pass
    # rare: parse again, marking, to say where the key is
    from fluoguide.errors import FluoInputError

    path, key = _first_duplicate(json.loads(text, object_pairs_hook=_pairs_marking))
    where = ": ".join(str(w) for w in (field, path) if w)
    raise FluoInputError("key given twice in one JSON object (JSON readers silently keep the "
                         "last one): give it once", file=file, field=where, value=key)


def read_json(path, expect=dict, field=None):
    """Parse the JSON file ``path``; FluoInputError naming the file, line and column
    (or, for a key given twice in one object, the path of keys: :func:`loads`).

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
        data = loads(text, file=path, field=field)
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
