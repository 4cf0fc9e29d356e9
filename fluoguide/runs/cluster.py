"""Which Dask cluster a run goes to, and the executor that sends tasks there.

- ``workers=N`` (or ``"auto"``: as many as the machine has cores for
  ``threads`` threads per task): an embedded local cluster of N worker
  processes, started for the run and shut down after it;
- ``scheduler="tcp://host:8786"``, else the ``FLUO_SCHEDULER`` environment
  variable, else Dask's own ``DASK_SCHEDULER_ADDRESS``: an existing cluster
  (``dask scheduler`` + ``dask worker`` on other machines, a batch system's
  dask-jobqueue, a Kubernetes operator); the same tasks go there unchanged.
  Its workers need FluoGuide installed (they import the task functions by
  name) and, when they do not share this machine's disk, nothing else: results
  come back to this process, which writes the run folder;
- neither: serial in this process.

Each worker process runs one task at a time (``threads_per_worker=1``) and
each task pins its BLAS/OpenMP/numba threads (:mod:`fluoguide.threads`).
The dashboard's address is printed when a cluster is used.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import time
import uuid

from fluoguide.errors import FluoDeviceError, FluoInputError
from fluoguide.progress import check_cancel
from fluoguide.runs.engine import (SerialExecutor, _error_text, _finish, call_shared, call_task,
                                   prepare_worker)
from fluoguide.runs.tasks import Shared
from fluoguide.threads import ENV_VARS, cpu_count

SCHEDULER_ENV = "FLUO_SCHEDULER"
CONNECT_TIMEOUT_S = 30.0
MAX_LOCAL_WORKERS = 256
_ADDRESS = re.compile(r"^(tcp|tls)://(\[[0-9a-fA-F:.]+\]|[A-Za-z0-9._-]+):(\d{1,5})$")


def scheduler_address(value=None):
    """The scheduler to use: ``value``, else $FLUO_SCHEDULER, else Dask's
    ``scheduler-address`` setting; None when none is set. Validated."""
    field = "--scheduler"
    if not value:
        value, field = os.environ.get(SCHEDULER_ENV) or None, SCHEDULER_ENV
    if not value:
        value, field = os.environ.get("DASK_SCHEDULER_ADDRESS") or None, "DASK_SCHEDULER_ADDRESS"
    if not value:
        return None
    text = str(value).strip()
    if "://" not in text:
        text = "tcp://" + text
    m = _ADDRESS.match(text)
    if not m or not 1 <= int(m.group(3)) <= 65535:
        raise FluoInputError("expected a scheduler address tcp://HOST:PORT", field=field,
                             value=value)
    return text


def local_workers(workers, threads):
    """Number of local worker processes for ``workers`` (int or "auto")."""
    if workers == "auto":
        return max(1, cpu_count() // max(1, threads or 1))
    try:
        n = int(workers)
        ok = n == float(workers) and 1 <= n <= MAX_LOCAL_WORKERS
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise FluoInputError(f"workers must be 'auto' or a whole number from 1 to "
                             f"{MAX_LOCAL_WORKERS}", field="--workers", value=workers)
    return n


def _slug(name):
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)[:80]


class DaskExecutor:
    """Sends tasks to a ``distributed.Client``; see :class:`SerialExecutor` for the contract."""

    name = "dask"

    def __init__(self, client, kind="local", dashboard=True):
        self.client = client
        self.kind = kind
        # a local cluster started without its dashboard still serves Dask's HTTP
        # routes under the name "dashboard" (on port 8787): not announced as one
        self.dashboard = dashboard

    @property
    def workers(self):
        return len(self.client.scheduler_info(n_workers=-1).get("workers", {}))

    def describe(self):
        info = {"executor": f"dask ({self.kind})", "workers": self.workers,
                "scheduler": self.client.scheduler.address}
        if self.dashboard:
            with contextlib.suppress(Exception):
                info["dashboard"] = self.client.dashboard_link
        return info

    def run(self, todo, threads, on_done, cancel=None, task_progress=None):
        # task_progress is the serial loop's: here the run's progress is per task
        from distributed import as_completed

        client = self.client
        token = uuid.uuid4().hex[:8]
        modules = sorted({t.func.__module__ for t in todo}
                         | {s.func.__module__ for t in todo for s in t.shared_closure()})
        try:
            client.run(prepare_worker, modules)
        except Exception as exc:  # noqa: BLE001 - any worker-side failure: say which and why
            raise FluoDeviceError(f"the Dask workers cannot import {', '.join(modules)} "
                                  f"({_error_text(exc)}): install FluoGuide on them") from None
        shared_f, need = {}, {}

        def submit_shared(s):
            if s.name not in shared_f:
                args = [submit_shared(a) if isinstance(a, Shared) else a for a in s.args]
                shared_f[s.name] = client.submit(call_shared, s.func, threads, *args,
                                                 key=f"shared-{_slug(s.name)}-{token}", pure=False)
            return shared_f[s.name]

        pending = {}
        for i, t in enumerate(todo):
            closure = t.shared_closure()
            for s in closure:
                submit_shared(s)
                need[s.name] = need.get(s.name, 0) + 1
            inputs = {k: shared_f[s.name] for k, s in t.inputs.items()}
            # earlier tasks first, as the serial loop runs them
            f = client.submit(call_task, t.func, t.params, threads, inputs,
                              key=f"task-{t.id}-{token}", pure=False, priority=-i)
            pending[f.key] = (f, t, closure)
        ac = as_completed([f for f, _, _ in pending.values()], with_results=True,
                          raise_errors=False, loop=client.loop)
        try:
            for fut, res in ac:
                check_cancel(cancel)
                _, t, closure = pending.pop(fut.key)
                if fut.status == "finished":
                    _finish(on_done, t, res)
                else:
                    exc = res[1] if isinstance(res, tuple) and len(res) == 3 else res
                    msg = _error_text(exc)
                    bad = next((s for s in closure if shared_f[s.name].status == "error"), None)
                    if bad is not None:
                        msg = f"shared input {bad.name!r} failed: {msg}"
                    on_done(t, None, msg, None, None)
                fut.release()
                for s in closure:
                    need[s.name] -= 1
                    if need[s.name] == 0:
                        shared_f[s.name].release()
        except BaseException:
            client.cancel([f for f, _, _ in pending.values()] + list(shared_f.values()))
            raise
        return len(shared_f)


@contextlib.contextmanager
def executor(workers=None, scheduler=None, threads=1, log=None, dashboard=True):
    """The executor for a run (module docstring): serial, local cluster or a scheduler.

    Parameters
    ----------
    workers : None, int or "auto"
        Local worker processes (ignored when a scheduler is given or set).
    scheduler : str, optional
        ``tcp://host:port`` of a running scheduler.
    threads : int or None
        Threads per task (the local workers' environment gets the same count).
    log : file, optional
        Where the cluster and its dashboard are announced (stderr by default).
    """
    log = sys.stderr if log is None else log
    address = scheduler_address(scheduler)
    if address is None and workers in (None, 0, "0"):
        yield SerialExecutor()
        return
    with dask_executor(address=address, workers=workers or "auto", threads=threads, log=log,
                       dashboard=dashboard) as ex:
        yield ex


@contextlib.contextmanager
def dask_executor(address=None, workers="auto", threads=1, log=None, dashboard=True):
    """A DaskExecutor on the scheduler at ``address``, or on a local cluster started here."""
    import dask
    from distributed import Client, LocalCluster

    log = sys.stderr if log is None else log
    cluster = client = None
    try:
        if address:
            try:
                client = Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise FluoDeviceError(f"cannot reach the Dask scheduler at {address} "
                                      f"({_error_text(exc)})") from None
            try:
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
            except (TimeoutError, OSError):
                raise FluoDeviceError(f"the Dask scheduler at {address} has no workers "
                                      f"(waited {CONNECT_TIMEOUT_S:g} s)") from None
            kind = "scheduler"
        else:
            n = local_workers(workers, threads)
            # the worker processes start with the same thread limits as each task
            # (and without Dask's MALLOC_TRIM_THRESHOLD_: see engine.prepare_worker)
            environ = {}
            if threads is not None:
                environ.update({v: int(threads) for v in ENV_VARS})
                # pocl (MCX-CL's CPU OpenCL) starts one thread per core in every worker
                # unless told; the photons a seed draws do not depend on it (Engine.run)
                environ["POCL_MAX_PTHREAD_COUNT"] = int(threads)
            # the worker's statistical profiler samples every thread's stack each 10 ms
            # under the GIL: off, the tasks are the workers' only work
            with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                                  "distributed.worker.daemon": False,
                                  "distributed.worker.profile.enabled": False}):
                t0 = time.perf_counter()
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                       host="127.0.0.1",
                                       dashboard_address=":0" if dashboard else None,
                                       silence_logs=logging.ERROR)
                client = Client(cluster, set_as_default=False)
                client.wait_for_workers(n, timeout=120)
            kind = f"local, started in {time.perf_counter() - t0:.1f} s"
        ex = DaskExecutor(client, kind=kind, dashboard=bool(address) or dashboard)
        d = ex.describe()
        msg = f"dask: {d['workers']} workers ({kind}) at {d['scheduler']}"
        if d.get("dashboard"):
            msg += f"; dashboard {d['dashboard']}"
        print(msg, file=log, flush=True)
        yield ex
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=20)
