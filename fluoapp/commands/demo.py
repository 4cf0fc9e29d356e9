"""``fluo demo --out DIR [--quick]``: the end-to-end main job."""

from __future__ import annotations

from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoapp.demo.run import run_demo
from fluoguide.progress import TqdmProgress


def _handler(args):
    only = [s.strip() for s in args.only.split(",")] if args.only is not None else None
    with TqdmProgress("fluo demo", force=not args.json) as bar:
        metrics = run_demo(args.out, quick=args.quick, seed=args.seed, progress=bar, only=only)
    metrics["report"] = str(Path(args.out).resolve() / "report.html")
    if args.json:
        return metrics
    # on a terminal: the headline numbers; everything else is in the report
    brief = {"report": metrics["report"], "stage_seconds": metrics["stage_seconds"]}
    for key in ("camera_calibration", "light_calibration", "surface_mapping", "tomography"):
        if key in metrics:
            brief[key] = {k: v for k, v in metrics[key].items()
                          if "error" in k or "per case" in k or "speed-up" in k
                          or "miss rate" in k or "frames/s" in k}
    return brief


def register(sub):
    p = sub.add_parser(
        "demo", help="run the end-to-end demo on the digital phantoms (writes DIR/report.html)",
        description="Phantoms -> calibrations -> tracked acquisition -> surface-flux mapping -> "
        "meshing -> reconstructions, writing DIR/report.html, DIR/metrics.json and the MRML scene.")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--quick", action="store_true", help="a first look in about a minute")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--only", default=None, help="comma-separated stage names to run")
    add_json_flag(p)
    p.set_defaults(func=_handler)
