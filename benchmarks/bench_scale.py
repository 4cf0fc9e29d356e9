"""Scaling a study out: serial, and on a local Dask cluster of 1 and 2 workers,
with and without thread pinning, in one run.

Each configuration runs in a fresh Python process (same imports, same start-up,
its own environment), one after the other:

- ``serial``          serial loop, BLAS/OpenMP/numba pinned to 1 thread per task
- ``serial-unpinned`` serial loop, the libraries' own thread counts (all cores)
- ``dask-1``          local cluster, 1 worker process, pinned
- ``dask-2``          local cluster, 2 worker processes, pinned
- ``dask-2-unpinned`` 2 workers, each library on every core (oversubscribed)

Printed per configuration: the run's wall time (tasks only; the cluster's
start-up and shutdown apart), the median task time, the CPU seconds the tasks
got per wall second, and the machine's load. Then the speed-up and efficiency
against the pinned serial run, the scheduler overhead per task (dask-1 minus
serial, per task), and what one machine and an N-worker cluster do per hour.
Every configuration's table must equal the serial one (stable columns): the
benchmark fails otherwise.

    python -m benchmarks scale [-- --study B --repeats 1 --json scale.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIGS = {
    "serial": dict(workers=None, threads=1),
    "serial-unpinned": dict(workers=None, threads=None),
    "dask-1": dict(workers=1, threads=1),
    "dask-2": dict(workers=2, threads=1),
    "dask-2-unpinned": dict(workers=2, threads=None),
}


def _noop(params):
    """A task that does nothing: what remains of its time is the engine's and the scheduler's."""
    return {"i": params["i"]}


N_NOOP = 200


def _one(study, config, out_dir, seeds=1):
    """Run one configuration in this process; print one JSON line."""
    t_import = time.perf_counter()
    from fluoguide.runs.cluster import executor
    from FluoTomoLib.studies.spec import study_spec
    from FluoTomoLib.studies.run import run_spec

    cfg = CONFIGS[config]
    t0 = time.perf_counter()
    load0 = os.getloadavg()[0]
    with open(os.devnull, "w") as quiet:
        with executor(workers=cfg["workers"], threads=cfg["threads"], log=quiet,
                      dashboard=False) as ex:
            t_started = time.perf_counter()
            # seeds 0..N-1: N noise draws of every (target, method), one shared Jacobian
            spec = study_spec(study, seeds=list(range(seeds)))
            out = run_spec(spec, out_dir=out_dir, executor=ex, threads=cfg["threads"])
            t_run = time.perf_counter()
            # the overhead per task: no-op tasks through the same engine and executor
            from fluoguide.runs.engine import run_tasks
            from fluoguide.runs.tasks import Task

            noop = run_tasks([Task(_noop, {"i": i}) for i in range(N_NOOP)], executor=ex,
                             threads=cfg["threads"])
            t_run_end = time.perf_counter()
    t_closed = time.perf_counter()
    rows = out["rows"]
    doc = {
        "config": config, "study": study, "tasks": out["tasks"], "failures": out["failures"],
        "workers": out["workers"], "threads_per_task": cfg["threads"],
        "import_s": t0 - t_import, "cluster_start_s": t_started - t0,
        "run_s": t_run - t_started, "cluster_close_s": t_closed - t_run_end,
        "noop_per_task_s": noop["seconds"] / N_NOOP,
        "task_s": [r["task_seconds"] for r in rows],
        "cpu_s": [r.get("cpu_seconds") for r in rows],
        "jacobian_s": rows[0].get("jacobian_seconds"),
        "load_before": load0, "load_after": os.getloadavg()[0],
    }
    print("RESULT " + json.dumps(doc), flush=True)


MC_CONFIGS = {
    # serial: pocl's own threads (every core); workers: 1 OpenCL thread each
    "mc-serial": dict(workers=None, threads=1),
    "mc-dask-1": dict(workers=1, threads=1),
    "mc-dask-2": dict(workers=2, threads=1),
}


def _one_mc(config, out_dir, photons, runs):
    """One Monte Carlo budget (half-space runs) in this process; print one JSON line."""
    from fluoguide.runs.cluster import executor
    from fluoguide.runs.store import RunStore
    from FluoTomoLib.montecarlo.halfspace import HalfSpace, simulate_halfspace

    cfg = MC_CONFIGS[config]
    med = HalfSpace(0.01, 1.0, 1.37, size_mm=(80, 80, 40))
    load0 = os.getloadavg()[0]
    with open(os.devnull, "w") as quiet:
        t0 = time.perf_counter()
        with executor(workers=cfg["workers"], threads=cfg["threads"], log=quiet,
                      dashboard=False) as ex:
            t_started = time.perf_counter()
            merged = simulate_halfspace(med, photons, runs=runs, seed=501, engine="mcxcl",
                                        executor=ex, threads=cfg["threads"],
                                        store=RunStore(out_dir))
            t_run = time.perf_counter()
    doc = {"config": config, "workers": cfg["workers"] or 1, "cluster_start_s": t_started - t0,
           "run_s": t_run - t_started, "photons": merged["photons"],
           "R_5mm": next(r["R_per_mm2"] for r in merged["R"] if r["rho_mm"] == 5.0),
           "device": merged["device"], "load_before": load0, "load_after": os.getloadavg()[0]}
    print("RESULT " + json.dumps(doc), flush=True)


def _main_mc(args):
    """Serial against 1 and 2 workers for one Monte Carlo photon budget."""
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-scale-mc-") as root:
        for c in MC_CONFIGS:
            r = subprocess.run([sys.executable, "-m", "benchmarks.bench_scale", "--one", c,
                                "--photons", str(args.photons), "--runs", str(args.runs),
                                "--out", str(Path(root) / c)], capture_output=True, text=True,
                               timeout=7200)
            line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
            if r.returncode != 0 or line is None:
                print(f"{c} failed (rc {r.returncode}): {r.stderr[-2000:]}", file=sys.stderr)
                return 1
            results[c] = json.loads(line[len("RESULT "):])
    base = results["mc-serial"]["run_s"]
    print(f"Monte Carlo: {args.runs} runs x {args.photons} photons, half-space 80 x 80 x 40 mm")
    print(f"{'configuration':<12} {'workers':>7} {'run [s]':>8} {'start [s]':>9} "
          f"{'photons/s':>10} {'speed-up':>8} {'R(5 mm)':>12} {'load':>9}")
    for c, d in results.items():
        print(f"{c:<12} {d['workers']:>7} {d['run_s']:>8.1f} {d['cluster_start_s']:>9.2f} "
              f"{d['photons'] / d['run_s']:>10.0f} {base / d['run_s']:>8.2f} {d['R_5mm']:>12.6e} "
              f"{d['load_before']:>4.1f}-{d['load_after']:<4.1f}")
    same = len({d["R_5mm"] for d in results.values()}) == 1
    print("same photons in every configuration (R(5 mm) identical):", same)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0 if same else 1


def _run_config(study, config, root, seeds=1):
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        if CONFIGS[config]["threads"] is None:
            env.pop(var, None)         # the libraries' own defaults: every core
        else:
            env[var] = "1"
    out = Path(root) / config
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "benchmarks.bench_scale", "--one", config,
                        "--study", study, "--seeds", str(seeds), "--out", str(out)], capture_output=True, text=True,
                       env=env, timeout=3600)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if r.returncode != 0 or line is None:
        raise RuntimeError(f"{config} failed (rc {r.returncode}): {r.stderr[-2000:]}")
    doc = json.loads(line[len("RESULT "):])
    doc["process_s"] = time.perf_counter() - t0
    doc["table"] = str(out / "table.csv")
    return doc


def _stable_rows(path):
    from fluoguide.runs.store import read_table, stable_columns

    cols, rows = read_table(path)
    keep = stable_columns(cols)
    return [[r[c] for c in keep] for r in rows]


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks scale")
    ap.add_argument("--study", default="B", choices=["A", "B", "C"])
    ap.add_argument("--seeds", type=int, default=1,
                    help="noise seeds per (target, method): study B has 15 tasks per seed, all "
                         "sharing one Jacobian (default 1)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of every configuration")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--json", default=None, help="write the numbers here")
    ap.add_argument("--mc", action="store_true",
                    help="instead of the study: one Monte Carlo photon budget (--runs runs of "
                         "--photons) serially and on 1 and 2 workers")
    ap.add_argument("--photons", type=int, default=20_000, help="--mc: photons per run")
    ap.add_argument("--runs", type=int, default=8, help="--mc: independent runs (tasks)")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one in MC_CONFIGS:
        _one_mc(args.one, args.out, args.photons, args.runs)
        return 0
    if args.one:
        _one(args.study, args.one, args.out, args.seeds)
        return 0
    if args.mc:
        return _main_mc(args)
    configs = [c.strip() for c in args.configs.split(",")]
    if any(c not in CONFIGS for c in configs) or "serial" not in configs or args.repeats < 1 \
            or not 1 <= args.seeds <= 1000:
        print(f"configs must include serial and be among {', '.join(CONFIGS)}; repeats >= 1; "
              f"seeds 1..1000",
              file=sys.stderr)
        return 2
    from fluoguide.threads import cpu_count

    print(f"study {args.study} x {args.seeds} seed(s); {cpu_count()} cores; load average before "
          f"{os.getloadavg()[0]:.1f} (other work on this machine slows every figure below)")
    results = {c: [] for c in configs}
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as root:
        for rep in range(args.repeats):
            for c in configs:          # interleaved: a load change hits every configuration
                doc = _run_config(args.study, c, Path(root) / f"r{rep}", args.seeds)
                doc["same_table_as_serial"] = None
                results[c].append(doc)
        ref = _stable_rows(results["serial"][0]["table"])
        for c in configs:
            for doc in results[c]:
                doc["same_table_as_serial"] = _stable_rows(doc["table"]) == ref
    med = {c: {k: statistics.median(d[k] for d in results[c])
               for k in ("run_s", "cluster_start_s", "cluster_close_s", "import_s", "process_s",
                         "noop_per_task_s", "load_before", "load_after")} for c in configs}
    for c in configs:
        tasks = results[c][0]["task_s"]
        cpu = [x for d in results[c] for x in d["cpu_s"] if x is not None]
        med[c]["task_median_s"] = statistics.median(t for d in results[c] for t in d["task_s"])
        med[c]["cpu_per_wall"] = sum(cpu) / sum(t for d in results[c] for t in d["task_s"])
        med[c]["task_cpu_median_s"] = statistics.median(cpu)
        med[c]["workers"] = results[c][0]["workers"]
        med[c]["tasks"] = len(tasks)
    base = med["serial"]["run_s"]
    n_tasks = med["serial"]["tasks"]
    print(f"{'configuration':<17} {'workers':>7} {'run [s]':>8} {'start [s]':>9} "
          f"{'task med [s]':>12} {'task cpu [s]':>12} {'cpu/wall':>8} {'no-op [ms]':>10} "
          f"{'speed-up':>8} {'effic.':>6} {'load':>9} same table")
    for c in configs:
        m = med[c]
        speed = base / m["run_s"]
        eff = speed / m["workers"]
        same = all(d["same_table_as_serial"] for d in results[c])
        m.update(speed_up=speed, efficiency=eff, same_table=same)
        print(f"{c:<17} {m['workers']:>7} {m['run_s']:>8.2f} {m['cluster_start_s']:>9.2f} "
              f"{m['task_median_s']:>12.3f} {m['task_cpu_median_s']:>12.3f} "
              f"{m['cpu_per_wall']:>8.2f} {1e3 * m['noop_per_task_s']:>10.2f} {speed:>8.2f} "
              f"{eff:>6.2f} {m['load_before']:>4.1f}-{m['load_after']:<4.1f} {same}")
    per_task = base / n_tasks
    summary = {"study": args.study, "seeds": args.seeds, "tasks": n_tasks, "serial_per_task_s": per_task,
               "serial_tasks_per_hour": 3600 / per_task, "configs": med, "runs": results}
    if "dask-1" in med:
        overhead = med["dask-1"]["noop_per_task_s"]
        summary["scheduler_overhead_per_task_s"] = overhead
        summary["study_overhead_per_task_s"] = (med["dask-1"]["run_s"] - base) / n_tasks
        summary["cluster_start_s"] = med["dask-1"]["cluster_start_s"]
        print(f"per task: {per_task:.3f} s serial (wall, Jacobian included); scheduler overhead "
              f"{1e3 * overhead:.1f} ms per task (no-op tasks on dask-1; serial "
              f"{1e3 * med['serial']['noop_per_task_s']:.2f} ms); study on dask-1 "
              f"{summary['study_overhead_per_task_s']:+.3f} s per task against serial (worker "
              f"warm-up, load); local cluster start {med['dask-1']['cluster_start_s']:.1f} s")
        per_cluster_task = per_task + max(overhead, 0.0)
        for n in (2, 8, 32, 128):
            print(f"  {n:>4} workers: ~{3600 * n / per_cluster_task:,.0f} tasks per hour "
                  f"(per-task cost x tasks / N, overhead included; no transfer limit assumed)")
    jac = results["serial"][0].get("jacobian_s")
    if jac:
        # Amdahl: the shared Jacobian runs once, on one worker, before the tasks that need it
        tasks_s = base - jac
        print(f"shared Jacobian {jac:.2f} s of the serial {base:.2f} s (computed once, on one "
              f"worker); the tasks alone: {tasks_s:.2f} s serial, so 2 workers can at best "
              f"give {base / (jac + tasks_s / 2):.2f}x")
        summary["jacobian_s"] = jac
    print(f"one machine, serial pinned: ~{3600 / per_task:,.0f} tasks per hour")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))
    # the same thread count must give the same numbers; unpinned runs may differ in the
    # last digits (a threaded BLAS sums in another order), which is reported, not failed
    if not all(m["same_table"] for c, m in med.items() if CONFIGS[c]["threads"] is not None):
        print("FAIL: a pinned configuration's table differs from the serial one", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
