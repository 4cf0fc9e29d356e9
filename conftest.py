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
  so two of them never run side by side on a small machine.
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


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "heavy: peaks at many GB of memory; never runs beside another heavy test "
                   "(a lock shared by the xdist workers)")


def pytest_collection_modifyitems(session, config, items):
    """Slow and browser tests first (stable otherwise): the longest work starts first."""
    def rank(item):
        if item.get_closest_marker("heavy"):
            return 0
        if item.get_closest_marker("slow") or item.get_closest_marker("browser"):
            return 1
        return 2

    items[:] = sorted(items, key=rank)


_SPENT = pytest.StashKey[float]()   # seconds of a test's phases so far


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
