"""Reconstruction meshes graded by newest-vertex bisection of a Kuhn grid
(meshing.bisection, tomography.model.graded_reconstruction_mesh;
docs/physics.md section 8.1): conforming, graded as asked, the regions' volumes
kept, and the data within a few % of a finer uniform mesh's."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fluoguide.errors import FluoInputError
from fluoguide.phantoms import make_phantom
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.meshing import bisection
from FluoTomoLib.meshing.bisection import bisection_mesh, element_size
from FluoTomoLib.meshing.mesh import Mesh
from FluoTomoLib.meshing.voxel import labelmap_region_volumes, mesh_labelmap_structured
from FluoTomoLib.tomography.model import (graded_reconstruction_mesh, membership,
                                          node_spacing, nodal_volumes, reconstruction_mesh)

ROI = (-10.0, 10.0, -12.0, 12.0, -8.0, 0.0)
LINE = np.array([[0.0, y, 0.0] for y in np.linspace(-6.0, 6.0, 9)])


def _size_at(points):
    d, _ = cKDTree(LINE).query(points)
    return np.clip(0.5 + 0.3 * d, 0.5, 2.0)


def _on_roi_faces(points, roi):
    on = np.zeros(len(points), bool)
    for a in range(3):
        on |= np.isclose(points[:, a], roi[2 * a]) | np.isclose(points[:, a], roi[2 * a + 1])
    return on


def test_bisection_is_conforming_graded_and_keeps_its_shapes():
    anchor = np.array([0.3, -0.7, -2.1])
    nodes, el = bisection_mesh(ROI, 2.0, _size_at, anchor_mm=anchor)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    # it fills the box, and every face is shared by two elements or lies on the
    # box: a hanging node would leave faces on the inside
    assert np.isclose(m.measures.sum(), 20 * 24 * 8, rtol=1e-12)
    f = m.boundary_facets
    assert _on_roi_faces(nodes[f].mean(axis=1), ROI).all()
    assert len(np.unique(el)) == len(nodes)
    # each element as small as asked at its centre (within half a bisection step)
    size = element_size(nodes, el)
    assert np.all(size <= _size_at(nodes[el].mean(axis=1)) * 2 ** (1 / 6) + 1e-9)
    # graded: fine at the optodes, coarse far away
    near = cKDTree(LINE).query(nodes[el].mean(axis=1))[0] < 1.0
    assert size[near].max() <= 0.85 and size.max() >= 1.9
    # the grid's lines (and their halvings) pass through the anchor
    assert np.any(np.all(np.isclose(nodes, anchor), axis=1))
    # a few shapes only (on a grid of cubes: no anchor, the box a multiple of
    # them): the edge lengths scaled by the longest, sorted
    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    p = nodes[el]
    e = np.stack([np.linalg.norm(p[:, i] - p[:, j], axis=1)
                  for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], axis=1)
    shapes = np.unique(np.round(np.sort(e / e.max(axis=1, keepdims=True), axis=1), 6), axis=0)
    assert len(shapes) <= 4, shapes


def _every_element_every_pass(roi, coarse, size_at, anchor):
    """bisection_mesh as first written: every element's size checked in every
    pass, every element's six edges in every round of the closure."""
    from FluoTomoLib.meshing.voxel import grid_edges

    b = bisection._Bisector(*bisection.kuhn_elements(grid_edges(np.asarray(roi), coarse,
                                                                   anchor)))
    for _ in range(3 * 4 + 3):
        pts, el = b.node_array(), b.elements
        want = np.maximum(size_at(pts[el].mean(axis=1)), coarse / 16)
        mark = element_size(pts, el) > want * 2 ** (1 / 6)
        if not mark.any():
            break
        b.bisect(mark)
        while True:
            h = b.hanging()
            if not h.any():
                break
            b.bisect(h)
    return b.node_array(), b.elements


def test_checking_only_what_changed_builds_the_same_mesh():
    """Each pass checks only the elements made since the last one, and the
    closure, after its first sweep, only the last bisection's children and the
    elements holding both ends of an edge it split: the mesh is node for node the
    one of checking every element every time."""
    rng = np.random.default_rng(3)
    for _ in range(3):
        pts = rng.uniform([-10, -12, -8], [10, 12, 0], (int(rng.integers(2, 12)), 3))
        tree, h, rate = cKDTree(pts), rng.uniform(0.3, 0.8), rng.uniform(0.15, 0.5)

        def size_at(p):
            return np.minimum(2.0, h + rate * tree.query(p)[0])

        anchor = rng.uniform(-3, 3, 3)
        fast = bisection_mesh(ROI, 2.0, size_at, anchor_mm=anchor)
        every = _every_element_every_pass(ROI, 2.0, size_at, anchor)
        assert len(fast[1]) > 3000       # refined past the 2 mm grid (2,880)
        assert np.array_equal(fast[0], every[0]) and np.array_equal(fast[1], every[1])


def test_bisection_refuses_what_would_not_fit(monkeypatch):
    monkeypatch.setattr(bisection, "MAX_ELEMENTS", 20_000)
    with pytest.raises(FluoInputError, match="elements"):
        bisection_mesh(ROI, 2.0, lambda p: np.full(len(p), 0.3))
    with pytest.raises(FluoInputError):
        bisection_mesh(ROI, 0.0, _size_at)


@pytest.fixture(scope="module")
def tube():
    return make_phantom("cylinder-tube", depth_mm=4.7)


def test_graded_tube_mesh_keeps_the_tube_with_a_fraction_of_the_nodes(tube):
    roi = (-14.0, 14.0, -20.0, 20.0, -14.0, 0.0)
    m = graded_reconstruction_mesh(tube.labels, tube.spacing_mm, 1.0, roi, LINE, 2.0,
                                   target=2, origin_mm=tube.origin_mm, burial_mm=1.0,
                                   see_mm=6.0)
    # the rectilinear mesh with the same sizes: 1 mm, the tube's cross-section
    # refined to 0.5 mm, the burial band under the optodes
    grid = reconstruction_mesh(tube.labels, tube.spacing_mm, 1.0, roi, target=2,
                               origin_mm=tube.origin_mm, optodes=LINE,
                               optode_normals=np.tile([0.0, 0.0, 1.0], (len(LINE), 1)),
                               burial_mm=1.0)
    assert m.meta["method"] == "bisection" and m.n_nodes < 0.5 * grid.n_nodes
    truth = labelmap_region_volumes(tube.labels, tube.spacing_mm, roi, tube.origin_mm)
    for r in (1, 2):
        v = m.measures[m.element_region == r].sum()
        assert abs(v - truth[r]) / truth[r] < 0.02, (r, v, truth[r])
    assert not m.meta["warnings"]
    # the nodes' own spacing: fine at the tube and the optodes, coarse away
    h = node_spacing(m)
    assert h.min() <= 0.5 + 1e-9 and h.max() >= 2.0 - 1e-9
    labs, F = membership(m, tube.labels, tube.spacing_mm, tube.origin_mm)
    assert np.allclose(F.sum(axis=1), 1.0)
    pv = F[:, list(labs).index(2)] @ nodal_volumes(m)
    assert abs(pv - truth[2]) / truth[2] < 0.05, (pv, truth[2])


def test_graded_mesh_data_match_a_finer_uniform_mesh():
    """Excitation and emission data of a slab with a smooth fluorescent blob
    3 mm deep: the graded mesh (1 mm at the optodes, up to 2 mm) against a
    uniform 0.5 mm mesh, another discretisation and finer everywhere; within
    4 %, as close as the uniform 1 mm grid (which has more nodes)."""
    spacing = np.array([0.5, 0.5, 0.5])
    shape = (24, 60, 40)                          # K (z), J (y), I (x)
    labels = np.ones(shape, np.int16)
    origin = np.array([-9.75, -14.75, -11.75])
    k, j, i = np.indices(shape)
    pts = np.stack([i, j, k], axis=-1) * spacing + origin
    labels[np.linalg.norm(pts - [0.0, 1.0, -4.0], axis=-1) < 1.5] = 2
    roi = (-10.0, 10.0, -15.0, 15.0, -12.0, 0.0)
    src = np.array([[0.0, y, 0.0] for y in (-6.0, -2.0, 2.0, 6.0)])
    det = np.array([[0.0, y, 0.0] for y in (-8.0, -4.0, 0.0, 4.0, 8.0)])
    opt = np.vstack([src, det])
    graded = graded_reconstruction_mesh(labels, spacing, 1.0, roi, opt, 2.0, target=2,
                                        origin_mm=origin, burial_mm=1.0)
    fine = mesh_labelmap_structured(labels, spacing, origin, 0.5, roi=roi)
    props = {"mua_per_mm": 0.01, "musp_per_mm": 1.0, "n": 1.4}

    def data(mesh):
        r2 = np.sum((mesh.nodes_mm - [0.0, 1.0, -3.0]) ** 2, axis=1)
        model = FluorescenceModel(mesh, props, props, src, det)
        return model.excitation_data(), model.emission_data(0.01 * np.exp(-r2 / 4.0))

    uniform = mesh_labelmap_structured(labels, spacing, origin, 1.0, roi=roi)
    gx, gm = data(graded)
    fx, fm = data(fine)
    ux, um = data(uniform)
    far = np.linalg.norm(src[:, None] - det[None], axis=-1) >= 2.0
    assert graded.n_nodes < 0.7 * uniform.n_nodes
    for got, ref, grid in ((gx, fx, ux), (gm, fm, um)):
        err = np.abs(got[far] / ref[far] - 1)
        assert err.max() < 0.04
        assert np.median(err) <= np.median(np.abs(grid[far] / ref[far] - 1)) + 0.01


def test_points_in_a_graded_mesh_are_found_in_one_batch():
    """The locator's nearest centroids are small elements where the mesh grades:
    the large element holding a point is found by the widened batch (a search
    element by element took minutes on a family scene's accuracy estimate)."""
    from FluoTomoLib.fem.locate import PointLocator

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    rng = np.random.default_rng(3)
    pts = rng.uniform(np.array(ROI[0::2]) + 1e-6, np.array(ROI[1::2]) - 1e-6, size=(4000, 3))
    elem, bary = PointLocator(m, k=4).locate(pts)
    assert np.all(elem >= 0) and np.all(bary >= -1e-9)
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", bary, m.nodes_mm[m.elements[elem]]), pts,
                               atol=1e-9)
    outside = pts + np.array([0.0, 0.0, 9.0])            # above the box
    assert np.all(PointLocator(m).locate(outside)[0] == -1)


def test_locating_in_batches_changes_no_point(monkeypatch):
    """The locator works a batch of points at a time (its candidate search holds
    ~100 bytes a point): small batches find the same elements and weights."""
    from FluoTomoLib.fem import locate

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    rng = np.random.default_rng(4)
    pts = rng.uniform(np.array(ROI[0::2]) - 1.0, np.array(ROI[1::2]) + 1.0, size=(3000, 3))
    whole = locate.PointLocator(m, k=4).locate(pts)
    monkeypatch.setattr(locate, "LOCATE_BATCH", 64)
    batched = locate.PointLocator(m, k=4).locate(pts)
    np.testing.assert_array_equal(whole[0], batched[0])
    np.testing.assert_array_equal(whole[1], batched[1])
    assert np.any(whole[0] < 0) and np.any(whole[0] >= 0)        # outside and inside


def test_label_mean_weights_are_the_mean_of_the_field_over_the_label():
    """A region's weights, applied to a nodal field, give the field's mean over
    the label's voxels inside the mesh (computed here point by point)."""
    from FluoTomoLib.fem.locate import locator
    from FluoTomoLib.tomography.model import label_mean_weights

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    rng = np.random.default_rng(6)
    spacing, origin = np.array([0.7, 0.9, 0.8]), np.array(ROI[0::2]) - 2.0
    shape = tuple((np.ceil((np.array(ROI[1::2]) - origin + 2.0) / spacing)).astype(int)[::-1])
    labels = rng.integers(0, 3, shape)
    w = label_mean_weights(m, labels, spacing, origin, [1, 2])
    field = rng.normal(size=m.n_nodes)
    k, j, i = np.indices(shape)
    pts = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * spacing + origin
    lo, hi = m.bounds()
    inside = np.all((pts >= lo - 1e-9) & (pts <= hi + 1e-9), axis=1)
    values = locator(m).interpolation_matrix(pts[inside], outside="zero") @ field
    for lab in (1, 2):
        assert w[lab] @ field == pytest.approx(values[labels.ravel()[inside] == lab].mean(),
                                               rel=1e-10)


def test_points_in_a_cavity_are_outside_at_once():
    """Points inside the mesh's box but in a hole of it (a section through the oral
    cavity, the air voxels of a label map) are searched among the elements that
    can reach them, each size class within its own reach: the same answer as the
    element-by-element scan, without the largest element's reach around every
    point (docs/changelog.md: the oral case's sections)."""
    from FluoTomoLib.fem.locate import PointLocator, _scan_locate

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    c = nodes[el].mean(axis=1)
    centre = np.array([(ROI[0] + ROI[1]) / 2, (ROI[2] + ROI[3]) / 2, (ROI[4] + ROI[5]) / 2])
    keep = np.linalg.norm(c - centre, axis=1) > 3.0
    m = Mesh(nodes, el[keep], np.ones(int(keep.sum()), int)).oriented()
    rng = np.random.default_rng(5)
    pts = np.vstack([centre + rng.normal(0.0, 1.5, size=(1500, 3)),
                     rng.uniform(np.array(ROI[0::2]), np.array(ROI[1::2]), size=(1500, 3))])
    elem, bary = PointLocator(m, k=4).locate(pts)
    ref, _ = _scan_locate(np.ascontiguousarray(m.nodes_mm), np.ascontiguousarray(m.elements),
                          pts, 1e-9)
    np.testing.assert_array_equal(elem < 0, ref < 0)
    assert np.sum(elem < 0) > 300 and np.sum(elem >= 0) > 1500
    ok = elem >= 0
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", bary[ok], m.nodes_mm[m.elements[elem[ok]]]),
                               pts[ok], atol=1e-9)


def test_grid_interpolation_is_the_point_interpolation_at_the_grid_points():
    """The element-driven grid search (each element visits the grid points in its
    box: the yield volume, a label's mean) gives the point locator's weights at
    every selected voxel centre of a graded mesh with a hole, points in the hole
    and beyond the mesh an empty row, rows in the selection's order."""
    from FluoTomoLib.fem.locate import PointLocator

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    c = nodes[el].mean(axis=1)
    centre = np.array([(ROI[0] + ROI[1]) / 2, (ROI[2] + ROI[3]) / 2, (ROI[4] + ROI[5]) / 2])
    m = Mesh(nodes, el[np.linalg.norm(c - centre, axis=1) > 3.0],
             np.ones(int(np.sum(np.linalg.norm(c - centre, axis=1) > 3.0)), int)).oriented()
    spacing, origin = np.array([0.7, 0.45, 0.8]), np.array(ROI[0::2]) - 1.3
    shape = tuple((np.ceil((np.array(ROI[1::2]) - origin + 1.0) / spacing)).astype(int)[::-1])
    select = np.random.default_rng(8).random(shape) < 0.6
    loc = PointLocator(m, k=4)
    G = loc.grid_interpolation_matrix(origin, spacing, shape, select=select).toarray()
    k, j, i = np.indices(shape)
    pts = (np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * spacing + origin)[select.ravel()]
    ref = loc.interpolation_matrix(pts, outside="zero").toarray()
    empty = ~ref.any(axis=1)
    assert empty.sum() > 100 and (~empty).sum() > 1000           # outside and inside
    np.testing.assert_array_equal(~G.any(axis=1), empty)
    # a point on a face shared by two elements may take either: the same weights
    np.testing.assert_allclose(G, ref, atol=1e-12)


def test_a_field_on_a_volume_grid_is_its_point_interpolation_at_the_voxel_centres():
    """The yield volumes' resampling (FluoTomoLib.scene.grid_weights): on an
    axis-aligned grid (the element-driven search) and on an oblique one (the
    point search), every voxel centre gets the point locator's value of a nodal
    field, zero outside the mesh."""
    from scipy.spatial.transform import Rotation

    from FluoTomoLib.fem.locate import locator
    from FluoTomoLib.scene import resample_to_grid

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    field = np.sin(m.nodes_mm @ np.array([0.3, -0.2, 0.5])) + 2.0
    # the grid reaches 4 mm beyond the mesh on every side: only the mesh's box is searched
    spacing, origin = np.array([1.1, 0.9, 1.3]), np.array(ROI[0::2]) - 4.3
    shape = tuple((np.ceil((np.array(ROI[1::2]) - origin + 4.0) / spacing)).astype(int)[::-1])
    for d in (None, Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix()):
        got = resample_to_grid(m, field, shape, spacing, origin, d)
        k, j, i = np.indices(shape)
        ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * spacing
        pts = origin + ijk @ (np.eye(3) if d is None else d).T
        ref = locator(m).interpolation_matrix(pts, outside="zero") @ field
        assert got.shape == shape and (ref == 0).sum() > 100 and (ref > 0).sum() > 1000
        np.testing.assert_allclose(got.ravel(), ref, rtol=1e-6, atol=1e-6)


def test_a_section_image_is_the_point_interpolation_at_its_pixels():
    """The demo's section images (pipelines.cases.section_images): each method's
    pixels are the point locator's values, NaN outside the mesh, in the window's
    own order whichever way its axes run."""
    from FluoTomoLib.fem.locate import locator
    from FluoTomoLib.pipelines.cases import section_images

    nodes, el = bisection_mesh(ROI, 2.0, _size_at)
    m = Mesh(nodes, el, np.ones(len(el), int)).oriented()
    f = np.sin(m.nodes_mm @ np.array([0.3, -0.2, 0.5])) + 2.0
    run = {"true_yield_at": lambda p: np.zeros(len(p)), "coarse": m,
           "results": {"HP": {"yield": f}}}
    y0, y1, z0, z1 = ROI[2] - 2.0, ROI[3] + 1.5, ROI[5] + 1.0, ROI[4] - 2.0
    for y, z in (((y0, y1), (z0, z1)), ((y1, y0), (z1, z0)), ((y0 + 3, y1 - 3), (z0 - 2, z1 + 2))):
        got = section_images(run, y, z, px_per_mm=4)["HP"]
        yy, zz = np.meshgrid(np.linspace(*y, got.shape[1]), np.linspace(*z, got.shape[0]))
        pts = np.stack([np.zeros(yy.size), yy.ravel(), zz.ravel()], axis=1)
        P = locator(m).interpolation_matrix(pts, outside="nan")
        ref = np.where(np.asarray(P.sum(axis=1)).ravel() > 0.5, P @ f, np.nan).reshape(yy.shape)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        np.testing.assert_allclose(got[~np.isnan(ref)], ref[~np.isnan(ref)], rtol=1e-12)
    assert np.isnan(ref).sum() == 0 and np.isnan(section_images(run, (y0, y1), (z0, z1))[
        "HP"]).sum() > 100


def _shares_against_reference(lab, spacing, origin, lo, hi, samples):
    """The compiled shares of labels 1 and 3 (others, air among them, count for
    none) checked against scipy's trilinear indicators (map_coordinates, order 1,
    mode "nearest") averaged over each cell's midpoint grid; returns them."""
    from scipy import ndimage

    from FluoTomoLib.meshing.voxel import cell_region_shares

    sub_col = np.where(lab == 1, 0, np.where(lab == 3, 1, -1)).astype(np.int32)
    got = cell_region_shares(sub_col, origin, spacing, lo, hi, samples, 2)
    t = (np.arange(samples) + 0.5) / samples
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = (lo[:, None, :] + g[None] * (hi - lo)[:, None, :]).reshape(-1, 3)
    for v, c in ((1, 0), (3, 1)):
        ref = ndimage.map_coordinates((lab == v).astype(float), ((pts - origin) / spacing).T,
                                      order=1, mode="nearest").reshape(len(lo), -1).mean(axis=1)
        np.testing.assert_allclose(got[:, c], ref, atol=1e-12)
    return got


def test_cell_shares_are_the_trilinear_indicators_mean():
    """The compiled quadrature of a node cell's region shares is the mean, over
    the midpoint grid, of each region's indicator interpolated trilinearly with
    the edge held, labels outside the asked ones (air) counting for none."""
    rng = np.random.default_rng(9)
    lab = rng.integers(0, 4, (9, 11, 7))
    spacing, origin = np.array([0.8, 0.5, 0.6]), np.array([1.0, -2.0, 0.5])     # k, j, i
    lo = origin + rng.uniform(-1.0, 4.0, (50, 3))
    _shares_against_reference(lab, spacing, origin, lo, lo + rng.uniform(0.2, 2.5, (50, 3)), 4)


def test_cell_shares_of_pure_cells_take_the_short_way():
    """Cells whose samples' trilinear stencils see one label only (most of those the
    partial volumes pass to the kernel near a target) are that label's alone, or
    nobody's in air: the same shares as the full quadrature, to rounding, on a map of
    blocks where cells fall inside, across and beyond (edge held) each block."""
    lab = np.zeros((20, 24, 18), int)
    lab[2:12, 3:20, 2:16] = 1
    lab[12:18, 3:20, 2:16] = 3
    spacing, origin = np.array([0.5, 0.4, 0.6]), np.array([0.0, 1.0, -1.0])     # k, j, i
    rng = np.random.default_rng(4)
    lo = origin + rng.uniform(-1.0, 9.0, (400, 3))
    got = _shares_against_reference(lab, spacing, origin, lo,
                                     lo + rng.uniform(0.2, 1.2, (400, 3)), 5)
    whole = np.isclose(got, 1.0, atol=1e-12).any(axis=1)
    empty = (got == 0).all(axis=1)
    mixed = ~whole & ~empty
    assert whole.sum() > 60 and empty.sum() > 20 and mixed.sum() > 50


def test_soft_prior_node_regions_hold_a_thin_targets_volume_on_a_graded_mesh():
    """SP's node regions (meshing.voxel.node_regions_volume_preserving) take the
    best-covered nodes until they hold the region's volume. Ranked by the voxel under
    each node (the label map averaged over a box of the mesh's nominal 1 mm), 0.5 mm
    nodes on 0.8 mm voxels alias: by where a 2.4 mm tube falls on them, the
    candidates ran out short of its volume (the demo's tube cases: -13 to -15 %, a
    warning on every case). Ranked by each node's partial volume over its own cell
    (the model's membership), they hold it at every offset."""
    from FluoTomoLib.meshing.voxel import node_regions_volume_preserving

    line = LINE + [0.0, 0.0, -3.0]
    nodes, el = bisection_mesh(ROI, 2.0, lambda p: np.clip(0.5 + 0.3 * cKDTree(line).query(p)[0],
                                                            0.5, 2.0))
    m = Mesh(nodes, el, np.ones(len(el), int), meta={"method": "bisection", "size_mm": 1.0})
    sp = np.full(3, 0.8)
    origin = np.array([ROI[0], ROI[2], ROI[4]]) + 0.4
    shape = np.round([(ROI[5] - ROI[4]) / 0.8, (ROI[3] - ROI[2]) / 0.8,
                      (ROI[1] - ROI[0]) / 0.8]).astype(int)
    k, _, i = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    x, z = origin[0] + i * 0.8, origin[2] + k * 0.8
    vol = nodal_volumes(m)
    off = {"box": [], "cells": []}
    for cx in (0.0, 0.2, 0.4, 0.6):
        for cz in (-3.0, -3.2, -3.4, -3.6):
            lab = np.where((x - cx) ** 2 + (z - cz) ** 2 <= 1.2 ** 2, 2, 1).astype(np.int16)
            want = np.count_nonzero(lab == 2) * 0.8 ** 3
            cover = membership(m, lab, sp, origin, region_labels=[1, 2])
            for name, c in (("box", None), ("cells", cover)):
                got = vol[node_regions_volume_preserving(m, lab, sp, origin, 1, c) == 2].sum()
                off[name].append(got / want - 1)
    assert np.max(np.abs(off["cells"])) < 0.04, off["cells"]
    assert np.min(off["box"]) < -0.25, off["box"]          # what it replaces
