"""The air-tissue surface of a CBCT label map, for ray casting and display.

Label map -> binary tissue mask -> VTK flying edges at the 0.5 iso-level ->
windowed-sinc smoothing (removes the voxel staircase without shrinking) ->
optional quadric decimation to a target triangle count -> consistently
oriented outward normals.  Coordinates are RAS mm (the label map's
IJK-to-RAS geometry is applied).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError


def surface_from_labelmap(labels_kji, ijk_to_ras, smoothing_iterations=20, pass_band=0.1,
                          target_triangles=None):
    """vtkPolyData of the boundary of ``labels > 0``.

    Parameters
    ----------
    labels_kji : (K, J, I) label map
    ijk_to_ras : (4, 4) voxel index to RAS mm
    smoothing_iterations : windowed-sinc iterations (0 = none)
    pass_band : windowed-sinc pass band (smaller = smoother)
    target_triangles : decimate to about this many triangles (None = keep)
    """
    import vtk
    from vtk.util import numpy_support as ns

    lab = np.asarray(labels_kji)
    if lab.ndim != 3:
        raise FluoInputError("label map must be 3D", field="labels", value=lab.shape)
    mask = (lab > 0).astype(np.uint8)
    if not mask.any():
        raise FluoInputError("label map has no tissue (all zero)", field="labels")
    # pad by one voxel so tissue touching the volume edge still closes
    mask = np.pad(mask, 1)
    img = vtk.vtkImageData()
    img.SetDimensions(mask.shape[2], mask.shape[1], mask.shape[0])
    img.SetOrigin(-1.0, -1.0, -1.0)
    img.GetPointData().SetScalars(ns.numpy_to_vtk(mask.ravel(), deep=True,
                                                  array_type=vtk.VTK_UNSIGNED_CHAR))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.5)
    fe.ComputeNormalsOff()
    fe.Update()
    poly = fe.GetOutput()
    if smoothing_iterations > 0:
        sm = vtk.vtkWindowedSincPolyDataFilter()
        sm.SetInputData(poly)
        sm.SetNumberOfIterations(int(smoothing_iterations))
        sm.SetPassBand(float(pass_band))
        sm.BoundarySmoothingOff()
        sm.FeatureEdgeSmoothingOff()
        sm.NonManifoldSmoothingOn()
        sm.NormalizeCoordinatesOn()
        sm.Update()
        poly = sm.GetOutput()
    if target_triangles is not None:
        n = poly.GetNumberOfPolys()
        if target_triangles < 4:
            raise FluoInputError("target triangle count must be >= 4", field="target_triangles",
                                 value=target_triangles)
        if target_triangles < n:
            dec = vtk.vtkQuadricDecimation()
            dec.SetInputData(poly)
            dec.SetTargetReduction(1.0 - float(target_triangles) / n)
            dec.VolumePreservationOn()
            dec.Update()
            poly = dec.GetOutput()
    # index space -> RAS
    m = vtk.vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            m.SetElement(i, j, float(ijk_to_ras[i][j]))
    tr = vtk.vtkTransform()
    tr.SetMatrix(m)
    tf = vtk.vtkTransformPolyDataFilter()
    tf.SetInputData(poly)
    tf.SetTransform(tr)
    tf.Update()
    normals = vtk.vtkPolyDataNormals()
    normals.SetInputData(tf.GetOutput())
    normals.ComputeCellNormalsOn()
    normals.ComputePointNormalsOn()
    normals.ConsistencyOn()
    normals.AutoOrientNormalsOn()  # outward for a closed surface
    normals.SplittingOff()
    normals.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(normals.GetOutput())
    return out


def surface_from_labelmap_node(node, target_triangles=None, **kwargs):
    """Surface of a label-map MRML node (RAS mm)."""
    from fluoguide import mrml_io

    geo = mrml_io.volume_geometry(node)
    return surface_from_labelmap(mrml_io.volume_array(node), geo["ijk_to_ras"],
                                 target_triangles=target_triangles, **kwargs)
