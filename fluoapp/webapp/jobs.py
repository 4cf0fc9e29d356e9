"""Long work off the UI thread: one background job at a time, with progress,
cancel, and results handed back to the scene's thread.

MRML and VTK are not thread-safe, so a job is split the way FluoTomo's logic
splits it: read what it needs from the scene first (caller's thread), compute
on a worker thread (numpy/scipy/PARDISO release the GIL, so the web server
stays responsive), and apply the result to the scene in ``on_done``, which
runs on the thread that calls :meth:`JobRunner.poll` (the app polls from its
event loop).
"""

from __future__ import annotations

import threading
import time
import traceback

from fluoguide.errors import FluoCancelled, FluoError
from fluoguide.progress import CancelToken
from fluoguide.threads import apply_in_this_thread

__all__ = ["JobRunner", "JobState"]


class JobState:
    """What the UI shows about the current or last job (plain values only)."""

    def __init__(self):
        self.name = ""
        self.running = False
        self.fraction = 0.0
        self.message = ""
        self.error = ""
        self.seconds = 0.0

    def as_dict(self):
        return {"name": self.name, "running": self.running, "fraction": self.fraction,
                "message": self.message, "error": self.error, "seconds": round(self.seconds, 2)}


class JobRunner:
    """Runs ``work(progress, cancel)`` on a daemon thread, one job at a time."""

    def __init__(self):
        self.state = JobState()
        self._lock = threading.Lock()
        self._thread = None
        self._cancel = None
        self._result = None
        self._failure = None
        self._on_done = None
        self._on_error = None
        self._finished = False
        self._t0 = 0.0

    @property
    def busy(self):
        return self.state.running

    def start(self, name, work, on_done=None, on_error=None):
        """Start a job; raises FluoError when one is already running."""
        with self._lock:
            if self.state.running:
                raise FluoError(f"'{self.state.name}' is still running; cancel it or wait")
            self.state = JobState()
            self.state.name = name
            self.state.running = True
            self.state.message = "starting"
            self._cancel = CancelToken()
            self._result = self._failure = None
            self._on_done, self._on_error = on_done, on_error
            self._finished = False
            self._t0 = time.perf_counter()
        cancel = self._cancel

        def progress(fraction, message=""):
            with self._lock:
                self.state.fraction = float(fraction)
                if message:
                    self.state.message = str(message)

        def target():
            try:
                apply_in_this_thread()      # numba's thread count is per thread
                result = work(progress, cancel)
                failure = None
            except FluoCancelled as exc:
                result, failure = None, ("cancelled", str(exc))
            except FluoError as exc:
                result, failure = None, ("error", str(exc))
            except Exception as exc:  # reported in the UI with its type, never swallowed
                traceback.print_exc()
                result, failure = None, ("error", f"{type(exc).__name__}: {exc}")
            with self._lock:
                self._result, self._failure = result, failure
                self._finished = True

        self._thread = threading.Thread(target=target, name=f"fluo-job-{name}", daemon=True)
        self._thread.start()

    def cancel(self):
        if self._cancel is not None and self.state.running:
            self._cancel.cancel()
            with self._lock:
                self.state.message = "cancelling..."

    def poll(self):
        """Call from the scene's thread: applies a finished job; returns True when
        the state changed to not running in this call."""
        with self._lock:
            if not self.state.running:
                return False
            self.state.seconds = time.perf_counter() - self._t0
            if not self._finished:
                return False
            result, failure = self._result, self._failure
            on_done, on_error = self._on_done, self._on_error
        try:
            if failure is None and on_done is not None:
                on_done(result)
        except Exception as exc:  # the scene is left as on_done left it; say so
            traceback.print_exc()
            failure = ("error", f"{type(exc).__name__}: {exc}")
        with self._lock:
            self.state.running = False
            if failure is None:
                self.state.fraction = 1.0
                self.state.message = "done"
            else:
                kind, text = failure
                self.state.message = kind
                self.state.error = "" if kind == "cancelled" else text
        if failure is not None and on_error is not None:
            on_error(failure[0], failure[1])
        return True

    def wait(self, timeout_s=None):
        """Block until the worker thread ends (tests and the CLI); then poll()."""
        if self._thread is not None:
            self._thread.join(timeout_s)
        return self.poll()
