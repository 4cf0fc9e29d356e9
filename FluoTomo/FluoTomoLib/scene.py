"""FluoTomo results into the MRML scene (node names per docs/scene.md)."""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io

from FluoTomoLib.fem.locate import locator
from FluoTomoLib.meshing.vtu_io import boundary_polydata


def store_mesh_surface(scene, mesh):
    """``FluoTomoMeshSurface``: the outer surface of a tetrahedral mesh."""
    return mrml_io.add_model(scene, "FluoTomoMeshSurface", boundary_polydata(mesh),
                             color=(0.6, 0.8, 1.0))


def resample_to_grid(mesh, nodal_values, shape_kji, spacing_mm, origin_mm):
    """P1 values of a mesh field at the voxel centres of an axis-aligned grid
    (zero outside the mesh), as float32 (K, J, I)."""
    k, j, i = np.meshgrid(*(np.arange(n) for n in shape_kji), indexing="ij")
    pts = np.asarray(origin_mm) + np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * np.asarray(
        spacing_mm)
    lo, hi = mesh.bounds()
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    out = np.zeros(len(pts), dtype=np.float32)
    P = locator(mesh).interpolation_matrix(pts[inside], outside="zero")
    out[inside] = P @ np.asarray(nodal_values, float)
    return out.reshape(shape_kji)


def store_reconstructions(scene, mesh, results, shape_kji, spacing_mm, origin_mm):
    """``FluoTomoYield<method>`` volumes on the CBCT grid, with the reconstruction
    summary as the ``FluoTomo.Reconstruction`` attribute, plus the mesh surface."""
    nodes = []
    for method, res in results.items():
        vol = resample_to_grid(mesh, res["yield"], shape_kji, spacing_mm, origin_mm)
        node = mrml_io.add_volume(scene, f"FluoTomoYield{method}", vol, spacing_mm, origin_mm)
        mrml_io.set_json_attribute(node, "FluoTomo.Reconstruction",
                                   {k: v for k, v in res.items() if k != "yield"})
        nodes.append(node)
    store_mesh_surface(scene, mesh)
    return nodes
