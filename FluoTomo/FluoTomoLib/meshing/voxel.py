"""Fast structured meshing of a label map: voxels to tetrahedra.

The preview/fast path of FluoTomo meshing: resample the label map onto a
grid of the requested element size (majority label per cell, so small
regions keep their volume), split every tissue cell into 6 Kuhn tetrahedra
that conform across cells, and label each tetrahedron with its cell's
region.  Boundaries are staircases at the element size; for flat tissue
surfaces (a cropped phantom, a slab) the outer surface is exact.
Any orthonormal IJK-to-RAS direction: a label map whose axes run along RAS
(identity, ``diag(-1, -1, 1)``, swapped axes) is re-indexed and meshed in RAS;
an oblique one is meshed on its own voxel axes and rotated into RAS.
Region volumes are kept to the label map's (exact voxel-cell overlaps, then
a volume-matching assignment) and checked: ``mesh.meta["volume_error_pct"]``.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

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
    if refine is not None and len(refine) and not np.isscalar(refine[0]):
        return _nested_edges(lo, hi, size_mm, anchor, refine)
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


def _nested_edges(lo, hi, size_mm, anchor, bands):
    """Edges on [lo, hi] with several bands [(a, b, h), ...] of smaller cells
    (where bands overlap the finest wins), all on one grid through ``anchor``
    (or lo): every level's lines are anchor + k h, so nested sizes in ratios
    of 2 share their lines and a transition is clean; where they do not, a
    line closer than half the local size to the previous one is dropped."""
    c = float(anchor) if anchor is not None and lo <= anchor <= hi else float(lo)
    levels = sorted(((max(float(a), lo), min(float(b), hi), float(h)) for a, b, h in bands
                     if min(float(b), hi) > max(float(a), lo)), key=lambda t: t[2])
    levels.append((lo, hi, float(size_mm)))
    pts, covered = [], []
    for a, b, h in levels:
        g = c + h * np.arange(np.ceil((a - c) / h - 1e-9), np.floor((b - c) / h + 1e-9) + 1)
        keep = np.ones(len(g), bool)
        for ca, cb in covered:
            keep &= ~((g > ca + 1e-9) & (g < cb - 1e-9))
        pts.append(g[keep])
        covered.append((a, b))

    def local(x):
        return min([h for a, b, h in levels if a - 1e-9 <= x <= b + 1e-9] or [size_mm])

    inner = np.unique(np.concatenate(pts))
    kept = []
    for x in inner:
        prev = kept[-1] if kept else lo
        if x - prev >= 0.5 * min(local(x), local(prev)) - 1e-9:
            kept.append(x)
    return _close_ends(np.array(kept), lo, hi, size_mm, min(h for _, _, h in levels))


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


def overlap_matrix(edges, centres, voxel_mm):
    """(cells, voxels) length [mm] of every voxel [c - s/2, c + s/2] inside every
    cell [e_j, e_j+1] along one axis (zero where they do not meet)."""
    e = np.asarray(edges, float)
    c = np.asarray(centres, float)
    lo = np.maximum(e[:-1, None], c[None, :] - 0.5 * voxel_mm)
    hi = np.minimum(e[1:, None], c[None, :] + 0.5 * voxel_mm)
    return np.clip(hi - lo, 0.0, None)


def region_cell_volumes(labels_kji, spacing, origin, edges, labels=None):
    """Exact volume [mm^3] of every label map region inside every cell of a
    rectilinear grid: the voxels are boxes, so a voxel's share of a cell is the
    product of its 1D overlaps on the three axes (no sampling, no aliasing
    between voxel and cell sizes).

    Returns (labels, V) with V (nx, ny, nz, R) for the non-zero ``labels``
    (default: every non-zero label present)."""
    lab = np.asarray(labels_kji)
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    shape_ijk = lab.shape[::-1]
    W = []
    keep = []
    for a in range(3):
        c = origin[a] + spacing[a] * np.arange(shape_ijk[a])
        w = overlap_matrix(edges[a], c, spacing[a])
        used = np.flatnonzero(w.sum(axis=0) > 0)      # voxels that touch the grid
        keep.append(used)
        W.append(w[:, used])
    if min(len(k) for k in keep) == 0:
        return [], np.zeros(tuple(len(e) - 1 for e in edges) + (0,))
    sub = lab[np.ix_(keep[2], keep[1], keep[0])]
    if labels is None:
        labels = [int(v) for v in np.unique(sub) if v != 0]
    out = np.zeros(tuple(len(e) - 1 for e in edges) + (len(labels),))
    for r, value in enumerate(labels):
        ind = (sub == value).astype(np.float32)          # (k, j, i)
        if not ind.any():
            continue
        t = np.tensordot(ind, W[0], axes=([2], [1]))      # (k, j, nx)
        t = np.tensordot(t, W[1], axes=([1], [1]))        # (k, nx, ny)
        t = np.tensordot(t, W[2], axes=([0], [1]))        # (nx, ny, nz)
        out[..., r] = t
    return list(labels), out


def grid_edges(roi, size_mm, anchor_mm=None, refine=None, edges_mm=None):
    """Cell edges per axis of the structured grid over ``roi`` (x0, x1, y0, y1,
    z0, z1): about ``size_mm`` wide, through ``anchor_mm``, refined per axis
    (see _axis_edges); ``edges_mm``: per axis None or the grid lines
    themselves (clipped to the roi)."""
    lo = np.array(roi[0::2], float)
    hi = np.array(roi[1::2], float)
    refine = refine or (None, None, None)
    edges = [_axis_edges(lo[a], hi[a], size_mm, None if anchor_mm is None else anchor_mm[a],
                         refine[a]) for a in range(3)]
    for a, given in enumerate(edges_mm or (None, None, None)):
        if given is not None:
            g = np.asarray(given, float)
            edges[a] = np.unique(np.concatenate([[lo[a]], g[(g > lo[a]) & (g < hi[a])], [hi[a]]]))
    return edges


def _cell_labels(labels_kji, spacing, origin, roi, edges):
    """Label of each cell of the grid ``edges`` inside roi (x0, x1, y0, y1, z0, z1).

    Returns (cell labels (nx, ny, nz), edges, {label: label-map volume inside
    the roi [mm^3]}, partial cells)."""
    lo = np.array(roi[0::2], float)
    hi = np.array(roi[1::2], float)
    if np.any(hi <= lo):
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=list(roi))
    region_labels, V = region_cell_volumes(labels_kji, spacing, origin, edges)
    if not region_labels:
        raise FluoInputError("region of interest does not overlap the label map", field="roi",
                             value=list(roi))
    widths = [np.diff(e) for e in edges]
    cell_vol = (widths[0][:, None, None] * widths[1][None, :, None]
                * widths[2][None, None, :])
    # Volume-preserving labels: every tissue region, smallest first, takes the
    # cells it covers most until their volume matches its label-map volume
    # inside the roi (the voxels' exact overlap with the roi, so a roi face
    # through a voxel counts the part of it inside).  A plain majority vote
    # drops thin regions (a 2.4 mm tube in 1.6 mm cells loses ~40 %) and a
    # half-cell rule adds a layer at every boundary the grid does not meet.
    # Cell fractions are exact volume shares, not voxel-centre counts: counting
    # centres aliased a 0.8 mm label map on a 1.0 mm grid (cells holding one or
    # two voxel centres per axis) into +59 % of a 2.4 mm tube's volume.
    frac = V / cell_vol[..., None]
    air = np.clip(1.0 - frac.sum(axis=-1), 0.0, 1.0).ravel()
    region_vol = V.sum(axis=(0, 1, 2))
    cell, partial = _assign_cells(frac.reshape(-1, len(region_labels)), cell_vol.ravel(), air,
                                  region_vol, region_labels)
    volumes = {int(region_labels[r]): float(region_vol[r]) for r in range(len(region_labels))
               if region_vol[r] > 0}
    return cell.reshape(frac.shape[:3]), edges, volumes, partial


def _assign_cells(frac, cell_vol, air, region_vol, region_labels):
    """Volume-matching region of every cell, smallest region first.

    A region takes the cells it covers most (majority first), then adds or
    drops rim cells until its volume is closest to its label-map volume; what
    is left (less than one cell) is matched by giving some of one rim cell's 6
    tetrahedra to the region (``partial``: {cell: (label, k)}: k of its
    tetrahedra carry ``label``, the others the cell's label), so a region a
    few cells across is kept within 1/12 of a cell of its volume.  The last
    (largest) region may give back only cells on the air side: one dropped at
    an internal interface would be a hole.
    """
    n_cells = len(cell_vol)
    cell = np.zeros(n_cells, dtype=np.int64)
    avail = cell_vol.copy()            # volume of each cell not yet given to a region
    partial = {}
    order_r = sorted((r for r in range(len(region_labels)) if region_vol[r] > 0),
                     key=lambda r: region_vol[r])
    for r in order_r:
        label = int(region_labels[r])
        free = avail > 1e-12 * cell_vol
        f = np.where(free, frac[:, r], -1.0)
        chosen = f >= 0.5                      # the majority cells, then adjust the rim
        have = float(avail[chosen].sum())
        last = r == order_r[-1]
        if have < region_vol[r]:               # add the best-covered remaining cells
            cand = np.flatnonzero(~chosen & (f > 0))
            cand = cand[np.argsort(-f[cand], kind="stable")]
            k = _closest_count(have + np.cumsum(avail[cand]), have, region_vol[r])
            k = max(k, 1) if not chosen.any() else k
            chosen[cand[:k]] = True
            have = float(avail[chosen].sum())
        else:
            # drop the least-covered partial cells; they return to the pool for the
            # regions still to come
            edge = (air > 1e-9) if last else (f < 1.0 - 1e-12)
            cand = np.flatnonzero(chosen & edge)
            cand = cand[np.argsort(f[cand], kind="stable")]
            k = _closest_count(have - np.cumsum(avail[cand]), have, region_vol[r])
            k = min(k, int(chosen.sum()) - 1)
            chosen[cand[:k]] = False
            have = float(avail[chosen].sum())
        cell[chosen] = label
        avail[chosen] = 0.0
        # the remainder, to a sixth of a cell: some tetrahedra of one rim cell
        missing = region_vol[r] - have
        if missing > 0:     # the best-covered whole free cell gives some tetrahedra
            pool = np.flatnonzero(~chosen & (f > 0) & (avail == cell_vol))
            pool = pool[np.argsort(-f[pool], kind="stable")]
        else:               # the least-covered rim cell keeps only some
            edge = (air > 1e-9) if last else (f < 1.0 - 1e-12)
            pool = np.flatnonzero(chosen & edge & (avail == 0.0))
            pool = pool[np.argsort(f[pool], kind="stable")]
        pool = [c for c in pool if int(c) not in partial]
        if pool:
            c = int(pool[0])
            k6 = int(round(6.0 * abs(missing) / cell_vol[c]))
            if missing > 0 and 0 < k6 < 6:
                partial[c] = (label, k6)
                avail[c] = cell_vol[c] * (6 - k6) / 6.0
            elif missing < 0 and 0 < k6 < 6:
                # the cell keeps 6 - k6 tetrahedra of this region; the others are free
                cell[c] = 0
                partial[c] = (label, 6 - k6)
                avail[c] = cell_vol[c] * k6 / 6.0
        # a later region claiming a partly given cell fills its free tetrahedra
    # free tetrahedra no region claimed: the region covering most of the cell
    # (never air inside tissue; a share of a cell of the largest region)
    for c, (label, _) in partial.items():
        if cell[c] == 0 and air[c] < 0.5:
            others = [r for r in range(len(region_labels))
                      if int(region_labels[r]) != label and frac[c, r] > 0]
            if others:
                cell[c] = int(region_labels[max(others, key=lambda r: frac[c, r])])
    # whole cells inside the tissue that no region kept: a smaller region dropped
    # a rim cell (its volume matched without it) that the region sharing it did
    # not claim (under half its own): a hole, whose faces the model took for skin
    # (a Robin boundary inside the tissue: the fields at a 7 mm deep inclusion
    # fell 12 % between 0.75 and 0.7 mm elements). The largest region sharing the
    # cell takes it (the smaller regions keep their matched volumes)
    if order_r:
        hole = np.flatnonzero((cell == 0) & (air <= 1e-9) & (avail > 1e-12 * cell_vol))
        hole = np.array([c for c in hole if int(c) not in partial], dtype=np.int64)
        if len(hole):
            sub = frac[hole][:, order_r]            # smallest region first
            share = sub > 0
            last = len(order_r) - 1 - np.argmax(share[:, ::-1], axis=1)
            cell[hole] = np.asarray(region_labels)[np.asarray(order_r)[last]]
    return cell, partial


class MeshFidelityWarning(UserWarning):
    """A region's volume in the mesh is off its label-map volume by more than
    :data:`VOLUME_WARN_PCT`."""


#: above this |region volume error| [%] the structured mesher warns (and says so
#: in ``mesh.meta["warnings"]``); it keeps every region within 1 % at element
#: sizes 0.5-2 mm on the phantoms (Testing: test_voxel_mesh.py)
VOLUME_WARN_PCT = 2.0

#: most cells one structured mesh may have (6 tetrahedra each; ~3 GB of work)
MAX_CELLS = 3_000_000

#: the peak memory the structured mesher adds per tetrahedron of tissue [bytes]:
#: node ids (int64), np.unique's sort and inverse, node coordinates, orientation
#: and the volume report. Measured (``fluo mesh --fast``, /usr/bin/time -v, peak
#: less the 0.43 GB of imports; the 0.8 mm cylinder-tube label map at 1, 0.6 and
#: 0.45 mm: 0.75, 3.5 and 8.4 million tetrahedra): 435, 415 and 397 B; 500 is
#: 1.15-1.26x that (docs/reliability.md, "Memory estimates")
STRUCTURED_BYTES_PER_TET = 500.0


def _check_memory(labels, spacing, extent_lo, roi, n_cells, size_mm):
    """Refuse a structured mesh whose estimated peak does not fit, before the
    grid is built: 6 tetrahedra per cell, times the tissue's share of the label
    map inside the roi (its voxels counted: cheap next to the meshing)."""
    from fluoguide.memory import check_fits

    shape_ijk = np.array(labels.shape[::-1])
    i0 = np.clip(np.floor((roi[0::2] - extent_lo) / spacing), 0, shape_ijk).astype(int)
    i1 = np.clip(np.ceil((roi[1::2] - extent_lo) / spacing), i0 + 1, shape_ijk).astype(int)
    sub = labels[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]]
    tissue = np.count_nonzero(sub) / max(sub.size, 1)
    tets = 6.0 * n_cells * tissue
    check_fits(STRUCTURED_BYTES_PER_TET * tets,
               f"a structured mesh of {tets / 1e6:.1f} million tetrahedra "
               f"({size_mm:g} mm cells)",
               "choose a larger element size or a smaller region of interest",
               field="size_mm", value=size_mm)


def check_direction(direction, field="direction"):
    """An IJK-to-RAS direction matrix as a (3, 3) array: orthonormal (a rotation,
    or a rotation and a reflection, as every scanner's volume is); anything else
    is refused."""
    d = np.eye(3) if direction is None else np.asarray(direction, float)
    if d.shape != (3, 3) or not np.all(np.isfinite(d)):
        raise FluoInputError("direction must be a finite 3x3 matrix", field=field,
                             value=np.ravel(d).tolist())
    if not np.allclose(d.T @ d, np.eye(3), atol=1e-5):
        raise FluoInputError("direction matrix is not orthonormal (skewed or scaled axes)",
                             field=field, value=np.round(d, 6).tolist())
    return d


def signed_permutation(direction):
    """True when each IJK axis runs along one RAS axis (either way): the label map
    can be re-indexed to run along x, y, z without resampling."""
    d = np.asarray(direction, float)
    return bool(np.allclose(np.abs(d) @ np.ones(3), 1.0) and np.all(
        np.isclose(np.abs(d), 0.0) | np.isclose(np.abs(d), 1.0))
        and np.allclose(np.abs(d).sum(axis=0), 1.0))


def axis_aligned_labelmap(labels_kji, spacing_mm, origin_mm, direction):
    """Re-index a label map whose direction is a signed permutation so that its
    index axes i, j, k run along +x, +y, +z (RAS).  Returns (labels_kji,
    spacing_mm, origin_mm) with the same voxels at the same RAS positions."""
    d = check_direction(direction)
    if not signed_permutation(d):
        raise FluoInputError("the label map's axes are oblique to RAS", field="direction",
                             value=np.round(d, 6).tolist())
    lab_ijk = np.asarray(labels_kji).transpose(2, 1, 0)
    spacing = np.asarray(spacing_mm, float)
    origin = np.asarray(origin_mm, float)
    axis = [int(np.argmax(np.abs(d[r]))) for r in range(3)]   # IJK axis along RAS r
    out = lab_ijk.transpose(axis)
    new_spacing = spacing[axis]
    new_origin = origin.copy()
    for r in range(3):
        if d[r, axis[r]] < 0:
            out = np.flip(out, axis=r)
            new_origin[r] = origin[r] - spacing[axis[r]] * (lab_ijk.shape[axis[r]] - 1)
    return np.ascontiguousarray(out.transpose(2, 1, 0)), new_spacing, new_origin


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
    direction : (3, 3) IJK-to-RAS direction cosines (columns = I, J, K axes), any
        orthonormal matrix.  When each axis runs along an RAS axis (identity,
        ``diag(-1, -1, 1)``, axis swaps) the grid is built in RAS; an oblique
        label map is meshed on its own voxel axes and the nodes are rotated
        into RAS (``roi``, ``anchor_mm`` and ``refine`` are then refused: they
        are boxes in RAS)
    anchor_mm : (x, y, z) RAS mm, optional: a point the grid passes through
        (cells every size_mm from it, the cells at the roi's faces absorbing the
        remainder).  Anchoring at a small target's centre makes the nodes
        sample it symmetrically, so its reconstructed centre is not shifted by
        up to half a cell (see region_centroid_mm)
    refine : per axis (x, y, z) None, (a_mm, b_mm, size_mm): a band [a, b]
        with smaller cells (the grid stays rectilinear, so the band runs
        through the whole roi along the other axes; refine only the axes a
        target is thin in), or a list of such bands (nested: the finest wins)
    edges_mm : per axis (x, y, z) None or increasing grid-line coordinates
        [mm] (e.g. ``structured.optode_axis``: fine at the optodes, coarse
        away from them); they replace that axis's lines (RAS, like ``roi``)

    Returns
    -------
    Mesh with ``element_region`` = label; ``meta``: ``seconds``,
    ``labelmap_volumes_mm3`` (each region's label-map volume inside the roi),
    ``volume_error_pct`` (mesh against label map, per region) and ``warnings``
    (regions off by more than VOLUME_WARN_PCT, also issued as
    MeshFidelityWarning).
    """
    t0 = time.perf_counter()
    labels, spacing, origin = _checked_labelmap(labels_kji, spacing_mm, origin_mm)
    labels, spacing, origin, rotate = _voxel_frame(labels, spacing, origin, direction,
                                                   ras_boxes=(roi, anchor_mm, refine, edges_mm))
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise FluoInputError("element size must be > 0", field="size_mm", value=size_mm)
    extent_lo = origin - 0.5 * spacing
    extent_hi = origin + spacing * (np.array(labels.shape[::-1]) - 0.5)
    roi = _checked_roi(roi, extent_lo, extent_hi, size_mm)
    report(progress, 0.1, "resampling labels")
    anchor_mm, refine = _checked_grid_options(anchor_mm, refine, edges_mm)
    edges = grid_edges(roi, size_mm, anchor_mm, refine, edges_mm)
    n_cells = int(np.prod([len(e) - 1 for e in edges]))
    if n_cells > MAX_CELLS:
        raise FluoInputError(f"{n_cells:.3g} cells: choose a larger element size, a smaller roi "
                             "or a narrower refinement", field="size_mm", value=size_mm)
    _check_memory(labels, spacing, extent_lo, roi, n_cells, size_mm)
    cell, edges, volumes, partial = _cell_labels(labels, spacing, origin, roi, edges)
    check_cancel(cancel)
    report(progress, 0.4, "building tetrahedra")
    tets, region = _cells_to_tets(cell, edges, partial, labels, spacing, origin)
    if len(tets) == 0:
        raise FluoInputError("no tissue inside the roi at this element size", field="roi",
                             value=roi.tolist())
    mesh = _grid_mesh(tets, region, edges, rotate, name)
    mesh.meta["seconds"] = time.perf_counter() - t0
    # "structured" (grid) meshes get the geometric ordering; a rotated grid's
    # planes are not coordinate planes, so it keeps METIS
    mesh.meta["method"] = "structured" if rotate is None else "structured-rotated"
    mesh.meta["size_mm"] = float(size_mm)
    if rotate is None:
        mesh.meta["roi"] = roi.tolist()
        if anchor_mm is not None or refine is not None or edges_mm is not None:
            mesh.meta["edges_mm"] = [e.tolist() for e in edges]   # the grid lines (non-uniform)
    _record_fidelity(mesh, volumes)
    report(progress, 1.0, "mesh done")
    return mesh


def _checked_labelmap(labels_kji, spacing_mm, origin_mm):
    """The label map, spacing and origin as arrays, refused unless 3D, non-empty
    and non-negative with three positive spacings [mm] and a finite origin [mm]."""
    labels = np.asarray(labels_kji)
    if labels.ndim != 3:
        raise FluoInputError("label map must be 3D", field="labels", value=labels.shape)
    if not np.any(labels > 0):
        raise FluoInputError("label map is empty (no non-zero label)", field="labels")
    if labels.min() < 0:
        raise FluoInputError("label values must be >= 0 (0 = outside)", field="labels",
                             value=int(labels.min()))
    spacing = np.asarray(spacing_mm, float)
    origin = np.asarray(origin_mm, float)
    if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise FluoInputError("spacing must be three positive numbers (mm)", field="spacing",
                             value=np.ravel(spacing).tolist())
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise FluoInputError("origin must be three finite numbers (mm)", field="origin",
                             value=np.ravel(origin).tolist())
    return labels, spacing, origin


def _voxel_frame(labels, spacing, origin, direction, ras_boxes):
    """The frame the grid is built in: (labels, spacing, origin, rotate).

    A label map whose axes run along RAS is re-indexed into RAS (``rotate`` is
    None); an oblique one keeps its voxel axes with the origin at 0, and
    ``rotate`` = (origin [mm], direction) takes the nodes into RAS afterwards.
    ``ras_boxes`` (roi, anchor, refine, edges) must then all be None: they are
    given in RAS.
    """
    if direction is None:
        return labels, spacing, origin, None
    d = check_direction(direction)
    if signed_permutation(d):
        labels, spacing, origin = axis_aligned_labelmap(labels, spacing, origin, d)
        return labels, spacing, origin, None
    if any(b is not None for b in ras_boxes):
        raise FluoInputError("roi, anchor and refinement are RAS boxes: they need a "
                             "label map whose axes run along RAS (this one is oblique)",
                             field="direction", value=np.round(d, 6).tolist())
    return labels, spacing, np.zeros(3), (origin, d)   # mesh on the voxel axes, then rotate


def _checked_roi(roi, extent_lo, extent_hi, size_mm):
    """The roi (x0, x1, y0, y1, z0, z1) [mm] clipped to the label map's extent
    (default: all of it), refused when it misses the map, is narrower than one
    cell of ``size_mm`` or would hold too many cells to build."""
    if roi is None:
        roi = (extent_lo[0], extent_hi[0], extent_lo[1], extent_hi[1], extent_lo[2], extent_hi[2])
    roi = np.asarray(roi, float)
    if roi.shape != (6,) or not np.all(np.isfinite(roi)) or np.any(roi[1::2] <= roi[0::2]):
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
    n_est = np.prod((roi[1::2] - roi[0::2]) / size_mm)
    if n_est > 3e6:           # before building edges that would not fit either
        raise FluoInputError(f"about {n_est:.3g} cells: choose a larger element size or a "
                             "smaller roi", field="size_mm", value=size_mm)
    return roi


def _checked_grid_options(anchor_mm, refine, edges_mm):
    """(anchor_mm as an array or None, refine as a list or None), refused unless
    the anchor is a finite point, ``refine`` three entries of None, a band
    (a_mm, b_mm, size_mm) or a list of bands, and ``edges_mm`` three entries of
    None or increasing finite coordinates [mm]."""
    if anchor_mm is not None:
        anchor_mm = np.asarray(anchor_mm, float)
        if anchor_mm.shape != (3,) or not np.all(np.isfinite(anchor_mm)):
            raise FluoInputError("anchor must be a finite x, y, z point", field="anchor_mm",
                                 value=np.ravel(anchor_mm).tolist())
    if refine is not None:
        refine = list(refine)

        def _band_ok(t):
            return len(t) == 3 and t[2] > 0 and t[1] > t[0]

        def _axis_ok(r):
            if r is None:
                return True
            if len(r) and not np.isscalar(r[0]):          # several bands
                return all(_band_ok(t) for t in r)
            return _band_ok(r)

        if len(refine) != 3 or not all(_axis_ok(r) for r in refine):
            raise FluoInputError("refine must be three entries of None, (a_mm, b_mm, size_mm) "
                                 "or a list of them, with a < b, size > 0", field="refine",
                                 value=refine)
    if edges_mm is not None:
        if len(edges_mm) != 3 or any(e is not None and (np.ndim(e) != 1 or len(e) < 2
                                                        or not np.all(np.isfinite(e))
                                                        or np.any(np.diff(e) <= 0))
                                     for e in edges_mm):
            raise FluoInputError("edges must be three entries of None or increasing finite "
                                 "coordinates", field="edges_mm")
    return anchor_mm, refine


def _grid_mesh(tets, region, edges, rotate, name):
    """The oriented Mesh of the tetrahedra ``tets`` (indices into the grid nodes
    of ``edges`` [mm], z fastest), keeping only the nodes they use; the nodes
    are rotated into RAS when ``rotate`` = (origin [mm], direction) is given."""
    used, inverse = np.unique(tets, return_inverse=True)
    X, Y, Z = np.meshgrid(*edges, indexing="ij")
    all_nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    nodes = all_nodes[used]
    if rotate is not None:
        nodes = rotate[0] + nodes @ rotate[1].T
    return Mesh(nodes, inverse.reshape(-1, 4), region, name=name).oriented()


def _cells_to_tets(cell, edges, partial, labels_kji, spacing, origin):
    """The 6 Kuhn tetrahedra of every tissue cell with their regions; in a cell
    shared by two regions (``partial``) the k tetrahedra whose centres lie
    deepest in the region's voxels (trilinear indicator) take its label."""
    from scipy import ndimage

    shape = tuple(len(e) for e in edges)
    flat = cell.ravel()
    pc = np.array(sorted(partial), dtype=np.int64)
    use = flat > 0
    use[pc] = True
    ci, cj, ck = np.unravel_index(np.flatnonzero(use), cell.shape)
    node_id = lambda i, j, k: (i * shape[1] + j) * shape[2] + k  # noqa: E731
    paths = kuhn_paths()
    tets = np.concatenate([np.stack([node_id(ci + a, cj + b, ck + c) for a, b, c in path], axis=1)
                           for path in paths])
    region = np.tile(flat[use], 6)
    if len(pc):
        n_used = len(ci)
        pos = np.searchsorted(np.flatnonzero(use), pc)     # row of each partial cell
        pi, pj, pk = np.unravel_index(pc, cell.shape)
        lo = np.stack([edges[0][pi], edges[1][pj], edges[2][pk]], axis=1)
        hi = np.stack([edges[0][pi + 1], edges[1][pj + 1], edges[2][pk + 1]], axis=1)
        cent = np.stack([lo + (hi - lo) * np.mean(np.array(path, float), axis=0)
                         for path in paths], axis=1)          # (P, 6, 3) tet centres
        kji = ((cent.reshape(-1, 3) - origin) / spacing)[:, ::-1].T
        for row, c in enumerate(pc):
            label, k = partial[int(c)]
            ind = ndimage.map_coordinates((np.asarray(labels_kji) == label).astype(np.float32),
                                          kji[:, 6 * row:6 * row + 6], order=1, mode="nearest")
            best = np.argsort(-ind, kind="stable")[:k]
            region[best * n_used + pos[row]] = label
    keep = region > 0
    return tets[keep], region[keep]


def _record_fidelity(mesh, labelmap_volumes):
    """Region volumes of the mesh against the label map's, into ``mesh.meta``;
    a MeshFidelityWarning (and a line in ``meta["warnings"]``) per region off by
    more than VOLUME_WARN_PCT."""
    import warnings

    got = mesh.region_measures()
    err = {}
    notes = []
    for label, ref in sorted(labelmap_volumes.items()):
        v = got.get(label, 0.0)
        err[label] = 100.0 * (v - ref) / ref
        if abs(err[label]) > VOLUME_WARN_PCT:
            notes.append(f"region {label}: mesh volume {v:.4g} mm^3 is {err[label]:+.1f} % off "
                         f"the label map's {ref:.4g} mm^3 (a region a few cells across: "
                         "use a smaller element size)")
    mesh.meta["labelmap_volumes_mm3"] = dict(labelmap_volumes)
    mesh.meta["volume_error_pct"] = err
    mesh.meta["warnings"] = notes
    for note in notes:
        warnings.warn(note, MeshFidelityWarning, stacklevel=3)


def labelmap_region_volumes(labels_kji, spacing_mm, roi=None, origin_mm=None):
    """Volume [mm^3] of each non-zero label (optionally inside an roi
    (x0, x1, y0, y1, z0, z1), RAS mm, axis-aligned label map: voxels cut by the
    roi's faces count with the part of them inside)."""
    labels = np.asarray(labels_kji)
    spacing = np.asarray(spacing_mm, float)
    if roi is not None:
        origin = np.asarray(origin_mm, float)
        edges = [np.array([roi[2 * a], roi[2 * a + 1]], float) for a in range(3)]
        region, V = region_cell_volumes(labels, spacing, origin, edges)
        return {int(v): float(V[0, 0, 0, r]) for r, v in enumerate(region) if V[0, 0, 0, r] > 0}
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
    return np.bincount(mesh.elements.ravel(),
                       weights=np.repeat(mesh.measures / (mesh.dim + 1), mesh.dim + 1),
                       minlength=mesh.n_nodes)


def node_regions_volume_preserving(mesh, labels_kji, spacing_mm, origin_mm, background=1,
                                   cover=None):
    """Region of each node of a (coarse) mesh such that every region's nodes carry
    its label-map volume.

    A region's nodal basis sum_n phi_n integrates to the nodes' lumped
    volumes; labelling nodes by the voxel under them makes a thin target's
    share jump with where the grid falls (a 2.4 mm tube on a 1.5 mm mesh gets
    one or two node rows: +-60 % in a hard-prior yield).  Here nodes are
    ranked by how much of their cell the region covers, and the best-covered
    ones are taken until their volumes add up to the region's volume inside
    the mesh.  The remaining nodes get ``background``.

    ``cover``: (labels, F) each node's share of each region over its own cell
    (``tomography.model.membership``) to rank the nodes by, instead of the label
    map averaged over a box of the mesh's nominal size at the node. On a mesh
    graded by bisection that box is not the node's cell: near a target the
    nodes are finer than the nominal size, and ranked by the one voxel under
    each (a box of 1.0 mm on 0.8 mm voxels) the candidates ran out at 86 % of a
    2.4 mm tube's volume (the demo's tube cases: -13 to -15 %).
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
        if cover is None:
            c = ndimage.uniform_filter((labels == r).astype(np.float32),
                                       size=size)[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        else:
            c = np.asarray(cover[1], float)[:, list(cover[0]).index(r)].copy()
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


@njit(cache=True, nogil=True)
def _axis_sample(lo, hi, frac, origin, spacing, n):
    """The two voxel indices on one axis around the point ``lo + frac (hi - lo)``
    [mm] and the second one's trilinear weight, the grid's edge value held
    beyond it."""
    x = min(max((lo + frac * (hi - lo) - origin) / spacing, 0.0), n - 1.0)
    i0 = min(int(np.floor(x)), n - 1)
    return i0, min(i0 + 1, n - 1), x - i0


#: :func:`_pure_column`'s answer for a cell that sees more than one column
_MIXED = -2


@njit(cache=True, nogil=True)
def _pure_column(sub_col, lo, hi, samples, origin, spacing):
    """The one column every voxel of a cell's samples' trilinear stencils holds
    (-1: none), or ``_MIXED``; ``lo``, ``hi`` the cell's box (mm, k-j-i order)."""
    first, last = 0.5 / samples, 1.0 - 0.5 / samples
    nk, nj, ni = sub_col.shape
    k0 = _axis_sample(lo[0], hi[0], first, origin[0], spacing[0], nk)[0]
    k1 = _axis_sample(lo[0], hi[0], last, origin[0], spacing[0], nk)[1]
    j0 = _axis_sample(lo[1], hi[1], first, origin[1], spacing[1], nj)[0]
    j1 = _axis_sample(lo[1], hi[1], last, origin[1], spacing[1], nj)[1]
    i0 = _axis_sample(lo[2], hi[2], first, origin[2], spacing[2], ni)[0]
    i1 = _axis_sample(lo[2], hi[2], last, origin[2], spacing[2], ni)[1]
    one = sub_col[k0, j0, i0]
    for kk in range(k0, k1 + 1):
        for jj in range(j0, j1 + 1):
            for ii in range(i0, i1 + 1):
                if sub_col[kk, jj, ii] != one:
                    return _MIXED
    return one


@njit(cache=True, nogil=True)
def cell_region_shares(sub_col, origin_kji, spacing_kji, cell_lo_kji, cell_hi_kji, samples,
                       n_cols):
    """(P, n_cols) each cell's share of every column's region: the mean over a
    ``samples``^3 midpoint grid on the box [cell_lo, cell_hi] (mm, k-j-i order)
    of the regions' indicators interpolated trilinearly between voxel centres,
    the grid's edge values held beyond it (what ``scipy.ndimage.map_coordinates``
    of order 1, mode "nearest", gives for each indicator, here all in one pass);
    ``sub_col`` (K, J, I): each voxel's column, -1 for none."""
    P = cell_lo_kji.shape[0]
    out = np.zeros((P, n_cols))
    nk, nj, ni = sub_col.shape
    w = 1.0 / samples ** 3
    for p in range(P):
        # a cell whose samples' trilinear stencils all see one column is that
        # column's alone (its sum is 1 to rounding, or nothing): the caller's test
        # for such cells takes one reach, the coarsest cell's of a graded mesh, so
        # near a target most of the cells it passes here are pure
        one = _pure_column(sub_col, cell_lo_kji[p], cell_hi_kji[p], samples, origin_kji,
                           spacing_kji)
        if one != _MIXED:
            if one >= 0:
                out[p, one] = 1.0
            continue
        for a in range(samples):
            k0, k1, tk = _axis_sample(cell_lo_kji[p, 0], cell_hi_kji[p, 0], (a + 0.5) / samples,
                                      origin_kji[0], spacing_kji[0], nk)
            for b in range(samples):
                j0, j1, tj = _axis_sample(cell_lo_kji[p, 1], cell_hi_kji[p, 1],
                                          (b + 0.5) / samples, origin_kji[1], spacing_kji[1], nj)
                for c in range(samples):
                    i0, i1, ti = _axis_sample(cell_lo_kji[p, 2], cell_hi_kji[p, 2],
                                              (c + 0.5) / samples, origin_kji[2],
                                              spacing_kji[2], ni)
                    for q in range(8):
                        kk, wk = (k1, tk) if q & 4 else (k0, 1.0 - tk)
                        jj, wj = (j1, tj) if q & 2 else (j0, 1.0 - tj)
                        ii, wi = (i1, ti) if q & 1 else (i0, 1.0 - ti)
                        v = sub_col[kk, jj, ii]
                        if v >= 0:
                            out[p, v] += w * wk * wj * wi
    return out
