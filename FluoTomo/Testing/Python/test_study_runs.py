"""Studies on the run engine: grids, shared Jacobians, failed tasks, resuming,
and the same table serially and on a 2-worker Dask cluster."""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.runs.store import read_table, stable_columns
from FluoTomoLib.studies.spec import spec_from_mapping, study_tasks, sweep_spec
from FluoTomoLib.studies.run import run_study, run_sweep


def _shared_names(tasks):
    return {s.name for t in tasks for s in t.shared_closure()}


def test_grid_expands_in_order_and_shares_one_jacobian_per_model():
    spec = spec_from_mapping({"targets": [[6, 3.5]], "methods": ["SP", "HP"],
                              "lambdas": [0.1, 1, 10], "seeds": [0, 1]})
    tasks = study_tasks(spec)
    assert len(tasks) == 1 * 2 * 2 * 3                     # targets x seeds x methods x lambdas
    assert [t.params["lambda"] for t in tasks[:3]] == [0.1, 1.0, 10.0]   # lambda fastest
    assert len({t.id for t in tasks}) == len(tasks)
    # twelve reconstructions, one model: one forward Jacobian and its mapping
    assert len(_shared_names(tasks)) == 2
    # study C keeps its per-method lambdas; A has 4 targets x 3 methods
    assert len(study_tasks(spec_from_mapping({"study": "C"}))) == 6
    assert len(study_tasks(spec_from_mapping({"study": "A"}))) == 12


def test_mesh_sweep_pairs_forward_and_reconstruction_sizes_and_simulates_finer_data():
    spec = sweep_spec("mesh")
    tasks = study_tasks(spec)
    pairs = {(t.params["forward_mm"], t.params["recon_mm"]) for t in tasks}
    assert all(r >= f for f, r in pairs) and {f for f, _ in pairs} == {0.5, 0.75, 1.0}
    assert {t.params["data_mm"] for t in tasks} == {0.25}  # finer than every forward mesh
    assert any("0.25 mm" in w for w in spec.warnings)
    # models: data 0.25 + three forward meshes + one mapping per pair
    assert len(_shared_names(tasks)) == 1 + 3 + len(pairs)


def test_roi_sweep_cuts_the_model_not_the_data():
    tasks = study_tasks(sweep_spec("roi", values=[15, 30]))
    names = {k: {t.inputs[k].name for t in tasks} for k in ("data", "forward")}
    assert names["data"] == {"jacobian 2D 0.5 mm, depth 30 mm"}
    assert names["forward"] == {"jacobian 2D 0.5 mm, depth 15 mm", "jacobian 2D 0.5 mm, depth 30 mm"}


@pytest.mark.parametrize("doc, field", [
    ({"study": "A", "lambdas": [float("nan")]}, "lambdas"),
    ({"study": "A", "lambdas": [-1]}, "lambdas"),
    ({"study": "A", "noise_pct": [-0.5]}, "noise_pct"),
    ({"study": "A", "seeds": [1.5]}, "seeds"),
    ({"study": "A", "recon_mm": [0.01]}, "recon_mm"),
    ({"study": "A", "forward_mm": [0.06]}, "forward_mm"),     # ~440k nodes
    ({"study": "A", "roi_depth_mm": [5]}, "target"),
    ({"study": "A", "methods": ["XP"]}, "methods"),
    ({"study": "A", "colour": 1}, "colour"),
    ({"study": "E"}, "study"),
    ({"sweep": "lambda", "values": ["x"]}, "values"),
    ({"targets": [[6]]}, "targets[0]"),
    ({"targets": [[40, 2]]}, "target"),
    ({"study": "A", "dim": 4}, "dim"),
])
def test_bad_grids_are_refused_naming_the_field(doc, field):
    with pytest.raises(FluoInputError) as exc:
        study_tasks(spec_from_mapping(doc, file="s.yaml"))
    assert field in str(exc.value) and "s.yaml" in str(exc.value)


def test_a_task_that_raises_is_a_row_of_the_table(tmp_path):
    # 300 % noise gives negative amplitudes: the log-data scheme refuses them, in
    # those tasks only; the others finish and every row is in the table
    out = run_sweep("noise", values=[1.0, 300.0], out_dir=tmp_path)
    assert out["tasks"] == 6 and out["failures"] == 3 and len(out["rows"]) == 6
    bad = [r for r in out["rows"] if r["noise_pct"] == 300.0]
    assert all(r["status"] == "failed" and "log data" in r["error"] for r in bad)
    assert all(r["status"] == "ok" and np.isfinite(r["peak"]) for r in out["rows"]
               if r["noise_pct"] == 1.0)
    cols, rows = read_table(tmp_path / "table.csv")
    assert [r["status"] for r in rows] == ["ok"] * 3 + ["failed"] * 3
    assert {f["task"] for f in out["failed"]} == {r["task"] for r in bad}
    rec = json.loads((tmp_path / "tasks" / f"{bad[0]['task']}.json").read_text())
    assert "Traceback" in rec["traceback"] and rec["status"] == "failed"
    assert (tmp_path / "error_vs_time.png").stat().st_size > 10_000
    assert any("3 of 6 tasks failed" in w for w in out["warnings"])

    # resuming computes the failed tasks again (they may have been the machine's
    # fault) and reuses the three finished ones
    again = run_sweep("noise", values=[1.0, 300.0], out_dir=tmp_path, resume=True)
    assert again["reused"] == 3 and again["computed"] == 3 and again["failures"] == 3
    _, rows2 = read_table(tmp_path / "table.csv")
    keep = stable_columns(cols)
    assert [[r[c] for c in keep] for r in rows2] == [[r[c] for c in keep] for r in rows]


def test_the_roi_sweep_at_full_depth_is_the_uncut_model():
    """The roi point at the full 30 mm depth is the ordinary study (same data, same
    model): its numbers must equal a plain custom-target run's exactly."""
    sweep = run_sweep("roi", values=[20.0, 30.0])
    plain = run_study("A", target=(6.0, 3.5))
    full = [r for r in sweep["rows"] if r["roi_depth_mm"] == 30.0]
    assert [r["peak"] for r in full] == [r["peak"] for r in plain["rows"]]
    cut = [r for r in sweep["rows"] if r["roi_depth_mm"] == 20.0]
    assert all(r["status"] == "ok" and r["forward_nodes"] < full[0]["forward_nodes"] for r in cut)


@pytest.mark.slow
def test_study_and_sweep_give_the_same_table_serially_and_on_two_workers(tmp_path):
    from fluoguide.runs.cluster import dask_executor

    serial_c = run_study("C", out_dir=tmp_path / "serial-C")
    serial_l = run_sweep("lambda", values=[0.1, 10.0], out_dir=tmp_path / "serial-lambda")
    with dask_executor(workers=2, threads=1, dashboard=False) as ex:
        assert ex.workers == 2
        dask_c = run_study("C", out_dir=tmp_path / "dask-C", executor=ex)
        dask_l = run_sweep("lambda", values=[0.1, 10.0], out_dir=tmp_path / "dask-lambda",
                           executor=ex)
    for a, b in ((serial_c, dask_c), (serial_l, dask_l)):
        assert a["tasks"] == b["tasks"] and b["failures"] == 0 and b["workers"] == 2
        assert a["shared_inputs"] == b["shared_inputs"] == 2   # one Jacobian, one mapping
    for name in ("C", "lambda"):
        ca, ra = read_table(tmp_path / f"serial-{name}" / "table.csv")
        cb, rb = read_table(tmp_path / f"dask-{name}" / "table.csv")
        assert ca == cb
        keep = stable_columns(ca)
        assert [[r[c] for c in keep] for r in ra] == [[r[c] for c in keep] for r in rb]
        # the tasks ran on both workers (host:pid), none in this process
        assert len({r["worker"] for r in rb}) == 2


def test_named_sweeps_use_their_default_values():
    from FluoTomoLib.studies.thesis import SWEEPS

    for kind, key in (("lambda", "lambda"), ("noise", "noise_pct"), ("roi", "roi_depth_mm"),
                      ("mesh", "recon_mm")):
        tasks = study_tasks(sweep_spec(kind))
        assert sorted({t.params[key] for t in tasks}) == sorted(SWEEPS[kind]), kind
        assert {t.params["value"] for t in tasks} == set(SWEEPS[kind])
    assert {t.params["noise_pct"] for t in study_tasks(sweep_spec("noise", values=[2]))} == {2.0}
