"""Structured simplex meshes: rectangles into triangles, boxes into tetrahedra.

Used for benchmarks (slabs), the fast voxel-to-tet preview, and tests.  Boxes
are split with the Kuhn (Freudenthal) subdivision, 6 tetrahedra per cell,
which is conforming across neighbouring cells.  Axis coordinates may be
graded (any increasing sequence), e.g. finer near the illuminated surface.
"""

from __future__ import annotations

import itertools

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.meshing.mesh import Mesh


def _axis(lo, hi, step_mm, name):
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise FluoInputError("needs lo < hi", field=name, value=(lo, hi))
    if not (np.isfinite(step_mm) and step_mm > 0):
        raise FluoInputError("step must be > 0", field=name, value=step_mm)
    n = max(1, int(round((hi - lo) / step_mm)))
    return np.linspace(lo, hi, n + 1)


def graded_axis(lo, hi, fine_mm, coarse_mm, fine_until, grow=1.15):
    """Coordinates from ``hi`` downwards: ``fine_mm`` steps for ``fine_until`` mm,
    then growing by ``grow`` per step up to ``coarse_mm`` (surface at ``hi``)."""
    z = [hi]
    step = fine_mm
    while z[-1] > lo + 1e-9:
        depth = hi - z[-1]
        if depth >= fine_until:
            step = min(step * grow, coarse_mm)
        z.append(max(lo, z[-1] - step))
    if z[-1] - lo < 0.3 * step and len(z) > 2:  # merge a sliver last layer
        z[-2] = lo
        z.pop()
    return np.array(sorted(z))


def optode_axis(lo, hi, optodes_mm, fine_mm, coarse_mm, fine_half_mm=None, grow=1.2):
    """Coordinates on [lo, hi] that are ``fine_mm`` apart within ``fine_half_mm``
    (default 2 fine steps) of any of the ``optodes_mm`` coordinates and grow by
    ``grow`` per step away from them, up to ``coarse_mm``: optode-aware
    grading (fine where light enters and leaves, coarse where it only
    diffuses).  The last step is stretched or merged so the axis ends at hi.
    """
    c = np.unique(np.asarray(optodes_mm, float).ravel())
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise FluoInputError("needs lo < hi", field="axis", value=(lo, hi))
    if not (0 < fine_mm <= coarse_mm) or not np.all(np.isfinite(c)) or not grow > 1:
        raise FluoInputError("needs 0 < fine <= coarse, grow > 1 and finite optode coordinates",
                             field="fine_mm", value=(fine_mm, coarse_mm, grow))
    half = 2.0 * fine_mm if fine_half_mm is None else float(fine_half_mm)

    def size(x):
        d = np.min(np.abs(c - x)) if len(c) else np.inf
        # a step of size s at distance d grows the next one by (grow - 1) s:
        # linear growth of the size with distance is geometric per step
        return float(np.clip(fine_mm + (grow - 1.0) * (d - half), fine_mm, coarse_mm))

    x = [float(lo)]
    while x[-1] < hi:
        s = size(x[-1])
        s = min(s, size(x[-1] + s))                 # do not step over a fine zone
        x.append(x[-1] + s)
    if x[-1] - hi > 0.5 * (x[-1] - x[-2]) and len(x) > 2:
        x.pop()                                     # merge a sliver last step
    x[-1] = float(hi)
    return np.array(x)


def rectangle_mesh(x, y, name="rectangle"):
    """Triangles on the grid x (nx+1,) by y (ny+1,), alternating diagonals."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    X, Y = np.meshgrid(x, y, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel()], axis=1)
    nx, ny = len(x) - 1, len(y) - 1
    idx = np.arange(len(x) * len(y)).reshape(len(x), len(y))
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
    flip = ((i + j) % 2 == 0)
    t1 = np.where(flip[..., None], np.stack([a, b, c], -1), np.stack([a, b, d], -1))
    t2 = np.where(flip[..., None], np.stack([a, c, d], -1), np.stack([b, c, d], -1))
    tris = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])
    mesh = Mesh(nodes, tris, name=name).oriented()
    mesh.meta["method"] = "structured"      # grid nodes: geometric ordering (ordering.py)
    return mesh


def kuhn_paths():
    """The 6 monotone corner paths 000 -> 111 of a unit cube (one per axis
    permutation); each is a tetrahedron, and together they tile the cube
    conformingly with the neighbouring cubes (Kuhn / Freudenthal)."""
    paths = []
    for perm in itertools.permutations(range(3)):
        path = [(0, 0, 0)]
        for ax in perm:
            nxt = list(path[-1])
            nxt[ax] = 1
            path.append(tuple(nxt))
        paths.append(path)
    return paths


def box_mesh(x, y, z, name="box"):
    """Tetrahedra on the grid x by y by z (coordinate arrays, mm)."""
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    shape = (len(x), len(y), len(z))
    idx = np.arange(np.prod(shape)).reshape(shape)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(n - 1) for n in shape), indexing="ij"))
    corner = {c: idx[i + c[0], j + c[1], k + c[2]] for c in itertools.product((0, 1), repeat=3)}
    tets = [np.stack([corner[c] for c in path], axis=1) for path in kuhn_paths()]
    mesh = Mesh(nodes, np.concatenate(tets), name=name).oriented()
    mesh.meta["method"] = "structured"      # grid nodes: geometric ordering (ordering.py)
    return mesh


def slab_mesh(size_xy_mm, depth_mm, step_mm, fine_mm=None, fine_until_mm=5.0, name="slab"):
    """A slab centred on x = y = 0 with its top face at z = 0 (tissue below)."""
    hx = 0.5 * size_xy_mm
    x = _axis(-hx, hx, step_mm, "size_xy_mm")
    if fine_mm is None:
        z = _axis(-depth_mm, 0.0, step_mm, "depth_mm")
    else:
        z = graded_axis(-depth_mm, 0.0, fine_mm, step_mm, fine_until_mm)
    return box_mesh(x, x, z, name=name)
