"""The image-guided tomography pipeline on the cylinder-tube phantom."""

import numpy as np
import pytest

from fluoguide.phantoms import make_phantom
from FluoTomoLib.pipelines.tube import simulate_and_reconstruct


@pytest.mark.slow
def test_tube_case_priors_beat_no_priors():
    ph = make_phantom("cylinder-tube", depth_mm=4.7)
    out = simulate_and_reconstruct(ph, fine_mm=1.0, accuracy="fast", roi_half_mm=(9.0, 21.0))
    r = out["results"]
    for m in ("SP", "HP"):
        assert abs(r[m]["centroid_error_pct"]) < 10
        assert abs(r[m]["peak_error_pct"]) < 40
    assert abs(r["HP"]["peak_error_pct"]) < abs(r["NP"]["peak_error_pct"]) or \
        abs(r["HP"]["centroid_error_pct"]) < abs(r["NP"]["centroid_error_pct"])
    assert 0.0 < out["source_error_mm"] < 2.0
    assert np.all(out["results"]["NP"]["yield"] >= 0)


@pytest.mark.slow
def test_self_absorption_feedback_corrects_the_hard_prior_yield():
    """The ICG tube absorbs 26x more than the liquid at 780 nm; a model blind to
    that underestimates its yield (about -20 % here); feeding the reconstructed
    dye's absorption back brings HP close to the truth."""
    ph = make_phantom("cylinder-tube", depth_mm=3.7)
    kw = dict(fine_mm=1.0, accuracy="fast", roi_half_mm=(9.0, 21.0), methods=("HP",))
    blind = simulate_and_reconstruct(ph, self_absorption=(), **kw)["results"]["HP"]
    fed = simulate_and_reconstruct(ph, **kw)["results"]["HP"]
    assert blind["peak_error_pct"] < -10, blind["peak_error_pct"]
    assert abs(fed["peak_error_pct"]) < abs(blind["peak_error_pct"]) - 5, \
        (fed["peak_error_pct"], blind["peak_error_pct"])
    assert "self-absorption converged" in fed["stop_reason"]
    assert fed["self_absorption_peaks"][-1] > fed["self_absorption_peaks"][0]
    assert abs(fed["centroid_error_pct"]) < 6


def test_oral_truth_and_line():
    """The oral case's analytic truth: the tongue's yield inside the tongue, the
    agar's elsewhere in the tissue, NaN in the cavity's air; its laser line runs
    along y over the tongue's centre and its beams land on the tongue's dome (the
    outermost may reach the cavity floor beside it)."""
    from FluoTomoLib.acquisition.tracked_scan import raster_scan
    from FluoTomoLib.pipelines.oral import BEAM_DIR, BEAM_ORIGIN, line_targets, oral_yield_at
    from FluoTomoLib.tomography import LabelMap

    ph = make_phantom("oral-cavity")
    truth = ph.truth()
    geo = truth["geometry"]
    y = {k: v["optics"]["yield_per_mm"] for k, v in truth["regions"].items()}
    c = np.asarray(geo["tongue_centre_mm"], float)
    pts = np.array([c, c + [0.0, 0.0, 12.0], [0.0, 0.0, -45.0], [30.0, 25.0, -5.0]])
    got = oral_yield_at(pts, ph)
    assert got[0] == y["2"] and np.isnan(got[1]) and got[2] == y["1"] and got[3] == y["1"]
    targets = line_targets(ph, 16, 1.5)
    assert np.allclose(targets[:, 0], c[0]) and np.ptp(targets[:, 1]) == 22.5
    lm = LabelMap(ph.labels, ph.spacing_mm, ph.origin_mm)
    s = lm.surface()
    hit = raster_scan(targets, BEAM_ORIGIN, BEAM_DIR, lm.to_ras(s.points),
                      s.triangles)["true_points_mm"]
    under = oral_yield_at(hit - [0.0, 0.0, 0.5], ph)                  # just under the hit
    assert np.sum(under == y["2"]) >= 14 and np.all(np.isfinite(under))


@pytest.mark.slow
@pytest.mark.parametrize("depth_mm", [5.7])
def test_tracked_tube_intervals_hold_the_truth_without_a_noise_statement(depth_mm):
    """`fluo demo`'s tube case (balanced, stored truth, tracked frames: no noise
    statement). At 5.7 mm SP's value was -16 %, HP's +20 % (the truth then held 13 %
    too much dye and SP ran blind; now HP +7 %, SP's value +5 %); SP's interval used
    to end at -8 % with no warning: the misfit was counted as noise only (no bound
    for the model's error without a noise statement) and SP's interval did not
    reach the regions-as-constants fit (HP) that its corrected value estimates.
    That part is HP's value in the segmentation test's unmoved solve less SP's,
    within 3 % of the truth of the quoted HP's (the two HP solves differ by the
    coupling and the quoted boundary; the difference itself is now small)."""
    from FluoTomoLib.pipelines.cases import tube_case

    rec = tube_case({"depth_mm": depth_mm, "seed": 0, "accuracy": "balanced",
                     "grading": "bisection"})
    res = rec["case"]["results"]
    truth = 0.0026
    for m in ("SP", "HP"):
        r = res[m]["regions"]["2"]
        lo, hi = r["ci95_per_mm"]
        assert lo <= truth <= hi, (m, r["yield_per_mm"], lo, hi, res[m]["warnings"])
        assert r["interval_parts"]["model_error_bound_per_mm"] > 0
    sp = res["SP"]["regions"]["2"]
    assert sp["interval_parts"]["region_fit_difference_per_mm"] == pytest.approx(
        res["HP"]["regions"]["2"]["yield_per_mm"] - sp["yield_per_mm"], abs=0.03 * truth)
