"""The test suite's shared set-up (every folder under ``testpaths``).

- Subprocesses (``python -m fluoapp``) import the tree under test, not whatever
  checkout the virtual environment's editable install points at (a git
  worktree shares one ``.venv`` with the main checkout).
- ``fluo``: a session fixture that runs ``fluo`` commands as children forked
  from one process that imported the stack once (``Testing/Python/forkserver.py``):
  the exit code, stdout and stderr of a real process without its start-up.
- The time guard: a test not marked ``slow`` that takes longer than
  ``FAST_TEST_LIMIT_S`` (set-up, call and tear-down together) fails, so the
  fast suite stays fast and CI's budget is spent where it is declared.
- Order: slow and browser tests first, so that with ``pytest -n 2`` the long
  tests start at once and the short ones fill the gaps (xdist's work stealing).
- ``heavy``: tests that need many GB hold a lock shared by the xdist workers,
  so two of them never run side by side on a small machine. The memory guard:
  a test not marked heavy whose process tree (the test process, the fork
  server's children, subprocesses) grows by more than ``LIGHT_TEST_LIMIT_GB``
  (resident, sampled every 0.2 s) fails, so the lock knows every big test.
  ``FLUO_TEST_MEMORY_REPORT=FILE`` appends each test's seconds and peak to FILE.
"""

import fcntl
import os
import sys
import tempfile
from pathlib import Path

import pytest

# VTK/MRML print warnings straight to stderr; keep test logs readable.
os.environ.setdefault("VTK_LOG_LEVEL", "ERROR")

_ROOT = Path(__file__).resolve().parent
_TREE = [str(_ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]
os.environ["PYTHONPATH"] = os.pathsep.join(
    _TREE + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p not in _TREE])
sys.path.insert(0, str(_ROOT / "Testing" / "Python"))

# A test that is not marked slow must finish within this (set-up + call +
# tear-down). 20 s is issue #29's rule; FLUO_FAST_TEST_LIMIT_S=0 turns it off
# (a profiling run on a loaded machine, say).
FAST_TEST_LIMIT_S = float(os.environ.get("FLUO_FAST_TEST_LIMIT_S", "20"))


def pytest_collection_modifyitems(session, config, items):
    """Slow and browser tests first (stable otherwise): the longest work starts first."""
    def rank(item):
        if item.get_closest_marker("heavy"):
            return 0
        if item.get_closest_marker("slow") or item.get_closest_marker("browser"):
            return 1
        return 2

    items[:] = sorted(items, key=rank)


# A test not marked heavy may grow its process tree's resident memory by this
# much: with two workers, one heavy test (the quick demo, ~12 GB) beside a light
# one then fits the 24 GB machine with room for the workers themselves.
LIGHT_TEST_LIMIT_GB = float(os.environ.get("FLUO_LIGHT_TEST_LIMIT_GB", "4"))

_SPENT = pytest.StashKey[float]()   # seconds of a test's phases so far
_MEMORY = pytest.StashKey[dict]()   # the memory sampler's findings


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    report = yield
    if FAST_TEST_LIMIT_S <= 0 or item.get_closest_marker("slow"):
        return report
    spent = item.stash.get(_SPENT, 0.0) + (call.stop - call.start)
    item.stash[_SPENT] = spent
    if call.when == "teardown" and spent > FAST_TEST_LIMIT_S and report.passed:
        report.outcome = "failed"
        report.longrepr = (f"{item.nodeid} took {spent:.1f} s (set-up, call and tear-down), over "
                           f"the {FAST_TEST_LIMIT_S:.0f} s allowed a test not marked slow: make "
                           "it faster, or mark it @pytest.mark.slow (conftest.py)")
    return report


def _tree_rss_bytes(proc):
    """Resident size of ``proc`` and every process below it (bytes)."""
    import psutil

    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


@pytest.fixture(autouse=True)
def _memory_watch(request):
    """Sample the test's process tree every 0.2 s; fail a light test that grew
    by more than ``LIGHT_TEST_LIMIT_GB``; report to ``FLUO_TEST_MEMORY_REPORT``."""
    import threading
    import time

    import psutil

    proc = psutil.Process()
    start = _tree_rss_bytes(proc)
    found = {"peak": start}
    stop = threading.Event()

    def sample():
        while not stop.wait(0.2):
            found["peak"] = max(found["peak"], _tree_rss_bytes(proc))

    t0 = time.monotonic()
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
    grew_gb = (found["peak"] - start) / 2**30
    report = os.environ.get("FLUO_TEST_MEMORY_REPORT")
    if report:
        import json

        with open(report, "a") as fh:
            fh.write(json.dumps({"test": request.node.nodeid, "seconds": time.monotonic() - t0,
                                 "grew_gb": round(grew_gb, 3),
                                 "peak_gb": round(found["peak"] / 2**30, 3)}) + "\n")
    if request.node.get_closest_marker("heavy") is None and grew_gb > LIGHT_TEST_LIMIT_GB:
        pytest.fail(f"{request.node.nodeid} grew its processes' resident memory by "
                    f"{grew_gb:.1f} GB, over the {LIGHT_TEST_LIMIT_GB:g} GB of a test not "
                    "marked heavy: make it smaller, or mark it @pytest.mark.heavy (conftest.py)",
                    pytrace=False)


@pytest.fixture(autouse=True)
def _heavy_lock(request):
    """One heavy test at a time across xdist workers (an exclusive file lock)."""
    if request.node.get_closest_marker("heavy") is None:
        yield
        return
    lock = Path(tempfile.gettempdir()) / f"fluo-heavy-{os.getuid()}.lock"
    with open(lock, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def fluo():
    """``fluo(*args, cwd=None, env=None, timeout=600)`` -> result with
    ``returncode``, ``stdout``, ``stderr``: a ``fluo`` command as a child forked
    from a server that imported the stack once (``Testing/Python/forkserver.py``;
    module-level helpers call ``forkserver.fluo`` directly, the same server)."""
    import forkserver

    return forkserver.fluo


@pytest.fixture(scope="session")
def own_scene(tmp_path_factory):
    """The shared own scene (``small_cases.write_own_scene``) and an acquisition
    simulated from it by ``fluo tomo simulate --accuracy fast`` (label 7 at
    ``small_cases.TRUE_YIELD``). A namespace: ``dir``, ``labels``, ``optics``,
    ``acq`` (paths), ``sc`` (the scene dict with its truth), ``simulated`` (the
    command's JSON). Read-only: a test that changes a file copies it first."""
    import json
    from types import SimpleNamespace

    import forkserver
    from small_cases import TRUE_YIELD, write_own_scene

    d = tmp_path_factory.mktemp("own_scene")
    sc = write_own_scene(d)
    r = forkserver.fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics",
                        d / "optics.json", "--yield", f"7:{TRUE_YIELD}", "--accuracy", "fast",
                        "--out", d / "acq", "--json")
    assert r.returncode == 0, r.stderr
    return SimpleNamespace(dir=d, labels=d / "labels.nrrd", optics=d / "optics.json",
                           acq=d / "acq", sc=sc, simulated=json.loads(r.stdout))


@pytest.fixture(scope="session")
def issue_acquisition(tmp_path_factory):
    """Issue #17's own scene at full resolution (``small_cases.write_scene()``'s
    defaults: 0.5 x 0.6 x 0.7 mm voxels, direction diag(-1, -1, 1), origin
    (120, -80, 340)) and an acquisition simulated at the ``fine`` level (1 %
    noise, seed 4): the accuracy tests of the CLI, the logic and the browser
    share it. A namespace like ``own_scene``'s (no ``simulated``). Read-only."""
    from types import SimpleNamespace

    import forkserver
    from small_cases import TRUE_YIELD, write_scene

    d = tmp_path_factory.mktemp("issue_scene")
    sc = write_scene(d)
    r = forkserver.fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics",
                        d / "optics.json", "--yield", f"7:{TRUE_YIELD}", "--noise-pct", "1",
                        "--seed", "4", "--accuracy", "fine", "--out", d / "acq", timeout=1800)
    assert r.returncode == 0, r.stderr
    return SimpleNamespace(dir=d, labels=d / "labels.nrrd", optics=d / "optics.json",
                           acq=d / "acq", sc=sc)
