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


def test_tissue_air_facets_and_detectors_on_a_curved_surface():
    from FluoTomoLib.pipelines.oral import ORAL_ROI_MM, tissue_air_facets
    from FluoTomoLib.pipelines.steps import onto_surface_from_above
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

    ph = make_phantom("oral-cavity")
    m = mesh_labelmap_structured(ph.labels, ph.spacing_mm, ph.origin_mm, 2.0, roi=ORAL_ROI_MM)
    air = tissue_air_facets(m, ph.labels, ph.spacing_mm, ph.origin_mm)
    c = m.nodes_mm[m.boundary_facets].mean(axis=1)
    lo, hi = np.array(ORAL_ROI_MM[0::2]), np.array(ORAL_ROI_MM[1::2])
    on_cut = np.any((np.abs(c - lo) < 1e-6) | (np.abs(c - hi) < 1e-6), axis=1)
    # the faces where the roi cut the agar are not tissue-air (except where the cut
    # runs along the cavity: there the probe lands in its air); the dome's are
    assert np.mean(air[on_cut]) < 0.1, np.mean(air[on_cut])
    dome = (np.abs(c[:, 0]) < 6) & (np.abs(c[:, 1] - 4) < 6) & (c[:, 2] > -20)
    up = dome & (m.boundary_normals[:, 2] > 0.5)
    assert up.sum() > 10 and np.mean(air[up]) > 0.9, np.mean(air[up])
    # a point between two sources on the tongue's dome drops onto the dome
    p = onto_surface_from_above(np.array([[0.0, 4.0, -10.0]]), m.nodes_mm,
                                m.boundary_facets[air])
    assert -18.5 < p[0, 2] < -15.0
    with pytest.raises(Exception, match="no surface below"):
        onto_surface_from_above(np.array([[100.0, 4.0, -10.0]]), m.nodes_mm,
                                m.boundary_facets[air])
