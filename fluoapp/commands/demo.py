"""``fluo demo --out DIR [--quick]``: the end-to-end main job."""

from __future__ import annotations

import contextlib
from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoapp.demo.run import STAGE_NAMES, run_demo, stages_to_run
from fluoapp.runopts import add_run_options, check_run_options, executor_for
from fluoguide.progress import TqdmProgress
from fluoguide.runs.cluster import scheduler_address

#: the stages whose cases run on the run engine (--workers/--scheduler)
CASE_STAGES = ("tomography", "oral_tomography")


def _handler(args):
    only = [s.strip() for s in args.only.split(",")] if args.only is not None else None
    names = stages_to_run(only)            # an unknown stage is refused before a cluster starts
    threads = check_run_options(args)
    distributed = args.workers is not None or scheduler_address(args.scheduler) is not None
    if distributed and args.threads is None:
        threads = 1                        # workers side by side: one library thread each
    if not any(n in CASE_STAGES for n in names):
        distributed = False                # nothing to send: no cluster for the other stages
    with executor_for(args, threads) if distributed else contextlib.nullcontext() as ex, \
            TqdmProgress("fluo demo") as bar:
        metrics = run_demo(args.out, quick=args.quick, seed=args.seed, progress=bar, only=only,
                           executor=ex, threads=threads, resume=args.resume,
                           case_options={"truth": "simulate"} if args.simulate_truth else None)
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
        "meshing -> reconstructions, writing DIR/report.html, DIR/metrics.json and the MRML scene. "
        "The tomography cases (one per tube depth, and the oral cavity) are tasks of the run "
        "engine: --workers/--scheduler send them to Dask workers (docs/scale.md gives their "
        "memory), their records are in DIR/runs, and --resume reuses the ones a killed demo "
        "finished.")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--quick", action="store_true",
                   help="a first look: fewer tube depths, views and a smaller tomography region")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of every simulated noise (default %(default)s)")
    p.add_argument("--simulate-truth", action="store_true",
                   help="simulate the tube cases' true fields on the whole phantom instead of "
                   "reading the stored ones, and write them to DIR/tube_truth (how the stored "
                   "sets in FluoTomoLib/pipelines/data/tube_truth are made)")
    p.add_argument("--only", default=None, metavar="STAGE[,STAGE...]",
                   help="run these stages, after the stages they need; stages in run order: "
                   f"{', '.join(STAGE_NAMES)} (default: all)")
    add_run_options(p, threads_default=None)
    add_json_flag(p)
    p.set_defaults(func=_handler)
