"""``fluo demo --out DIR [--quick]``: the end-to-end main job."""

from __future__ import annotations

from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoapp.demo.run import STAGE_NAMES, run_demo
from fluoguide.progress import TqdmProgress


def _handler(args):
    only = [s.strip() for s in args.only.split(",")] if args.only is not None else None
    with TqdmProgress("fluo demo") as bar:
        metrics = run_demo(args.out, quick=args.quick, seed=args.seed, progress=bar, only=only)
    metrics["report"] = str(Path(args.out).resolve() / "report.html")
    if args.json:
        return metrics
    # on a terminal: the headline numbers; everything else is in the report
    brief = {"report": metrics["report"], "stage_seconds": metrics["stage_seconds"]}
    for key in ("camera_calibration", "light_calibration", "surface_mapping", "tomography",
                "oral_tomography"):
        if key in metrics:
            brief[key] = {k: v for k, v in metrics[key].items()
                          if "error" in k or "per case" in k or "speed-up" in k
                          or "miss rate" in k or "frames/s" in k}
    if "warnings" in metrics:          # never left out of the short form
        brief["warnings"] = metrics["warnings"]
    return brief


def register(sub):
    p = sub.add_parser(
        "demo", help="run the end-to-end demo on the digital phantoms (writes DIR/report.html)",
        description="Phantoms -> calibrations -> tracked acquisition -> surface-flux mapping -> "
        "meshing -> reconstructions, writing DIR/report.html, DIR/metrics.json and the MRML scene.")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--quick", action="store_true",
                   help="a first look: fewer tube depths, views and a smaller tomography region")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of every simulated noise (default %(default)s)")
    p.add_argument("--only", default=None, metavar="STAGE[,STAGE...]",
                   help="run these stages, after the stages they need; stages in run order: "
                   f"{', '.join(STAGE_NAMES)} (default: all)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
