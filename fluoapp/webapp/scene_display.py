"""How FluoGuide nodes look in the app's views (slices and 3D).

Pure MRML/VTK display settings, so they are the same whether the views are
trame-slicer's remote views or desktop Slicer's.
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io
# the yield colour map and volume style are the foundation's (the desktop panel uses them too)
from fluoguide.display import YIELD_COLORMAP, style_yield_volume, yield_color_node_id

__all__ = ["YIELD_COLORMAP", "colormap_css_gradient", "style_yield_volume", "glyph_points_model",
           "isosurface_model"]

def colormap_css_gradient(scene, n_stops=9):
    """CSS linear-gradient sampled from the yield colour table (the colour bar)."""
    cid = yield_color_node_id(scene)
    if cid is None:
        return "linear-gradient(to right, black, white)"
    lut = scene.GetNodeByID(cid).GetLookupTable()
    n = lut.GetNumberOfTableValues()
    stops = []
    for k in range(n_stops):
        r, g, b, _ = lut.GetTableValue(int(round(k * (n - 1) / (n_stops - 1))))
        stops.append(f"rgb({int(255 * r)},{int(255 * g)},{int(255 * b)})")
    return "linear-gradient(to right, " + ", ".join(stops) + ")"


def glyph_points_model(scene, name, points_mm, radius_mm=0.6, color=(1.0, 0.2, 0.2)):
    """Small spheres at points (sources, detectors) as one model node."""
    import vtk

    pts = vtk.vtkPoints()
    for p in np.asarray(points_mm, float).reshape(-1, 3):
        pts.InsertNextPoint(*p)
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    sphere = vtk.vtkSphereSource()
    sphere.SetRadius(radius_mm)
    sphere.SetThetaResolution(10)
    sphere.SetPhiResolution(8)
    glyph = vtk.vtkGlyph3D()
    glyph.SetInputData(poly)
    glyph.SetSourceConnection(sphere.GetOutputPort())
    glyph.Update()
    return mrml_io.add_model(scene, name, glyph.GetOutput(), color=color)


def isosurface_model(scene, name, volume_node, level, color=(1.0, 0.75, 0.1)):
    """Iso-surface of a scalar volume at ``level`` (RAS mm) as a model node, or None."""
    import vtk

    img = vtk.vtkImageData()
    img.DeepCopy(volume_node.GetImageData())
    img.SetOrigin(0, 0, 0)
    img.SetSpacing(1, 1, 1)
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, float(level))
    m = vtk.vtkMatrix4x4()
    volume_node.GetIJKToRASMatrix(m)
    tf = vtk.vtkTransform()
    tf.SetMatrix(m)
    tpd = vtk.vtkTransformPolyDataFilter()
    tpd.SetInputConnection(fe.GetOutputPort())
    tpd.SetTransform(tf)
    tpd.Update()
    out = tpd.GetOutput()
    if out.GetNumberOfPoints() == 0:
        return None
    return mrml_io.add_model(scene, name, out, color=color)
