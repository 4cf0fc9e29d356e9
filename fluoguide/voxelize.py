"""Volume-preserving voxelisation of analytic shapes into a label map.

A label map at CBCT resolution (0.8 mm) cannot hold a 2.4 mm tube exactly:
labelling voxels by their centre alone changes the tube's volume by 10-30 %
depending on where the tube falls in the grid.  Here each voxel near a
boundary is supersampled to get the fraction of it each region covers; the
voxel takes the region with the largest fraction, and then each region's
voxel count is brought to its analytic volume by moving the voxels whose
fractions are closest to the decision (a volume-preserving threshold of the
partial-volume map).  Shapes keep their best voxel approximation and volumes
match to within a voxel.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def grid_points(shape_kji, spacing, origin, k_range=None):
    """RAS coordinates (x, y, z) of voxel centres for slices ``k_range``."""
    k0, k1 = (0, shape_kji[0]) if k_range is None else k_range
    k, j, i = np.meshgrid(np.arange(k0, k1), np.arange(shape_kji[1]), np.arange(shape_kji[2]),
                          indexing="ij")
    return (origin[0] + i * spacing[0], origin[1] + j * spacing[1], origin[2] + k * spacing[2])


def _label_points(regions, x, y, z, background):
    lab = np.full(x.shape, background, dtype=np.int16)
    for label, inside in regions:
        lab[inside(x, y, z)] = label
    return lab


def voxelize(regions, shape_kji, spacing, origin, analytic_volumes=None, supersample=4,
             background=0):
    """Label map of analytic regions painted in order (later regions win).

    Parameters
    ----------
    regions : list of (label, inside(x, y, z) -> bool array), RAS mm
    shape_kji : (K, J, I) grid shape
    spacing, origin : voxel size and voxel-(0,0,0) centre, mm (axis-aligned grid)
    analytic_volumes : dict label -> exact volume [mm^3] of the region as
        painted (after overrides); labels listed here get their voxel count
        matched to it
    supersample : samples per axis inside a boundary voxel

    Returns
    -------
    labels : (K, J, I) uint8 array
    fractions : dict label -> (K, J, I) float32 coverage fraction (for partial-
        volume CBCT rendering)
    """
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    x, y, z = grid_points(shape_kji, spacing, origin)
    centre = _label_points(regions, x, y, z, background)
    all_labels = sorted({background} | {lab for lab, _ in regions})
    # Boundary band: voxels whose 26-neighbourhood holds another label.
    band = ndimage.maximum_filter(centre, size=3) != ndimage.minimum_filter(centre, size=3)
    idx = np.flatnonzero(band)
    fractions = {lab: (centre == lab).astype(np.float32) for lab in all_labels}
    if len(idx):
        s = int(supersample)
        offs = (np.arange(s) + 0.5) / s - 0.5
        ox, oy, oz = np.meshgrid(offs, offs, offs, indexing="ij")
        ox, oy, oz = ox.ravel(), oy.ravel(), oz.ravel()
        chunk = max(1, 2_000_000 // (s ** 3))
        for c0 in range(0, len(idx), chunk):
            sel = idx[c0:c0 + chunk]
            px = x.ravel()[sel][:, None] + ox[None, :] * spacing[0]
            py = y.ravel()[sel][:, None] + oy[None, :] * spacing[1]
            pz = z.ravel()[sel][:, None] + oz[None, :] * spacing[2]
            lab = _label_points(regions, px, py, pz, background)
            for L in all_labels:
                fractions[L].ravel()[sel] = (lab == L).mean(axis=1)
    stack = np.stack([fractions[L] for L in all_labels])
    labels = np.asarray(all_labels, dtype=np.int16)[np.argmax(stack, axis=0)]
    if analytic_volumes:
        voxel_volume = float(np.prod(spacing))
        # Smallest regions first: they are the ones a voxel more or less matters to.
        locked = []
        for L in sorted(analytic_volumes, key=lambda k: analytic_volumes[k]):
            target = int(round(analytic_volumes[L] / voxel_volume))
            labels = _match_count(labels, fractions, L, target, all_labels, locked)
            locked.append(L)
    return labels.astype(np.uint8), fractions


def _match_count(labels, fractions, L, target, all_labels, locked):
    """Add or remove voxels of label L (by coverage fraction) to reach ``target``,
    never touching voxels of the already matched labels in ``locked``."""
    count = int(np.count_nonzero(labels == L))
    f = fractions[L]
    if count < target:
        free = ~np.isin(labels, locked) if locked else np.ones(labels.shape, bool)
        cand = np.flatnonzero((labels != L) & (f > 0) & free)
        order = cand[np.argsort(-f.ravel()[cand], kind="stable")]
        labels.ravel()[order[: target - count]] = L
    elif count > target:
        cand = np.flatnonzero(labels == L)
        order = cand[np.argsort(f.ravel()[cand], kind="stable")]
        drop = order[: count - target]
        others = [m for m in all_labels if m != L and m not in locked]
        second = np.argmax(np.stack([fractions[m].ravel()[drop] for m in others]), axis=0)
        labels.ravel()[drop] = np.asarray(others)[second]
    return labels
