"""Thread pools: ``fluo study B`` (2D, the thesis's study B: 15 reconstructions)
with one thread, ``auto`` (every core) and the libraries' own defaults
(``system``), each in a fresh process, interleaved so that every setting sees
the same machine load; medians of repeats and their ratio to one thread.

``python -m benchmarks threads [-- --repeats 3 --study B --dim 2]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = ("1", "auto", "system")


def _env():
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                        "NUMBA_NUM_THREADS", "FLUO_THREADS")}
    paths = [str(ROOT)] + [str(ROOT / m) for m in ("FluoCalib", "FluoNav", "FluoTomo")]
    env["PYTHONPATH"] = os.pathsep.join(paths + [env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def run_once(setting, study="B", dim=2):
    """Seconds of one ``fluo --threads SETTING study ...`` (process start included)."""
    cmd = [sys.executable, "-m", "fluoapp", "--threads", setting, "study", study, "--dim",
           str(dim), "--json"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=_env(), cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {r.stderr.strip()[-400:]}")
    return seconds


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks threads")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--study", default="B")
    ap.add_argument("--dim", type=int, default=2)
    ap.add_argument("--settings", default=",".join(SETTINGS),
                    help="comma-separated --threads values to compare")
    args = ap.parse_args(argv)
    settings = args.settings.split(",")
    times = {s: [] for s in settings}
    loads = []
    print(f"fluo study {args.study} --dim {args.dim}, {os.cpu_count()} cores, "
          f"{args.repeats} repeats, settings interleaved", flush=True)
    for rep in range(args.repeats):
        for s in settings:
            loads.append(os.getloadavg()[0])
            times[s].append(run_once(s, args.study, args.dim))
            print(f"  repeat {rep + 1}: --threads {s:7s} {times[s][-1]:7.1f} s "
                  f"(load average {loads[-1]:.1f})", flush=True)
    base = statistics.median(times[settings[0]])
    print(f"{'--threads':10s} {'median s':>9s} {'min s':>7s} {'max s':>7s} "
          f"{'x ' + settings[0]:>8s}")
    for s in settings:
        med = statistics.median(times[s])
        print(f"{s:10s} {med:9.1f} {min(times[s]):7.1f} {max(times[s]):7.1f} "
              f"{med / base:8.2f}")
    print(f"load average (1 min) during the runs: median {statistics.median(loads):.1f}, "
          f"max {max(loads):.1f}")
    return 0
