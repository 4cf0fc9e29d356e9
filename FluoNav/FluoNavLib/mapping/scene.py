"""Surface-flux mapping results in the MRML scene (docs/scene.md).

- ``FluoNavSurfaceFlux`` (or a caller-chosen model node): a copy of the
  tissue surface with cell data ``transport`` (view-weighted mean optical
  transport T, dimensionless), ``surface_flux_w_per_mm2`` (weighted mean
  exitance J), ``view_weight`` (summed view-quality weight; 0 = never seen) and
  ``views`` (number of frames that saw the face); and the same quantities as
  point data (each point: the view-weighted mean over the faces around it,
  0 where none was seen), which Slicer's model display colours smoothly.
- ``FluoNavTransport`` / ``FluoNavFlux`` / ``FluoNavRaw`` (or caller-chosen
  volume nodes): the last corrected frame as 2D volumes (one slice, 1 mm
  "pixels"): optical transport T (0 where masked), surface flux J
  [W/mm^2] (0 where not valid) and counts above the dark offset [ADU];
  ``FluoNav.Mapping`` on the transport volume holds the frame's numbers (JSON).
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io

__all__ = ["SURFACE_NODE", "TRANSPORT_NODE", "RAW_NODE", "FLUX_NODE", "MAPPING_KEY",
           "write_surface_flux", "write_frame_images", "point_means"]

SURFACE_NODE = "FluoNavSurfaceFlux"
TRANSPORT_NODE = "FluoNavTransport"
FLUX_NODE = "FluoNavFlux"
RAW_NODE = "FluoNavRaw"
MAPPING_KEY = "FluoNav.Mapping"


def _triangles(polydata):
    from vtk.util import numpy_support as ns

    polys = polydata.GetPolys()
    conn = ns.vtk_to_numpy(polys.GetConnectivityArray())
    off = ns.vtk_to_numpy(polys.GetOffsetsArray())
    if len(off) > 1 and not np.all(np.diff(off) == 3):
        raise ValueError("surface has non-triangle polygons")
    return conn.reshape(-1, 3).astype(np.int64)


def point_means(triangles, n_points, face_values, face_weight):
    """Per point: the ``face_weight``-weighted mean of ``face_values`` over the
    faces that share it; 0 where every such face has weight 0."""
    tri = np.asarray(triangles, np.int64)
    w = np.repeat(np.asarray(face_weight, float), 3)
    num = np.bincount(tri.ravel(), weights=w * np.repeat(np.asarray(face_values, float), 3),
                      minlength=n_points)
    den = np.bincount(tri.ravel(), weights=w, minlength=n_points)
    return np.divide(num, den, out=np.zeros(n_points), where=den > 0)


def write_surface_flux(scene, tissue_polydata, transport, flux_w_per_mm2, weight, views,
                       node=None):
    """The surface with per-face (cell data) and per-point results in
    ``FluoNavSurfaceFlux`` (created or replaced) or in the caller's model ``node``."""
    import vtk
    from vtk.util import numpy_support as ns

    n = tissue_polydata.GetNumberOfCells()
    poly = vtk.vtkPolyData()
    poly.DeepCopy(tissue_polydata)
    for a in (poly.GetCellData(), poly.GetPointData()):
        for name in ("transport", "surface_flux_w_per_mm2", "view_weight", "views"):
            a.RemoveArray(name)  # a surface mapped before: its old results go
    tri = _triangles(poly)
    n_points = poly.GetNumberOfPoints()
    weight = np.asarray(weight, float)
    seen = (weight > 0).astype(float)
    for name, arr, dtype in (("transport", transport, np.float32),
                             ("surface_flux_w_per_mm2", flux_w_per_mm2, np.float64),
                             ("view_weight", weight, np.float32), ("views", views, np.int32)):
        a = np.ascontiguousarray(arr, dtype)
        if a.shape != (n,):
            raise ValueError(f"{name}: {a.shape} values for {n} faces")
        va = ns.numpy_to_vtk(a, deep=True)
        va.SetName(name)
        poly.GetCellData().AddArray(va)
        # points: weighted means of the results, plain means of the counts of views
        pw = weight if name in ("transport", "surface_flux_w_per_mm2") else seen
        pa = ns.numpy_to_vtk(np.ascontiguousarray(point_means(tri, n_points, a, pw), dtype),
                             deep=True)
        pa.SetName(name)
        poly.GetPointData().AddArray(pa)
    poly.GetCellData().SetActiveScalars("transport")
    poly.GetPointData().SetActiveScalars("transport")
    color = (1.0, 0.8, 0.3)
    if node is None:
        node = mrml_io.add_model(scene, SURFACE_NODE, poly, color=color)
    else:
        mrml_io.set_model_polydata(node, poly, color=color)
    display = node.GetDisplayNode()
    if display is not None:
        display.SetActiveScalarName("transport")
        display.SetScalarVisibility(True)
    return node


def write_frame_images(scene, transport, transport_mask, raw_above_offset, numbers,
                       flux_w_per_mm2=None, flux_mask=None, transport_node=None, raw_node=None,
                       flux_node=None):
    """One slice each: transport (``FluoNavTransport``), counts above offset
    (``FluoNavRaw``) and, when given, surface flux (``FluoNavFlux``); each into
    the caller's node when one is passed. Returns the transport node."""
    def put(node, default_name, array):
        if node is None:
            return mrml_io.add_volume(scene, default_name, array, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
        return mrml_io.set_volume_array(node, array, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))

    T = np.where(transport_mask, transport, 0.0).astype(np.float32)[None]
    raw = np.asarray(raw_above_offset, np.float32)[None]
    node = put(transport_node, TRANSPORT_NODE, T)
    mrml_io.set_json_attribute(node, MAPPING_KEY, numbers)
    put(raw_node, RAW_NODE, raw)
    if flux_w_per_mm2 is not None:
        mask = np.ones(np.shape(flux_w_per_mm2), bool) if flux_mask is None else flux_mask
        put(flux_node, FLUX_NODE, np.where(mask, flux_w_per_mm2, 0.0).astype(np.float32)[None])
    return node
