"""A label map to a tetrahedral mesh file with its quality report (``fluo mesh``,
``FluoTomoLogic.meshToFile``): the quality mesher (fTetWild) or the structured
one, optionally graded to the optodes."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError


def optode_edges(labels_kji, spacing, origin, direction, optodes, fine_mm, size_mm):
    """Grid lines of the structured mesher, ``fine_mm`` (x, y, z) [mm] at the
    optodes' coordinates (``optodes``: (N, 3) [RAS mm], checked as field
    ``optodes``) growing to ``size_mm`` away (``structured.optode_axis``), over
    the label map's extent."""
    from FluoTomoLib.meshing.structured import optode_axis

    pts = np.asarray(optodes, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FluoInputError("optodes must be x,y,z points [mm]", field="optodes")
    shape = np.array(labels_kji.shape[::-1])
    corners = np.array([[i, j, k] for i in (-0.5, shape[0] - 0.5) for j in (-0.5, shape[1] - 0.5)
                        for k in (-0.5, shape[2] - 0.5)])
    ras = np.asarray(origin) + (corners * spacing) @ np.asarray(direction, float).T
    lo, hi = ras.min(axis=0), ras.max(axis=0)
    return [optode_axis(lo[a], hi[a], pts[:, a], fine_mm[a], size_mm) for a in range(3)]


def mesh_to_file(labels_kji, spacing, origin, direction, size_mm, out_file, roi=None,
                 quality=True, refine=None, threads=None, optodes=None, fine_mm=None,
                 progress=None):
    """Mesh a label map, write the mesh (.vtu) and report its quality.

    Parameters
    ----------
    labels_kji, spacing, origin, direction : the label map and its geometry
        (RAS mm)
    size_mm : float
        Element size [mm] (away from the optodes when graded).
    out_file : path
        The .vtu file to write (cell array ``region`` = label).
    roi : [x0, x1, y0, y1, z0, z1] RAS mm, optional
        Crop first (default: the whole label map).
    quality : bool
        fTetWild (smooth interfaces, seconds to minutes) instead of the
        structured voxel-to-tetrahedra mesher (a second, staircase surfaces).
    refine : tuple, optional
        Quality mesher: ``("sphere", x, y, z, r, size)`` or ``("box", x0, x1,
        y0, y1, z0, z1, size)`` [mm].
    threads : int, optional
        Quality mesher: fTetWild's threads (default: all).
    optodes, fine_mm : (N, 3) RAS mm and (x, y, z) [mm], optional
        Structured mesher: grid lines ``fine_mm`` at the optodes, growing to
        ``size_mm`` away.

    Returns
    -------
    dict
        The quality report (counts, region volumes against the label map's,
        dihedral angles, bad elements) with ``file`` and ``method``.
    """
    from FluoTomoLib.meshing.report import quality_report
    from FluoTomoLib.meshing.vtu_io import write_vtu

    if quality:
        from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality

        mesh = mesh_labelmap_quality(labels_kji, spacing, origin, size_mm, roi=roi,
                                     direction=direction, refine=refine, threads=threads,
                                     progress=progress)
        report = quality_report(mesh, mesh.meta["labelmap_volumes_mm3"])
        write_vtu(mesh, out_file)
        report["file"] = str(Path(out_file).resolve())
        report["method"] = "quality (SurfaceNets + fTetWild, regions cut at the surfaces)"
        for key in ("epsilon_mm", "timing", "merged_voxels", "boundary_slivers_removed",
                    "refine", "surface_triangles", "threads"):
            report[key] = mesh.meta[key]
        return report
    from FluoTomoLib.meshing.voxel import MeshFidelityWarning, mesh_labelmap_structured

    edges = None
    if optodes is not None:
        edges = optode_edges(labels_kji, spacing, origin, direction, optodes, fine_mm, size_mm)
    with warnings.catch_warnings():      # said in the report's "warnings" instead
        warnings.simplefilter("ignore", MeshFidelityWarning)
        mesh = mesh_labelmap_structured(labels_kji, spacing, origin, size_mm, roi=roi,
                                        direction=direction, edges_mm=edges)
    # the label map's own volume of each region inside the roi (exact voxel
    # overlaps, in the label map's frame: any direction)
    report = quality_report(mesh, mesh.meta["labelmap_volumes_mm3"])
    report["warnings"] = list(mesh.meta["warnings"])
    write_vtu(mesh, out_file)
    report["file"] = str(Path(out_file).resolve())
    report["method"] = "structured (Kuhn, 6 tets per cell)"
    if edges is not None:
        report["optode_grading"] = {"fine_mm": list(fine_mm), "coarse_mm": size_mm,
                                    "grid_lines": [len(e) for e in mesh.meta["edges_mm"]]}
    return report
