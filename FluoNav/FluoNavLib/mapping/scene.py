"""Surface-flux mapping results in the MRML scene (docs/scene.md).

- ``FluoNavSurfaceFlux``: a copy of ``TissueSurface`` with cell data
  ``transport`` (view-weighted mean optical transport T, dimensionless),
  ``surface_flux_w_per_mm2`` (weighted mean exitance J), ``view_weight``
  (summed view-quality weight; 0 = never seen) and ``views`` (number of frames
  that saw the face).
- ``FluoNavTransport`` / ``FluoNavRaw``: the last corrected frame as 2D
  volumes (one slice, 1 mm "pixels"): optical transport T (0 where masked) and
  counts above the dark offset [ADU]; ``FluoNav.Mapping`` on
  ``FluoNavTransport`` holds the frame's numbers (JSON).
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io

__all__ = ["SURFACE_NODE", "TRANSPORT_NODE", "RAW_NODE", "MAPPING_KEY", "write_surface_flux",
           "write_frame_images"]

SURFACE_NODE = "FluoNavSurfaceFlux"
TRANSPORT_NODE = "FluoNavTransport"
RAW_NODE = "FluoNavRaw"
MAPPING_KEY = "FluoNav.Mapping"


def write_surface_flux(scene, tissue_polydata, transport, flux_w_per_mm2, weight, views):
    """Create or replace ``FluoNavSurfaceFlux``: the surface with per-face results."""
    import vtk
    from vtk.util import numpy_support as ns

    n = tissue_polydata.GetNumberOfCells()
    poly = vtk.vtkPolyData()
    poly.DeepCopy(tissue_polydata)
    for name, arr, dtype in (("transport", transport, np.float32),
                             ("surface_flux_w_per_mm2", flux_w_per_mm2, np.float64),
                             ("view_weight", weight, np.float32), ("views", views, np.int32)):
        a = np.ascontiguousarray(arr, dtype)
        if a.shape != (n,):
            raise ValueError(f"{name}: {a.shape} values for {n} faces")
        va = ns.numpy_to_vtk(a, deep=True)
        va.SetName(name)
        poly.GetCellData().AddArray(va)
    poly.GetCellData().SetActiveScalars("transport")
    return mrml_io.add_model(scene, SURFACE_NODE, poly, color=(1.0, 0.8, 0.3))


def write_frame_images(scene, transport, transport_mask, raw_above_offset, numbers):
    """Create or replace ``FluoNavTransport`` and ``FluoNavRaw`` (one slice each)."""
    T = np.where(transport_mask, transport, 0.0).astype(np.float32)[None]
    raw = np.asarray(raw_above_offset, np.float32)[None]
    node = mrml_io.add_volume(scene, TRANSPORT_NODE, T, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    mrml_io.set_json_attribute(node, MAPPING_KEY, numbers)
    mrml_io.add_volume(scene, RAW_NODE, raw, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    return node
