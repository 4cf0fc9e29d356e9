"""``fluo mesh LABELMAP --out MESH.vtu``: label map to a tetrahedral mesh with regions."""

from __future__ import annotations

import time
from pathlib import Path

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
        return _quality(args, labels, spacing, origin, direction, roi, t0)
    if args.refine:
        raise FluoInputError("--refine needs the quality mesher (drop --fast)", field="--refine")
    import warnings

    from FluoTomoLib.meshing.voxel import MeshFidelityWarning

    with warnings.catch_warnings():      # said in the JSON's "warnings" instead
        warnings.simplefilter("ignore", MeshFidelityWarning)
        mesh = mesh_labelmap_structured(labels, spacing, origin, args.size, roi=roi,
                                        direction=direction)
    # the label map's own volume of each region inside the roi (exact voxel
    # overlaps, in the label map's frame: any direction)
    report = quality_report(mesh, mesh.meta["labelmap_volumes_mm3"])
    report["warnings"] = list(mesh.meta["warnings"])
    write_vtu(mesh, args.out)
    report["file"] = str(Path(args.out).resolve())
    report["method"] = "structured (Kuhn, 6 tets per cell)"
    report["seconds"] = time.perf_counter() - t0
    return report


def _quality(args, labels, spacing, origin, direction, roi, t0):
    from FluoTomoLib.meshing.report import quality_report
    from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality
    from FluoTomoLib.meshing.vtu_io import write_vtu

    refine = _parse_refine(args.refine) if args.refine else None
    mesh = mesh_labelmap_quality(labels, spacing, origin, args.size, roi=roi, direction=direction,
                                 refine=refine, threads=args.threads)
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
    p.add_argument("--roi", default=None, help="crop first: x0,x1,y0,y1,z0,z1 (RAS mm); write --roi=-10,10,... "
                   "when the first value is negative")
    p.add_argument("--fast", action="store_true", help="structured voxel-to-tet mesher "
                   "(seconds; staircase surfaces); default: the quality mesher (fTetWild)")
    p.add_argument("--refine", default=None, help="quality mesher: smaller elements in "
                   "sphere:x,y,z,r,size or box:x0,x1,y0,y1,z0,z1,size (mm)")
    p.add_argument("--threads", type=int, default=None, help="fTetWild threads (default: all)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
