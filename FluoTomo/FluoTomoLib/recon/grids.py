"""Fine (forward) and coarse (reconstruction) meshes and the operators between them.

The forward model wants a fine mesh (the fluence varies over millimetres
near the sources); the inverse problem is better posed and cheaper on a
coarse one.  ``coarse_to_fine`` (N_fine x N_coarse) interpolates a coarse
nodal field (the unknowns) onto the fine nodes; ``fine_to_coarse``
(N_coarse x N_fine) samples a fine field at the coarse nodes.  Both are P1
(barycentric) interpolation matrices from :mod:`locate`, so a field linear
in x, y, z is carried over exactly where a node lies inside the other mesh.
A node outside the other mesh (curved boundaries of two meshes never
coincide) takes the value at the closest boundary point of the other mesh:
rows still sum to 1, no value is lost, and the error there is the distance
to that point times the field gradient.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fluoguide.errors import FluoInputError

from FluoTomoLib.fem.locate import boundary_locator, locator


def interpolation_operator(source_mesh, points_mm):
    """Sparse (P, N_source) P1 interpolation of a nodal field of ``source_mesh``
    at ``points_mm``; points outside snap to the closest boundary point.

    Returns the matrix and the number of snapped points.
    """
    pts = np.atleast_2d(np.asarray(points_mm, float))
    if pts.shape[1] != source_mesh.dim:
        raise FluoInputError(f"points must be (P, {source_mesh.dim})", field="points_mm",
                             value=pts.shape)
    loc = locator(source_mesh)
    elem, _ = loc.locate(pts)
    outside = np.flatnonzero(elem < 0)
    if len(outside):
        q, _, _, _ = boundary_locator(source_mesh).closest(pts[outside])
        # nudge onto the closed facet: the locator tolerates 1e-9 in barycentrics
        pts = pts.copy()
        pts[outside] = q
    mat = loc.interpolation_matrix(pts, outside="zero")
    empty = np.flatnonzero(np.diff(mat.indptr) == 0)
    if len(empty):
        # closest points that still miss by rounding: nearest node
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(source_mesh.nodes_mm).query(pts[empty])
        fix = sp.csr_matrix((np.ones(len(empty)), (empty, nearest)), shape=mat.shape)
        mat = (mat + fix).tocsr()
    mat.eliminate_zeros()
    return mat, int(len(outside))


def mesh_interpolation_operators(fine, coarse):
    """Both operators between a fine and a coarse mesh.

    Returns
    -------
    dict: ``coarse_to_fine`` (N_fine, N_coarse) csr, ``fine_to_coarse``
    (N_coarse, N_fine) csr, and how many nodes of each were outside the
    other mesh (``fine_nodes_outside``, ``coarse_nodes_outside``).
    """
    if fine.dim != coarse.dim:
        raise FluoInputError("meshes of different dimension", field="coarse", value=coarse.dim)
    c2f, n_f = interpolation_operator(coarse, fine.nodes_mm)
    f2c, n_c = interpolation_operator(fine, coarse.nodes_mm)
    return {"coarse_to_fine": c2f, "fine_to_coarse": f2c,
            "fine_nodes_outside": n_f, "coarse_nodes_outside": n_c}


def reconstruction_mesh_pair(labels_kji, spacing_mm, origin_mm, fine_mm, coarse_mm, roi=None,
                             direction=None, method="fast"):
    """Fine and coarse meshes of one label map plus their operators.

    ``method``: "fast" (structured, seconds) or "quality" (fTetWild).
    Returns (fine, coarse, operators).
    """
    if not coarse_mm > fine_mm:
        raise FluoInputError("the reconstruction mesh must be coarser than the forward mesh",
                             field="coarse_mm", value=coarse_mm)
    if method == "fast":
        from FluoTomoLib.meshing.voxel import mesh_labelmap_structured as build
    elif method == "quality":
        from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality as build
    else:
        raise FluoInputError("method must be 'fast' or 'quality'", field="method", value=method)
    fine = build(labels_kji, spacing_mm, origin_mm, fine_mm, roi=roi, direction=direction,
                 name="forward")
    coarse = build(labels_kji, spacing_mm, origin_mm, coarse_mm, roi=roi, direction=direction,
                   name="reconstruction")
    return fine, coarse, mesh_interpolation_operators(fine, coarse)
