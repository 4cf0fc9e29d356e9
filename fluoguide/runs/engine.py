"""Run a list of tasks: serially in this process, or on a Dask cluster.

Both executors do the same things in the same way:

- every Shared input is computed once, before the first task that needs it,
  and released when the last one has finished;
- every task runs with BLAS/OpenMP/numba limited to ``threads`` threads
  (:mod:`fluoguide.threads`), in the serial loop and on every worker, so tasks
  side by side do not oversubscribe the cores and a task's numbers do not
  depend on where it ran;
- an exception in a task (or in a Shared input it needs) is caught and
  recorded as that task's row (status ``failed``, the error's type and
  message): the other tasks go on, nothing is dropped;
- each finished task is written to the run folder the moment its result
  arrives (:class:`fluoguide.runs.store.RunStore`).

Cancelling (CancelToken) or Ctrl-C stops the run; what finished is kept.

A task function that declares ``reports_progress = True`` (an attribute of the
function) is called with ``progress=`` and ``cancel=`` keywords by the serial
loop: a task of minutes (a demo case) then shows its own steps and stops
mid-way when cancelled. On a Dask worker it runs without them (the run's
progress is per task there), and its numbers are the same either way.
"""

from __future__ import annotations

import os
import socket
import time
import traceback

from fluoguide.errors import FluoCancelled, FluoInputError
from fluoguide.progress import check_cancel, report, scaled
from fluoguide.runs.tasks import check_unique
from fluoguide.threads import limited_threads


def _error_text(exc):
    return f"{type(exc).__name__}: {exc}".strip()


def prepare_worker(names):
    """Run on every Dask worker before the tasks: import the task modules (a worker
    without FluoGuide fails here, once, with a clear message) and undo Dask's
    malloc setting.

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which makes
    glibc hand every freed block over 64 KiB back to the system and map it anew
    on the next allocation: our tasks, which allocate and free arrays of a few
    MB each iteration, spent 2.7x the CPU time in a worker than in a plain
    process (0.13 against 0.047 s per study-C task, measured). Heap
    allocations up to 64 MiB and trimming above 128 MiB restore the plain
    process's speed. glibc only; elsewhere nothing is changed.
    """
    import importlib

    from fluoguide.memory import hand_back_large_blocks

    for name in names:
        importlib.import_module(name)
    relaxed = bool(os.environ.get("MALLOC_TRIM_THRESHOLD_")) and hand_back_large_blocks(64 << 20)
    return {"modules": len(names), "malloc_relaxed": relaxed}


def call_shared(func, threads, *args):
    """Compute one Shared input (serial loop or a Dask worker)."""
    with limited_threads(threads):
        return func(*args)


def takes_progress(func):
    """Whether the serial loop passes ``progress``/``cancel`` to ``func`` (module docstring)."""
    return getattr(func, "reports_progress", False) is True


def call_task(func, params, threads, inputs):
    """Run one task (serial loop or a Dask worker); never raises for the task's own error.

    Returns a dict: ``result`` (the task's dict) or ``error`` (type and message)
    and ``traceback``, with ``seconds`` and ``worker`` (host:pid) either way. A
    failure comes back as data, so the worker logs nothing and Dask does not
    retry a task that will fail again.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    where = f"{socket.gethostname()}:{os.getpid()}"
    try:
        with limited_threads(threads):
            result = func(params, **inputs)
        if not isinstance(result, dict):
            raise TypeError(f"a task returns a dict of row fields, got {type(result).__name__}")
        # CPU seconds of the process while the task ran: above the wall time, the task
        # used several threads; far below, it waited for a core (a loaded machine)
        result.setdefault("cpu_seconds", time.process_time() - c0)
        return {"result": result, "seconds": time.perf_counter() - t0, "worker": where}
    except (FluoCancelled, KeyboardInterrupt):
        raise
    except Exception as exc:  # noqa: BLE001 - a failed task is a row, not the end of the run
        return {"error": _error_text(exc), "traceback": traceback.format_exc(limit=-4),
                "seconds": time.perf_counter() - t0, "worker": where}


def _finish(on_done, task, out):
    on_done(task, out.get("result"), out.get("error"), out["seconds"], out["worker"],
            tb=out.get("traceback"))


class SerialExecutor:
    """Runs tasks one after another in this process (needs no Dask)."""

    name = "serial"
    workers = 1

    def describe(self):
        return {"executor": "serial", "workers": 1}

    def run(self, todo, threads, on_done, cancel=None, task_progress=None):
        """Call ``on_done(task, result, error, seconds, worker)`` for each task in order.

        ``task_progress(task)``: the progress callback handed to a task that
        reports its own (``takes_progress``), with ``cancel``.
        Returns the number of shared inputs computed (each once)."""
        self.shared_built = 0
        need = {}
        for t in todo:
            for s in t.shared_closure():
                need[s.name] = need.get(s.name, 0) + 1
        values, errors = {}, {}

        def build(s):
            if s.name in values or s.name in errors:
                return
            for d in s.dependencies():
                build(d)
                if d.name in errors:
                    errors[s.name] = f"shared input {d.name!r} failed: {errors[d.name]}"
                    return
            try:
                args = [values[a.name] if hasattr(a, "dependencies") else a for a in s.args]
                self.shared_built += 1
                values[s.name] = call_shared(s.func, threads, *args)
            except (FluoCancelled, KeyboardInterrupt):
                raise
            except Exception as exc:  # noqa: BLE001 - recorded in the row of every dependent task
                errors[s.name] = _error_text(exc)

        for t in todo:
            check_cancel(cancel)
            closure = t.shared_closure()
            for s in closure:
                build(s)
            failed = next((s for s in closure if s.name in errors), None)
            if failed is not None:
                on_done(t, None, f"shared input {failed.name!r} failed: {errors[failed.name]}"
                        if not errors[failed.name].startswith("shared input") else errors[failed.name],
                        None, "serial")
            else:
                inputs = {k: values[s.name] for k, s in t.inputs.items()}
                if takes_progress(t.func):
                    inputs.update(progress=task_progress(t) if task_progress else None,
                                  cancel=cancel)
                _finish(on_done, t, call_task(t.func, t.params, threads, inputs))
            for s in closure:           # free what no later task needs
                need[s.name] -= 1
                if need[s.name] == 0:
                    values.pop(s.name, None)
        return self.shared_built


def run_tasks(tasks, store=None, executor=None, threads=1, progress=None, cancel=None,
              label="run"):
    """Run ``tasks`` and return their rows in task order.

    Parameters
    ----------
    tasks : list of Task
    store : RunStore, optional
        Where each finished task is written; with ``store.resume`` its finished
        records are reused instead of computed again.
    executor : SerialExecutor or DaskExecutor, optional
        Default: serial in this process.
    threads : int or None
        BLAS/OpenMP/numba threads per task (None: leave the libraries alone).
    progress, cancel :
        ``progress(fraction, message)``; a CancelToken.

    Returns
    -------
    dict
        ``rows`` (one per task, task order; failed tasks have ``status``
        "failed" and ``error``), ``failed`` (task id, parameters, error),
        ``tasks``, ``computed``, ``reused``, ``failures``, ``shared_inputs``
        (shared inputs computed, each once) (counts),
        ``seconds`` (wall time), ``executor``, ``workers``, ``records``.
    """
    from fluoguide.runs.store import row_of
    from fluoguide.jsonable import to_jsonable

    if not tasks:
        raise FluoInputError("the run has no tasks", field=label)
    check_unique(tasks)
    executor = executor or SerialExecutor()
    t0 = time.perf_counter()
    records, todo = {}, []
    for t in tasks:
        rec = store.finished(t) if store is not None else None
        if rec is not None:
            records[t.id] = rec
        else:
            todo.append(t)
    reused = len(records)
    if store is not None:
        store.write_table([records[t.id] for t in tasks if t.id in records])
        store.write_json("run.json", {
            "label": label, "status": "running", "tasks": len(tasks), "reused": reused,
            "threads_per_task": threads, **executor.describe(),
            "task_ids": [t.id for t in tasks]})
    n_failed = 0
    report(progress, reused / len(tasks), f"{reused}/{len(tasks)} tasks (reused)" if reused else
           f"0/{len(tasks)} tasks")

    def on_done(task, result, error, seconds, worker, tb=None):
        nonlocal n_failed
        status = "ok" if error is None else "failed"
        n_failed += error is not None
        if store is not None:
            rec = store.write(task, result, status=status, error=error, task_seconds=seconds,
                              worker=worker, traceback=tb)
        else:
            result = dict(result or {})
            arrays = result.pop("arrays", None)
            rec = to_jsonable({"task": task.id, "params": task.params, "result": result,
                               "status": status, "error": error, "task_seconds": seconds,
                               "worker": worker, "traceback": tb})
            rec["_arrays"] = arrays
        records[task.id] = rec
        done = len(records)
        report(progress, done / len(tasks),
               f"{done}/{len(tasks)} tasks" + (f", {n_failed} failed" if n_failed else ""))

    def task_progress(task):
        """The slice of the bar between this task's start and its end."""
        done = len(records)
        return scaled(progress, done / len(tasks), (done + 1) / len(tasks),
                      f"task {done + 1} of {len(tasks)}")

    shared_built = executor.run(todo, threads, on_done, cancel=cancel,
                                task_progress=task_progress) if todo else 0
    ordered = [records[t.id] for t in tasks]
    rows = store.write_table(ordered) if store is not None else [row_of(r) for r in ordered]
    failed = [{"task": r["task"], "params": r["params"], "error": r["error"]}
              for r in ordered if r["status"] != "ok"]
    wall = time.perf_counter() - t0
    summary = {"tasks": len(tasks), "computed": len(todo), "reused": reused,
               "failures": len(failed), "shared_inputs": shared_built, "seconds": wall,
               "threads_per_task": threads,
               **executor.describe()}
    if store is not None:
        store.write_json("run.json", {"label": label, "status": "finished", **summary,
                                      "task_ids": [t.id for t in tasks]})
    return {"rows": rows, "failed": failed, "records": ordered, **summary}
