"""Point location in simplex meshes and closest points on their boundary.

Shared by FEM (sources, detectors), mesh-to-mesh interpolation and the
non-contact geometry.  A KD-tree of element centroids proposes candidates;
barycentric coordinates decide.  Built once per mesh and cached on it.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from fluoguide.errors import FluoInputError


def barycentric(mesh, element_ids, points):
    """Barycentric coordinates (P, d+1) of points in the given elements."""
    el = mesh.elements[element_ids]
    p = mesh.nodes_mm[el]                      # (P, d+1, d)
    T = (p[:, 1:, :] - p[:, :1, :]).transpose(0, 2, 1)  # (P, d, d)
    rhs = np.asarray(points, float) - p[:, 0, :]
    lam = np.linalg.solve(T, rhs[..., None])[..., 0]
    return np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)


class PointLocator:
    """Find the element containing each query point.

    Parameters
    ----------
    mesh : Mesh
    k : candidates checked per point before falling back to a wider search
    """

    def __init__(self, mesh, k=16, scan_max=64):
        self.mesh = mesh
        self.k = int(min(k, mesh.n_elements))
        self.scan_max = int(scan_max)
        self._tree = None
        self._classes = None

    def _build(self):
        centroids = self.mesh.nodes_mm[self.mesh.elements].mean(axis=1)
        self._tree = cKDTree(centroids)

    @property
    def tree(self):
        if self._tree is None:
            self._build()
        return self._tree

    def locate(self, points, tol=1e-9):
        """Element id (or -1 outside the mesh) and barycentric coordinates per point."""
        pts = np.atleast_2d(np.asarray(points, float))
        n = len(pts)
        if self._tree is None and n <= self.scan_max:
            # a few points (sources, detectors) on a mesh with no tree yet: one
            # compiled pass over the elements (5 ms for 330k tetrahedra) beats
            # building the KD-tree (0.26 s)
            return _scan_locate(np.ascontiguousarray(self.mesh.nodes_mm, dtype=float),
                                np.ascontiguousarray(self.mesh.elements), pts, tol)
        elem = np.full(n, -1, dtype=np.int64)
        bary = np.full((n, self.mesh.dim + 1), np.nan)
        # in batches: the candidate search holds k (and 16 k when widened)
        # indices and distances per point, which for a whole label map's voxels
        # at once was hundreds of MB
        for a in range(0, n, LOCATE_BATCH):
            sl = slice(a, min(n, a + LOCATE_BATCH))
            elem[sl], bary[sl] = self._locate_batch(pts[sl], tol)
        idx = np.flatnonzero(elem < 0)
        if len(idx):
            # thin/large elements whose centroid is farther still, or points outside
            # the mesh (a section through a cavity, the air voxels of a label map):
            # every element within reach, checked together
            self._locate_within_reach(pts, idx, elem, bary, tol)
        return elem, bary

    #: points searched together by the wide search
    REACH_BATCH = 8192

    def _size_classes(self):
        """Element centroids grouped by their reach (the farthest node from the
        centroid), each group a KD-tree with its own largest reach: a graded
        mesh's small elements are then searched within their own small reach,
        not the largest element's (which put thousands of candidates around a
        point outside a fine region)."""
        if self._classes is None:
            el = self.mesh.elements
            c = self.mesh.nodes_mm[el].mean(axis=1)
            r = np.max(np.linalg.norm(self.mesh.nodes_mm[el] - c[:, None, :], axis=2), axis=1)
            k = np.floor(np.log2(r / max(float(r.min()), 1e-12))).astype(np.int64)
            self._classes = []
            for v in np.unique(k):
                ids = np.flatnonzero(k == v)
                self._classes.append((cKDTree(c[ids]), ids, float(r[ids].max()) + 1e-9))
        return self._classes

    def _locate_within_reach(self, pts, idx, elem, bary, tol):
        """Every element whose centroid lies within its own reach of each point of
        ``idx`` (the only ones that can hold it), checked together; the lowest
        element id holding a point is its element, as the scan gives."""
        big = np.iinfo(np.int64).max
        for a in range(0, len(idx), self.REACH_BATCH):
            chunk = idx[a:a + self.REACH_BATCH]
            best = np.full(len(chunk), big, dtype=np.int64)
            for tree, ids, reach in self._size_classes():
                lists = tree.query_ball_point(pts[chunk], reach)
                counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
                if counts.sum() == 0:
                    continue
                owner = np.repeat(np.arange(len(chunk)), counts)
                cand = ids[np.concatenate([np.asarray(v, dtype=np.int64) for v in lists if v])]
                lam = barycentric(self.mesh, cand, pts[chunk[owner]])
                ok = np.all(lam >= -tol, axis=1)
                np.minimum.at(best, owner[ok], cand[ok])
            found = np.flatnonzero(best < big)
            if len(found):
                elem[chunk[found]] = best[found]
                bary[chunk[found]] = barycentric(self.mesh, best[found], pts[chunk[found]])

    def _locate_batch(self, pts, tol):
        """:meth:`locate` of a batch of points, by the nearest centroids (k, then
        16 k of them); -1 where neither holds the point."""
        n = len(pts)
        pts = np.ascontiguousarray(pts, dtype=float)
        _, cand = self.tree.query(pts, k=self.k)
        elem, bary = _first_containing(self._nodes(), self._elements(), pts,
                                       np.ascontiguousarray(cand.reshape(n, -1), np.int64), tol)
        # a graded mesh's large elements: their centroids lie beyond the nearest
        # k small ones; more candidates, a sixteenth of the batch at a time
        wide = int(min(16 * self.k, self.mesh.n_elements))
        left = np.flatnonzero(elem < 0)
        for b in range(0, len(left) if wide > self.k else 0, LOCATE_BATCH // 16):
            idx = left[b:b + LOCATE_BATCH // 16]
            _, more = self.tree.query(pts[idx], k=wide)
            more = np.ascontiguousarray(more.reshape(len(idx), -1)[:, self.k:], np.int64)
            elem[idx], bary[idx] = _first_containing(self._nodes(), self._elements(),
                                                     np.ascontiguousarray(pts[idx]), more, tol)
        return elem, bary

    def _nodes(self):
        """The mesh's nodes as the compiled search takes them (float64, C order)."""
        return np.ascontiguousarray(self.mesh.nodes_mm, dtype=float)

    def _elements(self):
        """The mesh's elements as the compiled search takes them (int64, C order)."""
        return np.ascontiguousarray(self.mesh.elements, dtype=np.int64)

    def grid_interpolation_matrix(self, origin_mm, spacing_mm, shape_kji, select=None):
        """Sparse (P, N) P1 interpolation weights at the points of a regular grid:
        point (i, j, k) at ``origin_mm + (i, j, k) * spacing_mm`` (mesh frame
        [mm], axis-aligned), in C order of ``shape_kji`` (i fastest), only where
        ``select`` (a bool array of that shape; None: every point) holds, rows in
        that order; a point outside the mesh gets an empty row.

        Each element visits the grid points in its bounding box (a compiled
        loop): for a voxel grid this is the :meth:`locate` result (the lowest
        element holding a point on a shared face, as the scan takes it) at a
        fraction of the candidate search's cost."""
        shape_kji = tuple(int(v) for v in shape_kji)
        sel = (np.ones(shape_kji, bool) if select is None
               else np.asarray(select, bool).reshape(shape_kji)).ravel()
        if self.mesh.dim != 3:
            k, j, i = np.indices(shape_kji)
            pts = (np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)[sel] * spacing_mm
                   + origin_mm)
            return self.interpolation_matrix(pts, outside="zero")
        elem, bary = _grid_locate(self._nodes(), self._elements(),
                                  np.ascontiguousarray(origin_mm, float).reshape(3),
                                  np.ascontiguousarray(spacing_mm, float).reshape(3),
                                  np.array(shape_kji[::-1], np.int64), sel, 1e-9)
        return self._p1_matrix(elem[sel], bary[sel])

    def interpolation_matrix(self, points, outside="error", what="point"):
        """Sparse (P, N) matrix of P1 interpolation weights at the points."""
        elem, bary = self.locate(points)
        bad = np.flatnonzero(elem < 0)
        # outside="error": raise; "nan"/"zero": the row stays empty (all zero)
        if len(bad) and outside == "error":
            raise FluoInputError("lies outside the mesh", field=f"{what}[{bad[0]}]",
                                 value=np.atleast_2d(points)[bad[0]].tolist())
        return self._p1_matrix(elem, bary)

    def _p1_matrix(self, elem, bary):
        """Sparse (P, N) P1 weights of located points (``elem``, ``bary``: element
        and barycentric coordinates per point); a point outside (-1) gets an
        empty row."""
        import scipy.sparse as sp

        rows = np.repeat(np.arange(len(elem)), self.mesh.dim + 1)
        cols = self.mesh.elements[np.maximum(elem, 0)].ravel()
        vals = np.where(elem[:, None] >= 0, bary, 0.0).ravel()
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(elem), self.mesh.n_nodes))


#: points located per batch (the wider search: a sixteenth of it)
LOCATE_BATCH = 65536


@njit(cache=True)
def _scan_locate(nodes, el, pts, tol):
    """First element (lowest index) containing each point, and its barycentric
    coordinates; -1 and NaN for points outside every element."""
    M, nl = el.shape
    d = nl - 1
    P = pts.shape[0]
    elem = np.full(P, -1, np.int64)
    bary = np.full((P, nl), np.nan)
    lo = np.empty(d)
    hi = np.empty(d)
    T = np.empty((d, d))
    lam = np.empty(nl)
    left = P
    for e in range(M):
        if left == 0:
            break
        for x in range(d):
            lo[x] = nodes[el[e, 0], x]
            hi[x] = lo[x]
            for a in range(1, nl):
                v = nodes[el[e, a], x]
                lo[x] = min(lo[x], v)
                hi[x] = max(hi[x], v)
        for p in range(P):
            if elem[p] >= 0:
                continue
            inside = True
            for x in range(d):
                pad = 1e-9 * (hi[x] - lo[x]) + 1e-12
                if pts[p, x] < lo[x] - pad or pts[p, x] > hi[x] + pad:
                    inside = False
                    break
            if not inside:
                continue
            for x in range(d):
                for k in range(d):
                    T[x, k] = nodes[el[e, k + 1], x] - nodes[el[e, 0], x]
            r = np.empty(d)
            for x in range(d):
                r[x] = pts[p, x] - nodes[el[e, 0], x]
            sol = np.linalg.solve(T, r)
            s = 0.0
            for k in range(d):
                lam[k + 1] = sol[k]
                s += sol[k]
            lam[0] = 1.0 - s
            ok = True
            for a in range(nl):
                if lam[a] < -tol:
                    ok = False
            if ok:
                elem[p] = e
                for a in range(nl):
                    bary[p, a] = lam[a]
                left -= 1
    return elem, bary


@njit(cache=True, nogil=True)
def _barycentric_into(nodes, el, e, p, lam, T, r):
    """``lam`` <- barycentric coordinates of point ``p`` in element ``e`` (the
    system T lam[1:] = p - x0 solved by Gaussian elimination with partial
    pivoting, as LAPACK's gesv does); False when T is singular."""
    d = T.shape[0]
    for x in range(d):
        for k in range(d):
            T[x, k] = nodes[el[e, k + 1], x] - nodes[el[e, 0], x]
        r[x] = p[x] - nodes[el[e, 0], x]
    for c in range(d):
        piv = c
        for x in range(c + 1, d):
            if abs(T[x, c]) > abs(T[piv, c]):
                piv = x
        if T[piv, c] == 0.0:
            return False
        if piv != c:
            for k in range(d):
                T[c, k], T[piv, k] = T[piv, k], T[c, k]
            r[c], r[piv] = r[piv], r[c]
        for x in range(c + 1, d):
            f = T[x, c] / T[c, c]
            for k in range(c, d):
                T[x, k] -= f * T[c, k]
            r[x] -= f * r[c]
    s = 0.0
    for c in range(d - 1, -1, -1):
        v = r[c]
        for k in range(c + 1, d):
            v -= T[c, k] * lam[k + 1]
        lam[c + 1] = v / T[c, c]
        s += lam[c + 1]
    lam[0] = 1.0 - s
    return True


@njit(cache=True, nogil=True)
def _first_containing(nodes, el, pts, cand, tol):
    """For each point, the first of its candidate elements (a row of ``cand``)
    that holds it (every barycentric coordinate >= -tol) and its barycentric
    coordinates; -1 and NaN where none does."""
    P, C = cand.shape
    nl = el.shape[1]
    d = nl - 1
    elem = np.full(P, -1, np.int64)
    bary = np.full((P, nl), np.nan)
    T = np.empty((d, d))
    r = np.empty(d)
    lam = np.empty(nl)
    for p in range(P):
        for c in range(C):
            e = cand[p, c]
            if not _barycentric_into(nodes, el, e, pts[p], lam, T, r):
                continue
            ok = True
            for a in range(nl):
                if lam[a] < -tol:
                    ok = False
                    break
            if ok:
                elem[p] = e
                for a in range(nl):
                    bary[p, a] = lam[a]
                break
    return elem, bary


@njit(cache=True, nogil=True)
def _grid_locate(nodes, el, origin, spacing, shape_ijk, select, tol):
    """:meth:`PointLocator.grid_interpolation_matrix`'s search: every element
    checks the selected grid points in its bounding box (padded as
    :func:`_scan_locate` pads it); the lowest element holding a point is its
    element. Returns (elem (P,), bary (P, 4)) over the whole grid, C order."""
    ni, nj, nk = shape_ijk[0], shape_ijk[1], shape_ijk[2]
    P = ni * nj * nk
    elem = np.full(P, -1, np.int64)
    bary = np.full((P, 4), np.nan)
    T = np.empty((3, 3))
    r = np.empty(3)
    lam = np.empty(4)
    p = np.empty(3)
    first = np.empty(3, np.int64)
    last = np.empty(3, np.int64)
    for e in range(el.shape[0]):
        for x in range(3):
            lo = nodes[el[e, 0], x]
            hi = lo
            for a in range(1, 4):
                v = nodes[el[e, a], x]
                lo = min(lo, v)
                hi = max(hi, v)
            pad = 1e-9 * (hi - lo) + 1e-12
            first[x] = max(int(np.ceil((lo - pad - origin[x]) / spacing[x])), 0)
            last[x] = min(int(np.floor((hi + pad - origin[x]) / spacing[x])),
                          shape_ijk[x] - 1)
        for k in range(first[2], last[2] + 1):
            for j in range(first[1], last[1] + 1):
                for i in range(first[0], last[0] + 1):
                    q = (k * nj + j) * ni + i
                    if elem[q] >= 0 or not select[q]:
                        continue
                    p[0] = origin[0] + i * spacing[0]
                    p[1] = origin[1] + j * spacing[1]
                    p[2] = origin[2] + k * spacing[2]
                    if not _barycentric_into(nodes, el, e, p, lam, T, r):
                        continue
                    if lam[0] >= -tol and lam[1] >= -tol and lam[2] >= -tol \
                            and lam[3] >= -tol:
                        elem[q] = e
                        for a in range(4):
                            bary[q, a] = lam[a]
    return elem, bary


def locator(mesh):
    """The mesh's cached PointLocator."""
    return mesh.cached("_locator", PointLocator)


def _closest_on_segments(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300),
                0, 1)
    q = a + t[:, None] * ab
    return q, np.stack([1 - t, t], axis=1)


def _closest_on_triangles(p, a, b, c):
    """Closest points on triangles (Ericson, Real-Time Collision Detection 5.1.5), vectorised."""
    ab, ac = b - a, c - a
    ap = p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = vb / denom
        w = vc / denom
    bary = np.stack([1 - v - w, v, w], axis=1)
    # region tests, from most to least specific
    def set_(mask, b0, b1, b2):
        bary[mask] = np.stack([b0[mask], b1[mask], b2[mask]], axis=1)
    one, zero = np.ones_like(d1), np.zeros_like(d1)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = d1 / (d1 - d3)
        set_(m, 1 - t, t, zero)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = d2 / (d2 - d6)
        set_(m, 1 - t, zero, t)
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        set_(m, zero, 1 - t, t)
    set_((d1 <= 0) & (d2 <= 0), one, zero, zero)
    set_((d3 >= 0) & (d4 <= d3), zero, one, zero)
    set_((d6 >= 0) & (d5 <= d6), zero, zero, one)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


class BoundaryLocator:
    """Closest point on the mesh boundary (edges in 2D, triangles in 3D)."""

    def __init__(self, mesh, k=12):
        self.mesh = mesh
        f = mesh.boundary_facets
        self.k = int(min(k, len(f)))
        self.tree = cKDTree(mesh.nodes_mm[f].mean(axis=1))

    def closest(self, points):
        """Closest boundary points, their facet ids, barycentric weights on the
        facet and distances [mm]."""
        pts = np.atleast_2d(np.asarray(points, float))
        m = self.mesh
        _, cand = self.tree.query(pts, k=self.k)
        cand = cand.reshape(len(pts), -1)
        best_d = np.full(len(pts), np.inf)
        best_q = np.zeros_like(pts)
        best_f = np.zeros(len(pts), dtype=np.int64)
        best_b = np.zeros((len(pts), m.dim))
        for c in range(cand.shape[1]):
            fac = m.boundary_facets[cand[:, c]]
            v = [m.nodes_mm[fac[:, j]] for j in range(m.dim)]
            if m.dim == 2:
                q, b = _closest_on_segments(pts, *v)
            else:
                q, b = _closest_on_triangles(pts, *v)
            d = np.linalg.norm(q - pts, axis=1)
            better = d < best_d
            best_d[better] = d[better]
            best_q[better] = q[better]
            best_f[better] = cand[better, c]
            best_b[better] = b[better]
        return best_q, best_f, best_b, best_d


def boundary_locator(mesh):
    """The mesh's cached BoundaryLocator."""
    return mesh.cached("_boundary_locator", BoundaryLocator)
