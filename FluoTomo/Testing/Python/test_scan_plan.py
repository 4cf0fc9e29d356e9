"""Planning the scan (issue #36): ``tomography.plan``, ``FluoTomoLogic.planScan``
and ``fluo tomo plan``.

The scene is built here: a domed block 48 x 28 mm with two 4 mm spheres 14 mm
apart (centre to centre) 3.5 mm under its top, an LPS-like direction and an
origin far from zero. The plan's prediction (the half-space screen's HP
interval) is checked against something it did not compute: the spread of HP
reconstructions over repeated noise draws of one FEM simulation, and the
reconstruction's own noise SD (the sandwich on its FEM Jacobian).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from FluoTomoLib.tomography import LabelMap, optics_from_dict

#: the planner's HP SD against the reconstruction's own noise SD (the sandwich on
#: its FEM Jacobian with the damped iterations' whole gain), as a ratio either way:
#: measured 1.00 (label 7) and 0.98 (8), the screen a half-space in the body's
#: optics, the reconstruction a FEM on the dome (1.21 and 1.15 against the last
#: step's gain, which understated the reconstruction's spread: solver._iterated_gain)
PREDICTION_FACTOR = 1.3
#: the same against the spread of HP over 8 noise draws per target, pooled (14
#: degrees of freedom: the measured SD itself is uncertain by about 19 %, one SD):
#: measured 0.74; HP's stop at a 2 % residual change adds its own jitter to the
#: spread (docs/reconstruction.md, "Intervals")
SPREAD_FACTOR = 2.0
SEP_MM = 14.0


def _optics_doc():
    p = lambda a, b: {"mua_per_mm": a, "musp_per_mm": b}                  # noqa: E731
    return {"n": 1.37,
            "excitation": {"3": p(0.01, 1.0), "7": p(0.012, 1.1), "8": p(0.012, 1.1)},
            "emission": {"3": p(0.008, 0.9), "7": p(0.009, 1.0), "8": p(0.009, 1.0)}}


def _scene(sep_mm=SEP_MM, sp=0.8):
    k, j, i = np.indices((28, 40, 64))
    x, y, z = (i + 0.5) * sp, (j + 0.5) * sp, (k + 0.5) * sp
    top = 19.0 - 0.004 * (x - 25.6) ** 2
    body = (x > 2) & (x < 49) & (y > 2) & (y < 30) & (z > 2) & (z < top)
    lab = np.where(body, 3, 0).astype(np.uint8)
    for c, v in ((25.6 - sep_mm / 2, 7), (25.6 + sep_mm / 2, 8)):
        zc = 19.0 - 0.004 * (c - 25.6) ** 2 - 3.5 - 2.0
        lab[((x - c) ** 2 + (y - 16) ** 2 + (z - zc) ** 2 < 2.0 ** 2) & body] = v
    return LabelMap(lab, np.array([sp] * 3), np.array([130.0, 60.0, -80.0]),
                    np.diag([-1.0, -1.0, 1.0]))


@pytest.fixture(scope="module")
def scene():
    return _scene(), optics_from_dict(_optics_doc())


@pytest.fixture(scope="module")
def logic():
    from fluoapp.commands import module_logic

    return module_logic("FluoTomo")


@pytest.fixture(scope="module")
def plan(scene, logic):
    lm, optics = scene
    return logic.planScan(lm, optics, [7, 8], positions=32, noise_pct=1.0)


@pytest.fixture(scope="module")
def files(tmp_path_factory, scene):
    from fluoguide.labelmap_io import write_volume_nrrd

    d = tmp_path_factory.mktemp("plan")
    lm, _ = scene
    write_volume_nrrd(d / "labels.nrrd", lm.labels_kji, lm.spacing_mm, lm.origin_mm,
                      lm.direction)
    (d / "optics.json").write_text(json.dumps(_optics_doc()))
    return d


def test_two_targets_14_mm_apart_are_both_covered(scene, plan):
    """Both targets get a finite predicted interval, each within the narrow bar;
    one default patch over the first leaves the second uncovered."""
    from FluoTomoLib.tomography.plan import COVERED_HALF_WIDTH_PCT, predict_scan
    from FluoTomoLib.tomography.simulate import default_scan, scan_pairs

    lm, optics = scene
    c7, c8 = (lm.region_centroid_local(v) for v in (7, 8))
    assert abs(np.linalg.norm(c7 - c8) - SEP_MM) < 1.0
    hp = plan["predicted"]["HP"]
    assert set(hp) == {"7", "8"} and plan["predicted"]["SP"] is None
    for t in ("7", "8"):
        assert hp[t]["covered"] and np.isfinite(hp[t]["half_width_pct"])
        assert hp[t]["half_width_pct"] < COVERED_HALF_WIDTH_PCT
        lo, hi = hp[t]["ci95_per_mm"]
        assert lo < hp[t]["assumed_yield_per_mm"] < hi
    # the plan is at least as good as the default grid with as many positions
    dflt = plan["default_scan_predicted"]["HP"]
    assert sum(hp[t]["half_width_pct"] for t in hp) <= sum(dflt[t]["half_width_pct"]
                                                           for t in dflt)
    s, d, cfg = default_scan(lm, [7])
    one = predict_scan(lm, optics, s, d, [7, 8], scan_pairs(cfg, len(s), len(d)))
    assert one["7"]["covered"] and not one["8"]["covered"]
    assert one["8"]["half_width_pct"] > 20 * one["7"]["half_width_pct"]
    # and each target's sources lie on both sides: the plan reaches over the second
    src = lm.to_local(plan["sources_ras"])
    near8 = np.linalg.norm(src[:, :2] - c8[:2], axis=1) < 0.5 * SEP_MM
    assert 4 <= near8.sum() <= 28


def test_positions_spacing_skin_and_approach(scene, plan):
    from FluoTomoLib.tomography import place_on_surface

    lm, _ = scene
    src = plan["sources_ras"]
    assert src.shape == (32, 3) and plan["mask"].shape == (32, len(plan["detectors_ras"]))
    gaps = np.linalg.norm(src[:, None] - src[None], axis=2) + np.eye(len(src)) * 1e9
    assert gaps.min() >= 2.0 - 1e-9                                 # the default spacing
    _, moved = place_on_surface(lm, src, "sources")                  # on skin, not on a cut
    assert moved.max() < 0.05
    _, outward, _ = lm.surface().closest(lm.to_local(src))
    a = lm.vector_to_local(plan["approach_ras"])
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0)
    assert np.all(np.sum(a * outward, axis=1) < -0.99)               # the inward normal
    dist = np.linalg.norm(src[:, None] - plan["detectors_ras"][None], axis=2)
    assert np.array_equal(plan["mask"], dist > 3.0)


def test_a_wider_spacing_and_a_view_are_respected(scene, logic):
    lm, optics = scene
    p = logic.planScan(lm, optics, [7], positions=10, min_spacing_mm=4.0,
                       visible_from=[0.0, 0.0, 1.0], max_angle_deg=25.0, time_budget_s=5)
    src = p["sources_ras"]
    gaps = np.linalg.norm(src[:, None] - src[None], axis=2) + np.eye(len(src)) * 1e9
    assert gaps.min() >= 4.0 - 1e-9
    _, outward, _ = lm.surface().closest(lm.to_local(src))
    up = lm.vector_to_local([0.0, 0.0, 1.0])[0]
    assert np.all(outward @ up >= np.cos(np.deg2rad(25.0)) - 1e-9)
    assert p["predicted"]["HP"]["7"]["covered"]


def test_progress_and_cancel(scene, logic):
    """Progress rises to 1 with a message; a cancel during the screen stops it."""
    from fluoguide.errors import FluoCancelled
    from fluoguide.progress import CancelToken

    lm, optics = scene
    seen = []
    logic.planScan(lm, optics, [7], positions=6, time_budget_s=2,
                   progress=lambda f, m: seen.append((f, m)))
    fr = [f for f, _ in seen]
    assert fr == sorted(fr) and fr[-1] == 1.0 and all(m for _, m in seen)
    token = CancelToken()

    def cancel_at_screen(f, m):
        if "sensitivity" in m:
            token.cancel()

    with pytest.raises(FluoCancelled):
        logic.planScan(lm, optics, [7], positions=6, progress=cancel_at_screen, cancel=token)


def test_the_plan_round_trips_into_simulate(files, fluo, tmp_path):
    out = tmp_path / "plan"
    r = fluo("tomo", "plan", "--labels", str(files / "labels.nrrd"), "--optics",
             str(files / "optics.json"), "--target", "7,8", "--positions", "12",
             "--detectors-per-side", "5", "--time-budget-s", "5", "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout)
    doc = json.loads((out / "plan.json").read_text())
    assert res["sources"] == 12 and len(doc["sources"]) == 12
    assert doc["predicted"]["HP"]["7"]["covered"] and doc["predicted"]["HP"]["8"]["covered"]
    assert "not predicted" in doc["assumptions"]["SP"]
    acq = tmp_path / "acq"
    r = fluo("tomo", "simulate", "--labels", str(files / "labels.nrrd"), "--optics",
             str(files / "optics.json"), "--yield", "7:0.002,8:0.002", "--sources",
             str(out / "sources.csv"), "--detectors", str(out / "detectors.csv"),
             "--accuracy", "fast", "--element-mm", "1.2", "--out", str(acq), "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    sim = json.loads(r.stdout)
    assert sim["sources"] == 12 and sim["detectors"] == len(
        (out / "detectors.csv").read_text().splitlines()) - 1
    assert sim["measurements"] == doc["pairs_measured"]
    planned = np.loadtxt(out / "sources.csv", delimiter=",", skiprows=1)
    written = np.loadtxt(acq / "sources.csv", delimiter=",", skiprows=1)
    assert np.abs(planned - written).max() < 0.05          # already on the surface
    for lab in ("7", "8"):
        assert sim["scan_coverage"][lab]["seen"]


@pytest.mark.parametrize("case,args,needle", [
    ("target-missing", ["--target", "5", "--positions", "8"], "--target"),
    ("target-text", ["--target", "seven", "--positions", "8"], "--target"),
    ("positions-zero", ["--target", "7", "--positions", "0"], "--positions"),
    ("too-many", ["--target", "7", "--positions", "200", "--min-spacing-mm", "6"],
     "--positions"),
    ("zero-view", ["--target", "7", "--positions", "8", "--visible-from", "0,0,0"],
     "--visible-from"),
    ("view-text", ["--target", "7", "--positions", "8", "--visible-from", "up"],
     "--visible-from"),
    ("both-views", ["--target", "7", "--positions", "8", "--visible-from", "0,0,1",
                    "--camera-at", "0,0,100"], "--visible-from"),
    ("bad-noise", ["--target", "7", "--positions", "8", "--noise-pct", "0"], "--noise-pct"),
    ("bad-yield", ["--target", "7", "--positions", "8", "--yield", "8:1"], "--yield"),
])
def test_bad_input_one_line_exit_2_nothing_written(files, fluo, tmp_path, case, args, needle):
    out = tmp_path / "plan"
    r = fluo("tomo", "plan", "--labels", str(files / "labels.nrrd"), "--optics",
             str(files / "optics.json"), *args, "--time-budget-s", "2", "--out", str(out))
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


@pytest.mark.slow
def test_the_predicted_interval_against_noise_draws(scene, logic):
    """The screen's HP SD against (a) the reconstruction's own noise SD (its FEM
    Jacobian), within PREDICTION_FACTOR, and (b) the spread of HP over 8 noise
    draws of one FEM simulation, within SPREAD_FACTOR (either way)."""
    from FluoTomoLib.tomography import simulate_acquisition
    from FluoTomoLib.tomography.acquisition_file import Acquisition
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap
    from FluoTomoLib.tomography.simulate import add_noise

    lm, optics = scene
    truth = {3: 2e-5, 7: 2e-3, 8: 2e-3}
    noise = 2.0
    p = logic.planScan(lm, optics, [7, 8], positions=16, noise_pct=noise,
                       yield_by_label=truth, time_budget_s=5)
    clean, _ = simulate_acquisition(lm, optics, truth, p["sources_ras"], p["detectors_ras"],
                                    noise_pct=0.0, accuracy="fast", target=7)
    rng = np.random.default_rng(36)
    vals, sds = {7: [], 8: []}, {7: [], 8: []}
    mesh = None
    for _ in range(8):
        acq = Acquisition(clean.sources_ras_mm, clean.detectors_ras_mm,
                          add_noise(clean.clean, noise, rng), clean.mask,
                          meta={"noise_pct": noise})
        res = reconstruct_labelmap(lm, optics, acq, method="HP", accuracy="fast", target=7,
                                   noise_pct=noise, segmentation_mm=0.0, mesh=mesh)
        mesh = res["mesh"]
        for lab in (7, 8):
            r = res["summary"]["regions"][str(lab)]
            vals[lab].append(r["yield_per_mm"])
            sds[lab].append(r["sd_per_mm"])
    ratios = {}
    for lab in (7, 8):
        pred = p["predicted"]["HP"][str(lab)]["sd_per_mm"]
        own = float(np.median(sds[lab]))
        ratios[lab] = {"own": pred / own, "spread": pred / float(np.std(vals[lab], ddof=1))}
    # the draws' spread pooled over both targets (14 degrees of freedom)
    z = np.concatenate([(np.asarray(vals[lab]) - np.mean(vals[lab]))
                        / p["predicted"]["HP"][str(lab)]["sd_per_mm"] for lab in (7, 8)])
    pooled = 1.0 / np.sqrt(np.sum(z ** 2) / (len(z) - 2))       # predicted / measured
    print("predicted/own, predicted/spread:", ratios, "pooled", pooled)
    for lab in (7, 8):
        assert 1 / PREDICTION_FACTOR < ratios[lab]["own"] < PREDICTION_FACTOR, ratios
    assert 1 / SPREAD_FACTOR < pooled < SPREAD_FACTOR, (pooled, ratios)
