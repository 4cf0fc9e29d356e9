"""Run benchmarks: ``python -m benchmarks`` (all) or ``python -m benchmarks fem meshing``.

Each ``benchmarks/bench_<name>.py`` has ``main(argv)``; arguments after ``--``
are passed to every selected benchmark.
"""

import importlib
import pkgutil
import sys
import time
from pathlib import Path


def available():
    here = Path(__file__).parent
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules([str(here)])
                  if m.name.startswith("bench_"))


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    names = argv or available()
    unknown = [n for n in names if n not in available()]
    if unknown:
        print(f"unknown benchmark(s): {', '.join(unknown)}; available: {', '.join(available())}",
              file=sys.stderr)
        return 2
    for name in names:
        print(f"===== benchmark {name} =====", flush=True)
        t0 = time.perf_counter()
        rc = importlib.import_module(f"benchmarks.bench_{name}").main(extra) or 0
        print(f"===== {name}: {time.perf_counter() - t0:.1f} s (rc {rc}) =====", flush=True)
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(main())
