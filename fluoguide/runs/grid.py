"""Grids of parameters: value lists from the command line, study files, products.

A study file is a JSON or YAML mapping of axis name -> one value or a list of
values; which names exist and what each may hold is the caller's (a Lib's)
schema. Everything here refuses bad input with one FluoInputError naming the
file, the field and the value.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

from fluoguide.errors import FluoInputError

MAX_FILE_BYTES = 1 << 20     # a study file is a few lines; anything larger is not one
MAX_TASKS = 100_000          # one run's grid; more is a typo (or a job for several runs)


def parse_values(text, field, kind=float, file=None):
    """``"0.1,1,10"`` -> [0.1, 1.0, 10.0]: a comma-separated list of numbers or words.

    ``kind`` is ``float``, ``int`` or ``str``. Numbers must be finite; ints whole.
    """
    if isinstance(text, (list, tuple)):
        items = list(text)
    else:
        items = [t.strip() for t in str(text).split(",")]
    if not items or any(isinstance(t, str) and t == "" for t in items):
        raise FluoInputError("expected a comma-separated list of values", file=file, field=field,
                             value=text)
    return [convert(t, field, kind, file) for t in items]


def convert(value, field, kind, file=None):
    """One value as ``kind`` (float: finite; int: whole; str: non-empty text)."""
    if kind is str:
        if not isinstance(value, str) or not value.strip():
            raise FluoInputError("expected a word", file=file, field=field, value=value)
        return value.strip()
    if isinstance(value, bool):
        raise FluoInputError("expected a number", file=file, field=field, value=value)
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise FluoInputError("expected a number", file=file, field=field, value=value) from None
    if not math.isfinite(x):
        raise FluoInputError("must be finite", file=file, field=field, value=value)
    if kind is int:
        if x != int(x) or abs(x) > 2**53:
            raise FluoInputError("expected a whole number", file=file, field=field, value=value)
        return int(x)
    return x


def read_small_text(path, what="study file", encoding="utf-8"):
    """The text of a settings file a person wrote (a study or batch file): refused
    (file named, ``what`` it is) when missing, over MAX_FILE_BYTES or not text."""
    p = Path(path)
    if not p.is_file():
        raise FluoInputError(f"{what} not found", file=p)
    if p.stat().st_size > MAX_FILE_BYTES:
        raise FluoInputError(f"{what} is larger than 1 MiB", file=p, value=p.stat().st_size)
    try:
        return p.read_text(encoding=encoding)
    except (OSError, UnicodeDecodeError) as exc:
        raise FluoInputError(f"cannot read the {what} ({exc.__class__.__name__})",
                             file=p) from None


def load_study_file(path, what="study file"):
    """The mapping in a JSON (``.json``) or YAML (``.yaml``/``.yml``) study file
    (or another settings file: ``what`` names it in messages).

    Raises FluoInputError (file named) when the file is missing, too large, not
    parseable, or not a mapping with text keys.
    """
    p = Path(path)
    text = read_small_text(p, what)
    suffix = p.suffix.lower()
    if suffix == ".json":
        from fluoguide.jsonable import read_json

        doc = read_json(p, expect=None)
    elif suffix in (".yaml", ".yml"):
        import yaml

        from fluoguide import strict_yaml

        try:
            doc = strict_yaml.load(text, file=p)        # a key twice is refused
        except (yaml.YAMLError, RecursionError) as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            raise FluoInputError(f"not valid YAML{where}", file=p) from None
    else:
        raise FluoInputError(f"a {what} ends in .json, .yaml or .yml", file=p, value=p.suffix)
    if not isinstance(doc, dict) or not doc:
        raise FluoInputError(f"a {what} holds a mapping of settings (name: value or list)",
                             file=p, value=type(doc).__name__)
    for k in doc:
        if not isinstance(k, str):
            raise FluoInputError("setting names must be text", file=p, value=k)
    return doc


def as_list(value):
    """A setting's values: a list as it is, one value as a one-element list."""
    return list(value) if isinstance(value, (list, tuple)) else [value]


def grid_product(axes, limit=MAX_TASKS, file=None):
    """Every combination of the axes, the first axis varying slowest.

    Parameters
    ----------
    axes : list of (name, list of values)
    limit : int
        Refuse grids with more combinations than this (FluoInputError).

    Returns
    -------
    list of dict
    """
    names = [n for n, _ in axes]
    sizes = [len(v) for _, v in axes]
    for (n, v) in axes:
        if not v:
            raise FluoInputError("an axis of the grid has no values", file=file, field=n)
    total = math.prod(sizes) if sizes else 1
    if total > limit:
        raise FluoInputError(f"the grid has {total} combinations; at most {limit} in one run",
                             file=file, field=" x ".join(names), value=sizes)
    return [dict(zip(names, combo)) for combo in itertools.product(*(v for _, v in axes))]
