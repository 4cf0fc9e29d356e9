"""Monte Carlo photon budgets on the run engine (fluoguide.runs, issue #22): the
independent runs of a set are tasks, split across Dask workers, resumable, and the
merged result does not depend on where the runs ran.

MCX seeds every work item from the run's seed; the engine fixes the launch shape
(Engine.run) so a seed draws the same photons on a 1-core worker as on the 2-core
serial loop.  What may differ is the float atomics' order in the fluence tally:
tolerance 1e-5 relative there, exact elsewhere (exit records, counts).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]


def _skip_without_engine():
    from FluoTomoLib.montecarlo.engine import engine_available

    if not engine_available("mcxcl"):
        pytest.skip("MCX-CL is not installed (the 'mc' extra, `make system-deps`)")


def _small_medium():
    from FluoTomoLib.montecarlo.halfspace import HalfSpace

    return HalfSpace(0.02, 1.0, 1.37, size_mm=(30, 30, 16), rho_mm=(2, 3, 5, 8),
                     fluence_depths_mm=(1.5, 4.5), fluence_rho_mm=(1, 3, 6))


def _same(a, b):
    """Two merged sets: identical photons (exits exact), fluence to the atomics' order."""
    for ra, rb in zip(a["R"], b["R"]):
        assert ra["n_exits"] == rb["n_exits"]
        assert ra["R_per_mm2"] == pytest.approx(rb["R_per_mm2"], rel=1e-12)
    for fa, fb in zip(a["fluence"], b["fluence"]):
        assert fa["phi_per_mm2"] == pytest.approx(fb["phi_per_mm2"], rel=1e-5)
    assert a["seeds"] == b["seeds"] and a["photons"] == b["photons"]


def test_halfspace_runs_are_tasks_serial_resume_and_two_workers(tmp_path):
    _skip_without_engine()
    from fluoguide.runs.cluster import dask_executor
    from fluoguide.runs.store import RunStore
    from FluoTomoLib.montecarlo.halfspace import simulate_halfspace

    med = _small_medium()
    serial = simulate_halfspace(med, 4000, runs=4, seed=11, engine="mcxcl",
                                store=RunStore(tmp_path / "a"))
    assert serial["executor"]["computed"] == 4 and serial["runs"] == 4
    # a killed set: two of the four runs' records lost -> resume computes only those
    recs = sorted((tmp_path / "a" / "tasks").glob("*.json"))
    for p in recs[:2]:
        p.unlink()
    resumed = simulate_halfspace(med, 4000, runs=4, seed=11, engine="mcxcl",
                                 store=RunStore(tmp_path / "a", resume=True))
    assert resumed["executor"]["computed"] == 2 and resumed["executor"]["reused"] == 2
    _same(serial, resumed)
    # the same budget split across two worker processes (1 OpenCL thread each)
    with dask_executor(workers=2, threads=1, dashboard=False) as ex:
        split = simulate_halfspace(med, 4000, runs=4, seed=11, engine="mcxcl", executor=ex,
                                   store=RunStore(tmp_path / "b"))
    assert split["executor"]["workers"] == 2
    _same(serial, split)
    # the merged standard errors come from the spread of the four runs
    assert all(r["se"] > 0 for r in split["R"])


def test_validate_mc_refuses_run_options_with_a_stored_set(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        str(ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")))
    r = subprocess.run([sys.executable, "-m", "fluoapp", "validate", "mc", "--mc-in",
                        str(tmp_path / "x.json"), "--workers", "2", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 2 and "--workers" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


def test_monte_carlo_acquisition_on_two_workers_and_resumed(tmp_path):
    """``fluo tomo simulate --engine mc``'s runs (each detector's and source's MCX run,
    per repeat) as tasks: a 2-worker cluster gives the serial data, a killed
    simulation resumes from its records, and what travels back is only the fluence
    on the fluorescing voxels."""
    _skip_without_engine()
    from fluoguide.runs.cluster import dask_executor
    from fluoguide.runs.store import RunStore
    from FluoTomoLib.montecarlo.acquisition import simulate_acquisition

    nx, ny, nz = 28, 20, 12
    lab = np.full((nz, ny, nx), 1, np.int16)
    lab[nz - 6:nz - 2, ny // 2 - 2:ny // 2 + 2, nx // 2 - 2:nx // 2 + 2] = 2
    top = nz - 0.5
    src = np.array([[nx / 2 - 5, ny / 2, top], [nx / 2 + 4, ny / 2, top]])
    det = np.array([[nx / 2 + 1, ny / 2, top], [nx / 2 - 1, ny / 2 + 2, top]])
    ox = {1: (0.01, 1.0, 1.37), 2: (0.03, 1.0, 1.37)}
    om = {1: (0.008, 0.9, 1.37), 2: (0.012, 0.9, 1.37)}
    kw = dict(photons=3000, seed=5, runs=2, engine="mcxcl")
    a = simulate_acquisition(lab, np.eye(4), ox, om, src, det, {2: 0.01},
                             store=RunStore(tmp_path / "a"), **kw)
    assert a["executor"]["computed"] == 8 and a["warnings"] == []
    assert np.all(a["emission"] > 0) and np.all(a["emission_se"] > 0)
    # the records hold the 64 fluorescing voxels, not the 6,720-voxel volume
    with np.load(next((tmp_path / "a" / "tasks").glob("*.npz"))) as z:
        assert max(v.size for v in z.values()) <= 64
    for p in sorted((tmp_path / "a" / "tasks").glob("*.json"))[:3]:
        p.unlink()
    b = simulate_acquisition(lab, np.eye(4), ox, om, src, det, {2: 0.01},
                             store=RunStore(tmp_path / "a", resume=True), **kw)
    assert b["executor"]["computed"] == 3 and b["executor"]["reused"] == 5
    with dask_executor(workers=2, threads=1, dashboard=False) as ex:
        c = simulate_acquisition(lab, np.eye(4), ox, om, src, det, {2: 0.01}, executor=ex, **kw)
    assert c["executor"]["workers"] == 2 and c["seeds"] == a["seeds"]
    for other in (b, c):
        np.testing.assert_allclose(other["emission"], a["emission"], rtol=1e-5)
        # the same exits, summed in the order the work items wrote them
        np.testing.assert_allclose(other["excitation"], a["excitation"], rtol=1e-12)
