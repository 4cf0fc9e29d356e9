"""``fluo phantom NAME --out DIR``: write a digital phantom as an MRML scene."""

from __future__ import annotations

import time

from fluoapp.cli import add_json_flag
from fluoguide.errors import FluoInputError
from fluoguide.phantoms import PHANTOMS, make_phantom, write_phantom


def _handler(args):
    t0 = time.perf_counter()
    params = {"voxel_mm": args.voxel_mm, "seed": args.seed}
    if args.depth_mm is not None:
        if args.name != "cylinder-tube":
            raise FluoInputError("--depth-mm applies to the cylinder-tube phantom only",
                                 field="--depth-mm", value=args.depth_mm)
        params["depth_mm"] = args.depth_mm
    phantom = make_phantom(args.name, **params)
    scene_path = write_phantom(phantom, args.out)
    truth = phantom.truth()
    return {
        "phantom": phantom.name,
        "scene": str(scene_path),
        "truth": str(scene_path.parent / "truth.json"),
        "optics": str(scene_path.parent / "optics.json"),
        "yields_per_mm": {str(k): v for k, v in phantom.yields_per_mm().items()},
        "shape_kji": truth["shape_kji"],
        "voxel_mm": truth["voxel_mm"],
        "regions": {k: {"name": r["name"], "analytic_volume_mm3": r["analytic_volume_mm3"],
                        "labelmap_volume_mm3": r["labelmap_volume_mm3"],
                        "volume_error_pct": r["volume_error_pct"]}
                    for k, r in truth["regions"].items()},
        "seconds": time.perf_counter() - t0,
    }


def register(sub):
    p = sub.add_parser(
        "phantom", help="write a digital phantom (CBCT, label map, optical truth) as an MRML scene",
        description="Write a digital phantom as DIR/scene.mrml (volumes CBCT and CBCTLabels, "
        "NRRD files), DIR/truth.json (geometry, region volumes, optical properties) and "
        "DIR/optics.json (the optics without each region's ICG, as the fluo tomo commands "
        "read them; the true yields are yields_per_mm in the --json output). "
        f"Phantoms: {', '.join(PHANTOMS)}.")
    p.add_argument("name", help=f"one of: {', '.join(PHANTOMS)}")
    p.add_argument("--out", required=True, help="output folder (created; files replaced)")
    p.add_argument("--voxel-mm", type=float, default=0.8, help="voxel size [mm] (default 0.8)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--depth-mm", type=float, default=None,
                   help="cylinder-tube: depth of the tube axis below the surface [mm] (default 4.7)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
