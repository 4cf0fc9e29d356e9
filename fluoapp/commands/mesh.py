"""``fluo mesh LABELMAP --out MESH.vtu``: label map to a tetrahedral mesh with regions."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag
from fluoguide.errors import FluoInputError


def _read_labelmap(path):
    """(labels_kji, spacing, origin, direction) in RAS (fluoguide.labelmap_io)."""
    from fluoguide.labelmap_io import read_labelmap

    return read_labelmap(path)


def _parse_floats(text, flag, count):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise FluoInputError("expected comma-separated numbers", field=flag, value=text) from None
    if len(vals) != count:
        raise FluoInputError(f"expected {count} numbers", field=flag, value=text)
    return vals


def _parse_refine(text):
    """``sphere:x,y,z,r,size`` or ``box:x0,x1,y0,y1,z0,z1,size`` (mm)."""
    kind, _, rest = text.partition(":")
    if kind not in ("sphere", "box"):
        raise FluoInputError("expected sphere:x,y,z,r,size or box:x0,x1,y0,y1,z0,z1,size",
                             field="--refine", value=text)
    return (kind, *_parse_floats(rest, "--refine", 5 if kind == "sphere" else 7))


def _handler(args):
    from FluoTomoLib.meshing.report import quality_report
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    t0 = time.perf_counter()
    labels, spacing, origin, direction = _read_labelmap(args.labelmap)
    roi = _parse_floats(args.roi, "--roi", 6) if args.roi else None
    if not args.fast:
        if args.optodes:
            raise FluoInputError("optode grading needs the structured mesher (--fast)",
                                 field="--optodes")
        return _quality(args, labels, spacing, origin, direction, roi, t0)
    if args.refine:
        raise FluoInputError("--refine needs the quality mesher (drop --fast)", field="--refine")
    if args.threads is not None:
        raise FluoInputError("--threads applies to the quality mesher (drop --fast)",
                             field="--threads", value=args.threads)
    import warnings

    from FluoTomoLib.meshing.voxel import MeshFidelityWarning

    edges = _optode_edges(args, labels, spacing, origin, direction) if args.optodes else None
    with warnings.catch_warnings():      # said in the JSON's "warnings" instead
        warnings.simplefilter("ignore", MeshFidelityWarning)
        mesh = mesh_labelmap_structured(labels, spacing, origin, args.size, roi=roi,
                                        direction=direction, edges_mm=edges)
    # the label map's own volume of each region inside the roi (exact voxel
    # overlaps, in the label map's frame: any direction)
    report = quality_report(mesh, mesh.meta["labelmap_volumes_mm3"])
    report["warnings"] = list(mesh.meta["warnings"])
    write_vtu(mesh, args.out)
    report["file"] = str(Path(args.out).resolve())
    report["method"] = "structured (Kuhn, 6 tets per cell)"
    if edges is not None:
        report["optode_grading"] = {"fine_mm": _fine_sizes(args.fine_size), "coarse_mm": args.size,
                                    "grid_lines": [len(e) for e in mesh.meta["edges_mm"]]}
    report["seconds"] = time.perf_counter() - t0
    return report


def _fine_sizes(text):
    vals = _parse_floats(text, "--fine-size", len(str(text).split(",")))
    if len(vals) not in (1, 3) or not all(np.isfinite(v) and v > 0 for v in vals):
        raise FluoInputError("needs one size or x,y,z sizes > 0 [mm]", field="--fine-size",
                             value=text)
    return vals * 3 if len(vals) == 1 else vals


def _optode_edges(args, labels, spacing, origin, direction):
    """Grid lines fine at the optodes' coordinates, growing to --size away
    (structured.optode_axis), over the label map's extent."""
    from fluoapp.commands.fem import _read_points_csv
    from FluoTomoLib.meshing.structured import optode_axis

    pts = np.concatenate([_read_points_csv(f, "--optodes") for f in args.optodes.split(",")])
    if pts.shape[1] != 3:
        raise FluoInputError("optodes must be x,y,z points [mm]", file=args.optodes,
                             field="--optodes")
    fine = _fine_sizes(args.fine_size)
    if any(f > args.size for f in fine):
        raise FluoInputError("must not be larger than --size", field="--fine-size",
                             value=args.fine_size)
    shape = np.array(labels.shape[::-1])
    corners = np.array([[i, j, k] for i in (-0.5, shape[0] - 0.5) for j in (-0.5, shape[1] - 0.5)
                        for k in (-0.5, shape[2] - 0.5)])
    ras = origin + (corners * spacing) @ np.asarray(direction, float).T
    lo, hi = ras.min(axis=0), ras.max(axis=0)
    return [optode_axis(lo[a], hi[a], pts[:, a], fine[a], args.size) for a in range(3)]


def _quality(args, labels, spacing, origin, direction, roi, t0):
    from FluoTomoLib.meshing.report import quality_report
    from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality
    from FluoTomoLib.meshing.vtu_io import write_vtu

    from fluoguide.progress import TqdmProgress

    refine = _parse_refine(args.refine) if args.refine else None
    with TqdmProgress("mesh (quality)") as prog:
        mesh = mesh_labelmap_quality(labels, spacing, origin, args.size, roi=roi,
                                     direction=direction, refine=refine, threads=args.threads,
                                     progress=prog)
    report = quality_report(mesh, mesh.meta["labelmap_volumes_mm3"])
    write_vtu(mesh, args.out)
    report["file"] = str(Path(args.out).resolve())
    report["method"] = "quality (SurfaceNets + fTetWild, regions cut at the surfaces)"
    for key in ("epsilon_mm", "timing", "merged_voxels", "boundary_slivers_removed", "refine",
                "surface_triangles", "threads"):
        report[key] = mesh.meta[key]
    report["seconds"] = time.perf_counter() - t0
    return report


def register(sub):
    p = sub.add_parser("mesh", help="label map to a tetrahedral mesh with region labels",
                       description="Label map (NRRD/NIfTI, or an MRML scene's CBCTLabels) to a "
                       "tetrahedral .vtu mesh; prints counts, per-region volumes against the "
                       "label map, dihedral angles, inverted and sliver elements.")
    p.add_argument("labelmap", help="label map file (.nrrd, .nii.gz), 3D Slicer segmentation "
                   "(.seg.nrrd: segment n -> label n+1) or scene (.mrml)")
    p.add_argument("--out", required=True, help="output mesh (.vtu)")
    p.add_argument("--size", type=float, default=1.6, help="element size [mm] (default 1.6)")
    p.add_argument("--roi", default=None, help="crop first: x0,x1,y0,y1,z0,z1 (RAS mm); write "
                   "--roi=-10,10,... when the first value is negative (default: the whole label map)")
    p.add_argument("--fast", action="store_true", help="structured voxel-to-tet mesher "
                   "(seconds; staircase surfaces); default: the quality mesher (fTetWild)")
    p.add_argument("--refine", default=None, help="quality mesher: smaller elements in "
                   "sphere:x,y,z,r,size or box:x0,x1,y0,y1,z0,z1,size (mm; default: none)")
    p.add_argument("--threads", type=int, default=None, help="fTetWild threads (default: all)")
    p.add_argument("--optodes", default=None, help="--fast: grade the grid to the optodes: "
                   "CSV file(s) of x,y,z points (sources,detectors); elements --fine-size at "
                   "their coordinates, growing by 1.2 per step to --size away from them "
                   "(docs/fem.md: optode-aware grading; default: a uniform grid)")
    p.add_argument("--fine-size", default="0.4", help="with --optodes: element size at the "
                   "optodes [mm], one value or x,y,z (default 0.4)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
