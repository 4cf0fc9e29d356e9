"""What a run computes, described as data.

A :class:`Task` is one unit of work: a module-level function, its parameters (plain
JSON values: they become the first columns of the task's row) and the
:class:`Shared` inputs it needs. A Shared input (a mesh, a Jacobian, a
factorisation) is computed once per run by the engine, wherever the run goes,
and handed to every task that names it: a study of twelve lambdas on one
model computes one Jacobian, not twelve.

Functions must be importable by name (``module.function``): a Dask worker on
another machine imports them, it does not receive their code.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Callable

from fluoguide.errors import FluoInputError


def _qualname(func):
    mod = getattr(func, "__module__", None)
    name = getattr(func, "__qualname__", None)
    if not mod or not name or "<" in name:
        raise FluoInputError("a task function must be a module-level function (importable by "
                             "name on a worker)", field="func", value=repr(func))
    return f"{mod}.{name}"


def _canonical(value, where="params"):
    """JSON text of plain values with sorted keys; refuses what JSON cannot hold exactly."""
    def check(v, path):
        if isinstance(v, float) and not math.isfinite(v):
            raise FluoInputError("task parameters must be finite", field=path, value=v)
        if isinstance(v, dict):
            for k, x in v.items():
                if not isinstance(k, str):
                    raise FluoInputError("parameter names must be text", field=path, value=k)
                check(x, f"{path}.{k}")
        elif isinstance(v, (list, tuple)):
            for i, x in enumerate(v):
                check(x, f"{path}[{i}]")
        elif not (v is None or isinstance(v, (str, int, float, bool))):
            raise FluoInputError("task parameters must be plain numbers, text, lists or dicts",
                                 field=path, value=type(v).__name__)
    check(value, where)
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


def task_id(func, params):
    """Stable id of a task: the hash of its function's name and its parameters.

    The same work gets the same id in every run, so a resumed or extended run
    finds the rows it already has whatever the order of its grid.
    """
    text = _qualname(func) + "\n" + _canonical(params)
    return hashlib.sha1(text.encode()).hexdigest()[:16]


@dataclass(frozen=True, eq=False)
class Shared:
    """An input computed once and given to every task that names it.

    Parameters
    ----------
    name : str
        Unique in the run and the same in every run (it names the input in
        progress messages and failure reports), e.g. ``"jacobian 2D fwd 0.5 mm"``.
    func : callable
        Module-level function; called as ``func(*args)``.
    args : tuple
        Plain values, or other Shared inputs (computed first and passed as values).
    """

    name: str
    func: Callable
    args: tuple = ()

    def __post_init__(self):
        _qualname(self.func)

    def dependencies(self):
        return [a for a in self.args if isinstance(a, Shared)]

    def signature(self):
        """Function name and arguments as text (dependencies by name)."""
        return (_qualname(self.func),
                tuple(a.name if isinstance(a, Shared) else _canonical(a, self.name)
                      for a in self.args))


@dataclass(eq=False)
class Task:
    """One unit of work: ``func(params, **{k: value of inputs[k]})`` -> dict.

    The returned dict holds the row's result fields (numbers, text, short
    lists); an optional ``"arrays"`` entry (name -> numpy array) goes to the
    task's own ``.npz`` file instead of the table.
    """

    func: Callable
    params: dict
    inputs: dict = field(default_factory=dict)

    def __post_init__(self):
        self.id = task_id(self.func, self.params)
        for k, s in self.inputs.items():
            if not isinstance(s, Shared):
                raise FluoInputError("task inputs must be Shared", field=f"inputs.{k}",
                                     value=type(s).__name__)

    def shared_closure(self):
        """Every Shared this task needs, dependencies first."""
        seen, order = set(), []

        def visit(s):
            if s.name in seen:
                return
            for d in s.dependencies():
                visit(d)
            seen.add(s.name)
            order.append(s)
        for s in self.inputs.values():
            visit(s)
        return order


def check_unique(tasks):
    """Refuse a run that holds the same task twice (same function and parameters)."""
    seen = {}
    for i, t in enumerate(tasks):
        if t.id in seen:
            raise FluoInputError("the run lists the same task twice (a repeated grid value?)",
                                 field=f"task {i}", value=t.params)
        seen[t.id] = i
    names = {}
    for t in tasks:
        for s in t.shared_closure():
            other = names.setdefault(s.name, s)
            if other is not s and other.signature() != s.signature():
                raise FluoInputError("two different shared inputs have one name", field="shared",
                                     value=s.name)
