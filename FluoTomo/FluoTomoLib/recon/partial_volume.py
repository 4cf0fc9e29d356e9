"""Partial-volume region membership of mesh nodes, for hard priors.

A hard prior writes the yield as one value per CBCT region, x(node) =
sum_r x_r K[node, r].  With 0/1 membership K the target is whatever set of
nodes the labelling picks; a 2.4 mm tube on a 1 mm grid needs 4.5 node rows
and gets 4 or 5, so its reconstructed extent (and its 50 %-of-peak centre)
shifts by up to half a cell depending on how the grid falls.  Here K[n, r] is
the share of node n's hat function covered by region r, sampled from the label
map: the piecewise-linear field sum_r x_r K[:, r] is then the interpolant of
the segmented regions' partial volumes, symmetric about the target, and its
integral reproduces each region's volume without any rounding to whole nodes.

The share is taken over the node's own cell (a box of one spacing centred on
the node; on a regular grid these boxes tile space, so sum_n K[n, r] vol_n is
region r's volume), not over the hat function's whole support: that would blur
the target a second time (measured: a 2.4 mm tube's profile peaked at 0.6-0.7
of its region value, where the cell share keeps the nodes inside it at 1).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.meshing.voxel import cell_region_shares
from FluoTomoLib.recon.solver import RegionPrior


def dual_cells(nodes_mm, edges_mm):
    """Each node's cell on a rectilinear grid: on every axis from halfway to the
    previous grid line to halfway to the next (the roi's faces at the ends).

    Returns (lo, hi): (N, 3) corners [mm]."""
    nodes = np.asarray(nodes_mm, float)
    lo = np.empty_like(nodes)
    hi = np.empty_like(nodes)
    for a in range(nodes.shape[1]):
        e = np.asarray(edges_mm[a], float)
        k = np.clip(np.searchsorted(e, nodes[:, a] - 1e-9), 0, len(e) - 1)
        mids = np.concatenate([[e[0]], 0.5 * (e[1:] + e[:-1]), [e[-1]]])
        lo[:, a] = mids[k]
        hi[:, a] = mids[k + 1]
    return lo, hi


def node_region_fractions(nodes_mm, labels_kji, spacing_mm, origin_mm, h_mm, labels=None,
                          samples_per_axis=6, background=1, edges_mm=None, cell_mm=None):
    """Share of each node's cell (a box h_mm wide centred on the node, or its
    dual cell on the grid ``edges_mm``) covered by each tissue region of the
    label map.

    Parameters
    ----------
    nodes_mm : (N, 3) node coordinates, RAS mm (axis-aligned label map)
    labels_kji, spacing_mm, origin_mm : the label map (0 = outside)
    h_mm : mesh spacing [mm], the cell width (the largest one with ``edges_mm``)
    edges_mm : per axis the grid lines of a rectilinear (graded) mesh, or None
    cell_mm : (N,) each node's own cell width [mm] (a mesh graded by bisection,
        ``tomography.model.node_spacing``), or None
    labels : region labels to return columns for (default: every non-zero label)
    samples_per_axis : midpoint quadrature points per axis (per node samples^3)
    background : label given to nodes whose support sees no tissue at all

    Returns
    -------
    (labels, F): F (N, R) with rows summing to 1 (air, label 0, is excluded
    and the rest renormalised).
    """
    lab = np.asarray(labels_kji)
    spacing = np.asarray(spacing_mm, float)
    origin = np.asarray(origin_mm, float)
    nodes = np.asarray(nodes_mm, float)
    if labels is None:
        labels = [int(v) for v in np.unique(lab) if v != 0]
    labels = list(labels)
    if not labels:
        raise FluoInputError("label map is empty (no non-zero label)", field="labels")
    col = {v: k for k, v in enumerate(labels)}
    shape_ijk = np.array(lab.shape[::-1])

    def lookup(p):
        ijk = np.clip(np.round((p - origin) / spacing).astype(int), 0, shape_ijk - 1)
        return lab[ijk[..., 2], ijk[..., 1], ijk[..., 0]]

    F = np.zeros((len(nodes), len(labels)))
    own = lookup(nodes)
    # only nodes whose support reaches another label need quadrature
    from scipy import ndimage

    if cell_mm is not None:
        cell_mm = np.asarray(cell_mm, float)
        h_mm = max(float(h_mm), float(np.max(cell_mm)))
    reach = [int(np.ceil(0.5 * h_mm / s)) + 1 for s in spacing[::-1]]
    lo_ = ndimage.minimum_filter(lab, size=[2 * r + 1 for r in reach])
    hi_ = ndimage.maximum_filter(lab, size=[2 * r + 1 for r in reach])
    ijk = np.clip(np.round((nodes - origin) / spacing).astype(int), 0, shape_ijk - 1)
    mixed = lo_[ijk[:, 2], ijk[:, 1], ijk[:, 0]] != hi_[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    pure = np.flatnonzero(~mixed)
    for v, k in col.items():
        F[pure[own[pure] == v], k] = 1.0
    # midpoint quadrature on each node's cell (meshing.voxel.cell_region_shares)
    if cell_mm is not None:
        cell_lo, cell_hi = nodes - 0.5 * cell_mm[:, None], nodes + 0.5 * cell_mm[:, None]
    elif edges_mm is None:
        cell_lo, cell_hi = nodes - 0.5 * h_mm, nodes + 0.5 * h_mm
    else:
        cell_lo, cell_hi = dual_cells(nodes, edges_mm)
    # Each region's indicator is sampled trilinearly (its partial volume between
    # voxel centres), not by nearest voxel: the 0.8 mm staircase of a thin
    # target otherwise makes its cell shares lopsided (a 2.4 mm tube gave 0.72
    # above its centre node and 0.50 below).
    idx = np.flatnonzero(mixed)
    if len(idx):
        lo_b = np.clip(ijk[idx].min(axis=0) - reach[::-1] - 1, 0, None)
        hi_b = np.minimum(ijk[idx].max(axis=0) + reach[::-1] + 2, shape_ijk)
        sub = lab[lo_b[2]:hi_b[2], lo_b[1]:hi_b[1], lo_b[0]:hi_b[0]]
        # each voxel's column in F (-1: a label not asked for, air among them)
        sub_col = _columns(sub, col)
        F[idx] = cell_region_shares(sub_col, (origin + lo_b * spacing)[::-1].copy(),
                                    spacing[::-1].copy(), cell_lo[idx][:, ::-1].copy(),
                                    cell_hi[idx][:, ::-1].copy(), int(samples_per_axis),
                                    len(labels))
    tissue = F.sum(axis=1)
    empty = tissue <= 0
    if np.any(empty):
        if background not in col:
            raise FluoInputError("nodes outside every tissue region and no background label",
                                 field="labels", value=int(np.sum(empty)))
        F[empty, col[background]] = 1.0
        tissue[empty] = 1.0
    return np.asarray(labels), F / tissue[:, None]


def _columns(labels, col):
    """(K, J, I) int32: each voxel's column ``col[label]``, -1 for a label not in
    ``col`` (air among them)."""
    labels = np.asarray(labels)
    if labels.dtype.kind in "iu" and labels.size and labels.min() >= 0 \
            and labels.max() < 2 ** 16:
        lut = np.full(int(max(labels.max(), max(col))) + 1, -1, np.int32)
        for v, k in col.items():
            if v >= 0:
                lut[v] = k
        return lut[labels]
    values = np.array(sorted(col), dtype=np.int64)
    pos = np.clip(np.searchsorted(values, labels), 0, len(values) - 1)
    return np.where(values[pos] == labels, np.array([col[int(v)] for v in values])[pos],
                    -1).astype(np.int32)


class PartialVolumePrior(RegionPrior):
    """A RegionPrior whose hard-prior basis K is the partial-volume membership
    (rows sum to 1) instead of 0/1; the soft prior's regions stay the node
    labels ``node_region`` (one region per node, as the reference defines L)."""

    def __init__(self, node_region, region_labels, fractions):
        super().__init__(node_region)
        F = np.asarray(fractions, float)
        if F.shape != (len(self.node_region), len(region_labels)):
            raise FluoInputError("fractions must be (nodes, regions)", field="fractions",
                                 value=F.shape)
        # columns in the order of self.labels (np.unique of node_region)
        order = {int(v): k for k, v in enumerate(region_labels)}
        missing = [int(v) for v in self.labels if int(v) not in order]
        if missing:
            raise FluoInputError("a node region has no fraction column", field="fractions",
                                 value=missing)
        self._F = F[:, [order[int(v)] for v in self.labels]]

    def K(self):
        return self._F.copy()


def region_unknowns(labels):
    """The prior of a problem whose unknowns are the regions themselves (HP on a
    region matrix J K): one "node" per region, each wholly its own region."""
    import warnings

    labels = np.asarray(labels)
    with warnings.catch_warnings():          # one unknown per region by design
        warnings.simplefilter("ignore")
        return PartialVolumePrior(labels, labels, np.eye(len(labels)))
