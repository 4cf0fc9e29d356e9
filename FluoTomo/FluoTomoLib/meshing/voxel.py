"""Fast structured meshing of a label map: voxels to tetrahedra.

The preview/fast path of FluoTomo meshing: resample the label map onto a
grid of the requested element size (majority label per cell, so small
regions keep their volume), split every tissue cell into 6 Kuhn tetrahedra
that conform across cells, and label each tetrahedron with its cell's
region.  Boundaries are staircases at the element size; for flat tissue
surfaces (a cropped phantom, a slab) the outer surface is exact.
Axis-aligned label maps only (the direction matrix must be a signed
permutation of the identity, as CBCT volumes from Slicer are).
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

from FluoTomoLib.meshing.mesh import Mesh
from FluoTomoLib.meshing.structured import kuhn_paths


def _axis_edges(lo, hi, size_mm, anchor=None, refine=None):
    """Cell edges on [lo, hi].

    Uniform (the interval split into round((hi-lo)/h) cells) unless
    ``anchor`` (a coordinate that must be an edge) or ``refine`` = (a, b,
    h_fine) (cells h_fine wide on [a, b], anchored at ``anchor`` or a) is
    given; then cells run every h from the anchor / the refined interval's
    ends, and the cells at lo and hi absorb the remainder (each between h/2
    and 3h/2 wide).
    """
    if refine is not None:
        a, b, hf = float(refine[0]), float(refine[1]), float(refine[2])
        a, b = max(a, lo), min(b, hi)
        if b - a > hf:
            c = anchor if anchor is not None and a <= anchor <= b else a
            mid = np.concatenate([c - hf * np.arange(int(np.floor((c - a) / hf)), 0, -1),
                                  c + hf * np.arange(0, int(np.floor((b - c) / hf)) + 1)])
            below = mid[0] - size_mm * np.arange(int(np.floor((mid[0] - lo) / size_mm)), 0, -1)
            above = mid[-1] + size_mm * np.arange(1, int(np.floor((hi - mid[-1]) / size_mm)) + 1)
            return _close_ends(np.concatenate([below, mid, above]), lo, hi, size_mm, hf)
    if anchor is None or not lo < anchor < hi:
        return np.linspace(lo, hi, max(1, int(round((hi - lo) / size_mm))) + 1)
    below = anchor - size_mm * np.arange(int(np.floor((anchor - lo) / size_mm)), 0, -1)
    above = anchor + size_mm * np.arange(1, int(np.floor((hi - anchor) / size_mm)) + 1)
    return _close_ends(np.concatenate([below, [anchor], above]), lo, hi, size_mm, size_mm)


def _close_ends(inner, lo, hi, size_mm, min_mm):
    """Edges lo, inner..., hi with no end cell narrower than half a cell: inner
    edges closer than that to lo or hi are dropped (the end cell widens)."""
    inner = inner[(inner - lo > 0.5 * min(size_mm, min_mm) + 1e-9)
                  & (hi - inner > 0.5 * min(size_mm, min_mm) + 1e-9)]
    return np.concatenate([[lo], inner, [hi]])


def _closest_count(cum_after, before, target):
    """How many candidates to take (0..len) so the running volume is closest to
    ``target``: ``cum_after[k-1]`` is the volume after taking k of them."""
    options = np.concatenate([[before], cum_after])
    return int(np.argmin(np.abs(options - target)))


def _cell_labels(labels_kji, spacing, origin, roi, size_mm, anchor_mm=None, refine=None,
                 edges_mm=None):
    """Label of each cell (about size_mm wide) inside roi (x0, x1, y0, y1, z0, z1),
    RAS mm; ``anchor_mm`` (x, y, z) or None: a point that is a node of the grid;
    ``refine``: per axis None or (a, b, h_fine), see _axis_edges; ``edges_mm``:
    per axis None or the grid lines themselves (clipped to the roi)."""
    lo = np.array(roi[0::2], float)
    hi = np.array(roi[1::2], float)
    if np.any(hi <= lo):
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=list(roi))
    refine = refine or (None, None, None)
    edges = [_axis_edges(lo[a], hi[a], size_mm, None if anchor_mm is None else anchor_mm[a],
                         refine[a]) for a in range(3)]
    for a, given in enumerate(edges_mm or (None, None, None)):
        if given is not None:
            g = np.asarray(given, float)
            edges[a] = np.unique(np.concatenate([[lo[a]], g[(g > lo[a]) & (g < hi[a])], [hi[a]]]))
    n_cells = np.array([len(e) - 1 for e in edges])
    # Cells narrower than a voxel (a refined band) may hold no voxel centre:
    # count sub-voxel samples instead (each voxel split s times per axis).
    s = int(np.ceil(float(np.max(spacing)) / min(float(np.min(np.diff(e))) for e in edges)))
    if s > 1:
        for ax in range(3):
            labels_kji = np.repeat(labels_kji, s, axis=ax)
        origin = origin - 0.5 * spacing + 0.5 * spacing / s
        spacing = spacing / s
    # voxel centre coordinates along each axis (x = i, y = j, z = k)
    shape_ijk = labels_kji.shape[::-1]
    centres = [origin[a] + spacing[a] * np.arange(shape_ijk[a]) for a in range(3)]
    # voxel -> cell index per axis (-1 outside the roi)
    idx = []
    for a in range(3):
        c = np.searchsorted(edges[a], centres[a], side="right") - 1
        c[(centres[a] < lo[a]) | (centres[a] >= hi[a])] = -1
        idx.append(c)
    ii, jj, kk = idx
    keep_i, keep_j, keep_k = (np.flatnonzero(v >= 0) for v in (ii, jj, kk))
    if min(len(keep_i), len(keep_j), len(keep_k)) == 0:
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=list(roi))
    sub = labels_kji[np.ix_(keep_k, keep_j, keep_i)]
    ci, cj, ck = ii[keep_i], jj[keep_j], kk[keep_k]
    if sub.min() < 0:
        raise FluoInputError("label values must be >= 0 (0 = outside)", field="labels",
                             value=int(sub.min()))
    # Count per label actually present (0, air, always first): a label value of
    # 65535 must not mean 65536 count columns per cell (3.95 GB for 4,800 voxels)
    values = np.union1d([0], np.unique(sub))
    sub = np.searchsorted(values, sub)
    n_labels = len(values)
    counts = np.zeros((n_cells[0], n_cells[1], n_cells[2], n_labels), dtype=np.int32)
    K, J, I = np.meshgrid(ck, cj, ci, indexing="ij")
    np.add.at(counts, (I.ravel(), J.ravel(), K.ravel(), sub.ravel().astype(np.int64)), 1)
    total = counts.sum(axis=3)
    # Volume-preserving labels: every tissue region, smallest first, takes the
    # cells it covers most until their volume matches its voxel volume (as the
    # phantom voxeliser does for voxels).  A plain majority vote drops thin
    # regions (a 2.4 mm tube in 1.6 mm cells loses ~40 %) and a half-cell rule
    # adds a layer at every boundary the grid does not meet.
    frac = counts / np.maximum(total, 1)[..., None]
    widths = [np.diff(e) for e in edges]
    cell_vol = (widths[0][:, None, None] * widths[1][None, :, None]
                * widths[2][None, None, :]).ravel()
    region_vol = counts.sum(axis=(0, 1, 2)) * float(np.prod(spacing))
    cell = np.zeros(total.shape, dtype=np.int64)
    taken = np.zeros(total.size, bool)
    order_r = sorted((r for r in range(1, n_labels) if region_vol[r] > 0),
                     key=lambda r: region_vol[r])
    for r in order_r:
        f = np.where(taken, -1.0, frac[..., r].ravel())
        chosen = f >= 0.5                      # the majority cells, then adjust the rim
        have = float(cell_vol[chosen].sum())
        if have < region_vol[r]:               # add the best-covered remaining cells
            cand = np.flatnonzero(~chosen & (f > 0))
            cand = cand[np.argsort(-f[cand], kind="stable")]
            k = _closest_count(have + np.cumsum(cell_vol[cand]), have, region_vol[r])
            k = max(k, 1) if not chosen.any() else k
            chosen[cand[:k]] = True
        elif have > region_vol[r]:
            # drop the least-covered partial cells; they return to the pool for the
            # regions still to come.  The last (largest) region may drop only cells
            # on the air side: one dropped at an internal interface would be a hole.
            edge = (frac[..., 0].ravel() > 0) if r == order_r[-1] else (f < 1.0)
            cand = np.flatnonzero(chosen & edge)
            cand = cand[np.argsort(f[cand], kind="stable")]
            k = _closest_count(have - np.cumsum(cell_vol[cand]), have, region_vol[r])
            k = min(k, int(chosen.sum()) - 1)
            chosen[cand[:k]] = False
        cell.ravel()[chosen] = r
        taken |= chosen
    return values[cell], edges


def mesh_labelmap_structured(labels_kji, spacing_mm, origin_mm, size_mm, roi=None,
                             direction=None, anchor_mm=None, refine=None, progress=None,
                             cancel=None, name="voxel-mesh", edges_mm=None):
    """Tetrahedral mesh of the non-zero labels of a label map.

    Parameters
    ----------
    labels_kji : (K, J, I) int label map (0 = outside)
    spacing_mm, origin_mm : voxel size and voxel-(0,0,0) centre (RAS mm)
    size_mm : edge length of the structured cells
    roi : (x0, x1, y0, y1, z0, z1) RAS mm to crop to; default: whole volume
    direction : (3, 3) IJK-to-RAS directions; must be diagonal (+-1)
    anchor_mm : (x, y, z) RAS mm, optional: a point the grid passes through
        (cells every size_mm from it, the cells at the roi's faces absorbing the
        remainder).  Anchoring at a small target's centre makes the nodes
        sample it symmetrically, so its reconstructed centre is not shifted by
        up to half a cell (see region_centroid_mm)
    refine : per axis (x, y, z) None or (a_mm, b_mm, size_mm): a band [a, b]
        with smaller cells (the grid stays rectilinear, so the band runs
        through the whole roi along the other axes; refine only the axes a
        target is thin in)
    edges_mm : per axis (x, y, z) None or increasing grid-line coordinates
        [mm] (e.g. ``structured.optode_axis``: fine at the optodes, coarse
        away from them); they replace that axis's uniform lines

    Returns
    -------
    Mesh with ``element_region`` = label; ``meta["seconds"]``.
    """
    t0 = time.perf_counter()
    labels = np.asarray(labels_kji)
    if labels.ndim != 3:
        raise FluoInputError("label map must be 3D", field="labels", value=labels.shape)
    if not np.any(labels > 0):
        raise FluoInputError("label map is empty (no non-zero label)", field="labels")
    spacing = np.asarray(spacing_mm, float)
    origin = np.asarray(origin_mm, float)
    if direction is not None:
        d = np.asarray(direction, float)
        if not np.allclose(np.abs(d), np.eye(3)):
            raise FluoInputError("the structured mesher needs an axis-aligned label map",
                                 field="direction", value=d.tolist())
        # flip axes with negative direction so coordinates increase with index
        for a in range(3):
            if d[a, a] < 0:
                labels = np.flip(labels, axis=2 - a)
                origin = origin.copy()
                origin[a] = origin[a] - spacing[a] * (labels.shape[2 - a] - 1)
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise FluoInputError("element size must be > 0", field="size_mm", value=size_mm)
    extent_lo = origin - 0.5 * spacing
    extent_hi = origin + spacing * (np.array(labels.shape[::-1]) - 0.5)
    if roi is None:
        roi = (extent_lo[0], extent_hi[0], extent_lo[1], extent_hi[1], extent_lo[2], extent_hi[2])
    roi = np.asarray(roi, float)
    if roi.shape != (6,) or np.any(roi[1::2] <= roi[0::2]):
        raise FluoInputError("roi must be x0,x1,y0,y1,z0,z1 with x0<x1 etc.", field="roi",
                             value=roi.tolist())
    roi = np.clip(roi, np.repeat(extent_lo, 2), np.repeat(extent_hi, 2))
    if np.any(roi[1::2] <= roi[0::2]):
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=roi.tolist())
    across = float(np.max(roi[1::2] - roi[0::2]))
    if size_mm > across:
        # one cell would hold everything: a mesh, but of nothing the label map says
        raise FluoInputError(f"element size is larger than the label map ({across:.3g} mm "
                             "across)", field="size_mm", value=size_mm)
    n_est = np.prod((roi[1::2] - roi[0::2]) / size_mm) * (8 if refine is not None else 1)
    if n_est > 3e6:
        raise FluoInputError(f"about {n_est:.3g} cells: choose a larger element size or a "
                             "smaller roi", field="size_mm", value=size_mm)
    report(progress, 0.1, "resampling labels")
    if anchor_mm is not None:
        anchor_mm = np.asarray(anchor_mm, float)
        if anchor_mm.shape != (3,) or not np.all(np.isfinite(anchor_mm)):
            raise FluoInputError("anchor must be a finite x, y, z point", field="anchor_mm",
                                 value=np.ravel(anchor_mm).tolist())
    if refine is not None:
        refine = list(refine)
        if len(refine) != 3 or any(r is not None and (len(r) != 3 or not r[2] > 0
                                                     or not r[1] > r[0]) for r in refine):
            raise FluoInputError("refine must be three entries of None or (a_mm, b_mm, "
                                 "size_mm) with a < b, size > 0", field="refine", value=refine)
    if edges_mm is not None:
        if len(edges_mm) != 3 or any(e is not None and (np.ndim(e) != 1 or len(e) < 2
                                                        or not np.all(np.isfinite(e))
                                                        or np.any(np.diff(e) <= 0))
                                     for e in edges_mm):
            raise FluoInputError("edges must be three entries of None or increasing finite "
                                 "coordinates", field="edges_mm")
        n_est = np.prod([len(e) if e is not None else (roi[2 * a + 1] - roi[2 * a]) / size_mm
                         for a, e in enumerate(edges_mm)])
        if n_est > 3e6:
            raise FluoInputError(f"about {n_est:.3g} cells: coarser grading or a smaller roi",
                                 field="edges_mm")
    cell, edges = _cell_labels(labels, spacing, origin, roi, size_mm, anchor_mm, refine, edges_mm)
    check_cancel(cancel)
    ci, cj, ck = np.nonzero(cell > 0)
    if len(ci) == 0:
        raise FluoInputError("no tissue inside the roi at this element size", field="roi",
                             value=roi.tolist())
    report(progress, 0.4, "building tetrahedra")
    shape = tuple(len(e) for e in edges)
    node_id = lambda i, j, k: (i * shape[1] + j) * shape[2] + k  # noqa: E731
    tets = np.concatenate([np.stack([node_id(ci + a, cj + b, ck + c) for a, b, c in path], axis=1)
                           for path in kuhn_paths()])
    region = np.tile(cell[ci, cj, ck], 6)
    used, inverse = np.unique(tets, return_inverse=True)
    X, Y, Z = np.meshgrid(*edges, indexing="ij")
    all_nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    mesh = Mesh(all_nodes[used], inverse.reshape(-1, 4), region, name=name).oriented()
    mesh.meta["seconds"] = time.perf_counter() - t0
    mesh.meta["method"] = "structured"
    mesh.meta["size_mm"] = float(size_mm)
    mesh.meta["roi"] = roi.tolist()
    if anchor_mm is not None or refine is not None or edges_mm is not None:
        mesh.meta["edges_mm"] = [e.tolist() for e in edges]   # the grid lines (non-uniform)
    report(progress, 1.0, "mesh done")
    return mesh


def labelmap_region_volumes(labels_kji, spacing_mm, roi=None, origin_mm=None):
    """Volume [mm^3] of each non-zero label (optionally inside an roi)."""
    labels = np.asarray(labels_kji)
    spacing = np.asarray(spacing_mm, float)
    if roi is not None:
        origin = np.asarray(origin_mm, float)
        sel = []
        for a in range(3):
            c = origin[a] + spacing[a] * np.arange(labels.shape[2 - a])
            sel.append((c >= roi[2 * a]) & (c < roi[2 * a + 1]))
        labels = labels[np.ix_(sel[2], sel[1], sel[0])]
    vals, counts = np.unique(labels, return_counts=True)
    vox = float(np.prod(spacing))
    return {int(v): float(c * vox) for v, c in zip(vals, counts) if v != 0}


def node_labels_from_labelmap(nodes_mm, labels_kji, spacing_mm, origin_mm, radius_mm=0.0):
    """Label of each node from the label map: the highest label within
    ``radius_mm`` of the node (axis-aligned box), so a target thinner than the
    mesh spacing still owns the nodes around it (what a prior needs).
    Nodes outside the label map get 0."""
    from scipy import ndimage

    labels = np.asarray(labels_kji)
    spacing = np.asarray(spacing_mm, float)
    if radius_mm > 0:
        size = [2 * int(np.ceil(radius_mm / s)) + 1 for s in spacing[::-1]]
        labels = ndimage.maximum_filter(labels, size=size)
    ijk = np.round((np.asarray(nodes_mm, float) - np.asarray(origin_mm, float)) / spacing).astype(int)
    shape_ijk = np.array(labels.shape[::-1])
    inside = np.all((ijk >= 0) & (ijk < shape_ijk), axis=1)
    out = np.zeros(len(ijk), dtype=np.int64)
    i, j, k = ijk[inside].T
    out[inside] = labels[k, j, i]
    return out


def nodal_volumes(mesh):
    """Lumped volume [mm^3] of each node: a share 1/(d+1) of every element around it."""
    v = np.zeros(mesh.n_nodes)
    np.add.at(v, mesh.elements.ravel(), np.repeat(mesh.measures / (mesh.dim + 1), mesh.dim + 1))
    return v


def node_regions_volume_preserving(mesh, labels_kji, spacing_mm, origin_mm, background=1):
    """Region of each node of a (coarse) mesh such that every region's nodes carry
    its label-map volume.

    A region's nodal basis sum_n phi_n integrates to the nodes' lumped
    volumes; labelling nodes by the voxel under them makes a thin target's
    share jump with where the grid falls (a 2.4 mm tube on a 1.5 mm mesh gets
    one or two node rows: +-60 % in a hard-prior yield).  Here nodes are
    ranked by how much of their cell the region covers, and the best-covered
    ones are taken until their volumes add up to the region's volume inside
    the mesh.  The remaining nodes get ``background``.
    """
    from scipy import ndimage

    labels = np.asarray(labels_kji)
    spacing = np.asarray(spacing_mm, float)
    origin = np.asarray(origin_mm, float)
    h = float(mesh.meta.get("size_mm", np.median(mesh.measures) ** (1 / mesh.dim)))
    size = [max(1, int(round(h / s))) for s in spacing[::-1]]
    ijk = np.round((mesh.nodes_mm - origin) / spacing).astype(int)
    ijk = np.clip(ijk, 0, np.array(labels.shape[::-1]) - 1)
    vol = nodal_volumes(mesh)
    lo, hi = mesh.bounds()
    region_out = np.full(mesh.n_nodes, background, dtype=np.int64)
    taken = np.zeros(mesh.n_nodes, bool)
    labs = [int(v) for v in np.unique(labels) if v not in (0, background)]
    voxel = float(np.prod(spacing))
    # label-map volume inside the mesh's bounding box
    sel = [slice(max(0, int(np.floor((lo[a] - origin[a]) / spacing[a]))),
                 int(np.ceil((hi[a] - origin[a]) / spacing[a])) + 1) for a in range(3)]
    inside = labels[sel[2], sel[1], sel[0]]
    targets = {r: np.count_nonzero(inside == r) * voxel for r in labs}
    for r in sorted(labs, key=lambda k: targets[k]):
        if targets[r] == 0:
            continue
        cover = ndimage.uniform_filter((labels == r).astype(np.float32), size=size)
        c = cover[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        c[taken] = -1
        order = np.argsort(-c, kind="stable")
        order = order[c[order] > 0]
        cum = np.cumsum(vol[order])
        k = int(np.argmin(np.abs(cum - targets[r]))) + 1
        region_out[order[:k]] = r
        taken[order[:k]] = True
    return region_out


def region_centroid_mm(labels_kji, spacing_mm, origin_mm, label=None, direction=None):
    """Centre [RAS mm] of one label's voxels; by default of the smallest
    non-zero label other than 1 (the target inside the background tissue), or
    of label 1 when it is the only one.  Used to anchor a reconstruction grid."""
    labels = np.asarray(labels_kji)
    present, counts = np.unique(labels[labels > 0], return_counts=True)
    if len(present) == 0:
        raise FluoInputError("label map is empty (no non-zero label)", field="labels")
    if label is None:
        others = present != 1
        label = (present[others][np.argmin(counts[others])] if others.any() else present[0])
    k, j, i = np.nonzero(labels == label)
    if len(k) == 0:
        raise FluoInputError("label is not in the label map", field="label", value=int(label))
    ijk = np.array([i.mean(), j.mean(), k.mean()])
    d = np.eye(3) if direction is None else np.asarray(direction, float)
    return np.asarray(origin_mm, float) + d @ (ijk * np.asarray(spacing_mm, float))


def target_refinement(labels_kji, spacing_mm, origin_mm, roi, size_mm, margin_mm, label=None):
    """``refine`` bands for mesh_labelmap_structured around a small target:
    its label-map bounding box plus ``margin_mm``, on the axes where it is
    thinner than half the roi (a tube along x is refined in y and z only, so
    the rectilinear grid does not refine the whole roi along the tube)."""
    labels = np.asarray(labels_kji)
    if label is None:
        present, counts = np.unique(labels[labels > 1], return_counts=True)
        if len(present) == 0:
            return None
        label = present[np.argmin(counts)]
    k, j, i = np.nonzero(labels == label)
    ijk = np.stack([i, j, k], axis=1)
    lo = np.asarray(origin_mm, float) + (ijk.min(axis=0) - 0.5) * np.asarray(spacing_mm, float)
    hi = np.asarray(origin_mm, float) + (ijk.max(axis=0) + 0.5) * np.asarray(spacing_mm, float)
    roi = np.asarray(roi, float)
    out = []
    for a in range(3):
        if hi[a] - lo[a] < 0.5 * (roi[2 * a + 1] - roi[2 * a]):
            out.append((lo[a] - margin_mm, hi[a] + margin_mm, float(size_mm)))
        else:
            out.append(None)
    return out
