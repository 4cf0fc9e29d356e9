"""The analytic fast path: when the tissue under the optodes is a homogeneous
half-space, the exact Robin solution (``analytic.robin_surface_fluence``)
replaces the FEM, with no discretisation error and no mesh to solve.

The check that decides it (:func:`half_space_check`):

1. the optical properties are the same at every node;
2. every source and detector snaps to a boundary facet of one plane (same
   outward normal, every optode on it);
3. every other boundary (the sides and the bottom of the mesh, a bump in the
   surface) is far enough away.  A boundary changes the fluence at a detector
   by at most what a mirror image of the source across it would add (a
   reflecting wall adds exactly that image, an absorbing one subtracts it,
   and the Robin boundary lies between them).  Light reaching the detector
   by way of any point w of such a boundary travels at least
   |s - w| + |w - d| >= d_s + d_d, the distances of source and detector to
   the nearest such boundary, so the relative change is at most
   Phi_hs(d_s + d_d) / Phi_hs(rho) with Phi_hs the half-space surface
   fluence (which falls with distance).  The fast path is taken when that
   bound is within ``tol`` (1 % by default) for every pair.
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError


def half_space_check(mesh, mua_per_mm, musp_per_mm, n, sources_mm, detectors_mm, tol=0.01,
                     max_snap_mm=5.0):
    """Whether the scene is a homogeneous half-space under the optodes.

    Returns a dict: ``usable`` (bool), ``reason`` (why not, or None),
    ``boundary_effect_bound`` (largest relative change other boundaries can
    make, see module docstring), ``tol``, ``plane_normal``, ``clearance_mm``
    (smallest distance from an optode to another boundary).
    """
    from FluoTomoLib.analytic import log_robin_surface_fluence
    from FluoTomoLib.fem.operators import snap_to_surface

    out = {"usable": False, "reason": None, "tol": float(tol), "boundary_effect_bound": None,
           "clearance_mm": None, "plane_normal": None}
    mua = np.atleast_1d(np.asarray(mua_per_mm, float))
    musp = np.atleast_1d(np.asarray(musp_per_mm, float))
    if np.ptp(mua) > 0 or np.ptp(musp) > 0:
        out["reason"] = "the optical properties vary over the mesh"
        return out
    src = np.atleast_2d(np.asarray(sources_mm, float))
    det = np.atleast_2d(np.asarray(detectors_mm, float))
    qs, fs, _ = snap_to_surface(mesh, src, max_snap_mm, "source")
    qd, fd, _ = snap_to_surface(mesh, det, max_snap_mm, "detector")
    normals = mesh.boundary_normals[np.concatenate([fs, fd])]
    nrm = normals[0]
    if np.max(np.linalg.norm(normals - nrm, axis=1)) > 1e-6:
        out["reason"] = "the optodes are not all on one flat face of the mesh"
        return out
    pts = np.concatenate([qs, qd])
    offset = float(np.median(pts @ nrm))
    scale = float(np.max(np.ptp(mesh.nodes_mm, axis=0)))
    if np.max(np.abs(pts @ nrm - offset)) > 1e-6 * scale:
        out["reason"] = "the optodes are not all on one plane"
        return out
    out["plane_normal"] = nrm.tolist()
    # every boundary facet that is not part of that plane
    f = mesh.boundary_facets
    on_plane = ((np.linalg.norm(mesh.boundary_normals - nrm, axis=1) <= 1e-6)
                & np.all(np.abs(mesh.nodes_mm[f] @ nrm - offset) <= 1e-6 * scale, axis=1))
    other = np.flatnonzero(~on_plane)
    if len(other) == 0:
        raise FluoInputError("the mesh has no boundary but one plane", field=mesh.name)
    dist = _distance_to_facets(mesh, other, pts)
    d_s, d_d = dist[:len(qs)], dist[len(qs):]
    out["clearance_mm"] = float(dist.min())
    rho = np.linalg.norm(qs[:, None, :] - qd[None, :, :], axis=2)
    via = d_s[:, None] + d_d[None, :]
    log_direct = log_robin_surface_fluence(rho, float(mua[0]), float(musp[0]), n)
    log_via = log_robin_surface_fluence(via, float(mua[0]), float(musp[0]), n)
    bound = float(np.exp(np.max(log_via - log_direct)))
    out["boundary_effect_bound"] = bound
    if bound > tol:
        out["reason"] = (f"other boundaries of the mesh ({dist.min():.3g} mm from the nearest "
                         f"optode) can change the data by up to {100 * min(bound, 1e3):.3g} % "
                         f"(> {100 * tol:g} %)")
        return out
    out["usable"] = True
    return out


def _distance_to_facets(mesh, facet_ids, points):
    """Distance from each point to the nearest of the given boundary facets."""
    from scipy.spatial import cKDTree

    from FluoTomoLib.fem.locate import _closest_on_segments, _closest_on_triangles

    f = mesh.boundary_facets[facet_ids]
    v = mesh.nodes_mm[f]
    centroid = v.mean(axis=1)
    radius = float(np.max(np.linalg.norm(v - centroid[:, None, :], axis=2)))
    tree = cKDTree(centroid)
    out = np.empty(len(points))
    for i, p in enumerate(points):
        d0, _ = tree.query(p)
        cand = tree.query_ball_point(p, d0 + 2 * radius + 1e-12)
        P = np.repeat(p[None, :], len(cand), axis=0)
        if mesh.dim == 2:
            q, _ = _closest_on_segments(P, v[cand, 0], v[cand, 1])
        else:
            q, _ = _closest_on_triangles(P, v[cand, 0], v[cand, 1], v[cand, 2])
        out[i] = np.min(np.linalg.norm(q - P, axis=1))
    return out


def half_space_excitation_data(mesh, mua_per_mm, musp_per_mm, n, sources_mm, detectors_mm,
                               max_snap_mm=5.0):
    """(S, D) exact Robin half-space surface fluence [1/mm^2] for unit-power
    sources buried 1/mut' below the surface points nearest ``sources_mm``,
    read at the surface points nearest ``detectors_mm``: the FEM's model
    without its mesh (use after :func:`half_space_check` says it applies)."""
    from FluoTomoLib.analytic import robin_surface_fluence
    from FluoTomoLib.fem.operators import snap_to_surface

    qs = snap_to_surface(mesh, sources_mm, max_snap_mm, "source")[0]
    qd = snap_to_surface(mesh, detectors_mm, max_snap_mm, "detector")[0]
    rho = np.linalg.norm(qs[:, None, :] - qd[None, :, :], axis=2)
    return robin_surface_fluence(rho, float(np.ravel(mua_per_mm)[0]),
                                 float(np.ravel(musp_per_mm)[0]), n)
