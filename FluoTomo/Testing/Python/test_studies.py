"""The 2D simulation studies: table format, prior benefit, bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.studies.run import run_case, run_study
from FluoTomoLib.studies.thesis import study_meshes

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
    # four panels two a row, each ~500 px wide: readable (they were ~140 x 70 px)
    from matplotlib.image import imread

    height, width = imread(out["figures"][0]).shape[:2]
    assert width >= 1000 and height >= 550
    # thesis: NP underestimates the small target (-68 %) and overestimates the 15 mm
    # one (+108 %); SP and HP within 10 % for targets >= 5 mm
    np_err = {r["case"]: r["peak_error_pct"] for r in rows if r["method"] == "NP"}
    assert np_err["A: 2.5 mm disc"] < -30 and np_err["A: 15 mm disc"] > 50
    big = [r for r in rows if r["method"] in ("SP", "HP") and "2.5 mm" not in r["case"]]
    assert all(abs(r["peak_error_pct"]) < 10 for r in big)


def test_cli_custom_target_json(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fluoapp", "study", "A", "--target", "6,3.5",
                        "--json", "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert {row["method"] for row in doc["rows"]} == {"NP", "SP", "HP"}
    # every reconstruction's diagnostics and warnings reach the JSON; NP's
    # over-regularised stall is among them (docs/reconstruction.md)
    assert all("effective_parameters" in row["diagnostics"] for row in doc["rows"])
    np_row = next(row for row in doc["rows"] if row["method"] == "NP")
    assert np_row["warnings"] and all(f"NP lambda 10: {w}" in " | ".join(doc["warnings"])
                                      for w in np_row["warnings"])
    assert doc["library_threads"] == 1
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
    from FluoTomoLib.studies.run import run_sweep

    out = run_sweep("noise", target=(6.0, 3.5))
    hp = [r for r in out["rows"] if r["method"] == "HP"]
    assert [r["value"] for r in hp] == [0.0, 0.5, 1.0, 2.0, 5.0]
    assert all(r["seconds"] > 0 and r["jacobian_seconds"] > 0 for r in hp)
    assert out["shared_inputs"] == 2      # one forward Jacobian, one mapping, for 15 tasks
    assert abs(hp[0]["peak_error_pct"]) < 20  # noise-free: only the model/mesh error
    with pytest.raises(FluoInputError, match="sweep"):
        run_sweep("colour")


def _by(rows, method):
    return [r for r in rows if r["method"] == method]


def test_study_b_matches_the_thesis_bounds():
    """Thesis: HP < 1 %, SP < 9 % at every depth 2.5-6.5 mm; NP falls with depth.
    Here HP's forward-mesh basis leaves +0.8 to +1.1 % (its 0/1 node regions on the
    0.5 mm forward mesh against the round disc, whose truth holds its true area)."""
    rows = run_study("B")["rows"]
    assert all(abs(r["peak_error_pct"]) < 2.0 for r in _by(rows, "HP"))
    assert all(abs(r["peak_error_pct"]) < 9.0 for r in _by(rows, "SP"))
    assert all(abs(r["centroid_error_pct"]) < 7.5 for r in _by(rows, "SP") + _by(rows, "HP"))
    np_err = [r["peak_error_pct"] for r in _by(rows, "NP")]
    assert np_err[-1] < -40 and np_err[-1] < np_err[0]


def test_study_c_soft_prior_recovers_the_annulus_as_lambda_falls():
    rows = run_study("C")["rows"]
    sp = sorted(_by(rows, "SP"), key=lambda r: -r["lambda"])      # 1e3, 10, 0.1, 1e-3
    err = [abs(r["peak_error_pct"]) for r in sp]
    assert err == sorted(err, reverse=True) and err[0] - err[-1] > 30
    hp = _by(rows, "HP")[0]["peak_error_pct"]
    assert -70 < hp < -50     # thesis -61 %: the filled-disc prior averages the annulus


def test_hp_basis_and_scheme_options():
    meshes = study_meshes()
    kw = dict(diameter_mm=6, top_depth_mm=3.5, methods=("HP",), meshes=meshes)
    fwd, _ = run_case("x", **kw)
    rec, _ = run_case("x", hp_basis="reconstruction", **kw)
    # the coarse basis interpolated to the forward mesh misses the disc by more
    # (2026-11-29, the truth's shares: +0.9 % against -1.7 %)
    assert abs(fwd[0]["peak_error_pct"]) < 1.5 < abs(rec[0]["peak_error_pct"])
    with pytest.raises(FluoInputError, match="scheme"):
        run_case("x", scheme="matlab", **kw)
    with pytest.raises(FluoInputError, match="HP basis"):
        run_study("B", hp_basis="fine")
