"""Quality report of a tetrahedral mesh: counts, region volumes, angles, bad elements."""

from __future__ import annotations

import numpy as np


def dihedral_angles_deg(mesh):
    """(M, 6) dihedral angles [deg] of every tetrahedron (one per edge)."""
    p = mesh.nodes_mm[mesh.elements]                       # (M, 4, 3)
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]   # face opposite node i
    normals = []
    for i, (a, b, c) in enumerate(faces):
        n = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])
        # orient outward: away from the opposite node
        flip = np.einsum("ij,ij->i", n, p[:, i] - p[:, a]) > 0
        n[flip] *= -1
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    out = []
    for i in range(4):
        for j in range(i + 1, 4):
            cosang = np.clip(-np.einsum("ij,ij->i", normals[i], normals[j]), -1, 1)
            out.append(np.degrees(np.arccos(cosang)))
    return np.stack(out, axis=1)


def aspect_ratio(mesh):
    """Longest edge / (2 sqrt(6) inradius): 1 for a regular tetrahedron."""
    p = mesh.nodes_mm[mesh.elements]
    edges = [np.linalg.norm(p[:, i] - p[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)]
    longest = np.max(edges, axis=0)
    area = sum(0.5 * np.linalg.norm(np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]), axis=1)
               for a, b, c in [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)])
    inradius = 3 * mesh.measures / area
    return longest / (2 * np.sqrt(6) * inradius)


def quality_report(mesh, labelmap_volumes_mm3=None, sliver_deg=5.0):
    """Counts, per-region volumes (vs label map), dihedral angles, aspect ratio,
    inverted and sliver elements (min dihedral below ``sliver_deg``)."""
    if mesh.dim != 3:
        raise ValueError("quality report is for tetrahedral meshes")
    dih = dihedral_angles_deg(mesh)
    ar = aspect_ratio(mesh)
    regions = {}
    for label, vol in mesh.region_measures().items():
        entry = {"volume_mm3": vol}
        if labelmap_volumes_mm3 and label in labelmap_volumes_mm3:
            ref = labelmap_volumes_mm3[label]
            entry["labelmap_volume_mm3"] = ref
            entry["volume_error_pct"] = 100.0 * (vol - ref) / ref
        regions[int(label)] = entry
    return {
        "nodes": mesh.n_nodes, "tets": mesh.n_elements, "regions": regions,
        "min_dihedral_deg": float(dih.min()), "mean_dihedral_deg": float(dih.mean()),
        "max_dihedral_deg": float(dih.max()),
        "aspect_ratio_mean": float(ar.mean()), "aspect_ratio_max": float(ar.max()),
        "inverted": int(np.sum(mesh.signed_measures <= 0)),
        "slivers": int(np.sum(dih.min(axis=1) < sliver_deg)),
    }
