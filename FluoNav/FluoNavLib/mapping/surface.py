"""The air-tissue surface of a CBCT, for ray casting and display.

Two sources, one pipeline: an iso-surface (VTK flying edges) -> windowed-sinc
smoothing (removes the voxel staircase without shrinking) -> optional quadric
decimation to a target triangle count -> consistently oriented outward
normals.  Coordinates are RAS mm (the volume's IJK-to-RAS geometry is applied).

- :func:`surface_from_cbct`: the CBCT's own intensities, iso-surface half-way
  between air and tissue HU.  The partial-volume grey levels place the surface
  to a fraction of a voxel: on the oral-cavity phantom (0.8 mm voxels) its
  points lie 0.016 mm (median) from the analytic surface.  Use it whenever the
  CBCT is at hand.
- :func:`surface_from_labelmap`: the boundary of ``labels > 0`` (the 0.5 level
  of the binary mask).  A label map knows each voxel only as in or out, so its
  surface is off by up to half a voxel where the true boundary crosses voxel
  centres: 0.41 mm (median) on the same phantom, and its normals carry the
  staircase.  The light model depends on the normals (docs/surface-mapping.md,
  "Validated against an independent surface").
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report


def surface_from_labelmap(labels_kji, ijk_to_ras, smoothing_iterations=20, pass_band=0.1,
                          target_triangles=None, progress=None, cancel=None):
    """vtkPolyData of the boundary of ``labels > 0``.

    Parameters
    ----------
    labels_kji : (K, J, I) label map
    ijk_to_ras : (4, 4) voxel index to RAS mm
    smoothing_iterations : windowed-sinc iterations (0 = none)
    pass_band : windowed-sinc pass band (smaller = smoother)
    target_triangles : decimate to about this many triangles (None = keep)
    progress, cancel : ``progress(fraction, message)`` and a CancelToken
        (``fluoguide.progress``): each VTK filter's own progress is relayed, and
        a cancel aborts the running filter at its next progress event
    """
    lab = np.asarray(labels_kji)
    if lab.ndim != 3:
        raise FluoInputError("label map must be 3D", field="labels", value=lab.shape)
    mask = (lab > 0).astype(np.uint8)
    if not mask.any():
        raise FluoInputError("label map has no tissue (all zero)", field="labels")
    return _iso_surface(mask, 0.5, 0, ijk_to_ras, smoothing_iterations, pass_band,
                        target_triangles, progress, cancel)


def surface_from_cbct(hu_kji, ijk_to_ras, threshold_hu=None, smoothing_iterations=20,
                      pass_band=0.1, target_triangles=None, progress=None, cancel=None):
    """vtkPolyData of the air-tissue boundary of a CBCT (HU), at sub-voxel accuracy.

    Parameters
    ----------
    hu_kji : (K, J, I) CBCT intensities [HU]
    ijk_to_ras : (4, 4) voxel index to RAS mm
    threshold_hu : iso-level; default half-way between the air and the tissue
        peaks of the histogram (Otsu's threshold over -1024..3071 HU)
    smoothing_iterations, pass_band, target_triangles, progress, cancel : as
        :func:`surface_from_labelmap`
    """
    hu = np.asarray(hu_kji, dtype=np.float32)
    if hu.ndim != 3:
        raise FluoInputError("CBCT must be 3D", field="cbct", value=hu.shape)
    if not np.all(np.isfinite(hu)):
        raise FluoInputError("CBCT has non-finite values", field="cbct")
    if threshold_hu is None:
        threshold_hu = _otsu(hu)
    threshold_hu = float(threshold_hu)
    if not (np.isfinite(threshold_hu) and hu.min() < threshold_hu < hu.max()):
        raise FluoInputError("threshold must lie between the CBCT's lowest and highest value",
                             field="threshold_hu", value=threshold_hu)
    # air beyond the volume's edge, so tissue touching it still closes
    return _iso_surface(hu, threshold_hu, min(float(hu.min()), -1000.0), ijk_to_ras,
                        smoothing_iterations, pass_band, target_triangles, progress, cancel)


def _otsu(values, bins=512):
    """Otsu's threshold of a sample (the level that best splits it into two classes)."""
    v = np.clip(np.asarray(values, float).ravel(), -1024.0, 3071.0)
    hist, edges = np.histogram(v, bins=bins)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[int(np.argmax(between)) + 1])


def _update(algorithm, progress, start, stop, message, cancel):
    """``algorithm.Update()`` with VTK's own progress events relayed to ``progress``
    (as ``start..stop``) and ``cancel`` aborting the filter at its next event
    (FluoCancelled then). A filter reports as often as VTK makes it (the quadric
    decimation every 10,000 edge collapses: see :func:`_decimate`)."""
    check_cancel(cancel)
    report(progress, start, message)

    def on_progress(caller, _event):
        done = caller.GetProgress()
        report(progress, start + (stop - start) * done, f"{message} ({100 * done:.0f} %)")
        if cancel is not None and cancel.cancelled:
            caller.AbortExecuteOn()

    tag = algorithm.AddObserver("ProgressEvent", on_progress)
    try:
        algorithm.Update()
    finally:
        algorithm.RemoveObserver(tag)
    check_cancel(cancel)      # an aborted filter's output is partial: never returned
    return algorithm.GetOutput()


#: quadric decimation starts from at most this many times the target triangle count;
#: vtkDecimatePro takes a finer surface down to it first (see :func:`_decimate`)
QUADRIC_START_FACTOR = 3.0


def _decimate(poly, target, progress, start, stop, cancel):
    """``poly`` decimated to about ``target`` triangles (volume-preserving quadric
    decimation), reporting at least every few tenths of a second.

    Quadric decimation alone is slow on a label map's surface, and silent: most
    of its vertices lie on the flat facets of the voxel staircase, where every
    edge collapse costs nothing, so the collapses pile up into fans of ever
    higher valence and each costs more than the last. On the 0.4 mm oral
    cavity (312,408 -> 62,000 triangles) it took 90-240 s on a shared 2-core
    machine with its 10,000-collapse reports up to 35 s apart (a sphere of the
    same size: 1.6 s). vtkDecimatePro removes those flat vertices in about a
    second, reporting every 0.1 s, so it first takes the surface down to
    :data:`QUADRIC_START_FACTOR` times the target and the quadric decimation
    finishes from there (2.7 s in all). The result is as close to the
    undecimated surface as the quadric decimation alone: 0.0001 mm mean and
    0.0037 mm largest distance (both ways) on that surface, vertex normals
    within 0.02 deg median, 0.73 deg p95 of the nearest undecimated vertex's
    (the quadric decimation alone: the same to these digits; vtkDecimatePro
    alone to the target: 0.001 mm mean, 0.048 mm largest). A surface with at
    most that factor more triangles than the target goes to the quadric
    decimation directly. ``cancel`` is checked between the two.
    """
    import vtk

    n = poly.GetNumberOfPolys()
    message = f"decimating {n:,} to {target:,} triangles"
    middle = int(QUADRIC_START_FACTOR * target)
    if n > middle:
        pro = vtk.vtkDecimatePro()
        pro.SetInputData(poly)
        pro.SetTargetReduction(1.0 - middle / n)
        pro.PreserveTopologyOn()   # no holes, no split: the surface stays closed
        pro.SplittingOff()
        split = start + 0.3 * (stop - start)      # about a third of the time
        poly = _update(pro, progress, start, split, f"{message}: flat facets", cancel)
        start = split
    dec = vtk.vtkQuadricDecimation()
    dec.SetInputData(poly)
    dec.SetTargetReduction(1.0 - float(target) / poly.GetNumberOfPolys())
    dec.VolumePreservationOn()
    return _update(dec, progress, start, stop, message, cancel)


def _iso_surface(volume_kji, level, pad_value, ijk_to_ras, smoothing_iterations, pass_band,
                 target_triangles, progress=None, cancel=None):
    import vtk
    from vtk.util import numpy_support as ns

    vol = np.pad(volume_kji, 1, constant_values=pad_value)
    img = vtk.vtkImageData()
    img.SetDimensions(vol.shape[2], vol.shape[1], vol.shape[0])
    img.SetOrigin(-1.0, -1.0, -1.0)
    img.GetPointData().SetScalars(ns.numpy_to_vtk(vol.ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, float(level))
    fe.ComputeNormalsOff()
    # fractions: decimation (when asked) is by far the longest step
    ends = (0.05, 0.2, 0.9) if target_triangles is not None else (0.2, 0.8, 0.8)
    poly = _update(fe, progress, 0.0, ends[0], "iso-surface", cancel)
    if poly.GetNumberOfPolys() == 0:
        raise FluoInputError("no surface at this level", field="iso-level", value=level)
    if smoothing_iterations > 0:
        sm = vtk.vtkWindowedSincPolyDataFilter()
        sm.SetInputData(poly)
        sm.SetNumberOfIterations(int(smoothing_iterations))
        sm.SetPassBand(float(pass_band))
        sm.BoundarySmoothingOff()
        sm.FeatureEdgeSmoothingOff()
        sm.NonManifoldSmoothingOn()
        sm.NormalizeCoordinatesOn()
        poly = _update(sm, progress, ends[0], ends[1],
                       f"smoothing {poly.GetNumberOfPolys():,} triangles", cancel)
    if target_triangles is not None:
        n = poly.GetNumberOfPolys()
        if target_triangles < 4:
            raise FluoInputError("target triangle count must be >= 4", field="target_triangles",
                                 value=target_triangles)
        if target_triangles < n:
            poly = _decimate(poly, int(target_triangles), progress, ends[1], ends[2], cancel)
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
    moved = _update(tf, progress, ends[2], ends[2], "to RAS", cancel)
    normals = vtk.vtkPolyDataNormals()
    normals.SetInputData(moved)
    normals.ComputeCellNormalsOn()
    normals.ComputePointNormalsOn()
    normals.ConsistencyOn()
    normals.AutoOrientNormalsOn()  # outward for a closed surface
    normals.SplittingOff()
    oriented = _update(normals, progress, ends[2], 1.0, "outward normals", cancel)
    out = vtk.vtkPolyData()
    out.DeepCopy(oriented)
    return out


def surface_from_labelmap_node(node, target_triangles=None, **kwargs):
    """Surface of a label-map MRML node (RAS mm); reads the node, so on its thread
    (``FluoNavLogic.prepareBuildSurface`` reads first and computes on a worker)."""
    from fluoguide import mrml_io

    geo = mrml_io.volume_geometry(node)
    return surface_from_labelmap(mrml_io.volume_array(node), geo["ijk_to_ras"],
                                 target_triangles=target_triangles, **kwargs)


def surface_from_cbct_node(node, target_triangles=None, **kwargs):
    """Surface of a CBCT scalar-volume MRML node (RAS mm), see :func:`surface_from_cbct`."""
    from fluoguide import mrml_io

    geo = mrml_io.volume_geometry(node)
    return surface_from_cbct(mrml_io.volume_array(node), geo["ijk_to_ras"],
                             target_triangles=target_triangles, **kwargs)
