"""Anchored / graded structured meshes, partial-volume hard priors and the
fluorophore's self-absorption feedback (docs/tomography.md)."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.optics_table import icg_absorption_per_yield
from fluoguide.phantoms import make_phantom
from FluoTomoLib.partial_volume import PartialVolumePrior, dual_cells, node_region_fractions
from FluoTomoLib.self_absorption import _aitken, absorbing_mua
from FluoTomoLib.voxel_mesh import (_axis_edges, labelmap_region_volumes,
                                    mesh_labelmap_structured, nodal_volumes,
                                    region_centroid_mm, target_refinement)

ROI = (-9.0, 9.0, -12.0, 12.0, -12.0, 0.0)


@pytest.fixture(scope="module")
def tube():
    return make_phantom("cylinder-tube", depth_mm=4.7)


def test_axis_edges_anchor_and_refined_band():
    e = _axis_edges(-20.0, 0.0, 1.0, anchor=-4.62)
    assert np.isclose(e, -4.62).any() and e[0] == -20.0 and e[-1] == 0.0
    w = np.diff(e)
    assert w.min() >= 0.5 - 1e-9 and w.max() <= 1.5 + 1e-9
    e = _axis_edges(-20.0, 0.0, 1.0, anchor=-4.62, refine=(-7.5, -1.5, 0.5))
    w = np.diff(e)
    band = (e[:-1] >= -7.5) & (e[1:] <= -1.5)
    assert np.allclose(w[band], 0.5) and np.isclose(e, -4.62).any()
    assert w.min() >= 0.25 - 1e-9 and w.max() <= 1.5 + 1e-9
    # without anchor or band: the plain uniform split
    assert np.allclose(_axis_edges(-15.0, 15.0, 1.0), np.arange(-15.0, 15.5, 1.0))


def test_anchored_graded_mesh_keeps_volumes_and_has_no_holes(tube):
    anchor = np.array([0.0, 0.0, region_centroid_mm(tube.labels, tube.spacing_mm,
                                                    tube.origin_mm)[2]])
    assert abs(anchor[2] - (-4.7)) < 0.2          # the voxelised tube's centre depth
    refine = target_refinement(tube.labels, tube.spacing_mm, tube.origin_mm, ROI, 0.5, 2.0)
    assert refine[0] is None and refine[1] is not None and refine[2] is not None
    m = mesh_labelmap_structured(tube.labels, tube.spacing_mm, tube.origin_mm, 1.0, roi=ROI,
                                 anchor_mm=anchor, refine=refine)
    assert np.isclose(m.nodes_mm[:, 2], anchor[2]).any()
    # cells narrower than a voxel still get a label: the mesh fills the roi
    assert np.isclose(m.measures.sum(), 18 * 24 * 12, rtol=1e-9)
    truth = labelmap_region_volumes(tube.labels, tube.spacing_mm, ROI, tube.origin_mm)
    for r in (1, 2):
        v = m.measures[m.element_region == r].sum()
        assert abs(v - truth[r]) / truth[r] < 0.05, (r, v, truth[r])
    with pytest.raises(FluoInputError):
        mesh_labelmap_structured(tube.labels, tube.spacing_mm, tube.origin_mm, 1.0, roi=ROI,
                                 refine=[None, (1.0, 0.0, 0.5), None])
    with pytest.raises(FluoInputError):
        mesh_labelmap_structured(tube.labels, tube.spacing_mm, tube.origin_mm, 1.0, roi=ROI,
                                 anchor_mm=(0.0, np.nan, 0.0))


def test_partial_volume_fractions_preserve_volume_and_are_symmetric(tube):
    anchor = np.array([0.0, 0.0, -4.7])
    m = mesh_labelmap_structured(tube.labels, tube.spacing_mm, tube.origin_mm, 1.0, roi=ROI,
                                 anchor_mm=anchor)
    labels, F = node_region_fractions(m.nodes_mm, tube.labels, tube.spacing_mm,
                                      tube.origin_mm, 1.0, edges_mm=m.meta["edges_mm"])
    assert list(labels) == [1, 2]
    assert np.allclose(F.sum(axis=1), 1.0) and F.min() >= 0
    # the node cells tile the roi, so the shares integrate to the region volumes
    lo, hi = dual_cells(m.nodes_mm, m.meta["edges_mm"])
    cell = np.prod(hi - lo, axis=1)
    assert np.isclose(cell.sum(), 18 * 24 * 12)
    truth = labelmap_region_volumes(tube.labels, tube.spacing_mm, ROI, tube.origin_mm)
    assert abs((F[:, 1] * cell).sum() - truth[2]) / truth[2] < 0.03
    # a node in the tube's middle is all tube; the ones 1 mm above and below
    # (the tube's radius is 1.2 mm) are partly tube, and comparably so
    on_line = np.flatnonzero((np.abs(m.nodes_mm[:, 0]) < 1e-9) & (np.abs(m.nodes_mm[:, 1]) < 1e-9))
    z = m.nodes_mm[on_line, 2]
    f = {round(zz, 2): F[i, 1] for zz, i in zip(z, on_line)}
    assert f[-4.7] > 0.95
    assert 0.25 < f[-3.7] < 0.8 and 0.25 < f[-5.7] < 0.8
    assert f[-2.7] < 0.1 and f[-6.7] < 0.1
    # the prior's K is the fractions, its soft-prior regions the node labels
    node_region = np.where(F[:, 1] > 0.5, 2, 1)
    pr = PartialVolumePrior(node_region, labels, F)
    assert np.allclose(pr.K(), F)
    with pytest.raises(FluoInputError):
        PartialVolumePrior(node_region, labels, F[:, :1])


def test_self_absorption_pieces():
    per_x, per_m = icg_absorption_per_yield()
    # 2 ug/mL ICG: yield 0.0026 /mm adds 0.0654 /mm at 780 nm, 0.0191 at 830 nm
    assert np.isclose(0.0026 * per_x, 0.068 - 0.0026, rtol=0.01)
    assert np.isclose(0.0026 * per_m, 0.022 - 0.0029, rtol=0.01)
    mua = absorbing_mua(0.0026, np.array([0.0, 0.0026, -1.0]), 0.0, per_x)
    assert np.allclose(mua, [0.0026, 0.068, 0.0026], rtol=0.01)
    # Aitken: x_{k+1} = 0.25 x_k + 0.75 c converges to c; one extrapolation lands on it
    c = np.array([2.6e-3, 1e-5])
    v = [np.array([2.0e-3, 0.0])]
    for _ in range(2):
        v.append(0.25 * v[-1] + 0.75 * c)
    assert np.allclose(_aitken(*v), c, rtol=1e-9)
    # a component that does not contract is left as it is
    assert _aitken(np.array([1.0]), np.array([2.0]), np.array([4.0]))[0] == 4.0
