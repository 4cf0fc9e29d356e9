"""Long work off the GUI thread (issue #33): a reconstruction as the desktop
panel runs it (``FluoTomoLogic.prepareReconstruction``'s job in a
``fluoguide.jobs.BackgroundJob``), watched from a Qt event loop (PySide6,
offscreen: Slicer's PythonQt is not here) that must keep turning, and cancelled
mid-way. Progress says what it is doing at every step."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from contextlib import contextmanager

import numpy as np
import pytest

from event_loop import Reports, watch
from fluoguide.jobs import BackgroundJob


@pytest.fixture
def reconstruction_job(own_scene):
    """The desktop panel's reconstruction job on the shared own scene (HP, fast)."""
    from fluoguide import mrml_io
    from FluoTomo import FluoTomoLogic

    logic = FluoTomoLogic(mrml_io.new_scene())
    lab = logic.loadLabelMap(own_scene.labels, name="CBCTLabels")
    return logic, logic.prepareReconstruction(lab, own_scene.optics, own_scene.acq, method="HP",
                                              accuracy="fast")


@contextmanager
def kernels_frozen():
    """The FEM kernels ready (``prepare_kernels``) and then unable to compile: a
    call site passing argument types that ``kernels._examples`` does not know
    raises TypeError instead of compiling silently inside a step."""
    from FluoTomoLib.fem import kernels

    kernels.prepare_kernels()
    dispatchers = [d for d, _ in kernels._examples()]
    for d in dispatchers:
        d.disable_compile()
    try:
        yield
    finally:
        for d in dispatchers:
            d.disable_compile(False)


@pytest.mark.slow      # a whole reconstruction (5-12 s) plus the shared scene's simulation
def test_the_event_loop_keeps_turning_during_a_reconstruction(qt_app, reconstruction_job):
    """... and the reconstruction reports at least every 2 s from start to end (the
    moved segmentation's solves were 12-37 s silent, each self-absorption pass's
    model 2-9 s: measured unpinned, as here and in Slicer)."""
    logic, work = reconstruction_job
    reports = Reports()
    with kernels_frozen():       # and no kernel is compiled inside a step
        job = BackgroundJob(reports.wrap(work), name="Reconstruction").start()
        ticks, states = watch(job)
        final = job.wait(60)
    assert final.status == "done", final.error
    gaps = [b - a for a, b in zip(ticks, ticks[1:])]
    # the loop ran all along: a 20 ms timer never waited a second (the GIL is
    # released in the numerical kernels); on the GUI thread it would not tick at all
    worst = int(np.argmax(gaps))
    assert len(ticks) > 20 and max(gaps) < 1.0, (len(ticks), max(gaps), [
        (round(t - ticks[worst], 2), m) for t, _, m in reports.items
        if ticks[worst] - 3 < t < ticks[worst + 1] + 1])       # what ran then
    print(f"{len(ticks)} ticks of the 20 ms timer in {final.seconds:.1f} s; longest wait "
          f"{1000 * max(gaps):.0f} ms, median {1000 * sorted(gaps)[len(gaps) // 2]:.0f} ms; "
          f"{final.updates} progress reports, the longest step without one "
          f"{max(st.step_seconds for st in states):.1f} s; longest gap between reports "
          f"{reports.longest_gap():.2f} s")
    # issue #33's rule, the whole way (1.1-1.4 s measured on a loaded 2-core machine)
    assert reports.longest_gap() <= 2.0, [(round(t - reports.started, 2), m)
                                          for t, _, m in reports.items]
    for step in ("segmentation moved by", "moved by +1 mm (4 of 4)", "self-absorption pass 1",
                 "excitation: factorising", "tissue-air nodes onto the surface"):
        assert any(step in m for m in reports.messages), (step, reports.messages)
    node = logic.storeReconstructionResult(final.result)          # back on this thread
    assert node.GetName() == "FluoTomoYieldHP"
    # progress said what it was doing at each step, in order
    messages = [s.message for s in states]
    for step in ("Jacobian", "reconstruction HP"):
        assert any(step in m for m in messages), messages
    assert final.updates >= 10
    fractions = [s.fraction for s in states]
    assert fractions == sorted(fractions)


def test_a_reconstruction_is_cancelled_mid_way(qt_app, reconstruction_job):
    _, work = reconstruction_job
    job = BackgroundJob(work, name="Reconstruction").start()
    asked = {}

    def cancel_in_the_jacobian(state):
        if "asked" not in asked and "Jacobian" in state.message:
            asked["asked"] = time.monotonic()
            job.cancel()                       # what the dialog's Cancel button does

    _, states = watch(job, on_state=cancel_in_the_jacobian)
    final = job.wait(60)
    assert "asked" in asked, [s.message for s in states]
    assert final.status == "cancelled" and final.result is None
    # it stopped at the next check, not after the whole reconstruction
    assert not any("reconstruction HP" in s.message for s in states[-1:]) or \
        final.fraction < 0.99
    assert time.monotonic() - asked["asked"] < 30


def test_a_failing_job_hands_its_error_to_the_gui_thread():
    from fluoguide.errors import FluoInputError

    def work(progress, cancel):
        progress(0.5, "halfway")
        raise FluoInputError("bad value", field="lambda", value=-1)

    state = BackgroundJob(work).start().wait(10)
    assert state.status == "failed" and isinstance(state.error, FluoInputError)
    assert state.message == "halfway" and state.fraction == 0.5
    with pytest.raises(RuntimeError, match="started already"):
        job = BackgroundJob(work).start()
        job.start()


# -- the first run's kernel compilation ---------------------------------------------------
def test_work_that_cannot_report_is_reported_from_beside_it():
    """``run_reporting``: a step without reports of its own (a numba compilation)
    is announced, then its seconds every ``every_s``; its result and errors come
    back; a cancel ends the wait at the next report."""
    from fluoguide.errors import FluoCancelled, FluoInputError
    from fluoguide.progress import CancelToken, run_reporting

    items = []

    def progress(fraction, message):
        items.append((time.monotonic(), fraction, message))

    t0 = time.monotonic()
    assert run_reporting(lambda: time.sleep(1.3) or 42, progress, 0.25, "compiling",
                         every_s=0.2) == 42
    times = [t0] + [t for t, _, _ in items] + [time.monotonic()]
    assert max(b - a for a, b in zip(times, times[1:])) < 0.2 + 0.5      # load margin
    assert items[0][2] == "compiling" and items[-1][2].startswith("compiling, ")
    assert {f for _, f, _ in items} == {0.25} and len(items) >= 4

    def fails():
        raise FluoInputError("bad", field="x")

    with pytest.raises(FluoInputError):
        run_reporting(fails, None, 0.0, "failing", every_s=0.1)

    token, cancelled_at = CancelToken(), {}

    def cancel_at_first(fraction, message):
        if not token.cancelled:
            cancelled_at["t"] = time.monotonic()
            token.cancel()

    with pytest.raises(FluoCancelled):
        run_reporting(lambda: time.sleep(5), cancel_at_first, 0.0, "long", token,
                      every_s=0.1)
    assert time.monotonic() - cancelled_at["t"] < 2.0


COMPILE_PROBE = """
import json, time
from FluoTomoLib.fem import kernels
t0 = time.monotonic()
items = []
kernels.prepare_kernels(lambda f, m: items.append((time.monotonic(), m)))
print(json.dumps({"start": t0, "end": time.monotonic(), "items": items,
                  "missing": len(kernels.missing())}))
"""


def _prepare_in_a_fresh_process(cache_dir):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    r = subprocess.run([sys.executable, "-c", COMPILE_PROBE], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    times = [out["start"]] + [t for t, _ in out["items"]] + [out["end"]]
    return out, max(b - a for a, b in zip(times, times[1:])), [m for _, m in out["items"]]


@pytest.mark.slow      # every FEM kernel compiled from nothing: 11-14 s on 2 cores
def test_the_first_run_s_kernel_compilation_reports_every_second(tmp_path):
    """A truly cold start (numba's cache in an empty folder): the compilation is
    announced and its seconds reported, never 2 s apart (every 1 s asked; it
    was one silent 11-14 s step inside the first simulation or reconstruction).
    The next process loads the compiled kernels from the cache."""
    cold, gap, messages = _prepare_in_a_fresh_process(tmp_path / "numba")
    seconds = cold["end"] - cold["start"]
    print(f"cold compile: {seconds:.1f} s, {len(messages)} reports, longest gap {gap:.2f} s")
    assert cold["missing"] == 0
    assert messages[0] == "compiling the FEM kernels (first run only)", messages
    assert seconds > 3.0            # it did compile: the gap below means something
    assert gap <= 2.0, (gap, messages)
    assert messages[-1].startswith("compiling the FEM kernels (first run only), ")
    warm, gap, messages = _prepare_in_a_fresh_process(tmp_path / "numba")
    assert warm["missing"] == 0 and messages[0] == "loading the compiled FEM kernels"
    assert warm["end"] - warm["start"] < seconds / 2
