"""A Qt event loop watching a background job, as a desktop panel runs one
(``FluoModuleWidget.runWithProgress(background=True)``), for the headless tests
of long work off the GUI thread (test_jobs.py, test_desktop_jobs.py).

PySide6 stands in for Slicer's PythonQt (not here): a ``QCoreApplication``, a
20 ms timer whose ticks are the loop's heartbeat (on a blocked GUI thread it
would not tick at all) and a 100 ms timer that polls the job as the panel's
progress dialog does. The ``qt_app`` fixture (conftest.py) makes the application.
"""

from __future__ import annotations

import threading
import time


def watch(job, until=lambda state: state.finished, on_state=None):
    """Run a Qt event loop while ``job`` (a started ``BackgroundJob``) works: a 20 ms
    timer records its ticks, a 100 ms timer polls the job as the panel does and
    ends the loop when ``until(state)`` or the job has finished. Returns (tick
    times, polled states)."""
    from PySide6.QtCore import QEventLoop, QTimer

    loop, ticks, states = QEventLoop(), [], []
    beat = QTimer()
    beat.setInterval(20)
    beat.timeout.connect(lambda: ticks.append(time.monotonic()))
    poll = QTimer()
    poll.setInterval(100)

    def check():
        state = job.poll()
        states.append(state)
        if on_state is not None:
            on_state(state)
        if until(state) or state.finished:
            loop.quit()

    poll.timeout.connect(check)
    beat.start()
    poll.start()
    QTimer.singleShot(300_000, loop.quit)          # a hung job ends the test, not CI
    loop.exec()
    beat.stop()
    poll.stop()
    return ticks, states


def gaps(times):
    """Seconds between consecutive times (empty for fewer than two)."""
    return [b - a for a, b in zip(times, times[1:])]


class Reports:
    """Every progress report of a job with its time, and, optionally, a point where
    the job waits until it is cancelled.

    ``wrap(work)`` is ``work`` reporting through this recorder. With
    ``hold_at=text``, the first report whose message starts with ``text`` waits
    (up to 10 s) until the job's cancel token is set: the GUI thread, which
    sees that message when it polls, cancels the job there, as a click on
    Cancel at that moment would (a job of a fraction of a second would
    otherwise end before the first poll).
    """

    def __init__(self, hold_at=None):
        self.items = []             # (monotonic time, fraction, message)
        self.hold_at = hold_at
        self.held = threading.Event()
        self.started = None
        self.ended = None

    def wrap(self, work):
        def recorded(progress, cancel):
            self.started = time.monotonic()

            def report(fraction, message=""):
                self.items.append((time.monotonic(), fraction, message))
                progress(fraction, message)
                if (self.hold_at is not None and not self.held.is_set()
                        and message.startswith(self.hold_at)):
                    self.held.set()
                    t_end = time.monotonic() + 10.0
                    while not cancel.cancelled and time.monotonic() < t_end:
                        time.sleep(0.005)

            try:
                return work(report, cancel)
            finally:
                self.ended = time.monotonic()

        return recorded

    @property
    def messages(self):
        return [m for _, _, m in self.items]

    @property
    def fractions(self):
        return [f for _, f, _ in self.items]

    def longest_gap(self):
        """The longest time without a report, from the job's start to its end [s]."""
        return max(gaps([self.started] + [t for t, _, _ in self.items] + [self.ended]))
