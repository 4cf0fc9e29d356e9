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

A scheduler is a peer, and a peer may accept a connection and never answer,
send bytes that are not Dask's, close at once, or stop answering mid-run
(issue #34). Dask's own client waits for the handshake without a limit, so
every exchange with a scheduler has a stated time limit here:
$FLUO_SCHEDULER_TIMEOUT seconds (default :data:`SCHEDULER_TIMEOUT_S`) for the
connection, the Dask handshake and the identity the scheduler owes (checked
by :func:`probe_scheduler` before a ``Client`` exists, so a peer that is not a
scheduler never gets one), for the client's own connection, for at least one
worker to be there, for every question asked of it (its workers, cancelling)
and, during a run, for a sign of life whenever no result has come for that
long (a task may take hours; the scheduler must still answer). The workers'
first import of the task modules may take :data:`PREPARE_FACTOR` times as
long. A limit that passes is one :class:`FluoDeviceError` naming the address
and what was awaited (``fluo``: one line, exit code 1).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import re
import socket
import sys
import threading
import time
import uuid

from fluoguide.errors import FluoDeviceError, FluoInputError
from fluoguide.progress import check_cancel
from fluoguide.runs.engine import (SerialExecutor, _error_text, _finish, call_shared, call_task,
                                   prepare_worker)
from fluoguide.runs.tasks import Shared
from fluoguide.threads import ENV_VARS, cpu_count

SCHEDULER_ENV = "FLUO_SCHEDULER"
#: the variable that sets the scheduler's time limit [s]
SCHEDULER_TIMEOUT_ENV = "FLUO_SCHEDULER_TIMEOUT"
#: default time limit [s] of each answer a scheduler owes (module docstring)
SCHEDULER_TIMEOUT_S = 30.0
#: accepted range of $FLUO_SCHEDULER_TIMEOUT [s]: a tenth of a second is the
#: shortest a loaded machine answers in; an hour is already a hang to a user
SCHEDULER_TIMEOUT_RANGE_S = (0.1, 3600.0)
#: the workers' first import of the task modules (numba, VTK, SciPy: tens of
#: seconds on a cold disk) may take this many scheduler time limits
PREPARE_FACTOR = 10
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


def scheduler_timeout():
    """The time limit [s] of each answer a scheduler owes: $FLUO_SCHEDULER_TIMEOUT,
    else :data:`SCHEDULER_TIMEOUT_S`. Validated (FluoInputError naming the variable)."""
    text = os.environ.get(SCHEDULER_TIMEOUT_ENV, "").strip()
    if not text:
        return SCHEDULER_TIMEOUT_S
    lo, hi = SCHEDULER_TIMEOUT_RANGE_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    # NaN fails both comparisons: refused with the rest
    if not lo <= value <= hi:
        raise FluoInputError(f"must be a number of seconds in [{lo:g}, {hi:g}]",
                             field=SCHEDULER_TIMEOUT_ENV, value=text)
    return value


def _within(seconds, fn):
    """``fn()`` in a daemon thread, waited for at most ``seconds``.

    Returns ``(True, value)``, or ``(False, None)`` when the time passed (the
    thread is left to finish on its own; it may not hold the caller). An
    exception of ``fn`` is raised here.
    """
    box = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = exc

    t = threading.Thread(target=target, name="fluo-scheduler-call", daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        return False, None
    if "error" in box:
        raise box["error"]
    return True, box["value"]


def probe_scheduler(address, timeout_s=None):
    """Connect to ``address``, do the Dask handshake and ask its identity, all of it
    within ``timeout_s`` [s] (default :func:`scheduler_timeout`); a refused connection
    is tried again within that time (a scheduler may be starting).

    Returns
    -------
    dict
        The scheduler's identity (``type``, ``id``, ``n_workers`` ...).

    Raises
    ------
    FluoDeviceError
        Nothing accepted a connection, the peer did not answer the handshake or
        the identity, closed the connection, or is not a Dask scheduler; the
        message names the address and the step.
    FluoInputError
        The host name does not resolve.
    """
    from distributed.comm import CommClosedError, parse_address
    from distributed.comm.registry import get_backend
    from distributed.security import Security
    from tornado.iostream import StreamClosedError

    timeout_s = scheduler_timeout() if timeout_s is None else float(timeout_s)
    scheme, loc = parse_address(address)
    connection_args = Security().get_connection_args("client")
    step = {"now": "a connection"}

    async def ask():
        # every step below is bounded by the one limit around ask() (run() below)
        connector = get_backend(scheme).get_connector()
        comm = None
        while comm is None:
            try:
                comm = await connector.connect(loc, deserialize=True, **connection_args)
            except OSError as exc:
                cause = exc.__cause__ if exc.__cause__ is not None else exc  # Dask wraps it
                if isinstance(cause, socket.gaierror):
                    raise FluoInputError("host name does not resolve", field="--scheduler",
                                         value=address) from None
                # accepted, then closed at once (reported below); Dask says so as
                # CommClosedError (seen when a module file was imported before the probe)
                if isinstance(cause, (StreamClosedError, ConnectionResetError, CommClosedError)):
                    raise
                if not isinstance(cause, ConnectionRefusedError):
                    raise FluoDeviceError(f"cannot connect to the Dask scheduler at {address} "
                                          f"({_error_text(cause)})") from None
                # a scheduler may still be starting (a batch script that starts both):
                # tried again within the limit, as Dask's own connect does
                step["refused"] = cause
                await asyncio.sleep(0.2)
        try:
            # the handshake Dask's connect() does, here under the deadline
            step["now"] = "the Dask handshake"
            local = comm.handshake_info()
            await comm.write(local)
            remote = await comm.read()
            if not isinstance(remote, dict) or "compression" not in remote:
                raise FluoDeviceError(f"{address} is not a Dask scheduler (its handshake "
                                      f"was {_short(remote)})")
            comm.remote_info, comm.local_info = remote, local
            comm.handshake_options = comm.handshake_configuration(local, remote)
            step["now"] = "its identity"
            await comm.write({"op": "identity", "reply": True, "n_workers": 0})
            info = await comm.read()
            if not isinstance(info, dict) or info.get("type") != "Scheduler":
                raise FluoDeviceError(f"{address} is not a Dask scheduler (its identity was "
                                      f"{_short(info)})")
            return info
        finally:
            comm.abort()

    def run():
        return asyncio.run(asyncio.wait_for(ask(), timeout_s))

    try:
        # a thread of its own: the caller may be inside an event loop (a web app)
        done, info = _within(timeout_s + 5.0, run)
    except (FluoDeviceError, FluoInputError):
        raise
    except (TimeoutError, asyncio.TimeoutError):
        done, info = False, None
    except Exception as exc:  # noqa: BLE001 - whatever the bytes made Dask's reader raise
        if isinstance(exc, (CommClosedError, EOFError, ConnectionError)):
            when = ("as soon as it accepted it" if step["now"] == "a connection" else
                    f"while we waited for {step['now']}")
            detail = f" ({_error_text(exc)})" if str(exc).strip() else ""
            raise FluoDeviceError(f"the Dask scheduler at {address} closed the connection "
                                  f"{when}{detail}") from None
        raise FluoDeviceError(f"{address} is not a Dask scheduler: its answer to "
                              f"{step['now']} could not be read ({_error_text(exc)})") from None
    if not done and "refused" in step and step["now"] == "a connection":
        raise FluoDeviceError(f"nothing accepts connections at the Dask scheduler address "
                              f"{address} (refused for {timeout_s:g} s; "
                              f"${SCHEDULER_TIMEOUT_ENV} sets the limit)")
    if not done:
        raise FluoDeviceError(f"the Dask scheduler at {address} did not answer within "
                              f"{timeout_s:g} s (waited for {step['now']}; "
                              f"${SCHEDULER_TIMEOUT_ENV} sets the limit)")
    return info


def _short(value, n=80):
    text = repr(value)
    return text if len(text) <= n else text[:n] + "..."


def _ask(client, address, what, timeout_s, fn, *args, **kwargs):
    """``client.sync(fn, ...)`` within ``timeout_s``: a scheduler that does not
    answer is a FluoDeviceError naming ``address`` and ``what`` was asked."""
    try:
        return client.sync(fn, *args, callback_timeout=timeout_s, **kwargs)
    except (TimeoutError, asyncio.TimeoutError):
        raise FluoDeviceError(f"the Dask scheduler at {address} did not answer within "
                              f"{timeout_s:g} s (waited for {what}; ${SCHEDULER_TIMEOUT_ENV} "
                              f"sets the limit)") from None
    except OSError as exc:
        raise FluoDeviceError(f"lost the Dask scheduler at {address} while waiting for {what} "
                              f"({_error_text(exc)})") from None


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
    """Sends tasks to a ``distributed.Client``; see :class:`SerialExecutor` for the contract.

    Every question to the scheduler and every wait for the run's results is
    bounded by ``timeout_s`` (module docstring): a scheduler that stops answering
    is a FluoDeviceError, not a run that waits for ever.
    """

    name = "dask"

    def __init__(self, client, kind="local", dashboard=True, timeout_s=None):
        self.client = client
        self.kind = kind
        # a local cluster started without its dashboard still serves Dask's HTTP
        # routes under the name "dashboard" (on port 8787): not announced as one
        self.dashboard = dashboard
        self.timeout_s = scheduler_timeout() if timeout_s is None else float(timeout_s)
        self.address = client.scheduler.address

    def _ask(self, what, fn, *args, timeout_s=None, **kwargs):
        return _ask(self.client, self.address, what, timeout_s or self.timeout_s, fn, *args,
                    **kwargs)

    def identity(self):
        """The scheduler's identity with every worker (bounded)."""
        return self._ask("its identity", self.client.scheduler.identity, n_workers=-1)

    @property
    def workers(self):
        return len(self.identity().get("workers", {}))

    def describe(self):
        info = self.identity()
        out = {"executor": f"dask ({self.kind})", "workers": len(info.get("workers", {})),
               "scheduler": self.address}
        if self.dashboard:
            with contextlib.suppress(Exception):
                out["dashboard"] = self._dashboard_link(info)
        return out

    def _dashboard_link(self, info):
        from distributed.utils import format_dashboard_link

        if self.client.cluster is not None:   # our own local cluster: no question asked
            return self.client.dashboard_link
        port = info.get("services", {}).get("dashboard")
        if port is None:
            return None
        host = self.address.split("://", 1)[1].rsplit(":", 1)[0]
        return format_dashboard_link(host, port)

    def _cancel(self, futures):
        """Cancel ``futures`` on the scheduler, within the time limit (best effort:
        closing the client releases them too)."""
        with contextlib.suppress(Exception):
            self._ask("cancelling the run's tasks", self.client._cancel, futures)

    def run(self, todo, threads, on_done, cancel=None, task_progress=None):
        # task_progress is the serial loop's: here the run's progress is per task
        from distributed import as_completed

        client = self.client
        token = uuid.uuid4().hex[:8]
        modules = sorted({t.func.__module__ for t in todo}
                         | {s.func.__module__ for t in todo for s in t.shared_closure()})
        prepare_s = PREPARE_FACTOR * self.timeout_s
        try:
            client.run(prepare_worker, modules, callback_timeout=prepare_s)
        except (TimeoutError, asyncio.TimeoutError):
            raise FluoDeviceError(f"the Dask scheduler at {self.address} did not answer within "
                                  f"{prepare_s:g} s (waited for its workers to import "
                                  f"{', '.join(modules)}; ${SCHEDULER_TIMEOUT_ENV} x "
                                  f"{PREPARE_FACTOR} sets the limit)") from None
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
        # results are taken as they come; when none has come for a time limit the
        # scheduler must show it is alive (tasks may take hours, a silent peer never ends)
        quiet_since = time.monotonic()
        try:
            while not ac.is_empty():
                check_cancel(cancel)
                batch = ac.next_batch(block=False)
                if not batch:
                    if time.monotonic() - quiet_since > self.timeout_s:
                        self._ask(f"a sign of life during the run, {len(pending)} of "
                                  f"{len(todo)} tasks not done",
                                  client.scheduler.identity, n_workers=0)
                        quiet_since = time.monotonic()
                    _wait_for_results(ac, 0.05)
                    continue
                quiet_since = time.monotonic()
                for fut, res in batch:
                    check_cancel(cancel)
                    self._take(fut, res, pending, shared_f, need, on_done, len(todo))
        except FluoDeviceError:
            # the scheduler does not answer: nothing to cancel there (closing the client
            # releases what it holds, should it come back)
            raise
        except BaseException:
            self._cancel([f for f, _, _ in pending.values()] + list(shared_f.values()))
            raise
        return len(shared_f)

    def _take(self, fut, res, pending, shared_f, need, on_done, total):
        """One finished future: its row (or its error), and the shared inputs released."""
        _, t, closure = pending.pop(fut.key)
        if fut.status == "finished":
            _finish(on_done, t, res)
        else:
            if fut.status != "error":
                # cancelled or lost, not the task's own exception: the client gave its
                # futures up, as it does when the scheduler's connection is lost. A
                # scheduler that still answers cancelled it (recorded as the task's
                # failure); one that does not ends the run (not a failed task)
                try:
                    self._ask("its identity after it gave a task up",
                              self.client.scheduler.identity, n_workers=0)
                except FluoDeviceError:
                    raise FluoDeviceError(
                        f"lost the connection to the Dask scheduler at {self.address} during "
                        f"the run ({len(pending) + 1} of {total} tasks not done; task {t.id} "
                        f"{fut.status}, client {self.client.status})") from None
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


def _wait_for_results(ac, seconds):
    """Wait up to ``seconds`` for ``as_completed`` to queue a result: on the condition it
    notifies when it has one (as its own iterator waits), else a plain sleep."""
    cond = getattr(ac, "thread_condition", None)
    if cond is None:
        time.sleep(seconds)
        return
    with cond:
        if not ac.has_ready():
            cond.wait(timeout=seconds)


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
    timeout_s = scheduler_timeout()
    quiet = contextlib.ExitStack()
    try:
        if address:
            # Dask's client logs a lost or garbled connection as tracebacks on stderr;
            # what went wrong is this module's one FluoDeviceError line
            quiet.enter_context(_loggers_quiet(("distributed", "tornado")))
            # a peer that is not a scheduler (silent, random bytes, closing) is found here,
            # within the limit, before Dask's client (whose handshake has none) meets it
            probe_scheduler(address, timeout_s)
            abandoned = threading.Event()

            def connect():
                c = Client(address, timeout=timeout_s, set_as_default=False)
                if abandoned.is_set():  # the caller gave up waiting: do not leak it
                    with contextlib.suppress(Exception):
                        c.close(timeout=timeout_s)
                return c

            try:
                done, client = _within(timeout_s, connect)
            except (OSError, TimeoutError) as exc:
                raise FluoDeviceError(f"cannot reach the Dask scheduler at {address} "
                                      f"({_error_text(exc)})") from None
            if not done:
                abandoned.set()
                raise FluoDeviceError(f"the Dask scheduler at {address} did not answer within "
                                      f"{timeout_s:g} s (waited for the client's connection; "
                                      f"${SCHEDULER_TIMEOUT_ENV} sets the limit)")
            ex = DaskExecutor(client, kind="scheduler", dashboard=True, timeout_s=timeout_s)
            deadline = time.monotonic() + timeout_s
            while not ex.identity().get("workers"):
                if time.monotonic() > deadline:
                    raise FluoDeviceError(f"the Dask scheduler at {address} has no workers "
                                          f"(waited {timeout_s:g} s; ${SCHEDULER_TIMEOUT_ENV} "
                                          f"sets the limit)")
                time.sleep(0.2)
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
            ex = DaskExecutor(client, kind=kind, dashboard=dashboard, timeout_s=timeout_s)
        d = ex.describe()
        msg = f"dask: {d['workers']} workers ({kind}) at {d['scheduler']}"
        if d.get("dashboard"):
            msg += f"; dashboard {d['dashboard']}"
        print(msg, file=log, flush=True)
        yield ex
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close(timeout=min(10.0, timeout_s))
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=20)
        quiet.close()


@contextlib.contextmanager
def _loggers_quiet(roots):
    """The loggers ``roots`` and those below them that have a level of their own
    (Dask's configuration sets ``distributed.client``'s) at CRITICAL within the
    block; their levels restored after it."""
    names = [n for n in list(logging.Logger.manager.loggerDict)
             if any(n == r or n.startswith(r + ".") for r in roots)]
    saved = {}
    for name in set(roots) | set(names):
        logger = logging.getLogger(name)
        if name in roots or logger.level != logging.NOTSET:
            saved[name] = logger.level
            logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)
