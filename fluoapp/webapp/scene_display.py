"""How FluoGuide nodes look in the app's views (slices and 3D).

Pure MRML/VTK display settings, so they are the same whether the views are
trame-slicer's remote views or desktop Slicer's.
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io

__all__ = ["YIELD_COLORMAP", "colormap_css_gradient", "style_yield_volume", "glyph_points_model",
           "isosurface_model"]

# Slicer's "Iron" table (black - purple - red - yellow - white): monotonic in
# lightness, so a brighter colour always means more yield, and it is in
# slicer-core's built-in colours (the file-based Inferno/Viridis are not).
YIELD_COLORMAP = "vtkMRMLColorTableNodeIron"


def _color_node_id(scene, preferred=YIELD_COLORMAP):
    for cid in (preferred, "vtkMRMLColorTableNodeRainbow"):
        if scene.GetNodeByID(cid) is not None:
            return cid
    return None


def colormap_css_gradient(scene, n_stops=9):
    """CSS linear-gradient sampled from the yield colour table (the colour bar)."""
    cid = _color_node_id(scene)
    if cid is None:
        return "linear-gradient(to right, black, white)"
    lut = scene.GetNodeByID(cid).GetLookupTable()
    n = lut.GetNumberOfTableValues()
    stops = []
    for k in range(n_stops):
        r, g, b, _ = lut.GetTableValue(int(round(k * (n - 1) / (n_stops - 1))))
        stops.append(f"rgb({int(255 * r)},{int(255 * g)},{int(255 * b)})")
    return "linear-gradient(to right, " + ", ".join(stops) + ")"


def style_yield_volume(scene, node, threshold_fraction=0.2):
    """Colour map, window over [0, max] and a lower threshold at a fraction of the max.

    Returns ``(vmin, vmax, threshold)`` in the volume's units [1/mm].
    """
    arr = mrml_io.volume_array(node)
    vmax = float(np.nanmax(arr)) if arr.size else 0.0
    vmax = vmax if vmax > 0 else 1.0
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    disp = node.GetDisplayNode()
    cid = _color_node_id(scene)
    if cid:
        disp.SetAndObserveColorNodeID(cid)
    disp.SetAutoWindowLevel(0)
    disp.SetWindowLevelMinMax(0.0, vmax)
    thr = float(threshold_fraction) * vmax
    disp.SetAutoThreshold(0)
    disp.SetApplyThreshold(1)
    disp.SetThreshold(thr, vmax * 1.0001)
    return 0.0, vmax, thr


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
