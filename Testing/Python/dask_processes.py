"""A real Dask cluster for the tests, as a user starts one: ``dask scheduler`` and
``dask worker`` on 127.0.0.1, each a process in a session of its own (so it can be
stopped, killed or continued with everything it started)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def stop_process(proc):
    """End a process started with ``start_new_session``, and everything it started
    (also when it was stopped with SIGSTOP: it is continued so SIGTERM can act)."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        os.killpg(proc.pid, signal.SIGCONT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(15)
    else:  # the leader has gone; its children (Dask's worker processes) may not have
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


class DaskProcesses:
    """``with DaskProcesses(folder, nworkers=2) as dask:`` a scheduler at
    ``dask.address`` (its log and scheduler file in ``folder``) and ``nworkers``
    single-threaded worker processes; ``dask.scheduler`` and ``dask.workers`` are
    the ``Popen`` objects. Both are ended on leaving the block."""

    def __init__(self, folder, nworkers=2, start_timeout_s=120):
        folder = Path(folder)
        self.log_path = folder / "dask.log"
        self._log = open(self.log_path, "w")
        sfile = folder / "scheduler.json"
        self.workers = None
        self.scheduler = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
             "--port", "0", "--no-dashboard", "--scheduler-file", str(sfile)],
            stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + start_timeout_s
            while not sfile.exists() or not sfile.read_text().strip():
                assert self.scheduler.poll() is None and time.monotonic() < deadline, \
                    self.log_path.read_text()
                time.sleep(0.05)
            self.address = json.loads(sfile.read_text())["address"]
            self.workers = subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", self.address,
                 "--nworkers", str(nworkers), "--nthreads", "1", "--no-dashboard", "--host",
                 "127.0.0.1"], stdout=self._log, stderr=subprocess.STDOUT,
                start_new_session=True)
        except BaseException:
            self.close()
            raise

    def close(self):
        for p in (self.workers, self.scheduler):
            if p is not None:
                stop_process(p)
        self._log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
