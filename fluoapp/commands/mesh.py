"""``fluo mesh LABELMAP --out MESH.vtu``: label map to a tetrahedral mesh with regions."""

from __future__ import annotations

import time

import numpy as np

from fluoapp.cli import add_json_flag
from fluoapp.commands import as_flags, module_logic
from fluoguide.errors import FluoInputError


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


def _fine_sizes(text):
    vals = _parse_floats(text, "--fine-size", len(str(text).split(",")))
    if len(vals) not in (1, 3) or not all(np.isfinite(v) and v > 0 for v in vals):
        raise FluoInputError("needs one size or x,y,z sizes > 0 [mm]", field="--fine-size",
                             value=text)
    return vals * 3 if len(vals) == 1 else vals


def _check_options(args):
    """Options of the other mesher are refused, not ignored; returns the
    optode files and the element sizes at them (or None)."""
    if not args.fast:
        if args.optodes:
            raise FluoInputError("optode grading needs the structured mesher (--fast)",
                                 field="--optodes")
        return None, None
    if args.refine:
        raise FluoInputError("--refine needs the quality mesher (drop --fast)", field="--refine")
    if args.threads is not None:
        raise FluoInputError("--threads applies to the quality mesher (drop --fast)",
                             field="--threads", value=args.threads)
    if not args.optodes:
        return None, None
    fine = _fine_sizes(args.fine_size)
    if any(f > args.size for f in fine):
        raise FluoInputError("must not be larger than --size", field="--fine-size",
                             value=args.fine_size)
    return args.optodes.split(","), fine


def _handler(args):
    from contextlib import nullcontext

    from fluoguide.progress import TqdmProgress

    t0 = time.perf_counter()
    roi = _parse_floats(args.roi, "--roi", 6) if args.roi else None
    optodes, fine = _check_options(args)
    refine = _parse_refine(args.refine) if args.refine else None
    logic = module_logic("FluoTomo")
    bar = nullcontext() if args.fast else TqdmProgress("mesh (quality)")
    with bar as prog, as_flags({"optodes": "--optodes"}):
        report = logic.meshToFile(args.labelmap, args.out, args.size, roi=roi, quality=not args.fast,
                                  refine=refine, threads=args.threads, optodes=optodes,
                                  fineSizeMm=fine, progress=prog)
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
