"""Progress reporting and cancellation for long work.

Logic code takes an optional ``progress`` callable ``progress(fraction, message)``
and an optional ``cancel`` token.  The CLI passes a tqdm-backed reporter, the web
app passes one that updates its state, tests pass nothing.  Keeping it a plain
callable means Lib code never imports a UI toolkit.
"""

from __future__ import annotations

import sys
import threading

from fluoguide.errors import FluoCancelled


class CancelToken:
    """A thread-safe flag that long loops check between steps."""

    def __init__(self):
        self._event = threading.Event()

    def cancel(self):
        self._event.set()

    @property
    def cancelled(self):
        return self._event.is_set()

    def check(self):
        """Raise FluoCancelled if cancel() was called."""
        if self._event.is_set():
            raise FluoCancelled("cancelled by the user")


def check_cancel(cancel):
    """Raise FluoCancelled if ``cancel`` (a CancelToken or None) is set."""
    if cancel is not None:
        cancel.check()


def report(progress, fraction, message=""):
    """Call ``progress(fraction, message)`` if a reporter was given."""
    if progress is not None:
        progress(float(min(max(fraction, 0.0), 1.0)), str(message))


def scaled(progress, start, stop, prefix=""):
    """A reporter for one part of a longer job: fractions 0..1 of the part map to
    ``start..stop`` of ``progress``, messages get ``prefix`` (None stays None)."""
    if progress is None:
        return None

    def part(fraction, message=""):
        text = f"{prefix}: {message}" if prefix and message else (prefix or message)
        report(progress, start + (stop - start) * min(max(fraction, 0.0), 1.0), text)

    return part


def run_reporting(work, progress, fraction, message, cancel=None, every_s=1.0):
    """``work()`` on a helper thread while this thread reports ``message`` and the
    seconds it has run, at ``fraction``, every ``every_s`` seconds; returns what
    ``work`` returns and raises what it raises.

    For a step that cannot report from inside (numba compiling a kernel). A cancel
    raises FluoCancelled at the next report; ``work`` then runs on to its end on
    its helper thread (a daemon), so it must leave nothing half-done that a later
    call would trust.
    """
    import time

    check_cancel(cancel)
    report(progress, fraction, message)
    outcome = {}

    def run():
        try:
            outcome["value"] = work()
        except BaseException as exc:            # handed to the caller's thread
            outcome["error"] = exc

    t0 = time.monotonic()
    worker = threading.Thread(target=run, name=message, daemon=True)
    worker.start()
    while True:
        worker.join(every_s)
        if not worker.is_alive():
            break
        check_cancel(cancel)
        report(progress, fraction, f"{message}, {time.monotonic() - t0:.0f} s")
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


_COMMAND_START = [None]     # time.monotonic() when the running command began


def mark_command_start():
    """Note that a command starts now (``fluo``'s main calls it): progress lines count
    their seconds from here, so a step that starts late in a long command is shown
    even when it holds the interpreter for a minute (fTetWild does)."""
    import time

    _COMMAND_START[0] = time.monotonic()


class TqdmProgress:
    """A ``progress(fraction, message)`` reporter on stderr for the command line.

    On a terminal it draws a tqdm bar.  Elsewhere (a pipe, a log file, a test) it
    writes plain lines, ``desc: 42% message (12 s)``, once the command has run
    ``after_s`` seconds (counted from :func:`mark_command_start`, else from this
    reporter's creation), so a command that ends quickly (or refuses its input at
    once) prints nothing; after that one line whenever the message changes and
    at most one per ``every_s`` seconds otherwise.  ``force`` draws the bar even
    when stderr is not a terminal.  stdout is never written.

    ``after_s`` defaults to the environment's ``FLUO_PROGRESS_AFTER_S`` (seconds),
    else 2; 0 prints from the first call (tests of short commands use it).
    """

    def __init__(self, desc="", force=False, after_s=None, every_s=10.0):
        import os
        import time

        from tqdm import tqdm

        if after_s is None:
            try:
                after_s = float(os.environ.get("FLUO_PROGRESS_AFTER_S", "2"))
            except ValueError:
                after_s = 2.0
        self._desc = desc
        self._clock = time.monotonic
        self._t0 = self._clock()
        if _COMMAND_START[0] is not None:
            self._t0 = min(self._t0, _COMMAND_START[0])
        self._after, self._every = after_s, every_s
        self._lines = not (force or sys.stderr.isatty())
        self._pending = None          # (fraction, message) not printed yet
        self._printed = (None, -1e9)  # (message, time) of the last line
        self._message = ""
        self._bar = None if self._lines else tqdm(
            total=1000,
            desc=desc,
            file=sys.stderr,
            bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}{postfix}",
        )
        self._last = 0

    def __call__(self, fraction, message=""):
        if self._bar is not None:
            n = int(round(fraction * 1000))
            if n > self._last:
                self._bar.update(n - self._last)
                self._last = n
            if message:
                self._bar.set_postfix_str(message, refresh=True)
            return
        self._message = message or self._message
        self._pending = (fraction, self._message)
        now = self._clock()
        if now - self._t0 < self._after:
            return
        if self._message != self._printed[0] or now - self._printed[1] >= self._every:
            self._line(now)

    def _line(self, now):
        fraction, message = self._pending
        from fluoguide.errors import one_line

        # one line whatever a name in the message holds (a newline, an escape sequence)
        text = one_line(f"{self._desc}: {100 * fraction:3.0f}% {message}".rstrip())
        print(f"{text} ({now - self._t0:.0f} s)", file=sys.stderr, flush=True)
        self._printed = (message, now)
        self._pending = None

    def close(self):
        if self._bar is not None:
            self._bar.close()
        elif self._pending is not None and self._printed[0] is not None:
            self._line(self._clock())      # the final state of a run that printed before

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
