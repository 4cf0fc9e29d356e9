"""Thread pools of the numerical libraries, set once and on purpose.

numpy/scipy's BLAS (OpenBLAS), MKL (PARDISO) and numba's parallel kernels each
start one thread per core by default.  On a machine whose cores are busy (two
cores, other jobs running: CI, a shared workstation, several Dask workers on
one node) those threads spin and wait for each other: ``fluo study B`` took
75-115 s with the libraries' defaults against 15-25 s with one thread on a
loaded 2-core machine (docs/performance.md).  The reconstruction's dense
products are small (M x N with M a few hundred measurements) and gain little
from threads even on an idle machine, so one thread is the default.

The choice, strongest first: the ``threads`` argument (``fluo --threads N``),
the environment variable ``FLUO_THREADS``, the default 1.  Values: a count
>= 1; ``auto``: every core this process may run on; ``system``: leave the
libraries as they are (their own defaults and OMP_NUM_THREADS & co.).

Call :func:`configure_threads` once per process before the numerical work
(the CLI, the demo and the web app do, through ``fluoapp.cli.main``; a Dask
worker's start-up should too), and :func:`apply_in_this_thread` at the start
of a worker thread: numba's thread count is per thread.
"""

from __future__ import annotations

import os
import sys

from fluoguide.errors import FluoInputError

ENV_VAR = "FLUO_THREADS"
DEFAULT = "1"
# what each library reads when it starts (MKL is loaded late, for PARDISO;
# numba reads NUMBA_NUM_THREADS once, at import)
_ENV_NAMES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

_state = {"threads": None, "source": None}


def available_cores():
    """Cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def resolve_threads(threads=None):
    """(count or None for 'system', where the choice came from)."""
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
        return available_cores(), source
    try:
        n = int(text)
    except ValueError:
        raise FluoInputError("threads must be a count >= 1, 'auto' or 'system'", field=field,
                             value=value) from None
    if n < 1:
        raise FluoInputError("threads must be a count >= 1, 'auto' or 'system'", field=field,
                             value=value)
    return n, source


def configure_threads(threads=None):
    """Set every numerical library's thread pool to the chosen count.

    Parameters
    ----------
    threads : int or str, optional
        A count >= 1, "auto" or "system"; None: ``FLUO_THREADS``, else 1.

    Returns
    -------
    dict: ``threads`` (the count, or None for "system"), ``source`` (argument,
    FLUO_THREADS or default) and ``libraries`` (what was set: the loaded BLAS /
    OpenMP pools that threadpoolctl found, numba).
    """
    n, source = resolve_threads(threads)
    _state.update(threads=n, source=source)
    applied = []
    if n is not None:
        # libraries not loaded yet read these when they start
        for name in _ENV_NAMES:
            os.environ[name] = str(n)
        if "numba" not in sys.modules:
            os.environ["NUMBA_NUM_THREADS"] = str(n)
        # the loaded ones are set directly
        try:
            from threadpoolctl import threadpool_info, threadpool_limits

            threadpool_limits(limits=n)
            applied = sorted({f"{i['internal_api']}:{i['num_threads']}"
                              for i in threadpool_info()})
        except ImportError:           # pragma: no cover - threadpoolctl is a dependency
            applied = ["threadpoolctl missing: environment variables only"]
        applied += apply_in_this_thread()
    return {"threads": n, "source": source, "libraries": applied}


def apply_in_this_thread():
    """Apply the configured count to numba in the calling thread (numba's count
    is per thread; a new thread starts with numba's pool size).  Call at the
    start of a worker thread (web app jobs, Dask tasks).  Returns what it set."""
    n = _state["threads"]
    if n is None or "numba" not in sys.modules:
        return []
    import numba

    k = max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS)))
    numba.set_num_threads(k)
    return [f"numba:{k}"]


def current_threads():
    """The configured count (None: not configured, or 'system')."""
    return _state["threads"]
