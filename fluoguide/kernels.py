"""Compiled (numba) kernels made ready before long work uses them, with progress.

numba compiles a kernel on its first call with new argument types. Kernels
declared ``cache=True`` keep their machine code in numba's on-disk cache, so
this happens once per installation (and per numba version), but then it takes
seconds to tens of seconds inside whatever step first calls a kernel, and that
step reports nothing meanwhile (issue #33: long work reports at least every
2 s). :func:`prepare` compiles (or loads from the cache) every kernel of a list
for the argument types its callers pass, on a helper thread
(:func:`fluoguide.progress.run_reporting`), while the caller's thread says what
it is doing and how long it has run, every ``every_s`` seconds, and honours a
cancel.

A Lib names its kernels as ``[(dispatcher, example arguments)]``: tiny arrays of
the dtypes, dimensions, layouts and writeability its call sites pass (a
signature that differs in any of them is compiled again at the call). Its own
``prepare_kernels`` hands them here (``FluoTomoLib.fem.kernels``,
``FluoNavLib.mapping.kernels``). numba is imported only when a list is
examined: this module costs nothing to import.
"""

from __future__ import annotations

import logging
import os
import time

from fluoguide.progress import run_reporting

#: where a compile with no ``progress`` reporter is announced (a Lib function called
#: directly, outside the logic's jobs): a first run is then slow for a stated reason
log = logging.getLogger("fluoguide.kernels")

__all__ = ["REPORT_EVERY_S", "signatures", "missing", "cached_on_disk", "prepare",
           "KernelSet"]

#: the longest wait between two reports while kernels compile [s]
REPORT_EVERY_S = 1.0


def signatures(examples):
    """The numba signatures of ``examples``.

    Parameters
    ----------
    examples : [(dispatcher, tuple of example arguments)]

    Returns
    -------
    [(dispatcher, tuple of numba types)]: what numba's dispatcher would look up
    for a call with those arguments.
    """
    from numba import typeof

    return [(d, tuple(typeof(a) for a in args)) for d, args in examples]


def missing(examples):
    """[(dispatcher, signature)] of ``examples`` not compiled in this process yet."""
    return [(d, sig) for d, sig in signatures(examples) if sig not in d.overloads]


def cached_on_disk(dispatcher):
    """Whether numba's on-disk cache has an index for ``dispatcher`` (False when
    it cannot tell: the cache layout is numba's own, not a public interface)."""
    try:
        return os.path.exists(dispatcher._cache._cache_file._index_path)
    except AttributeError:
        return False


def prepare(examples, what, progress=None, fraction=0.0, cancel=None, every_s=None):
    """Compile (or load from numba's cache) the kernels of ``examples`` not ready in
    this process, reporting at ``fraction`` of ``progress`` at least every
    ``every_s`` seconds.

    Parameters
    ----------
    examples : [(dispatcher, tuple of example arguments)]
    what : the kernels' name in the reports: "compiling the {what} (first run
        only)", or "loading the compiled {what}" when numba's cache holds every one
    progress : ``progress(fraction, message)`` or None (None: the message and the
        seconds spent go to the ``fluoguide.kernels`` logger at INFO)
    fraction : the fraction reported meanwhile (this step's place in the caller's job)
    cancel : CancelToken or None; a cancel raises FluoCancelled at the next report
        (the compilation goes on to its end on its helper thread, then serves the
        next call: a compiled signature is whole or absent, never half there)
    every_s : seconds between reports (None: :data:`REPORT_EVERY_S`)

    Returns
    -------
    float: seconds spent (0.0 when every kernel was ready: nothing reported)
    """
    todo = missing(examples)
    if not todo:
        return 0.0
    # an index on disk means numba loads the machine code (well under a second a
    # kernel) instead of compiling it: say which, so a user knows what to expect
    message = (f"loading the compiled {what}" if all(cached_on_disk(d) for d, _ in todo)
               else f"compiling the {what} (first run only)")

    def compile_all():
        for dispatcher, sig in todo:
            dispatcher.compile(sig)

    t0 = time.monotonic()
    if progress is None:
        log.info("%s ...", message)
    run_reporting(compile_all, progress, fraction, message, cancel,
                  REPORT_EVERY_S if every_s is None else float(every_s))
    seconds = time.monotonic() - t0
    if progress is None:
        log.info("%s: done in %.1f s", message, seconds)
    return seconds


class KernelSet:
    """One Lib's kernels: ``examples()`` lists them as ``[(dispatcher, example
    arguments)]`` (called when needed: importing the Lib compiles nothing) and
    ``what`` names them in the reports. A Lib module exposes its set's
    :meth:`missing` and :meth:`prepare` (``FluoTomoLib.fem.kernels``,
    ``FluoNavLib.mapping.kernels``)."""

    def __init__(self, examples, what):
        self.examples = examples
        self.what = str(what)
        # a signature numba has compiled stays in the process: once every kernel
        # was ready, prepare() need not look again (typing the examples costs
        # ~0.5 ms, and FluoNav's cast_camera prepares before every cast)
        self._ready = False

    def missing(self):
        """[(dispatcher, signature)] not compiled in this process yet."""
        return missing(self.examples())

    def prepare(self, progress=None, fraction=0.0, cancel=None, every_s=None):
        """Compile (or load from numba's cache) the kernels not ready in this
        process, reporting at ``fraction`` of ``progress`` at least every
        ``every_s`` seconds (:func:`prepare`; None: :data:`REPORT_EVERY_S`); a
        cancel raises FluoCancelled at the next report. Returns the seconds spent
        (0.0 when every kernel was ready)."""
        if self._ready:
            return 0.0
        seconds = prepare(self.examples(), self.what, progress, fraction, cancel, every_s)
        self._ready = True
        return seconds
