"""The test suite's shared set-up (every folder under ``testpaths``).

- Subprocesses (``python -m fluoapp``) import the tree under test, not whatever
  checkout the virtual environment's editable install points at (a git
  worktree shares one ``.venv`` with the main checkout).
- ``fluo``: a session fixture that runs ``fluo`` commands as children forked
  from one process that imported the stack once (``Testing/Python/forkserver.py``):
  the exit code, stdout and stderr of a real process without its start-up.
- Shared small inputs: ``own_scene`` and ``issue_acquisition`` (built once per
  test process; ``Testing/Python/small_cases.py``).
- ``qt_app``: a PySide6 ``QCoreApplication`` for the tests that watch a
  background job from a Qt event loop (``Testing/Python/event_loop.py``).
- The time guard: a test not marked ``slow`` that takes longer than
  ``FAST_TEST_LIMIT_S`` (set-up, call and tear-down together) fails, so the
  fast suite stays fast and CI's budget is spent where it is declared.
- The memory guard and budget: every test's process tree (the test process,
  the fork server and its children, subprocesses) is sampled every 0.2 s. A
  test marked ``@pytest.mark.heavy(gb=G)`` reserves G GB of a budget shared by
  every test process of the machine (``heavy_budget_gb``) before it starts, and
  waits while the reservations would exceed it; a test that grows by more than
  its G (``LIGHT_TEST_LIMIT_GB`` without the mark) fails, so the reservations
  stay honest. ``FLUO_TEST_MEMORY_REPORT=FILE`` appends each test's seconds and
  peak to FILE.
- Order: whole files (``make test`` distributes files, ``--dist loadfile``): the
  largest heavy test's first, then heavy files that fit beside it, then files
  with slow tests, then the other heavy files, then the rest, so long work
  starts at once, the other worker is not left waiting for memory, and the
  short files fill the gaps.
"""

import fcntl
import json
import os
import sys
import tempfile
import threading
import time
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
NEAR_FAST_LIMIT = 0.7      # the share of it that the summary names as near

# A test not marked heavy may grow its process tree's memory (_tree_bytes) by this
# much: two light tests, or a light one beside the heavy reservations, fit.
LIGHT_TEST_LIMIT_GB = float(os.environ.get("FLUO_LIGHT_TEST_LIMIT_GB", "4"))

_SPENT = pytest.StashKey[float]()   # seconds of a test's phases so far


def heavy_budget_gb():
    """GB that heavy tests may hold at once on this machine: its memory less 7 GB
    for the test processes themselves (about 1.5 GB each with its fork server) and
    a light test beside them (24 GB: 17); ``FLUO_HEAVY_BUDGET_GB`` overrides. One
    heavy test always may run."""
    if os.environ.get("FLUO_HEAVY_BUDGET_GB"):
        return float(os.environ["FLUO_HEAVY_BUDGET_GB"])
    with open("/proc/meminfo") as fh:
        total_kb = next(int(line.split()[1]) for line in fh if line.startswith("MemTotal:"))
    return max(0.0, total_kb / 2**20 - 7.0)


def _heavy_gb(item):
    """The GB a heavy test declares (``@pytest.mark.heavy(gb=G)``), else None."""
    mark = item.get_closest_marker("heavy")
    if mark is None:
        return None
    gb = mark.kwargs.get("gb", mark.args[0] if mark.args else None)
    if not isinstance(gb, (int, float)) or gb <= 0:
        raise pytest.UsageError(f"{item.nodeid}: @pytest.mark.heavy needs gb=<its peak in GB>")
    return float(gb)


def pytest_collection_modifyitems(session, config, items):
    """Order whole files (a file's tests keep their order: some share state through
    module fixtures, the browser's page): the file of the largest heavy test first;
    then heavy files that fit beside it in the memory budget; then files with slow
    or browser tests; then the other heavy files, largest first; then the rest.
    While the largest reservation runs, the other worker has long work that fits
    beside it instead of waiting for memory."""
    files = {}
    for k, item in enumerate(items):
        f = files.setdefault(str(item.path), {"first": k, "gb": 0.0, "slow": False})
        f["gb"] = max(f["gb"], _heavy_gb(item) or 0.0)       # a bad mark: refused here
        f["slow"] |= bool(item.get_closest_marker("slow") or item.get_closest_marker("browser"))
    if not files:
        return
    largest = max(files.values(), key=lambda f: f["gb"])
    room = heavy_budget_gb() - largest["gb"]

    def rank(f):
        if f is largest and f["gb"] > 0:
            return (0, 0.0)
        if f["gb"] > 0:
            return (1, -f["gb"]) if f["gb"] <= room else (3, -f["gb"])
        return (2, 0.0) if f["slow"] else (4, 0.0)

    items[:] = sorted(items, key=lambda it: (*rank(files[str(it.path)]),
                                             files[str(it.path)]["first"]))


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
    elif call.when == "teardown" and spent > NEAR_FAST_LIMIT * FAST_TEST_LIMIT_S:
        report.user_properties.append(("near_fast_limit_s", round(spent, 1)))
    return report


_NEAR = []      # (seconds, test) of the tests near the limit, as their reports arrive


def pytest_runtest_logreport(report):
    # here, not in makereport: under xdist only the controlling process prints
    spent = dict(report.user_properties).get("near_fast_limit_s")
    if report.when == "teardown" and spent is not None:
        _NEAR.append((spent, report.nodeid))


def pytest_terminal_summary(terminalreporter):
    """Name the tests not marked slow that came within a few seconds of the limit:
    a loaded CI machine is slower than the run that measured them."""
    near = sorted(_NEAR, reverse=True)
    if near:
        terminalreporter.write_line(
            f"{len(near)} test(s) not marked slow took over {NEAR_FAST_LIMIT:.0%} of the "
            f"{FAST_TEST_LIMIT_S:.0f} s allowed (make them faster or mark them slow):")
        for spent, nodeid in near:
            terminalreporter.write_line(f"  {spent:5.1f} s  {nodeid}")


# ----------------------------------------------------------------- memory
def _proportional_bytes(p):
    """Memory ``p`` holds (bytes): its proportional set size plus its proportional
    share of swap (``/proc/PID/smaps_rollup``), its resident size where the kernel
    has no rollup. Resident size counts a page shared by N processes N times: a
    child forked from a large process (the fork server's, a worker's) reads as
    large as its parent until it writes, and pages swapped out and back in read
    as growth. The proportional size is what the machine actually spends."""
    try:
        with open(f"/proc/{p.pid}/smaps_rollup") as fh:
            next(fh)                          # the address range the rollup spans
            kb = {k: int(v.split()[0]) for k, v in (line.split(":", 1) for line in fh)}
        return (kb.get("Pss", 0) + kb.get("SwapPss", 0)) * 1024
    except (OSError, ValueError):
        return p.memory_info().rss


def _tree_bytes(proc, exclude=(), per_pid=None):
    """Memory held by ``proc`` and every process below it (bytes,
    ``_proportional_bytes``), but the pids in ``exclude``; ``per_pid`` (a dict)
    keeps each process's largest value, for the failure message."""
    import psutil

    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        if p.pid in exclude:
            continue
        try:
            b = _proportional_bytes(p)
        except psutil.Error:
            continue
        total += b
        if per_pid is not None and b > per_pid.get(p.pid, (0, ""))[0]:
            try:
                name = " ".join(p.cmdline())[:60]
            except psutil.Error:
                name = "?"
            per_pid[p.pid] = (b, name)
    return total


class _Reservations:
    """The heavy tests' reservations of every test process on this machine: a
    JSON file {pid: GB} under an exclusive lock (a crashed process's entry is
    dropped, its pid gone)."""

    def __init__(self):
        tmp = Path(tempfile.gettempdir())
        self.path = tmp / f"fluo-heavy-{os.getuid()}.json"
        self.lock = tmp / f"fluo-heavy-{os.getuid()}.lock"

    def _update(self, change):
        with open(self.lock, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                try:
                    held = json.loads(self.path.read_text())
                except (OSError, ValueError):
                    held = {}
                held = {pid: gb for pid, gb in held.items() if _alive(int(pid))}
                ok = change(held)
                self.path.write_text(json.dumps(held))
                return ok
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def acquire(self, gb, budget):
        me = str(os.getpid())

        def take(held):
            if not held or sum(held.values()) + gb <= budget:
                held[me] = gb
                return True
            return False

        while not self._update(take):
            time.sleep(0.5)

    def release(self):
        self._update(lambda held: held.pop(str(os.getpid()), None))


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@pytest.fixture(autouse=True)
def _memory(request):
    """Reserve a heavy test's GB; sample the memory of the test's process tree
    (``_tree_bytes``) every 0.2 s; fail
    a test that grew by more than it declared (``LIGHT_TEST_LIMIT_GB`` if light);
    report to ``FLUO_TEST_MEMORY_REPORT``."""
    import psutil

    gb = _heavy_gb(request.node)
    reservations = _Reservations() if gb is not None else None
    if reservations is not None:
        reservations.acquire(gb, heavy_budget_gb())
    proc = psutil.Process()
    # processes already running below this one are an earlier test's (one still
    # shutting down grew by 4.4 GB during a 22 MB test in CI): not this test's
    earlier = {p.pid for p in proc.children(recursive=True)}
    start = _tree_bytes(proc, earlier)
    found = {"peak": start}
    per_pid = {}
    stop = threading.Event()

    def sample():
        while not stop.wait(0.2):
            found["peak"] = max(found["peak"], _tree_bytes(proc, earlier, per_pid))

    t0 = time.monotonic()
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        if reservations is not None:
            reservations.release()
    grew_gb = (found["peak"] - start) / 2**30
    report = os.environ.get("FLUO_TEST_MEMORY_REPORT")
    if report:
        with open(report, "a") as fh:
            fh.write(json.dumps({"test": request.node.nodeid, "seconds": time.monotonic() - t0,
                                 "declared_gb": gb, "grew_gb": round(grew_gb, 3),
                                 "peak_gb": round(found["peak"] / 2**30, 3)}) + "\n")
    allowed = LIGHT_TEST_LIMIT_GB if gb is None else gb
    if grew_gb > allowed:
        fix = ("make it smaller, or mark it @pytest.mark.heavy(gb=...)" if gb is None
               else "raise its @pytest.mark.heavy(gb=...) or make it smaller")
        largest = sorted(per_pid.items(), key=lambda kv: -kv[1][0])[:3]
        who = "; ".join(f"pid {pid} {b / 2**30:.1f} GB ({name})" for pid, (b, name) in largest)
        pytest.fail(f"{request.node.nodeid} grew its processes' memory by "
                    f"{grew_gb:.1f} GB, over the {allowed:g} GB it may: {fix} (conftest.py; "
                    f"largest at their peaks: {who})", pytrace=False)


# ----------------------------------------------------------------- shared inputs
@pytest.fixture(scope="session")
def fluo():
    """``fluo(*args, cwd=None, env=None, timeout=600)`` -> result with
    ``returncode``, ``stdout``, ``stderr``: a ``fluo`` command as a child forked
    from a server that imported the stack once (``Testing/Python/forkserver.py``;
    module-level helpers call ``forkserver.fluo`` directly, the same server)."""
    import forkserver

    return forkserver.fluo


@pytest.fixture(scope="session")
def qt_app():
    """The process's Qt application (PySide6; the test is skipped without it)."""
    pytest.importorskip("PySide6")
    from PySide6.QtCore import QCoreApplication

    return QCoreApplication.instance() or QCoreApplication([])


@pytest.fixture(scope="session")
def own_scene(tmp_path_factory):
    """The shared own scene (``small_cases.write_own_scene``) and an acquisition
    simulated from it by ``fluo tomo simulate --accuracy fast`` (label 7 at
    ``small_cases.TRUE_YIELD``). A namespace: ``dir``, ``labels``, ``optics``,
    ``acq`` (paths), ``sc`` (the scene dict with its truth), ``simulated`` (the
    command's JSON). Read-only: a test that changes a file copies it first."""
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
    noise, seed 4; 2 GB, 14 s): the accuracy tests of the CLI, the logic and the
    browser share it. A namespace like ``own_scene``'s (no ``simulated``). Read-only."""
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
