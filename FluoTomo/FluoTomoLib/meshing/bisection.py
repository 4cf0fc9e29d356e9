"""Locally refined tetrahedral meshes by newest-vertex bisection of a Kuhn grid.

The structured meshes of :mod:`FluoTomoLib.meshing.voxel` are rectilinear: a
band of small cells runs through the whole region of interest, so refining
near a line of optodes refines every plane it crosses.  Here the grid of
``coarse_mm`` cubes is split into its 6 Kuhn tetrahedra, and the tetrahedra
are bisected where a size function asks for smaller elements, the
neighbours bisected with them until no node hangs (Maubach's tagged
bisection, docs/physics.md section 8.1).  The elements stay in a few
similarity classes of the Kuhn tetrahedron (three generations of bisection
give back a Kuhn grid of half the size), so grading costs no element
quality, and the size changes smoothly: the closure grades it.
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

#: elements a refinement may reach before it is refused (about 0.3 GB of
#: element arrays, ~1/5 as many nodes)
MAX_ELEMENTS = 12_000_000


def kuhn_elements(edges):
    """The Kuhn tetrahedra of the rectilinear grid ``edges`` (per axis the
    lines), their vertices ordered along each cube's monotone path (000 ->
    111), with the tag 3 of Maubach's bisection (first refinement edge: the
    cube's main diagonal, shared by its 6 tetrahedra).

    Returns (nodes (N, 3), elements (E, 4), tags (E,))."""
    from FluoTomoLib.meshing.structured import kuhn_paths

    shape = tuple(len(e) for e in edges)
    X, Y, Z = np.meshgrid(*edges, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    ci, cj, ck = np.meshgrid(*(np.arange(n - 1) for n in shape), indexing="ij")
    ci, cj, ck = ci.ravel(), cj.ravel(), ck.ravel()

    def node_id(i, j, k):
        return (i * shape[1] + j) * shape[2] + k

    elements = np.concatenate([np.stack([node_id(ci + a, cj + b, ck + c) for a, b, c in path],
                                        axis=1) for path in kuhn_paths()])
    return nodes, elements.astype(np.int64), np.full(len(elements), 3, np.int8)


def _edge_keys(a, b, n_max):
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    return lo * n_max + hi


class _Bisector:
    """The mesh under refinement: nodes, ordered elements, tags and the
    midpoints of every bisected edge (sorted keys for lookup)."""

    N_MAX = np.int64(1) << 31

    def __init__(self, nodes, elements, tags):
        self.nodes = [np.asarray(nodes, float)]
        self.n_nodes = len(nodes)
        self.elements = np.asarray(elements, np.int64)
        self.tags = np.asarray(tags, np.int8)
        self.mid_keys = np.zeros(0, np.int64)
        self.mid_nodes = np.zeros(0, np.int64)
        #: per element: its size was checked against the wanted size and kept (an
        #: element does not change while it exists, so it is not checked again)
        self.settled = np.zeros(len(self.elements), bool)

    def node_array(self):
        if len(self.nodes) > 1:
            self.nodes = [np.concatenate(self.nodes)]
        return self.nodes[0]

    def bisect(self, which):
        """Bisect the elements ``which`` (bool mask) at their refinement edges; the
        untouched elements keep their order, the children follow them. Returns
        the split edges' end nodes (K, 2)."""
        idx = np.flatnonzero(which)
        if len(idx) == 0:
            return np.zeros((0, 2), np.int64)
        el, tag = self.elements[idx], self.tags[idx].astype(np.int64)
        rows = np.arange(len(idx))
        a, b = el[:, 0], el[rows, tag]
        keys = _edge_keys(a, b, self.N_MAX)
        # midpoints: those of edges bisected before, new ones for the rest
        known, pos = self._find(keys)
        z = np.empty(len(idx), np.int64)
        z[known] = self.mid_nodes[pos[known]]
        new_keys, inv = np.unique(keys[~known], return_inverse=True)
        if len(new_keys):
            lo, hi = new_keys // self.N_MAX, new_keys % self.N_MAX
            pts = self.node_array()
            self.nodes.append(0.5 * (pts[lo] + pts[hi]))
            new_ids = self.n_nodes + np.arange(len(new_keys))
            self.n_nodes += len(new_keys)
            z[~known] = new_ids[inv]
            keys_all = np.concatenate([self.mid_keys, new_keys])
            nodes_all = np.concatenate([self.mid_nodes, new_ids])
            order = np.argsort(keys_all, kind="stable")
            self.mid_keys, self.mid_nodes = keys_all[order], nodes_all[order]
        # Maubach: T = (x0..x3), tag k, z = mid(x0, xk):
        #   T1 = (x0, .., x_{k-1}, z, x_{k+1}, .., x3), T2 = (x1, .., xk, z, x_{k+1}, .., x3)
        #   tag k - 1, or 3 after 1
        c1 = el.copy()
        c1[rows, tag] = z
        c2 = np.empty_like(el)
        for k in (1, 2, 3):
            s = tag == k
            if not s.any():
                continue
            e = el[s]
            c2[s] = np.concatenate([e[:, 1:k + 1], z[s, None], e[:, k + 1:]], axis=1)
        new_tag = np.where(tag > 1, tag - 1, 3).astype(np.int8)
        keep = np.ones(len(self.elements), bool)
        keep[idx] = False
        self.elements = np.concatenate([self.elements[keep], c1, c2])
        self.tags = np.concatenate([self.tags[keep], new_tag, new_tag])
        self.settled = np.concatenate([self.settled[keep], np.zeros(2 * len(idx), bool)])
        return np.stack([a, b], axis=1)

    def _find(self, keys):
        """(found, position): which edge keys were bisected, and where they sit in
        ``mid_keys`` (meaningful where found)."""
        if not len(self.mid_keys):
            return np.zeros(len(keys), bool), np.zeros(len(keys), np.int64)
        pos = np.minimum(np.searchsorted(self.mid_keys, keys), len(self.mid_keys) - 1)
        return self.mid_keys[pos] == keys, pos

    def hanging(self, only=None):
        """Elements with a bisected edge (a midpoint node on one of their edges);
        ``only`` (element indices): check these alone, the rest False."""
        el = self.elements if only is None else self.elements[only]
        found = np.zeros(len(el), bool)
        for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
            found |= self._find(_edge_keys(el[:, i], el[:, j], self.N_MAX))[0]
        if only is None:
            return found
        out = np.zeros(len(self.elements), bool)
        out[only[found]] = True
        return out

    def close(self, cancel=None):
        """Bisect until no node hangs (terminates on a Kuhn grid, Maubach 1995).
        After the first sweep only the elements that a bisection can have left
        hanging are checked: its children, and the elements holding both ends of
        an edge it split (an element none of whose edges was split keeps its
        state; every hanging one is bisected)."""
        h = None
        for _ in range(200):
            check_cancel(cancel)
            if h is None:
                h = self.hanging()
            if not h.any():
                return
            split = self.bisect(h)
            # bisect() keeps the untouched elements first, the two children of
            # each split element after them
            n_kept = len(self.elements) - 2 * len(split)
            ends = np.zeros(self.n_nodes, bool)
            ends[split.ravel()] = True
            near = np.flatnonzero(ends[self.elements[:n_kept]].sum(axis=1) >= 2)
            only = np.concatenate([near, np.arange(n_kept, len(self.elements))])
            h = self.hanging(only)
        raise RuntimeError("bisection closure did not end")     # pragma: no cover


def element_size(nodes, elements):
    """Each element's size [mm]: the edge of the cube its volume is a sixth of
    (a Kuhn tetrahedron of an h cube: h; each bisection divides it by 2^(1/3))."""
    from FluoTomoLib.meshing.mesh import element_measures

    return np.cbrt(6.0 * element_measures(nodes, elements))


def bisection_mesh(roi, coarse_mm, size_at, anchor_mm=None, min_mm=None, progress=None,
                   cancel=None):
    """Kuhn grid of ``coarse_mm`` cells over ``roi`` bisected until every element
    is no larger than ``size_at`` asks at its centre, and conforming.

    Parameters
    ----------
    roi : (x0, x1, y0, y1, z0, z1) [mm]
    coarse_mm : the grid's cell size [mm] (the largest elements)
    size_at : callable, (P, 3) points [mm] -> (P,) wanted element size [mm]
    anchor_mm : (3,) point the grid passes through (every refinement level's
        nodes too), or None
    min_mm : smallest element size refined to (default ``coarse_mm`` / 16)
    progress, cancel : progress(fraction, message) per refinement pass and a
        CancelToken checked between passes

    Returns
    -------
    (nodes (N, 3), elements (E, 4)): every element positively oriented is not
    guaranteed (Mesh.oriented() fixes it); no hanging node.
    """
    from FluoTomoLib.meshing.voxel import grid_edges

    roi = np.asarray(roi, float)
    coarse = float(coarse_mm)
    if not (np.isfinite(coarse) and coarse > 0):
        raise FluoInputError("element size must be > 0", field="coarse_mm", value=coarse_mm)
    floor = coarse / 16.0 if min_mm is None else float(min_mm)
    edges = grid_edges(roi, coarse, anchor_mm)
    nodes, elements, tags = kuhn_elements(edges)
    b = _Bisector(nodes, elements, tags)
    # three bisections halve a Kuhn element: passes enough for coarse -> floor
    passes = 3 * int(np.ceil(np.log2(max(coarse / floor, 1.0)))) + 3
    for it in range(passes):
        check_cancel(cancel)
        pts = b.node_array()
        # only the elements made since the last pass: the others were checked
        # and kept (an element's size and centre do not change)
        new = np.flatnonzero(~b.settled)
        el = b.elements[new]
        size = element_size(pts, el)
        want = np.maximum(np.asarray(size_at(pts[el].mean(axis=1)), float), floor)
        # a step of bisection divides the size by 2^(1/3): refine while it is
        # over the wanted size by more than half a step
        split = size > want * 2 ** (1 / 6)
        b.settled[new[~split]] = True
        mark = np.zeros(len(b.elements), bool)
        mark[new[split]] = True
        report(progress, min(0.95, it / passes),
               f"bisection pass {it + 1}: {len(b.elements)} elements, {int(split.sum())} to "
               "split")
        if not split.any():
            break
        b.bisect(mark)
        b.close(cancel)
        if len(b.elements) > MAX_ELEMENTS:
            raise FluoInputError(f"the refinement passed {MAX_ELEMENTS:.3g} elements: choose a "
                                 "larger element size or a smaller region", field="size_mm",
                                 value=float(np.min(want)) if len(want) else coarse)
    report(progress, 1.0, f"{len(b.elements)} elements")
    return b.node_array(), b.elements
