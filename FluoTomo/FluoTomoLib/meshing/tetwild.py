"""Quality tetrahedral meshing of a label map with fTetWild (pytetwild).

The quality path of FluoTomo meshing (``fluo mesh`` without ``--fast``):

1. label map -> (optional ROI crop, tiny regions merged into their
   surroundings, one voxel of air padding so every surface closes);
2. one multi-label surface with ``vtkSurfaceNets3D``: the outer boundary and
   every interface between regions, shared (each interface once), smoothed
   within the voxels it separates;
3. fTetWild tetrahedralises the whole bounding box with every surface
   triangle inserted (simplified inside an envelope of ``epsilon_mm``), at an
   ideal edge length ``size_mm`` (or a sizing field for local refinement);
4. regions: the tet faces lying on the input surface cut the tet adjacency
   graph into connected pieces; each piece takes the label the label map
   gives most of its volume (label 0 pieces, the air, are dropped).  Region
   borders are therefore surface faces: interfaces conform by construction,
   and one tet never straddles two regions.

Orientation is fixed (all tets positive); boundary slivers (min dihedral
below ``sliver_deg``) are peeled off, interior ones are counted in the
report (removing them would leave holes).  Works for any integer labels,
anisotropic spacing and any orthonormal direction matrix.
"""

from __future__ import annotations

import os
import time

import numpy as np

from fluoguide.errors import FluoInputError, check_number
from fluoguide.progress import check_cancel, report

from FluoTomoLib.meshing.mesh import Mesh

#: above this many estimated tetrahedra in fTetWild's bounding box we refuse
#: (memory ~1.5 kB per tet inside fTetWild, minutes per million tets on 2 cores)
MAX_BOX_TETS = 4.0e6

#: the peak memory of the quality mesher [bytes]: per tetrahedron of fTetWild's
#: padded box (its background mesh, the output, the region labelling) and per
#: voxel of the label map (SurfaceNets surfaces). Measured (``fluo mesh``,
#: /usr/bin/time -v, peak less the 0.43 GB of imports; the 0.8 mm cylinder-tube
#: label map, 0.48 million voxels, at 3, 2 and 1.5 mm: 0.16, 0.47 and 1.06
#: million box tetrahedra): 100, 227 and 406 MB; the estimate (500 and 120 B)
#: gives 136, 294 and 587 MB, 1.3-1.45x (docs/reliability.md, "Memory estimates")
QUALITY_BYTES_PER_BOX_TET = 500.0
QUALITY_BYTES_PER_VOXEL = 120.0


# ----------------------------------------------------------------- label map
def _check_geometry(labels, spacing_mm, origin_mm, direction):
    labels = np.asarray(labels)
    if labels.ndim != 3:
        raise FluoInputError("label map must be 3D", field="labels", value=labels.shape)
    if not np.issubdtype(labels.dtype, np.integer):
        if labels.dtype == bool:
            labels = labels.astype(np.uint8)
        else:
            raise FluoInputError("label map must hold integers", field="labels",
                                 value=str(labels.dtype))
    if labels.min() < 0:
        raise FluoInputError("labels must be >= 0 (0 = outside)", field="labels",
                             value=int(labels.min()))
    spacing = np.asarray(spacing_mm, float).reshape(-1)
    if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise FluoInputError("spacing must be three positive numbers (mm)", field="spacing_mm",
                             value=spacing.tolist())
    origin = np.asarray(origin_mm, float).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise FluoInputError("origin must be three finite numbers (mm)", field="origin_mm",
                             value=origin.tolist())
    d = np.eye(3) if direction is None else np.asarray(direction, float)
    if d.shape != (3, 3) or not np.allclose(d.T @ d, np.eye(3), atol=1e-5):
        raise FluoInputError("direction must be an orthonormal 3x3 matrix", field="direction",
                             value=np.asarray(direction).tolist())
    return labels, spacing, origin, d


def _crop_to_roi(labels, spacing, origin, d, roi):
    """Crop to the voxels whose centres lie inside roi (x0,x1,y0,y1,z0,z1 RAS mm).

    Returns the cropped labels and the new voxel-(0,0,0) origin.  For rotated
    label maps the index box around the roi is cropped and voxels outside
    the roi are set to 0.
    """
    roi = np.asarray(roi, float)
    if roi.shape != (6,) or not np.all(np.isfinite(roi)) or np.any(roi[1::2] <= roi[0::2]):
        raise FluoInputError("roi must be x0,x1,y0,y1,z0,z1 with x0<x1 etc.", field="roi",
                             value=np.asarray(roi).tolist())
    corners = np.array([[roi[a], roi[2 + b], roi[4 + c]] for a in (0, 1) for b in (0, 1)
                        for c in (0, 1)])
    ijk = ((corners - origin) @ d) / spacing          # continuous voxel indices
    shape_ijk = np.array(labels.shape[::-1])
    lo = np.clip(np.floor(ijk.min(axis=0)).astype(int), 0, shape_ijk)
    hi = np.clip(np.ceil(ijk.max(axis=0)).astype(int) + 1, 0, shape_ijk)
    if np.any(hi <= lo):
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=roi.tolist())
    sub = labels[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]].copy()
    new_origin = origin + d @ (spacing * lo)
    inside = np.ones(sub.shape, bool)
    for a in range(3):     # voxel-centre RAS coordinate a, built axis by axis (no big grids)
        c = (new_origin[a]
             + (d[a, 0] * spacing[0] * np.arange(sub.shape[2]))[None, None, :]
             + (d[a, 1] * spacing[1] * np.arange(sub.shape[1]))[None, :, None]
             + (d[a, 2] * spacing[2] * np.arange(sub.shape[0]))[:, None, None])
        inside &= (c >= roi[2 * a]) & (c < roi[2 * a + 1])
    sub[~inside] = 0
    return sub, new_origin


def _merge_tiny_regions(labels, min_voxels):
    """Relabel connected pieces smaller than ``min_voxels`` voxels with the most
    common label around them (what a one-voxel speck in a segmentation is:
    noise a mesh of millimetre elements cannot carry).  Returns the merged
    {label: voxels} counts."""
    from scipy import ndimage

    merged = {}
    if min_voxels <= 1:
        return merged
    for lab in np.unique(labels):
        if lab == 0:
            continue
        comp, n = ndimage.label(labels == lab)
        if n == 0:
            continue
        sizes = np.bincount(comp.ravel())[1:]
        boxes = ndimage.find_objects(comp)
        for c in np.flatnonzero(sizes < min_voxels) + 1:
            sl = boxes[c - 1]
            grown = tuple(slice(max(0, s.start - 1), s.stop + 1) for s in sl)
            piece = comp[grown] == c
            ring = ndimage.binary_dilation(piece) & ~piece
            around = labels[grown][ring]
            new = np.bincount(around).argmax() if around.size else 0
            labels[grown][piece] = new
            merged[int(lab)] = merged.get(int(lab), 0) + int(sizes[c - 1])
    return merged


def labelmap_volumes(labels, spacing_mm):
    """{label: volume mm^3} of the non-zero labels."""
    counts = np.bincount(labels.ravel())
    vox = float(np.prod(spacing_mm))
    return {int(v): float(c * vox) for v, c in enumerate(counts) if v and c}


# ------------------------------------------------------------------- surface
def labelmap_surface(labels, spacing_mm, origin_mm, direction=None, smoothing_iterations=8):
    """Outer and interface surfaces of a label map, each interface once.

    Returns
    -------
    points_mm : (P, 3) RAS mm
    triangles : (T, 3) int
    pair : (T, 2) the labels on the two sides of each triangle (0 = air)
    """
    import vtk
    from vtk.util import numpy_support as ns

    d = np.eye(3) if direction is None else np.asarray(direction, float)
    spacing = np.asarray(spacing_mm, float)
    padded = np.pad(labels, 1)      # air all round: every surface closes
    img = vtk.vtkImageData()
    img.SetDimensions(padded.shape[2], padded.shape[1], padded.shape[0])
    img.SetSpacing(*spacing)
    img.SetOrigin(*(-spacing))      # voxel (0,0,0) of the unpadded map at 0
    vals = padded.astype(np.int32 if padded.max() > 32767 else np.int16)
    arr = ns.numpy_to_vtk(vals.ravel(), deep=True)
    arr.SetName("labels")
    img.GetPointData().SetScalars(arr)
    sn = vtk.vtkSurfaceNets3D()
    sn.SetInputData(img)
    present = [int(v) for v in np.unique(labels) if v != 0]
    sn.SetNumberOfLabels(len(present))
    for i, v in enumerate(present):
        sn.SetLabel(i, v)
    sn.SetBackgroundLabel(0)
    sn.SetOutputMeshTypeToTriangles()
    sn.SetSmoothing(smoothing_iterations > 0)
    sn.SetNumberOfIterations(int(max(smoothing_iterations, 0)))
    sn.Update()
    out = sn.GetOutput()
    if out.GetNumberOfCells() == 0:
        raise FluoInputError("no surface found in the label map", field="labels")
    local = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(float)
    tri = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    pair = ns.vtk_to_numpy(out.GetCellData().GetArray("BoundaryLabels")).astype(np.int64)
    if smoothing_iterations > 0:
        _restore_region_volumes(local, tri, pair, labelmap_volumes(labels, spacing))
    # local = index * spacing; RAS = origin + D @ local
    pts = np.asarray(origin_mm, float) + local @ d.T
    return pts, tri, pair


def _region_surface(points, tri, pair, label):
    """Triangles of region ``label``'s closed surface, normals pointing out of it
    (SurfaceNets orients each triangle from its first label towards its second)."""
    sel = (pair == label).any(axis=1)
    t = tri[sel].copy()
    inward = pair[sel, 1] == label
    t[inward] = t[inward][:, [0, 2, 1]]
    return t


def _restore_region_volumes(points, tri, pair, volumes_mm3, passes=3):
    """Undo the shrinkage of surface smoothing: move each region's surface along
    its outward vertex normals until it encloses the label-map volume again.

    Smoothing takes ~0.4 % off a large region but 13-67 % off a 3-voxel tube
    (2 to 16 iterations); a uniform normal offset per region restores it to
    first order.  Regions go smallest first; vertices of a region already
    done stay put, so a small inclusion keeps its volume when its larger
    neighbour is corrected afterwards.  ``points`` is changed in place.
    """
    locked = np.zeros(len(points), bool)
    for label in sorted(volumes_mm3, key=volumes_mm3.get):
        t = _region_surface(points, tri, pair, label)
        if len(t) == 0:
            continue
        free = np.unique(t)
        free = free[~locked[free]]
        for _ in range(passes):
            p = points[t]
            cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            enclosed = np.einsum("ij,ij->i", p[:, 0], cross).sum() / 6.0
            area = 0.5 * np.linalg.norm(cross, axis=1).sum()
            shift = (volumes_mm3[label] - enclosed) / max(area, 1e-12)
            if abs(shift) < 1e-6:
                break
            normal = np.zeros_like(points)
            for k in range(3):
                np.add.at(normal, t[:, k], cross)
            length = np.linalg.norm(normal[free], axis=1, keepdims=True)
            points[free] += shift * normal[free] / np.maximum(length, 1e-300)
        locked[np.unique(t)] = True


def decimate_surface(points, triangles, max_error_mm, target_reduction=0.9):
    """Fewer triangles within ``max_error_mm`` of the input (vtkDecimatePro,
    topology kept: no holes, junction curves of three regions stay), so
    fTetWild's own, slower simplification has less to do."""
    import vtk
    from vtk.util import numpy_support as ns

    from fluoguide.mrml_io import polydata_from_arrays

    dec = vtk.vtkDecimatePro()
    dec.SetInputData(polydata_from_arrays(points, triangles))
    dec.SetTargetReduction(float(target_reduction))
    dec.PreserveTopologyOn()
    dec.BoundaryVertexDeletionOff()
    dec.SplittingOff()
    dec.SetErrorIsAbsolute(1)
    dec.SetAbsoluteError(float(max_error_mm))
    dec.Update()
    out = dec.GetOutput()
    pts = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(float)
    tri = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    return pts, tri


# ------------------------------------------------------ distance to surface
class _SurfaceDistance:
    """Unsigned distance [mm] from points to a triangle surface, exact within
    ``reach`` (farther points get a value > reach), vectorised."""

    def __init__(self, points, triangles, reach):
        from scipy.spatial import cKDTree

        self.a, self.b, self.c = (points[triangles[:, k]] for k in range(3))
        cen = (self.a + self.b + self.c) / 3
        self.tree = cKDTree(cen)
        self.r_tri = float(np.max(np.linalg.norm(np.stack([self.a, self.b, self.c]) - cen,
                                                 axis=2)))
        self.reach = float(reach)

    def __call__(self, q, k=8):
        from FluoTomoLib.fem.locate import _closest_on_triangles

        q = np.asarray(q, float)
        out = np.full(len(q), np.inf)
        d0, _ = self.tree.query(q, k=1)
        near = np.flatnonzero(d0 <= self.reach + self.r_tri)
        if len(near) == 0:
            return out
        k = min(k, len(self.a))
        _, cand = self.tree.query(q[near], k=k)
        cand = cand.reshape(len(near), -1)
        best = np.full(len(near), np.inf)
        for j in range(cand.shape[1]):
            t = cand[:, j]
            p, _ = _closest_on_triangles(q[near], self.a[t], self.b[t], self.c[t])
            best = np.minimum(best, np.linalg.norm(p - q[near], axis=1))
        out[near] = best
        return out


# ---------------------------------------------------------------- refinement
def _parse_refine(refine, size_mm):
    """Normalise a refinement spec to ('sphere', centre(3), radius, size) or
    ('box', lo(3), hi(3), size)."""
    if refine is None:
        return None
    kind = refine[0]
    vals = np.asarray(refine[1:], float)
    if kind == "sphere" and vals.shape == (5,) and vals[3] > 0 and 0 < vals[4]:
        spec = ("sphere", vals[:3], float(vals[3]), float(vals[4]))
    elif kind == "box" and vals.shape == (7,) and np.all(vals[1:6:2] > vals[0:6:2]) and vals[6] > 0:
        spec = ("box", vals[0:6:2], vals[1:6:2], float(vals[6]))
    else:
        raise FluoInputError("refine must be ('sphere', x, y, z, radius, size) or "
                             "('box', x0, x1, y0, y1, z0, z1, size), mm", field="refine",
                             value=list(refine))
    if not np.all(np.isfinite(vals)):
        raise FluoInputError("refine values must be finite", field="refine", value=list(refine))
    if spec[-1] >= size_mm:
        raise FluoInputError("the refined size must be smaller than the element size",
                             field="refine", value=spec[-1])
    return spec


def _sizing_field(spec, lo, hi, size_mm):
    """Background tetrahedral mesh with the target edge length at its nodes:
    the refined size inside the sphere/box, growing linearly back to
    ``size_mm`` over two coarse elements outside it (fTetWild interpolates it)."""
    from FluoTomoLib.meshing.structured import box_mesh

    fine = spec[-1]
    step = max(fine, (hi - lo).max() / 40.0)
    axes = [np.linspace(lo[a], hi[a], max(2, int(np.ceil((hi[a] - lo[a]) / step)) + 1))
            for a in range(3)]
    bg = box_mesh(*axes, name="sizing")
    p = bg.nodes_mm
    if spec[0] == "sphere":
        dist = np.maximum(np.linalg.norm(p - spec[1], axis=1) - spec[2], 0.0)
    else:
        dist = np.linalg.norm(np.maximum(np.maximum(spec[1] - p, p - spec[2]), 0.0), axis=1)
    ramp = 2.0 * max(size_mm, step)
    values = fine + (size_mm - fine) * np.clip(dist / ramp, 0.0, 1.0)
    return bg.nodes_mm, bg.elements.astype(np.int32), values


# ------------------------------------------------------------------- regions
def _tet_faces(tets):
    """Unique faces: (F, 3) sorted node ids, and for each face its (up to) two tets."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]],
                            tets[:, [0, 1, 2]]])
    owner = np.tile(np.arange(len(tets)), 4)
    faces = np.sort(faces, axis=1)
    n = int(tets.max()) + 1
    code = (faces[:, 0].astype(np.int64) * n + faces[:, 1]) * n + faces[:, 2]
    order = np.argsort(code, kind="stable")
    code, owner, faces = code[order], owner[order], faces[order]
    first = np.r_[True, code[1:] != code[:-1]]
    idx = np.cumsum(first) - 1
    tets_of = np.full((int(idx[-1]) + 1, 2), -1, dtype=np.int64)
    tets_of[idx[first], 0] = owner[first]
    tets_of[idx[~first], 1] = owner[~first]
    return faces[first], tets_of


def _label_lookup(points, labels, spacing, origin, d):
    """Label of the voxel containing each point (0 outside the map)."""
    ijk = np.round(((points - origin) @ d) / spacing).astype(np.int64)
    shape = np.array(labels.shape[::-1])
    ok = np.all((ijk >= 0) & (ijk < shape), axis=1)
    out = np.zeros(len(points), dtype=np.int64)
    out[ok] = labels[ijk[ok, 2], ijk[ok, 1], ijk[ok, 0]]
    return out


def _assign_regions(v, tets, surf_pts, surf_tri, tol_mm, labels, spacing, origin, d):
    """Region per tet: components of the tet graph cut at surface faces, each
    labelled by volume-weighted label-map majority.  Returns (region, stats)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces, tets_of = _tet_faces(tets)
    interior = tets_of[:, 1] >= 0
    dist = _SurfaceDistance(surf_pts, surf_tri, reach=tol_mm)
    near_v = dist(v) <= tol_mm
    cand = np.flatnonzero(interior & near_v[faces].all(axis=1))
    on_surface = np.zeros(len(faces), bool)
    if len(cand):
        # the face centre too: a chord across a curved surface is not on it
        on_surface[cand] = dist(v[faces[cand]].mean(axis=1)) <= tol_mm
    keep = interior & ~on_surface
    a, b = tets_of[keep, 0], tets_of[keep, 1]
    g = sp.coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(len(tets), len(tets)))
    n_comp, comp = connected_components(g, directed=False)
    p = v[tets]
    vol = np.abs(np.linalg.det(p[:, 1:] - p[:, :1])) / 6.0
    look = _label_lookup(p.mean(axis=1), labels, spacing, origin, d)
    n_lab = int(labels.max()) + 1
    # volume of each label in each component, via one sparse accumulation
    acc = sp.coo_matrix((vol, (comp, look)), shape=(n_comp, n_lab)).toarray()
    comp_label = acc.argmax(axis=1)
    comp_vol = acc.sum(axis=1)
    purity = acc.max(axis=1) / np.maximum(comp_vol, 1e-300)
    # a large component that mixes labels means a surface face was missed
    big = comp_vol > 0.05 * comp_vol.sum() / max(1, len(np.unique(comp_label)))
    stats = {"components": int(n_comp), "surface_faces": int(on_surface.sum()),
             "min_purity_large_components": float(purity[big].min()) if big.any() else 1.0}
    return comp_label[comp], stats


def _peel_boundary_slivers(mesh, sliver_deg, max_passes=3):
    """Drop slivers that touch the boundary (a flat tet lying on the surface
    adds nothing but a tiny volume); interior slivers stay (removal = hole)."""
    from FluoTomoLib.meshing.report import dihedral_angles_deg

    removed = 0
    for _ in range(max_passes):
        bad = dihedral_angles_deg(mesh).min(axis=1) < sliver_deg
        if not bad.any():
            break
        _, tets_of = _tet_faces(mesh.elements)
        on_bnd = np.zeros(mesh.n_elements, bool)
        on_bnd[tets_of[tets_of[:, 1] < 0, 0]] = True      # owns a face no other tet shares
        drop = bad & on_bnd
        if not drop.any():
            break
        keep = ~drop
        removed += int(drop.sum())
        mesh = mesh.keep_elements(keep)[0]
    return mesh, removed


# ---------------------------------------------------------------------- main
def mesh_labelmap_quality(labels_kji, spacing_mm, origin_mm, size_mm, roi=None, direction=None,
                          refine=None, epsilon_mm=None, smoothing_iterations=8,
                          min_region_voxels=8, optimize_iterations=4, stop_energy=10.0,
                          sliver_deg=5.0, threads=None, decimate=False, progress=None, cancel=None,
                          name="tet-mesh"):
    """Tetrahedral mesh of a label map with smooth, conforming region interfaces.

    Parameters
    ----------
    labels_kji : (K, J, I) int label map, 0 = outside; any number of regions
    spacing_mm, origin_mm : voxel size and voxel-(0,0,0) centre (RAS mm)
    size_mm : ideal tet edge length [mm]
    roi : (x0, x1, y0, y1, z0, z1) RAS mm to crop to first; default whole map
    direction : (3, 3) IJK-to-RAS direction cosines (orthonormal); default identity
    refine : ('sphere', x, y, z, radius_mm, size_mm) or
        ('box', x0, x1, y0, y1, z0, z1, size_mm): smaller elements there
        (fTetWild sizing field), growing back to ``size_mm`` over 2 elements
    epsilon_mm : envelope: how far fTetWild may move the surface; default
        min(0.2 voxel, 0.1 size) - smaller keeps thin regions' volume, costs time
    smoothing_iterations : SurfaceNets smoothing (0 = voxel staircase)
    min_region_voxels : connected pieces smaller than this are merged into
        their surroundings first (listed in ``meta["merged_voxels"]``)
    optimize_iterations, stop_energy : fTetWild optimisation (quality vs time)
    sliver_deg : tets with a smaller dihedral angle are slivers
    threads : fTetWild threads (default: the CPUs this process may use)
    decimate : pre-decimate the surface (vtkDecimatePro within eps/2): less
        work for fTetWild's simplification, but corners get cut (a box lost
        1.3 % instead of 0.2 % in our test), so off by default

    Returns
    -------
    Mesh, all tets positive, ``element_region`` = label; ``meta`` holds
    ``seconds`` (and per stage ``timing``), ``labelmap_volumes_mm3`` (of the
    cropped map), ``lost_regions`` (always empty: a lost region raises),
    ``boundary_slivers_removed``.
    """
    import pytetwild

    t0 = time.perf_counter()
    timing = {}
    labels, spacing, origin, d, merged = _prepared_labels(
        labels_kji, spacing_mm, origin_mm, direction, roi, size_mm, threads, min_region_voxels)
    ref = labelmap_volumes(labels, spacing)
    _check_box_size(labels, spacing, size_mm, refine)
    spec = _parse_refine(refine, size_mm)
    timing["labels_s"] = time.perf_counter() - t0
    check_cancel(cancel)

    report(progress, 0.05, "extracting surfaces")
    t = time.perf_counter()
    pts, tri, pair = labelmap_surface(labels, spacing, origin, d, smoothing_iterations)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    eps = float(epsilon_mm) if epsilon_mm is not None else min(0.2 * spacing.min(), 0.1 * size_mm)
    if not (np.isfinite(eps) and eps > 0):
        raise FluoInputError("epsilon must be > 0 (mm)", field="epsilon_mm", value=epsilon_mm)
    n_smooth = len(tri)
    fine_pts, fine_tri = pts, tri       # distances are measured to these (small triangles)
    if decimate:
        pts, tri = decimate_surface(pts, tri, 0.5 * eps)
    timing["surface_s"] = time.perf_counter() - t
    check_cancel(cancel)

    report(progress, 0.15, "tetrahedralising (fTetWild)")
    t = time.perf_counter()
    n_threads = threads or len(os.sched_getaffinity(0))
    v, tets = _tetrahedralize(pytetwild, pts, tri, spec, (lo, hi), size_mm, eps / diag,
                              stop_energy, optimize_iterations, n_threads)
    timing["tetwild_s"] = time.perf_counter() - t
    check_cancel(cancel)

    report(progress, 0.85, "labelling regions")
    t = time.perf_counter()
    # the output surface lies within eps of the decimated surface, which lies
    # within eps/2 of the smooth one: 2 eps, with margin for rounding
    tol = 2.0 * eps + 1e-6 * diag
    mesh, stats = _region_mesh(v, tets, (fine_pts, fine_tri), tol,
                               (labels, spacing, origin, d), size_mm, name)
    mesh, peeled = _peel_boundary_slivers(mesh, sliver_deg)
    timing["regions_s"] = time.perf_counter() - t
    lost = sorted(set(ref) - set(mesh.regions.tolist()))
    if lost:
        raise FluoInputError(f"region(s) {lost} vanished at this size (too thin for "
                             f"{size_mm:g} mm elements): choose a smaller size or refine there",
                             field="size_mm", value=size_mm)
    mesh.meta.update({
        "seconds": time.perf_counter() - t0, "timing": timing, "method": "quality (fTetWild)",
        "size_mm": float(size_mm), "epsilon_mm": eps, "labelmap_volumes_mm3": ref,
        "merged_voxels": merged, "lost_regions": lost, "boundary_slivers_removed": peeled,
        "surface_triangles": n_smooth, "decimated_triangles": int(len(tri)), "box_tets": int(len(tets)),
        "roi": None if roi is None else [float(x) for x in roi],
        "refine": None if spec is None else [spec[0]] + [float(x) for x in np.hstack(spec[1:])],
        "threads": int(n_threads), **stats})
    report(progress, 1.0, "mesh done")
    return mesh


def _prepared_labels(labels_kji, spacing_mm, origin_mm, direction, roi, size_mm, threads,
                     min_region_voxels):
    """The label map made ready for its surfaces: checked, cropped to the roi (a
    copy either way), as int16 (int32 for labels above 32767), with the pieces
    smaller than ``min_region_voxels`` merged into their surroundings.

    Returns (labels, spacing [mm], origin [mm], direction, merged voxels per label);
    refuses an empty map (or roi), a size that is not > 0 [mm] and a thread
    count outside 1..1024.
    """
    labels, spacing, origin, d = _check_geometry(labels_kji, spacing_mm, origin_mm, direction)
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise FluoInputError("element size must be > 0", field="size_mm", value=size_mm)
    if threads is not None:
        # fTetWild spins forever on a negative thread count
        check_number("threads", threads, 1, 1024, integer=True)
    if roi is not None:
        labels, origin = _crop_to_roi(labels, spacing, origin, d, roi)
    else:
        labels = labels.copy()
    if not np.any(labels > 0):
        raise FluoInputError("label map is empty (no non-zero label)" +
                             (" inside the roi" if roi is not None else ""), field="labels")
    labels = labels.astype(np.int32 if labels.max() > 32767 else np.int16)
    merged = _merge_tiny_regions(labels, min_region_voxels)
    if not np.any(labels > 0):
        raise FluoInputError(f"every region is smaller than min_region_voxels="
                             f"{min_region_voxels} voxels", field="labels")
    return labels, spacing, origin, d, merged


def _check_box_size(labels, spacing, size_mm, refine):
    """Refuse a size [mm] the tissue is less than two elements across, and (before
    fTetWild starts) a meshing box of more than MAX_BOX_TETS tetrahedra (unless
    refined: the sizing field decides there) or one that would not fit in memory."""
    nz = np.argwhere(labels > 0)
    extent_mm = (nz.max(axis=0) - nz.min(axis=0) + 1)[::-1] * spacing
    if np.max(extent_mm) < 2 * size_mm:
        raise FluoInputError(f"the tissue ({np.max(extent_mm):.3g} mm across) is smaller than "
                             "two elements: choose a smaller size", field="size_mm",
                             value=size_mm)
    # fTetWild meshes the padded bounding box: ~12 tets per size^3 there
    box_tets = np.prod(extent_mm * 1.15 + 2 * size_mm) * 12.0 / size_mm ** 3
    if refine is None and box_tets > MAX_BOX_TETS:
        raise FluoInputError(f"about {box_tets:.3g} tetrahedra in the meshing box: choose a "
                             "larger element size or an roi (or --fast)", field="size_mm",
                             value=size_mm)
    from fluoguide.memory import check_fits

    check_fits(QUALITY_BYTES_PER_BOX_TET * box_tets + QUALITY_BYTES_PER_VOXEL * labels.size,
               f"the quality mesh ({box_tets / 1e6:.1f} million tetrahedra in fTetWild's box "
               f"at {size_mm:g} mm)", "choose a larger element size or an roi (or --fast)",
               field="size_mm", value=size_mm)


def _tetrahedralize(pytetwild, pts, tri, spec, bounds, size_mm, epsilon_rel, stop_energy,
                    optimize_iterations, n_threads):
    """fTetWild's tetrahedra of the surface (pts [mm], tri) at edge length
    ``size_mm`` (a sizing field over ``bounds`` = (lo, hi) [mm] plus two elements
    when ``spec`` refines), within ``epsilon_rel`` (of the surface's bounding-box
    diagonal).  Returns (vertices [mm] as float, tets as int64); its failure is a
    FluoInputError."""
    kw = {}
    if spec is not None:
        lo, hi = bounds
        bg_v, bg_t, bg_val = _sizing_field(spec, lo - 2 * size_mm, hi + 2 * size_mm, size_mm)
        kw = {"bg_vertices": bg_v, "bg_tets": bg_t, "bg_values": bg_val}
    try:
        v, tets = pytetwild.tetrahedralize(
            pts, tri.astype(np.int32), edge_length_abs=float(size_mm), epsilon=epsilon_rel,
            stop_energy=float(stop_energy), num_opt_iter=int(optimize_iterations),
            num_threads=int(n_threads), disable_filtering=True, quiet=True, **kw)
    except (RuntimeError, ValueError) as exc:
        from fluoguide.library_errors import scrub

        # its text may carry the library's source files: scrubbed, one line
        raise FluoInputError(f"fTetWild failed ({scrub(exc, limit=160)})",
                             field="labels") from None
    return np.asarray(v, float), np.asarray(tets, dtype=np.int64)


def _region_mesh(v, tets, surface, tol_mm, labelmap, size_mm, name):
    """The oriented Mesh of fTetWild's tissue tetrahedra, each labelled by the
    piece of the tet graph it lies in (``_assign_regions``: pieces cut by the
    faces within ``tol_mm`` of ``surface`` = (points [mm], triangles), labelled
    from ``labelmap`` = (labels, spacing, origin, direction)); the air dropped.

    Returns (mesh, labelling statistics); refuses pieces that mix labels and a
    mesh with no tissue left.
    """
    region, stats = _assign_regions(v, tets, surface[0], surface[1], tol_mm, *labelmap)
    if stats["min_purity_large_components"] < 0.9:
        raise FluoInputError("region labelling failed: a mesh piece mixes labels "
                             f"({100 * stats['min_purity_large_components']:.0f} % pure); try a "
                             "smaller epsilon or size", field="labels")
    tissue = region > 0
    if not tissue.any():
        raise FluoInputError("no tissue left after meshing: choose a smaller size",
                             field="size_mm", value=size_mm)
    return Mesh(v, tets, region, name=name).keep_elements(tissue)[0].oriented(), stats
