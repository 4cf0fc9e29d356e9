"""The Monte Carlo reference (FluoTomoLib/montecarlo): engine, units, merging of
independent runs, stored sets against the FEM, reciprocity, the CLI.

The engine is MCX-CL on the CPU (pocl); `make test` installs it (the 'mc' extra and
`make system-deps`).  Photon counts in fast tests are a few thousand (seconds);
anything statistical with real budgets is marked slow.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import forkserver
import numpy as np
import pytest

from fluoguide.errors import FluoInputError

from FluoTomoLib.montecarlo import reference
from FluoTomoLib.montecarlo.halfspace import HalfSpace, merge_halfspace
from FluoTomoLib.optics import fresnel_moments, robin_A

ROOT = Path(__file__).resolve().parents[3]


def _engine():
    from FluoTomoLib.montecarlo.engine import load_engine

    return load_engine("mcxcl")


# ---------------------------------------------------------------- optics: the boundary constant

def test_fresnel_boundary_constant_against_direct_quadrature():
    from scipy.integrate import quad

    def R(mu, n):   # Fresnel, written here from the textbook formula (inside -> air)
        s_t = n * np.sqrt(1 - mu * mu)
        if s_t >= 1:
            return 1.0
        c_t = np.sqrt(1 - s_t * s_t)
        rs = (n * mu - c_t) / (n * mu + c_t)
        rp = (n * c_t - mu) / (n * c_t + mu)
        return 0.5 * (rs * rs + rp * rp)

    for n in (1.33, 1.37, 1.4, 1.5):
        mu_c = np.sqrt(1 - 1 / n**2)
        r_phi = 2 * (quad(lambda m: R(m, n) * m, 0, mu_c)[0] + quad(lambda m: R(m, n) * m, mu_c, 1)[0])
        r_j = 3 * (quad(lambda m: R(m, n) * m * m, 0, mu_c)[0] +
                   quad(lambda m: R(m, n) * m * m, mu_c, 1)[0])
        assert fresnel_moments(n) == pytest.approx((r_phi, r_j), abs=1e-7)
        assert robin_A(n, "fresnel") == pytest.approx((1 + r_j) / (1 - r_phi), rel=1e-7)
    assert robin_A(1.0, "fresnel") == 1.0
    assert robin_A(1.37, "fresnel") == pytest.approx(2.7586, abs=1e-4)
    assert float(robin_A(1.37, "empirical")) == pytest.approx(3.0499, abs=1e-4)
    with pytest.raises(FluoInputError, match="boundary"):
        robin_A(1.37, "exact")


# ---------------------------------------------------------------- engine and units

def test_package_imports_and_fails_in_one_line_without_the_engine(tmp_path):
    code = ("import sys; sys.modules['pmcxcl'] = None; sys.modules['pmcx'] = None\n"
            "from FluoTomoLib.montecarlo import HalfSpace, MonteCarloUnavailable, load_engine\n"
            "HalfSpace(0.01, 1.0, 1.37)\n"
            "try:\n    load_engine()\nexcept MonteCarloUnavailable as e:\n"
            "    print('ERR', e); sys.exit(3)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 3, r.stderr
    line = r.stdout.strip()
    assert line.startswith("ERR the Monte Carlo engine is not installed") and "\n" not in line
    assert "pocl-opencl-icd" in line
    cli = ("import sys; sys.modules['pmcxcl'] = None; sys.modules['pmcx'] = None\n"
           "from fluoapp.cli import main; sys.exit(main(sys.argv[1:]))")
    r = subprocess.run([sys.executable, "-c", cli, "validate", "mc", "--quick", "--out",
                        str(tmp_path / "out"), "--json"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1
    assert r.stdout == ""
    assert r.stderr.strip().count("\n") == 0 and "fluo: error:" in r.stderr
    assert "Traceback" not in r.stderr


def test_energy_output_converts_to_mcx_fluence_and_sums_to_the_absorbed_fraction():
    eng = _engine()
    base = dict(nphoton=800, vol=np.ones((12, 12, 8), np.uint8),
                prop=np.array([[0, 0, 1, 1], [0.05, 2.0, 0.0, 1.37]]), tstart=0, tend=5e-9,
                tstep=5e-9, srcpos=[6, 6, 0], srcdir=[0, 0, 1], issrcfrom0=1, seed=3,
                isreflect=1, autopilot=1, unitinmm=0.5)
    e = eng.run(dict(base, outputtype="energy"))
    f = eng.run(dict(base, outputtype="fluence"))
    E, F = e["flux"][..., 0], f["flux"][..., 0]
    stat = e["stat"]
    # energy per voxel per launched photon: sums to the absorbed fraction
    assert E.sum() == pytest.approx(stat["energyabs"] / stat["energytot"], rel=1e-5)
    # our fluence E / (mua V) is MCX's own normalised fluence (same seed: same photons)
    phi = E / (0.05 * 0.5 ** 3)
    m = F > 0
    np.testing.assert_allclose(F[m], phi[m], rtol=1e-5)


def test_halfspace_run_tallies_and_balances_energy(tmp_path):
    from FluoTomoLib.montecarlo.halfspace import run_halfspace

    m = HalfSpace(0.05, 1.0, 1.37, g=0.0, size_mm=(30, 30, 15), rho_mm=(2.0, 5.0, 10.0),
                  fluence_depths_mm=(2.5,), fluence_rho_mm=(1.0, 3.0))
    r = run_halfspace(m, 2000, seed=5, engine=_engine())
    bal = r["absorbed"] + r["exit_top"] + r["exit_other"]
    assert bal == pytest.approx(1.0, abs=2e-4)
    assert r["absorbed_voxels"] == pytest.approx(r["absorbed"], rel=1e-4)
    assert np.all(r["W"] > 0) and np.all(np.diff(r["W"] / (2 * np.pi * m.rho_mm * m.width_mm)) < 0)
    assert r["records"] < r["records_max"]
    json.dumps({k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()})


def _fake_run(m, seed, scale, photons=1000):
    k = len(m.rho_mm)
    return {"photons": photons, "seed": seed, "seconds": 1.0, "engine": "mcxcl",
            "engine_version": "x", "device": "d", "W": np.full(k, 10.0 * scale),
            "W2": np.full(k, 1.0), "count": np.full(k, 10), "exit_top": 0.6 * scale,
            "exit_other": 0.0, "absorbed": 1 - 0.6 * scale, "absorbed_voxels": 0.4,
            "records": 10, "records_max": photons,
            "fluence": np.full((len(m.layers), len(m.fluence_rho_mm)), scale)}


def test_merging_is_composable_and_errors_come_from_the_spread():
    m = HalfSpace(0.01, 1.0, 1.37)
    runs = [_fake_run(m, s, sc) for s, sc in ((1, 1.0), (2, 1.1), (3, 0.9), (4, 1.0))]
    all4 = merge_halfspace(m, runs)
    # the pooled mean does not depend on how the runs are grouped
    a, b = merge_halfspace(m, runs[:2]), merge_halfspace(m, runs[2:])
    R = [r["R_per_mm2"] for r in all4["R"]]
    R2 = [0.5 * (x["R_per_mm2"] + y["R_per_mm2"]) for x, y in zip(a["R"], b["R"])]
    np.testing.assert_allclose(R, R2, rtol=1e-12)
    # batch-means standard error of the four scales (1, 1.1, 0.9, 1): std/sqrt(4)
    rel = all4["R"][0]["se"] / all4["R"][0]["R_per_mm2"]
    assert rel == pytest.approx(np.std([1, 1.1, 0.9, 1], ddof=1) / 2, rel=1e-9)
    assert all4["photons"] == 4000 and all4["seeds"] == [1, 2, 3, 4]
    with pytest.raises(FluoInputError, match="not independent"):
        merge_halfspace(m, [runs[0], runs[0]])


# ---------------------------------------------------------------- stored sets

@pytest.mark.parametrize("name", sorted(reference.HALFSPACE_SETS))
def test_stored_halfspace_sets_carry_their_provenance(name):
    data = reference.read_set(reference.set_path(name))
    mua, musp, n = reference.HALFSPACE_SETS[name]
    assert data["medium"]["mua_per_mm"] == mua and data["medium"]["n_inside"] == n
    assert data["command"].startswith("fluo validate mc ")
    for key in ("photons", "seeds", "voxel_mm", "volume_mm", "engine_version", "device"):
        assert data[key]
    assert len(set(data["seeds"])) == data["runs"] >= 2
    e = data["energy"]
    assert abs(e["lost"]) < 1e-4


def test_our_mc_agrees_with_the_independent_run():
    ours = reference.read_set(reference.set_path("halfspace_n137"))
    ind = reference.read_independent_reflectance()
    z = []
    for r in ours["R"]:
        j = np.flatnonzero(np.isclose(ind["rho_mm"], r["rho_mm"]))[0]
        z.append((r["R_per_mm2"] - ind["R"][j]) / np.hypot(r["se_cp"], ind["se_cp"][j]))
    z = np.array(z)
    # 30 annuli: |z| <= 3.5 fails by chance with p ~ 1 %; chi2/dof <= 2 with p < 0.1 %
    assert np.max(np.abs(z)) <= 3.5
    assert np.mean(z ** 2) <= 2.0


@pytest.fixture(scope="module")
def fem_n137():
    from FluoTomoLib import optics
    from FluoTomoLib.montecarlo.compare import validate_halfspace

    data = reference.read_set(reference.set_path("halfspace_n137"))
    med = reference.medium_of_set(data)
    return validate_halfspace(med, reference.merged_of_set(data), level="test",
                              boundaries=(optics.DEFAULT_BOUNDARY,))


def test_fem_matches_stored_mc_from_5_mm_at_n137(fem_n137):
    """FEM (default A) against our stored MC: within 3 % + 2 MC errors + the FEM's
    1 % discretisation allowance of the test mesh from 5 mm outwards; the near-source
    excess (diffusion over-predicts at 2 mm) is positive and stated."""
    rows = {r["rho_mm"]: r for r in fem_n137["rows"]}
    for rho, r in rows.items():
        if 5 <= rho <= 25:
            assert abs(r["fem_vs_mc_pct"]) <= 4.0 + 2 * r["mc_rel_se_pct"], (rho, r)
    assert rows[2.0]["fem_vs_mc_pct"] > 3.0
    assert fem_n137["agree_from_mm"][fem_n137["boundary"]] <= 5.0


def test_stored_fluorescence_set_against_the_fem():
    """Emission (reciprocity MC) and excitation against the FEM on the same label map.

    Measured with the 0.5 mm FEM mesh (docs/validation.md): emission within 5 % for
    both boundary constants, the spread between mirror-image pairs (+-3 %) being the
    diffusion model's near-source error of the optode above the inclusion (its top 3
    mm deep); excitation 10 mm apart within 5.2 %.  Tolerance 8 % + 2 MC errors
    (the test mesh is 0.75 mm).  Pairs 20 mm apart are not tested: fewer than 10
    photons per run reach a 2 mm disc there."""
    from FluoTomoLib.montecarlo.compare import fem_acquisition

    data = reference.read_set(reference.set_path(reference.FLUORESCENCE_SET))
    case = reference.fluorescence_case()
    assert data["command"].startswith("fluo validate mc-fluorescence")
    assert np.allclose(data["sources_ras"], case["sources_ras"])
    fem = fem_acquisition(case, detector_radius_mm=data["detector_radius_mm"], fine_mm=0.75)
    em, em_se = np.array(data["emission"]), np.array(data["emission_se"])
    rel = np.abs(fem["emission"] / em - 1)
    assert np.all(rel <= 0.08 + 2 * em_se / em), rel
    ex, ex_se = np.array(data["excitation"]), np.array(data["excitation_se"])
    src, det = np.array(case["sources_ras"]), np.array(case["detectors_ras"])
    dist = np.linalg.norm(src[:, None] - det[None], axis=2)
    pair = (dist >= 5) & (dist <= 15)
    rel_x = np.abs(fem["excitation"][pair] / ex[pair] - 1)
    assert np.all(rel_x <= 0.08 + 2 * ex_se[pair] / ex[pair]), rel_x


# ---------------------------------------------------------------- CLI

def _fluo(*args):
    """``fluo ARGS`` forked from the tests' fork server (conftest.py; one library thread)."""
    return forkserver.fluo(*args, cwd=ROOT)


def test_cli_validate_mc_on_a_stored_set(tmp_path):
    r = _fluo("validate", "mc", "--mc-in", str(reference.set_path("halfspace_n100")),
              "--boundary", "empirical", "--mesh-level", "test", "--out", str(tmp_path), "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for key in ("photons", "device", "seconds", "warnings", "energy", "agree_from_mm", "rows"):
        assert key in out
    row = out["rows"][5]
    for key in ("rho_mm", "mc", "mc_se", "fem", "fem_vs_mc_pct"):
        assert key in row
    assert out["agree_from_mm"]["empirical"] <= 6.0  # n 1.0: +3.5 % at 5 mm (issue 19)
    assert (tmp_path / "validate_mc.png").stat().st_size > 10_000
    assert (tmp_path / "validate_mc_reflectance.csv").read_text().startswith("rho_mm,")


def test_cli_validate_mc_refuses_bad_input_in_one_line(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{\"kind\": 3}")
    r = _fluo("validate", "mc", "--mc-in", str(bad), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "kind" in r.stderr
    r = _fluo("validate", "mc", "--mc-in", str(reference.set_path("halfspace_n100")), "--n",
              "1.37", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "--n" in r.stderr and "Traceback" not in r.stderr
    r = _fluo("validate", "mc", "--mua", "-1", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "--mua" in r.stderr


# ---------------------------------------------------------------- slow: real photon budgets

@pytest.mark.slow
def test_regenerated_small_set_agrees_with_the_stored_one():
    """A fresh, smaller run (other seeds) of the stored n 1.37 medium agrees with the
    stored set within the two sets' errors (z-scores per annulus, 5-20 mm)."""
    from FluoTomoLib.montecarlo.halfspace import simulate_halfspace

    data = reference.read_set(reference.set_path("halfspace_n137"))
    med = reference.medium_of_set(data)
    new = simulate_halfspace(med, 15_000, runs=2, seed=90001, engine=_engine())
    z = []
    for a, b in zip(new["R"], data["R"]):
        if 5 <= a["rho_mm"] <= 20:
            z.append((a["R_per_mm2"] - b["R_per_mm2"]) / np.hypot(a["se_cp"], b["se_cp"]))
    z = np.array(z)
    assert np.max(np.abs(z)) <= 3.5 and np.mean(z ** 2) <= 2.5, z
    assert new["energy"]["balance"] == pytest.approx(1.0, abs=2e-4)


@pytest.mark.slow
def test_reciprocity_isotropic_source_against_detector_launch():
    """Exitance at a detector from an isotropic point source (forward MC, exit
    records over a 2 mm disc) equals C/(4 pi) times the fluence at the source of an
    MC run launched from the detector with the Fresnel-weighted cosine distribution
    (acquisition.py): the formula the emission data rest on."""
    from FluoTomoLib.montecarlo.acquisition import (
        LabelMapGeometry,
        _cfg,
        _fluence,
        detector_acceptance,
        detector_launch_icdf,
    )

    eng = _engine()
    n, mua, musp, g = 1.37, 0.05, 1.0, 0.9
    geo = LabelMapGeometry(np.ones((15, 30, 30), np.uint8), np.eye(4))
    rows = [(mua, musp, n)]
    det = np.array([15.0, 15.0, 0.0])
    r0 = np.array([19.5, 15.5, 3.5])          # a voxel centre 4.5 mm off, 3.5 mm deep
    N = 60_000
    fwd = _cfg(geo, rows, g, N, 11, r0, [0, 0, 1])
    fwd["srcdir"] = [0.0, 0.0, 1.0, float("nan")]       # MCX: isotropic point source
    res = eng.run(fwd)
    p, w = res["detp"]["p"], np.exp(-mua * res["detp"]["ppath"][:, 0])
    near = (np.hypot(p[:, 0] - det[0], p[:, 1] - det[1]) <= 2.0) & (p[:, 2] < 1e-3)
    J_fwd = w[near].sum() / (N * np.pi * 4.0)
    rel_fwd = np.sqrt(np.sum(w[near] ** 2)) / w[near].sum()
    adj = eng.run(_cfg(geo, rows, g, N, 12, det + [0, 0, 1e-3], [0, 0, 1],
                       icdf=detector_launch_icdf(n)))
    phi = _fluence(adj, geo, np.array([0.0, mua]))
    # the disc average of J(d) against the voxel at r0 (both about 1 % curvature bias)
    J_adj = detector_acceptance(n) / (4 * np.pi) * phi[19, 15, 3]
    assert J_adj == pytest.approx(J_fwd, rel=0.06 + 3 * rel_fwd)


@pytest.mark.slow
def test_mc_acquisition_small_case_against_the_fem():
    """simulate_acquisition on a small label map (one source, two detectors, a
    fluorescent cube) against the FEM on the same map."""
    from FluoTomoLib.montecarlo.acquisition import simulate_acquisition
    from FluoTomoLib.montecarlo.compare import fem_acquisition

    nx, ny, nz = 40, 24, 16
    M = np.eye(4)
    M[:3, 3] = [-(nx - 1) / 2, -(ny - 1) / 2, -(nz - 0.5)]
    labels = np.ones((nz, ny, nx), np.uint8)
    labels[nz - 8:nz - 4, ny // 2 - 2:ny // 2 + 2, nx // 2 - 2:nx // 2 + 2] = 2  # 4 mm cube, 4-8 mm deep
    case = {"labels_kji": labels, "ijk_to_ras": M,
            "optics_x": {1: (0.03, 1.0, 1.37), 2: (0.04, 1.0, 1.37)},
            "optics_m": {1: (0.02, 0.9, 1.37), 2: (0.02, 0.9, 1.37)},
            "yield_per_label": {2: 0.01},
            "sources_ras": np.array([[-6.0, 0.0, 0.0]]),
            "detectors_ras": np.array([[2.0, 0.0, 0.0], [6.0, 0.0, 0.0]])}
    keys = ("labels_kji", "ijk_to_ras", "optics_x", "optics_m", "sources_ras", "detectors_ras",
            "yield_per_label")
    mc = simulate_acquisition(*[case[k] for k in keys], photons=20_000, seed=71, runs=2,
                              detector_radius_mm=2.0, engine=_engine())
    assert mc["excitation"].shape == (1, 2) and np.all(mc["emission_se"] > 0)
    fem = fem_acquisition(case, detector_radius_mm=2.0, fine_mm=0.75)
    rel = np.abs(fem["emission"] / mc["emission"] - 1)
    assert np.all(rel <= 0.12 + 2.5 * mc["emission_se"] / mc["emission"]), rel
    rel_x = np.abs(fem["excitation"] / mc["excitation"] - 1)
    assert np.all(rel_x <= 0.12 + 2.5 * mc["excitation_se"] / mc["excitation"]), rel_x


@pytest.mark.slow
@pytest.mark.heavy(gb=5)     # 4.0 GB in CI (the default allowance is 4)
def test_cli_validate_mc_quick_end_to_end(tmp_path):
    r = _fluo("validate", "mc", "--quick", "--out", str(tmp_path), "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    assert out["photons"] == 100_000 and out["runs"] == 4
    assert out["reference"]["agrees"], out["reference"]
    assert out["agree_from_mm"]["empirical"] is not None
    assert out["energy"]["balance"] == pytest.approx(1.0, abs=2e-4)
    stored = reference.read_set(tmp_path / "mc_halfspace.json")
    assert stored["command"].startswith("fluo validate mc --quick")


def test_default_boundary_constant_fits_the_interior_fluence(fem_n137):
    """The evidence behind optics.DEFAULT_BOUNDARY (docs/validation.md): with it the
    FEM's fluence inside the n 1.37 medium is within 3 % of MC (median per depth,
    1.5-15.5 mm deep, rho 1-20 mm); the empirical A was 5-6 % high."""
    depths = sorted({r["depth_mm"] for r in fem_n137["fluence_rows"]})
    for z in depths:
        d = [r["fem_vs_mc_pct"] for r in fem_n137["fluence_rows"] if r["depth_mm"] == z]
        assert abs(np.median(d)) <= 3.0, (z, d)
