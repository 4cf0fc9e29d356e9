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


def unique_name(scene, base):
    """``base``, or ``base_1``, ``base_2``... when a node of that name exists: a
    second run never replaces the first's node."""
    if mrml_io.get_node(scene, base, required=False) is None:
        return base
    k = 1
    while mrml_io.get_node(scene, f"{base}_{k}", required=False) is not None:
        k += 1
    return f"{base}_{k}"


def store_mesh_model(scene, mesh_ras, output_node=None, base_name="FluoTomoMesh"):
    """A tetrahedral mesh (RAS mm) as a model node holding the volume mesh
    (vtkUnstructuredGrid, cell array ``region`` = label): into ``output_node``,
    or a new node ``FluoTomoMesh`` / ``FluoTomoMesh_1``..."""
    import slicer

    from FluoTomoLib.meshing.vtu_io import to_vtk

    node = output_node
    if node is None:
        node = slicer.vtkMRMLModelNode()
        node.SetName(unique_name(scene, base_name))
        scene.AddNode(node)
    node.SetAndObserveMesh(to_vtk(mesh_ras))
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    node.GetDisplayNode().SetColor(0.6, 0.8, 1.0)
    node.GetDisplayNode().SetOpacity(0.3)
    return node


def store_yield_volume(scene, array_kji, spacing_mm, origin_mm, direction, summary,
                       output_node=None, base_name="FluoTomoYield"):
    """A yield volume [1/mm] with its reconstruction summary (attribute
    ``FluoTomo.Reconstruction``): into ``output_node`` (a scalar volume node the
    caller chose) or a new node ``base_name`` / ``base_name_1``..."""
    name = output_node.GetName() if output_node is not None else unique_name(scene, base_name)
    if output_node is not None and output_node.GetScene() is not scene:
        scene.AddNode(output_node)
    if output_node is not None and not output_node.IsA("vtkMRMLScalarVolumeNode"):
        from fluoguide.errors import FluoInputError

        raise FluoInputError("the output must be a scalar volume node", field="outputVolumeNode",
                             value=output_node.GetClassName())
    node = mrml_io.add_volume(scene, name, np.asarray(array_kji, np.float32), spacing_mm,
                              origin_mm, direction=direction)
    mrml_io.set_json_attribute(node, "FluoTomo.Reconstruction", summary)
    return node


def grid_weights(mesh, shape_kji, spacing_mm, origin_mm, direction=None):
    """Sparse (K*J*I, N) P1 weights of a mesh's nodes (RAS) at the voxel centres
    of a volume grid (any IJK-to-RAS direction; an empty row outside the mesh),
    rows in C order of ``shape_kji``: one matrix for every field on that mesh."""
    import scipy.sparse as sp

    d = np.eye(3) if direction is None else np.asarray(direction, float)
    lo, hi = mesh.bounds()
    if np.allclose(d, np.eye(3), atol=1e-12):
        # axis-aligned: each element visits the voxel centres in its box (a
        # compiled loop), instead of a candidate search per voxel (14 s for the
        # demo's three volumes); only the voxels in the mesh's box, as the
        # search's arrays are per voxel
        org, step = np.asarray(origin_mm, float), np.asarray(spacing_mm, float)
        shape_ijk = np.array([int(n) for n in shape_kji][::-1])
        a = np.clip(np.floor((lo - org) / step).astype(int) - 1, 0, shape_ijk)
        b = np.clip(np.ceil((hi - org) / step).astype(int) + 2, a, shape_ijk)
        W = locator(mesh).grid_interpolation_matrix(org + a * step, step,
                                                    tuple((b - a)[::-1])).tocoo()
        i, j, k = np.unravel_index(W.row, tuple((b - a)[::-1]))[::-1]
        rows = np.ravel_multi_index((k + a[2], j + a[1], i + a[0]), tuple(shape_ijk[::-1]))
        return sp.csr_matrix((W.data, (rows, W.col)), shape=(int(np.prod(shape_ijk)), W.shape[1]))
    k, j, i = np.meshgrid(*(np.arange(n) for n in shape_kji), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * np.asarray(spacing_mm, float)
    pts = np.asarray(origin_mm, float) + ijk @ d.T
    inside = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
    P = locator(mesh).interpolation_matrix(pts[inside], outside="zero").tocoo()
    return sp.csr_matrix((P.data, (inside[P.row], P.col)), shape=(len(pts), P.shape[1]))


def resample_to_grid(mesh, nodal_values, shape_kji, spacing_mm, origin_mm, direction=None,
                     weights=None):
    """P1 values of a mesh field (RAS) at the voxel centres of a volume grid
    (any IJK-to-RAS direction; zero outside the mesh), as float32 (K, J, I).
    ``weights``: :func:`grid_weights` of this mesh and grid, when the caller
    resamples several fields."""
    if weights is None:
        weights = grid_weights(mesh, shape_kji, spacing_mm, origin_mm, direction)
    out = weights @ np.asarray(nodal_values, float)
    return out.astype(np.float32).reshape(tuple(int(n) for n in shape_kji))


def store_reconstructions(scene, mesh, results, shape_kji, spacing_mm, origin_mm,
                          direction=None):
    """``FluoTomoYield<method>`` volumes on the CBCT grid (its direction
    honoured), with the reconstruction summary as the ``FluoTomo.Reconstruction``
    attribute, plus the mesh surface."""
    nodes = []
    weights = grid_weights(mesh, shape_kji, spacing_mm, origin_mm, direction)
    for method, res in results.items():
        vol = resample_to_grid(mesh, res["yield"], shape_kji, spacing_mm, origin_mm, direction,
                               weights)
        node = mrml_io.add_volume(scene, f"FluoTomoYield{method}", vol, spacing_mm, origin_mm,
                                  direction=direction)
        mrml_io.set_json_attribute(node, "FluoTomo.Reconstruction",
                                   {k: v for k, v in res.items() if k != "yield"})
        nodes.append(node)
    store_mesh_surface(scene, mesh)
    return nodes
