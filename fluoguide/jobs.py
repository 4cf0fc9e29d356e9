"""Long work on a worker thread, watched from the GUI's event loop.

A reconstruction takes a minute; on Slicer's GUI thread it would freeze the
application (no repaint, no Cancel) for all that time. :class:`BackgroundJob`
runs ``work(progress, cancel)`` on a thread of its own; the GUI thread keeps
running its event loop and reads :meth:`BackgroundJob.poll` from a timer
(every 100 ms in the desktop panels, ``fluoguide.slicer_module``): the latest
fraction and message, how long the current step has run (so a step that holds
for a minute still shows it is alive), and, once finished, the result or the
error. Cancel sets the job's ``CancelToken``, which the Libs check between steps.

The work must not touch MRML or Qt (neither is thread-safe): the logic classes
split such work into ``prepare*`` (read the scene, on the GUI thread), a job
(pure computation, here) and ``store*`` (write the results, on the GUI thread).
Numerical libraries (NumPy, SciPy, numba, PARDISO) release the GIL in their
kernels, so the GUI thread gets the interpreter between the worker's Python
steps (``test_jobs.py`` measures the event loop's ticks during a reconstruction).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from fluoguide.errors import FluoCancelled
from fluoguide.progress import CancelToken

__all__ = ["BackgroundJob", "JobState"]


@dataclass(frozen=True)
class JobState:
    """What :meth:`BackgroundJob.poll` returns: ``status`` is "running", "done",
    "failed" or "cancelled"; ``fraction`` 0..1 and ``message`` the latest progress;
    ``step_seconds`` how long ago that report came; ``seconds`` since the start;
    ``updates`` how many reports came; ``result`` and ``error`` once finished."""

    status: str
    fraction: float
    message: str
    step_seconds: float
    seconds: float
    updates: int
    result: object = None
    error: BaseException | None = None

    @property
    def finished(self):
        return self.status != "running"


class BackgroundJob:
    """``work(progress, cancel)`` on a daemon thread (see the module docstring).

    Parameters
    ----------
    work : callable (progress, cancel) -> result
        Pure computation: it must not touch MRML or Qt.
    name : str
        For the thread's name and messages.
    """

    def __init__(self, work, name="job"):
        self._work = work
        self.name = str(name)
        self.cancel_token = CancelToken()
        self._lock = threading.Lock()
        self._fraction, self._message, self._updates = 0.0, "", 0
        self._t_start = self._t_step = None
        self._status, self._result, self._error = "new", None, None
        self._thread = None

    def _progress(self, fraction, message=""):
        now = time.monotonic()
        with self._lock:
            self._fraction = max(0.0, min(1.0, float(fraction)))
            if message:
                self._message = str(message)
            self._updates += 1
            self._t_step = now

    def _run(self):
        try:
            result = self._work(self._progress, self.cancel_token)
        except FluoCancelled as exc:
            status, result, error = "cancelled", None, exc
        except BaseException as exc:          # handed to the GUI thread to show
            status, result, error = "failed", None, exc
        else:
            status, error = "done", None
        with self._lock:
            self._status, self._result, self._error = status, result, error

    def start(self):
        """Start the work (once); returns self."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name} was started already")
        self._t_start = self._t_step = time.monotonic()
        self._status = "running"
        self._thread = threading.Thread(target=self._run, name=f"fluoguide-{self.name}",
                                        daemon=True)
        self._thread.start()
        return self

    def cancel(self):
        """Ask the work to stop at its next check (it ends as "cancelled")."""
        self.cancel_token.cancel()

    def poll(self):
        """The job's state now (:class:`JobState`); cheap, for a GUI timer."""
        now = time.monotonic()
        with self._lock:
            return JobState(self._status, self._fraction, self._message,
                            now - (self._t_step or now), now - (self._t_start or now),
                            self._updates, self._result, self._error)

    def wait(self, timeout=None):
        """Block until the work ends (for scripts and headless callers); the state."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.poll()
