"""The 2D simulation studies: table format, prior benefit, bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.studies import run_case, run_study, study_meshes

KEYS = {"case", "method", "lambda", "true_peak", "peak", "peak_error_pct", "true_centroid_mm",
        "centroid_mm", "centroid_error_pct", "seconds"}


def test_study_a_rows_and_prior_benefit(tmp_path):
    out = run_study("A", out_dir=tmp_path)
    rows = out["rows"]
    assert len(rows) == 12 and all(KEYS <= set(r) for r in rows)
    assert out["forward_mesh"][0] > 3 * out["reconstruction_mesh"][0]
    for r in rows:
        assert np.isfinite(r["peak"]) and r["true_peak"] == pytest.approx(1.2e-3)
    big = [r for r in rows if r["method"] == "HP" and "2.5 mm" not in r["case"]]
    assert all(abs(r["peak_error_pct"]) < 20 and abs(r["centroid_error_pct"]) < 5 for r in big)
    for case in {r["case"] for r in rows}:
        by = {r["method"]: r for r in rows if r["case"] == case}
        assert abs(by["HP"]["peak_error_pct"]) < abs(by["NP"]["peak_error_pct"])
    assert len(out["figures"]) == 4


def test_cli_custom_target_json(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fluoguide", "study", "A", "--target", "6,3.5",
                        "--json", "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert {row["method"] for row in doc["rows"]} == {"NP", "SP", "HP"}
    assert (tmp_path / "study.json").exists() and (tmp_path / "case_00.png").exists()


def test_bad_targets():
    meshes = study_meshes()
    with pytest.raises(FluoInputError, match="target"):
        run_case("x", diameter_mm=40, top_depth_mm=2.5, meshes=meshes)
    with pytest.raises(FluoInputError, match="study"):
        run_study("D")


@pytest.mark.slow
def test_3d_slab_study_custom_target(tmp_path):
    out = run_study("A", target=(6.0, 3.5), dim=3, out_dir=tmp_path)
    assert out["dim"] == 3 and 8000 < out["reconstruction_mesh"][0] < 12000
    by = {r["method"]: r for r in out["rows"]}
    assert "sphere" in by["HP"]["case"]
    assert abs(by["HP"]["peak_error_pct"]) < 25 and abs(by["HP"]["centroid_error_pct"]) < 10
    assert abs(by["HP"]["peak_error_pct"]) < abs(by["NP"]["peak_error_pct"])
    assert (tmp_path / "case_00.png").exists()


def test_sweeps_report_error_and_time():
    from FluoTomoLib.studies import run_sweep

    out = run_sweep("noise", target=(6.0, 3.5))
    hp = [r for r in out["rows"] if r["method"] == "HP"]
    assert [r["value"] for r in hp] == [0.0, 0.5, 1.0, 2.0, 5.0]
    assert all(r["case_seconds_including_jacobian"] > 0 for r in hp)
    assert abs(hp[0]["peak_error_pct"]) < 20  # noise-free: only the model/mesh error
    with pytest.raises(FluoInputError, match="sweep"):
        run_sweep("colour")
