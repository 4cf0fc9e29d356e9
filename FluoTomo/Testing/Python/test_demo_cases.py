"""The demo's tomography cases on the run engine (issue #22): one task per tube
depth and one for the oral cavity, plain arrays back, the same numbers serially
and on Dask workers, a killed demo resumed from its finished cases.

The tube cases here are the demo's pipeline at a coarser resolution (1.2 mm
simulation mesh, 6 sources: ~25 s and 2.3 GB each, against 105 s and 9.7 GB for a
quick-demo depth); the oral case is the quick demo's own (about 60 s, 2.1 GB).
"""

from __future__ import annotations

import json
from pathlib import Path

import forkserver
import numpy as np
import pytest
from small_cases import SMALL_TUBE

from fluoguide.errors import FluoInputError

ROOT = Path(__file__).resolve().parents[3]
SMALL = SMALL_TUBE          # the demo's tube at coarser settings (small_cases.py)


def _untimed(value):
    """A case's numbers without its timings (seconds differ run to run)."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items()
                if not (k.endswith("seconds") or k in ("timings", "seconds"))}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


def _arrays_equal(a, b):
    assert sorted(a) == sorted(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
@pytest.mark.heavy(gb=4.5)     # two tube cases side by side on Dask workers: 3.6 GB (SP fed back)
def test_tube_cases_serial_two_workers_and_resume(tmp_path):
    from fluoguide.runs import RunStore, read_table, run_tasks, stable_columns
    from fluoguide.runs.cluster import dask_executor
    from FluoTomoLib.pipelines.cases import case_of_record, case_tasks

    tasks = case_tasks((2.7, 6.7), seed=3, tube_options=SMALL)
    seen = []
    serial = run_tasks(tasks, store=RunStore(tmp_path / "serial"), threads=1,
                       progress=lambda f, m="": seen.append(m))
    assert serial["computed"] == 2 and not serial["failed"]
    # the serial loop hands the case its own progress: the steps inside a case show
    assert any("reconstruction" in m for m in seen), seen[:10]

    with dask_executor(workers=2, threads=1, dashboard=False) as ex:
        dist = run_tasks(tasks, store=RunStore(tmp_path / "dask"), executor=ex, threads=1)
    assert dist["workers"] == 2 and not dist["failed"]
    assert len({r["worker"] for r in dist["records"]}) == 2      # side by side

    ca, ra = read_table(tmp_path / "serial" / "table.csv")
    cb, rb = read_table(tmp_path / "dask" / "table.csv")
    cols = stable_columns(ca)
    assert cols == stable_columns(cb)
    # every number of the case (the nested "case" column holds timings: not compared)
    for x, y in zip(ra, rb):
        assert {c: x[c] for c in cols if c != "case"} == {c: y[c] for c in cols if c != "case"}
    sa, sb = RunStore(tmp_path / "serial"), RunStore(tmp_path / "dask")
    for x, y in zip(serial["records"], dist["records"]):
        _arrays_equal(sa.arrays(x), sb.arrays(y))
        assert _untimed(x["result"]["case"]) == _untimed(y["result"]["case"])

    # what the demo draws from: a Mesh again, the yields on it, the section images
    case = case_of_record(serial["records"][0], sa.arrays(serial["records"][0]))
    assert case["coarse"].n_nodes == case["mesh_nodes"]["reconstruction"]
    assert case["results"]["HP"]["yield"].shape == (case["coarse"].n_nodes,)
    assert set(case["profiles"]) == {"truth", "NP", "SP", "HP"}
    assert case["sections"]["truth"].shape == case["sections"]["HP"].shape
    assert np.nanmax(case["sections"]["truth"]) > 0
    assert case["results"]["HP"]["peak_error_pct"] == serial["rows"][0]["HP_peak_error_pct"]

    # a killed demo: one case's record lost -> resume computes that one only
    lost = serial["records"][1]
    (tmp_path / "serial" / "tasks" / f"{lost['task']}.json").unlink()
    again = run_tasks(tasks, store=RunStore(tmp_path / "serial", resume=True), threads=1)
    assert (again["reused"], again["computed"]) == (1, 1)
    _arrays_equal(sa.arrays(again["records"][1]), sb.arrays(dist["records"][1]))


def test_case_options_are_checked():
    from FluoTomoLib.pipelines.cases import case_tasks, tube_case

    with pytest.raises(FluoInputError, match="unknown case option"):
        case_tasks((4.7,), tube_options={"fine_m": 1.0})
    with pytest.raises(FluoInputError, match="unknown case option"):
        tube_case({"depth_mm": 4.7, "seed": 0, "sources": 3})


def _fluo(*args):
    """``fluo ARGS`` forked from the tests' fork server (conftest.py; one library thread)."""
    return forkserver.fluo(*args, cwd=ROOT, timeout=900)


@pytest.mark.slow      # three oral cases, two computed (one on a Dask worker): about 2.5 min
@pytest.mark.heavy(gb=3)     # one oral case at a time: grew 2.4 GB (SP fed back)
def test_demo_cli_oral_case_on_workers_and_resumed(tmp_path):
    """``fluo demo --workers``: the oral-cavity case on a local Dask cluster gives
    the serial demo's numbers; ``--resume`` reuses the finished case."""
    out_s, out_w = tmp_path / "serial", tmp_path / "workers"
    r = _fluo("demo", "--quick", "--only", "oral_tomography", "--out", str(out_s), "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    r = _fluo("demo", "--quick", "--only", "oral_tomography", "--out", str(out_w), "--json",
              "--workers", "1", "--no-dashboard")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "dask: 1 workers" in r.stderr
    ms = json.loads((out_s / "metrics.json").read_text())
    mw = json.loads((out_w / "metrics.json").read_text())
    assert mw["runs"]["oral_tomography"]["executor"].startswith("dask")
    assert ms["runs"]["oral_tomography"]["executor"] == "serial"
    for k, v in ms["oral_tomography"].items():
        if k != "stage times [s]":
            assert mw["oral_tomography"][k] == v, k
    assert (out_w / "oral_sections.png").stat().st_size > 10_000

    r = _fluo("demo", "--quick", "--only", "oral_tomography", "--out", str(out_w), "--json",
              "--resume")
    assert r.returncode == 0, r.stderr[-2000:]
    again = json.loads((out_w / "metrics.json").read_text())
    assert again["runs"]["oral_tomography"]["reused"] == 1
    assert again["runs"]["oral_tomography"]["computed"] == 0
    assert again["oral_tomography"]["HP tongue yield error %"] == \
        mw["oral_tomography"]["HP tongue yield error %"]


def test_demo_cli_run_options_refused_before_work(tmp_path):
    out = tmp_path / "o"
    for args, field in ((["--workers", "0"], "--workers"), (["--threads", "x"], "--threads"),
                        (["--scheduler", "nowhere"], "--scheduler")):
        r = _fluo("demo", "--quick", "--only", "oral_tomography", "--out", str(out), *args)
        assert r.returncode == 2, (args, r.stderr[-500:])
        assert field in r.stderr and "Traceback" not in r.stderr
        assert not out.exists()
