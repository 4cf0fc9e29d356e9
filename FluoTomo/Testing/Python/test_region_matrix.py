"""HP without the nodal Jacobian (issue #32): each region's sensitivity comes from
the stored fields (``TissueModel.region_matrix``: G_d^T M(K_r) F_s), equal to the
Jacobian summed over the region's basis, and an HP-only model never builds the
measurements x nodes array."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def scene(own_scene):
    """The shared own scene on a 2 mm reconstruction mesh (seconds), with its data."""
    from FluoTomoLib.tomography import LabelMap, read_acquisition, read_optics
    from FluoTomoLib.tomography.labelmap import place_on_surface
    from FluoTomoLib.tomography.model import reconstruction_mesh

    lm, optics = LabelMap.from_file(own_scene.labels), read_optics(own_scene.optics)
    acq = read_acquisition(own_scene.acq, lm, optics)
    src, _ = place_on_surface(lm, acq.sources_ras_mm, "sources")
    det, _ = place_on_surface(lm, acq.detectors_ras_mm, "detectors")
    mesh = reconstruction_mesh(lm.labels_kji, lm.spacing_mm, 2.0, None, target=7,
                               surface=lm.surface())
    return lm, optics, acq, src, det, mesh


def _model(scene, nodal_jacobian):
    from FluoTomoLib.tomography.model import TissueModel

    lm, optics, acq, src, det, mesh = scene
    return TissueModel(mesh, lm.labels_kji, lm.spacing_mm, optics, src, det, acq.mask,
                       nodal_jacobian=nodal_jacobian)


def test_region_sensitivities_equal_the_jacobian_summed_over_each_region(scene):
    tm = _model(scene, nodal_jacobian=True)
    K = tm.prior.K()
    via_j = tm.J @ K
    direct = tm.region_matrix(tm.prior)
    assert direct.shape == via_j.shape == (int(tm.mask.sum()), K.shape[1])
    # every column carries signal, and the two agree to rounding
    assert np.all(np.max(np.abs(via_j), axis=0) > 0)
    np.testing.assert_allclose(direct, via_j, rtol=1e-9, atol=1e-12 * np.max(np.abs(via_j)))
    # a perturbed basis (the segmentation shifts' kind) too
    moved, _ = tm.prior_for(tm.labels_kji, basis_only=True)
    np.testing.assert_allclose(tm.region_matrix(moved), tm.J @ moved.K(), rtol=1e-9,
                               atol=1e-12 * np.max(np.abs(via_j)))


def test_hp_alone_never_builds_the_nodal_jacobian_and_gets_the_same_values(scene):
    lm, optics, acq, *_ = scene
    lean = _model(scene, nodal_jacobian=False)
    full = _model(scene, nodal_jacobian=True)
    y = acq.y()
    res_lean, _ = lean.solve(y, "HP", lam=10.0)
    shifts = lean.segmentation_shifts(y, "HP", 10.0, 0.5)
    assert lean._J is None, "an HP-only model built the (M, N) Jacobian"
    res_full, _ = full.solve(y, "HP", lam=10.0)

    def values(res):
        return {k: v["mean_yield_per_mm"] for k, v in res.region_confidence.items()}

    a, b = values(res_lean), values(res_full)
    assert a.keys() == b.keys() and 7 in a
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-8, abs=1e-15)
    np.testing.assert_allclose(res_lean.yield_per_mm, res_full.yield_per_mm, rtol=1e-8,
                               atol=1e-12)
    assert set(shifts["shifts"]) == set(a) and len(shifts["offsets_mm"]) == 4


def test_a_model_for_hp_alone_skips_the_soft_prior_and_gets_the_same_values(scene):
    """The mesh placement test's model solves HP only: HP's basis (the partial
    volumes) without the soft prior's volume-preserving node regions and region
    weights, and the same HP values to rounding."""
    from FluoTomoLib.tomography.model import TissueModel

    lm, optics, acq, src, det, mesh = scene
    lean = TissueModel(mesh, lm.labels_kji, lm.spacing_mm, optics, src, det, acq.mask,
                       nodal_jacobian=False, soft_prior=False)
    full = _model(scene, nodal_jacobian=False)
    assert lean.region_weights is None and full.region_weights is not None
    assert list(lean.prior.labels) == list(full.prior.labels)
    np.testing.assert_array_equal(lean.prior.K(), full.prior.K())
    y = acq.y()
    a, _ = lean.solve(y, "HP", lam=10.0)
    b, _ = full.solve(y, "HP", lam=10.0)
    np.testing.assert_allclose(a.yield_per_mm, b.yield_per_mm, rtol=1e-10, atol=1e-15)


def test_every_region_keeps_a_node_in_hp_s_basis_holder():
    from FluoTomoLib.tomography.model import _dominant_regions

    # region 9 never dominates a node; it keeps the node of its largest share
    F = np.array([[0.9, 0.1, 0.0], [0.6, 0.1, 0.3], [0.2, 0.7, 0.1], [0.5, 0.1, 0.4]])
    out = _dominant_regions(F, [3, 7, 9])
    assert sorted(set(out.tolist())) == [3, 7, 9] and out[3] == 9
