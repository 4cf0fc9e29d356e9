"""One error type for bad input, so every entry point fails the same way.

A ``FluoInputError`` names the file, the field and the offending value; the
CLI turns it into a one-line message and exit code 2.

Every message is one line: :func:`one_line` escapes the control characters a
file name or a value may carry (a newline in a path would split the message,
an escape sequence would drive the terminal).
"""

from __future__ import annotations


def one_line(text, limit=None):
    """``text`` with every non-printable character escaped as Python writes it
    (a newline as ``\\n``, ESC as ``\\x1b``, a right-to-left override as
    ``\\u202e``), so it shows as one line of what it holds.

    Backslashes already there are kept as they are, so escaping twice changes
    nothing (a message wrapped in another keeps its text). ``limit`` cuts the
    result to that many characters (with ``...``).
    """
    text = str(text)
    if not text.isprintable():
        text = "".join(c if c.isprintable() else c.encode("unicode_escape", "backslashreplace")
                       .decode("ascii") for c in text)
    if limit is not None and len(text) > limit:
        text = text[: max(0, limit - 3)] + "..."
    return text


class FluoError(Exception):
    """Base class of the project's own errors.

    Its text is what the user reads (``fluo: error: TEXT``): one line, see
    :func:`one_line`.
    """

    def __str__(self):
        return one_line(super().__str__())


class FluoInputError(FluoError, ValueError):
    """Bad input: a file, field or value that cannot be used.

    The message is one line whatever the parts hold (:func:`one_line`); the
    attributes keep them as given.

    Parameters
    ----------
    problem : str
        What is wrong, in words.
    file : str or path, optional
        The file the bad input came from.
    field : str, optional
        The field, argument or node name.
    value : object, optional
        The offending value (shown with ``repr``).
    """

    def __init__(self, problem, file=None, field=None, value=None):
        self.problem = str(problem)
        self.file = None if file is None else str(file)
        self.field = field
        self.value = value
        parts = []
        if self.file:
            parts.append(self.file)
        if field:
            parts.append(str(field))
        where = ": ".join(parts)
        text = f"{where}: {self.problem}" if where else self.problem
        if value is not None:
            text += f" (got {value!r})"
        super().__init__(text)


class FluoCancelled(FluoError):
    """Raised inside long work when the user cancels it."""


class FluoDeviceError(FluoError):
    """A device or a peer (tracker, OpenIGTLink server, camera) misbehaved.

    Not the user's bad input: the CLI prints one line and exits with code 1.
    """


def require_finite(name, value, file=None):
    """Raise FluoInputError unless every element of ``value`` is finite."""
    import numpy as np

    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        bad = arr[~np.isfinite(arr)].ravel()[0]
        raise FluoInputError("must be finite", file=file, field=name, value=float(bad))
    return arr


def require_positive(name, value, file=None, allow_zero=False):
    """Raise FluoInputError unless ``value`` (scalar or array) is > 0 (or >= 0)."""
    import numpy as np

    arr = require_finite(name, value, file=file)
    ok = arr >= 0 if allow_zero else arr > 0
    if not np.all(ok):
        bad = arr[~ok].ravel()[0]
        need = "non-negative" if allow_zero else "positive"
        raise FluoInputError(f"must be {need}", file=file, field=name, value=float(bad))
    return arr


def check_number(name, value, lo=None, hi=None, *, lo_open=False, hi_open=False, integer=False,
                 file=None, what=None):
    """``value`` if it is a finite number within the bounds, else FluoInputError.

    NaN passes every ``<``/``>`` range check (all its comparisons are False), so
    each parameter that reaches arithmetic is checked here, where it is used.

    Parameters
    ----------
    name : str
        The field or option named in the message (``"--views"``, ``"noise_sigma"``).
    value : number
    lo, hi : number, optional
        Bounds (inclusive unless ``lo_open`` / ``hi_open``).
    integer : bool
        Require an integer (bool is refused).
    file : path, optional
        The file the value came from.
    what : str, optional
        The requirement in words, for every message (default: built from the bounds).
    """
    import numbers

    import numpy as np

    ok_type = (isinstance(value, numbers.Integral) if integer else isinstance(value, numbers.Real))
    if isinstance(value, (bool, np.bool_)) or not ok_type:
        raise FluoInputError(what or ("must be an integer" if integer else "must be a number"),
                             file=file, field=name, value=value)
    if not np.isfinite(value):
        raise FluoInputError(what or "must be a finite number", file=file, field=name,
                             value=float(value))
    bad = ((lo is not None and (value <= lo if lo_open else value < lo))
           or (hi is not None and (value >= hi if hi_open else value > hi)))
    if bad:
        if what is None:
            lb = "(" if lo_open else "["
            rb = ")" if hi_open else "]"
            what = f"must be within {lb}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{rb}"
        raise FluoInputError(what, file=file, field=name, value=value)
    return value


def seeded_rng(seed, name="seed"):
    """``numpy.random.default_rng(seed)`` for a seed in 0..2**32-1 (None: fresh entropy;
    a Generator is passed through); anything else is a FluoInputError naming ``name``."""
    import numpy as np

    if seed is None or isinstance(seed, np.random.Generator):
        return np.random.default_rng(seed)
    check_number(name, seed, 0, 2**32 - 1, integer=True, what="must be an integer within 0..2**32-1")
    return np.random.default_rng(int(seed))
