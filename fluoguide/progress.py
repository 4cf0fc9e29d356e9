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


class TqdmProgress:
    """A ``progress(fraction, message)`` reporter drawing a tqdm bar on stderr.

    Quiet when stderr is not a terminal unless ``force`` is set, so JSON on
    stdout and CI logs stay clean.
    """

    def __init__(self, desc="", force=False):
        from tqdm import tqdm

        self._bar = tqdm(
            total=1000,
            desc=desc,
            file=sys.stderr,
            disable=not (force or sys.stderr.isatty()),
            bar_format="{desc} {percentage:3.0f}%|{bar}| {postfix}",
        )
        self._last = 0

    def __call__(self, fraction, message=""):
        n = int(round(fraction * 1000))
        if n > self._last:
            self._bar.update(n - self._last)
            self._last = n
        if message:
            self._bar.set_postfix_str(message, refresh=True)

    def close(self):
        self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
