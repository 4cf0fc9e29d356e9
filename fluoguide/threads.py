"""How many threads the numerical libraries may use: one place that pins them.

NumPy/SciPy call a BLAS (MKL or OpenBLAS) and OpenMP code, and our kernels are
numba; each starts as many threads as the machine has cores. Two processes
doing that on the same cores, or one process running several tasks at once,
oversubscribe the machine (a study ran 4-50x slower on a loaded 2-core machine
with default threads than with one). Whoever runs several tasks side by side
(the run engine's serial loop and its Dask workers, ``fluoguide.runs``) gives
each task a fixed number of threads with :func:`limited_threads` or
:func:`pin_threads`.

Three mechanisms, because no single one reaches every library:

- environment variables (``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
  ``OPENBLAS_NUM_THREADS``, ``NUMBA_NUM_THREADS``): read when a library loads
  and inherited by child processes (Dask's worker processes);
- ``threadpoolctl``: changes the pools of BLAS/OpenMP libraries already loaded;
- ``numba.set_num_threads``: numba's own pool (per calling thread; it cannot
  exceed the ``NUMBA_NUM_THREADS`` the pool was launched with).

The numbers a task computes do not depend on which of these set the count,
but they may depend on the count itself (a threaded BLAS sums in another
order), so a run and its re-run use the same count.

The application's process-wide choice (:func:`configure_threads`, called by
``fluoapp.cli.main`` before any command, so by the CLI, ``fluo demo`` and
``fluo app``): ``fluo --threads N|auto|system``, else the environment variable
``FLUO_THREADS``, else 1.  ``fluo study B`` took 75-473 s with the libraries'
defaults against 15-61 s with one thread on a loaded 2-core machine
(docs/performance.md).  A worker thread calls :func:`apply_in_this_thread`
first (numba's count is per thread; the web app's job runner does).
"""

from __future__ import annotations

import contextlib
import os
import sys

ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def cpu_count():
    """Cores this process may run on (its affinity mask, not the whole machine)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _numba_threads(n):
    """Set numba's thread count for the calling thread if numba is loaded; return
    the previous count (None when numba is not loaded or its pool cannot be set)."""
    numba = sys.modules.get("numba")
    if numba is None:
        return None
    try:
        before = numba.get_num_threads()
        numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
        return before
    except (ValueError, RuntimeError, AttributeError):
        return None


def pin_threads(n=1, environ=True):
    """Limit BLAS, OpenMP and numba to ``n`` threads for the rest of this process.

    Parameters
    ----------
    n : int
        Threads per library (>= 1).
    environ : bool
        Also set the environment variables, so libraries loaded later and child
        processes start with ``n``.

    Returns
    -------
    dict
        What is in force afterwards (:func:`thread_settings`).
    """
    n = _check_n(n)
    if environ:
        for var in ENV_VARS:
            os.environ[var] = str(n)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=n)
    _numba_threads(n)
    return thread_settings()


@contextlib.contextmanager
def limited_threads(n=1):
    """Context manager: BLAS/OpenMP/numba use ``n`` threads inside, as before after.

    ``n=None`` leaves every library as it is (the "unpinned" case the scale
    benchmark measures).
    """
    if n is None:
        yield
        return
    n = _check_n(n)
    from threadpoolctl import threadpool_limits

    before = _numba_threads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        if before is not None:
            _numba_threads(before)


def thread_settings():
    """The thread counts in force: each loaded BLAS/OpenMP pool, numba's, the variables."""
    from threadpoolctl import threadpool_info

    out = {"cpu_count": cpu_count(),
           "pools": sorted({(p.get("internal_api"), p.get("num_threads")) for p in threadpool_info()},
                           key=str),
           "environ": {v: os.environ.get(v) for v in ENV_VARS}}
    numba = sys.modules.get("numba")
    if numba is not None:
        out["numba"] = numba.get_num_threads()
    out["pools"] = [{"api": a, "threads": t} for a, t in out["pools"]]
    return out


def _check_n(n):
    from fluoguide.errors import FluoInputError

    try:
        ok = int(n) == n and 1 <= int(n) <= 4096
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise FluoInputError("threads per task must be a whole number from 1 to 4096",
                             field="threads", value=n)
    return int(n)


# --- the application's process-wide choice ------------------------------------

ENV_VAR = "FLUO_THREADS"
DEFAULT = "1"
_state = {"threads": None, "source": None}


def resolve_threads(threads=None):
    """(count, or None for "system"; where the choice came from).

    ``threads``: a count >= 1, "auto" (every core this process may run on) or
    "system" (leave the libraries as they are); None: ``FLUO_THREADS``, else 1.
    """
    from fluoguide.errors import FluoInputError

    if threads is not None:
        value, source, field = threads, "argument", "--threads"
    elif os.environ.get(ENV_VAR, "").strip():
        value, source, field = os.environ[ENV_VAR].strip(), ENV_VAR, ENV_VAR
    else:
        value, source, field = DEFAULT, "default", ENV_VAR
    text = str(value).strip().lower()
    if text == "system":
        return None, source
    if text == "auto":
        return cpu_count(), source
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise FluoInputError("threads must be a count >= 1, 'auto' or 'system'", field=field,
                             value=value)
    return n, source


def configure_threads(threads=None):
    """Set every numerical library's thread pool for this process (:func:`pin_threads`)
    from the application's choice (:func:`resolve_threads`).

    Returns a dict: ``threads`` (the count, None for "system"), ``source``
    (argument, FLUO_THREADS or default) and ``settings`` (:func:`thread_settings`
    afterwards; None for "system").
    """
    n, source = resolve_threads(threads)
    _state.update(threads=n, source=source)
    settings = pin_threads(n) if n is not None else None
    return {"threads": n, "source": source, "settings": settings}


def apply_in_this_thread():
    """Apply the configured count to numba in the calling thread (numba's count
    is per thread).  Call at the start of a worker thread.  Returns numba's
    count before, or None when nothing was set."""
    n = _state["threads"]
    return None if n is None else _numba_threads(n)


def current_threads():
    """The count :func:`configure_threads` set (None: not configured, or "system")."""
    return _state["threads"]
