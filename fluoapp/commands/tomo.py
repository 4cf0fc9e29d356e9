"""``fluo tomo simulate``, ``fluo tomo plan``, ``fluo tomo reconstruct``, ``fluo tomo acquire``,
``fluo tomo record-scan`` and ``fluo tomo batch``:
fluorescence tomography of any label map from the shell
(docs/tomography-own-scene.md; the batch runs on the run engine, docs/scale.md)."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import GRADINGS, module_logic
from fluoapp.runopts import add_run_options, check_run_options, executor_for
from fluoguide.errors import FluoInputError
from fluoguide.progress import TqdmProgress
# the accuracy levels' settings, named in --help (read when the parser is built:
# the logic class, and the scene it needs, only when a command runs)
from FluoTomoLib.tomography.accuracy import LEVELS


def _accuracy_help(pct="%%", lead="accuracy level (default %(default)s): "):
    """What each accuracy level sets (``accuracy.LEVELS``), for ``--help``.

    ``pct``: "%%" in an option's help (%-formatted), "%" in a description. The
    levels' measured error and time are not printed: they belong to one machine
    and one run, and live in docs/tomography-own-scene.md ("Accuracy levels")
    next to the benchmark that measures them.
    """
    parts = [f"{name} = {lv['recon_mm']:g} mm reconstruction elements, region-of-interest "
             f"tolerance {lv['truncation_pct']:g} {pct}" for name, lv in LEVELS.items()]
    return (lead + "; ".join(parts) + "; each refined to half across the target, capped at "
            "the sources' burial depth (each level's error and time: "
            "docs/tomography-own-scene.md, \"Accuracy levels\")")


ACCURACY_HELP = _accuracy_help()


def _simulate_accuracy_help():
    sizes = ", ".join(f"{k} {v['simulate_mm']:g} / {v['simulate_coarse_mm']:g}"
                      for k, v in LEVELS.items())
    return ("simulation mesh (default %(default)s), element size near the optodes and target "
            f"/ elsewhere [mm]: {sizes}")


def _parse_yields(text):
    """``LABEL:VALUE[,LABEL:VALUE...]`` -> {label: yield per mm}."""
    from fluoguide.parameters import parse_yields

    return parse_yields(text, field="--yield")


def _load(args):
    """(FluoTomoLogic, LabelMap, Optics) of ``--labels`` and ``--optics``, every
    label of the map in the optics."""
    logic = module_logic("FluoTomo")
    lm = logic.labelMap(args.labels)
    optics = logic.readOptics(args.optics)
    optics.check_labels(lm.labels)
    return logic, lm, optics


def _check_simulate_options(args):
    """The options that apply to the Monte Carlo engine only, and the optode
    files given both or neither."""
    if args.photons is not None and args.engine != "mc":
        raise FluoInputError("photons are for the Monte Carlo engine (--engine mc)",
                             field="--photons", value=args.photons)
    for name, v in (("--workers", args.workers), ("--scheduler", args.scheduler),
                    ("--mc-runs", args.mc_runs), ("--resume", args.resume or None)):
        if v is not None and args.engine != "mc":
            raise FluoInputError("runs Monte Carlo's photon budgets (--engine mc)", field=name,
                                 value=v)
    if args.resume and not args.mc_runs:
        raise FluoInputError("--resume needs the folder of the earlier runs (--mc-runs)",
                             field="--resume")


def _scan_targets(args, logic, lm):
    """The labels the default scan covers: --scan-targets, else --target alone,
    else None (every inclusion: the Lib's default); the labels are checked by
    the Lib (``logic.checkScanTargets``) before any progress is drawn."""
    if args.scan_targets is None:
        return None if args.target is None else \
            logic.checkScanTargets(lm, [args.target], field="--target")
    if args.sources:
        raise FluoInputError("the scan's targets are for the default scan: the positions "
                             "were given", field="--scan-targets", value=args.scan_targets)
    if args.scan_targets.strip().lower() == "inclusions":
        return None
    try:
        labels = [int(v) for v in args.scan_targets.split(",") if v.strip()]
    except ValueError:
        raise FluoInputError("expected labels separated by commas, or 'inclusions'",
                             field="--scan-targets", value=args.scan_targets) from None
    return logic.checkScanTargets(lm, labels, field="--scan-targets")


def _simulate(args):
    from fluoguide import atomic

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)      # before any work
    yields = _parse_yields(args.yield_spec)
    _check_simulate_options(args)
    threads = check_run_options(args)
    store = None
    if args.mc_runs:
        atomic.check_writable(args.mc_runs, "--mc-runs", folder=True)
    if (args.sources is None) != (args.detectors is None):
        raise FluoInputError("give both --sources and --detectors, or neither (default scan)",
                             field="--sources" if args.sources is None else "--detectors")
    logic, lm, optics = _load(args)
    for label in yields:        # checked before any progress is drawn
        if label not in lm.labels:
            raise FluoInputError("label is not in the label map", file=args.labels,
                                 field="--yield", value=label)
    scan_targets = _scan_targets(args, logic, lm)
    src = det = None
    if args.sources:            # read, and on the tissue surface, before any progress
        src = logic.readPoints(args.sources, "--sources", lm, "sources")
        det = logic.readPoints(args.detectors, "--detectors", lm, "detectors")
    if args.mc_runs:
        from fluoguide.runs.store import RunStore

        store = RunStore(args.mc_runs, resume=args.resume)
    # a bar only on a terminal: a pipe gets the JSON or one error line; the Monte
    # Carlo runs go where the run options say (serial here by default)
    with TqdmProgress("simulate") as bar, executor_for(args, threads) as ex:
        acq, info = logic.simulateToFolder(
            lm, optics, yields, args.out, src, det, noise=args.noise_pct, seed=args.seed,
            engine=args.engine, accuracy=args.accuracy, progress=bar,
            exclude_mm=args.exclude_mm, simulate_mm=args.element_mm, target=args.target,
            photons=args.photons, executor=ex, mc_store=store, threads=threads,
            scan_targets=scan_targets)
    return {"output": str(args.out), "sources": len(acq.sources_ras_mm),
            "detectors": len(acq.detectors_ras_mm), "measurements": acq.n_measurements,
            "engine": info["engine"], "simulation_mesh_nodes": info.get("mesh_nodes"),
            "photon_noise_pct": info.get("photon_noise_pct"),
            "mc_executor": info.get("mc_executor"),
            "noise_pct": info["noise_pct"], "seed": info["seed"], "target": info["target"],
            "scan_patches": None if not info.get("scan") else info["scan"]["patches"],
            "scan_coverage": info["scan_coverage"]["regions"],
            "warnings": info["warnings"], "seconds": time.perf_counter() - t0}


def _triple(text, field):
    """``X,Y,Z`` -> three floats (the Lib checks what they mean)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3:
        raise FluoInputError("expected three numbers X,Y,Z (RAS)", field=field, value=text)
    return vals


def _plan(args):
    from fluoguide import atomic

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)      # before any work
    try:
        targets = [int(v) for v in args.target.split(",") if v.strip()]
    except ValueError:
        raise FluoInputError("expected labels separated by commas", field="--target",
                             value=args.target) from None
    options = {"min_spacing_mm": args.min_spacing_mm, "noise_pct": args.noise_pct,
               "max_angle_deg": args.max_angle_deg, "time_budget_s": args.time_budget_s,
               "exclude_mm": args.exclude_mm, "detectors_per_side": args.detectors_per_side,
               "visible_from": None if args.visible_from is None else
               _triple(args.visible_from, "--visible-from"),
               "camera_ras": None if args.camera_at is None else
               _triple(args.camera_at, "--camera-at"),
               "yield_by_label": None if args.yield_spec is None else
               _parse_yields(args.yield_spec)}
    names = {"targets": "--target", "positions": "--positions", "min_spacing_mm":
             "--min-spacing-mm", "noise_pct": "--noise-pct", "max_angle_deg": "--max-angle-deg",
             "time_budget_s": "--time-budget-s", "exclude_mm": "--exclude-mm",
             "detectors_per_side": "--detectors-per-side", "visible_from": "--visible-from",
             "camera_ras": "--camera-at", "yield": "--yield"}
    from fluoapp.commands import as_flags

    with as_flags(names):
        logic, lm, optics = _load(args)
        targets = logic.checkPlanInputs(lm, targets, args.positions, **options)
        with TqdmProgress("plan") as bar:
            doc = logic.planScanToFolder(lm, optics, targets, args.out, args.positions,
                                         progress=bar, **options)
    return {"output": str(args.out), "sources": len(doc["sources"]),
            "pairs_measured": doc["pairs_measured"], "predicted": doc["predicted"],
            "default_scan_predicted": doc["default_scan_predicted"],
            "warnings": doc["warnings"], "seconds": time.perf_counter() - t0}


def _check_reconstruct_options(args, lm):
    """The usual bad input, refused before any progress is drawn; returns the
    region of interest of ``--roi`` (or None)."""
    roi = None
    if args.roi:
        try:
            roi = [float(v) for v in args.roi.split(",")]
        except ValueError:
            raise FluoInputError("expected x0,x1,y0,y1,z0,z1 (RAS mm)", field="--roi",
                                 value=args.roi) from None
    if args.target is not None and args.target not in lm.labels:
        raise FluoInputError("target label is not in the label map", file=args.labels,
                             field="--target", value=args.target)
    if args.noise_pct is not None and not (math.isfinite(args.noise_pct)
                                           and 0 < args.noise_pct < 100):
        raise FluoInputError("the data's relative noise must be within 0..100 % (one SD per "
                             "measurement)", field="--noise-pct", value=args.noise_pct)
    if args.segmentation_mm is not None and not (math.isfinite(args.segmentation_mm)
                                                 and 0 <= args.segmentation_mm <= 5):
        raise FluoInputError("the segmentation's accuracy must be within 0..5 mm",
                             field="--segmentation-mm", value=args.segmentation_mm)
    return roi


def _reconstruct(args):
    from fluoguide import atomic

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)      # before any work
    logic, lm, optics = _load(args)
    acq = logic.readAcquisition(args.acquisition, lm, optics)
    roi = _check_reconstruct_options(args, lm)
    if args.data_model == "log":
        acq.check_for_log()
    acq = logic.readAcquisition(acq, lm, optics, checkOptodes=True)
    with TqdmProgress(f"reconstruct {args.method}") as bar:
        summary = logic.reconstructToFolder(
            lm, optics, acq, args.out, method=args.method, lam=args.lam, target=args.target,
            accuracy=args.accuracy, progress=bar, size_mm=args.element_mm, roi_ras=roi,
            truncation_pct=args.truncation_pct, data_model=args.data_model,
            self_absorption=("HP", "SP") if args.self_absorption else (),
            grading=GRADINGS[args.grading], noise_pct=args.noise_pct,
            segmentation_mm=args.segmentation_mm)
    summary["seconds"] = time.perf_counter() - t0
    return summary


def _batch(args):
    from fluoguide import atomic
    from fluoguide.jsonable import dumps

    t0 = time.perf_counter()
    threads = check_run_options(args)
    logic = module_logic("FluoTomo")
    # every row and input checked, and the output folder, before any work or writing
    cases = logic.loadBatch(args.batch, methods=args.methods, lam=args.lam,
                            accuracy=args.accuracy)
    atomic.check_writable(args.out, "--out", folder=True)
    with TqdmProgress("tomo batch") as bar, executor_for(args, threads) as ex:
        out = logic.runBatch(cases, args.out, executor=ex, threads=threads, resume=args.resume,
                             progress=bar)
    # seconds: the whole command (checks, cluster start and stop, files); run_seconds:
    # the run engine's part (the tasks, and writing their records)
    out = {"batch": str(args.batch), "out": str(args.out), **out,
           "run_seconds": out["seconds"], "seconds": time.perf_counter() - t0}
    atomic.write_text(Path(args.out) / "batch.json", dumps(out))
    if out["failures"]:
        out["_exit_code"] = 1     # every case is written; the batch is not a success
        print(f"fluo: error: {out['failures']} of {out['tasks']} cases failed (their rows in "
              f"{Path(args.out) / 'table.csv'} say why)", file=sys.stderr)
    return out


def _frame_list(text, field):
    """``N[,N...]`` -> frame numbers (the faults of record-scan)."""
    if not text:
        return []
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise FluoInputError("expected frame numbers separated by commas", field=field,
                             value=text) from None


def _record_scan(args):
    from fluoguide import atomic

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)
    yields = _parse_yields(args.yield_spec)
    faults = {"missing_pose": _frame_list(args.missing_pose, "--missing-pose"),
              "saturated": _frame_list(args.saturated_frames, "--saturated-frames"),
              "spot_off": _frame_list(args.spot_off, "--spot-off")}
    logic, lm, optics = _load(args)
    for label in yields:
        if label not in lm.labels:
            raise FluoInputError("label is not in the label map", file=args.labels,
                                 field="--yield", value=label)
    with TqdmProgress("record-scan") as bar:
        r = logic.recordScan(lm, optics, yields, args.out, trackingErrorMm=args.tracking_error_mm,
                             handEyeErrorMm=args.hand_eye_error_mm, seed=args.seed,
                             accuracy=args.accuracy, progress=bar,
                             tracking_error_deg=args.tracking_error_deg, **faults)
    return {"output": str(args.out), "frames": r["frames"], "faults": r["truth"]["faults"],
            "tracking_error_mm": args.tracking_error_mm,
            "hand_eye_error_mm": args.hand_eye_error_mm, "seed": args.seed,
            "simulation_mesh_nodes": r["truth"]["mesh_nodes"],
            "seconds": time.perf_counter() - t0}


def _acquire(args):
    from fluoguide import atomic

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)
    if args.calibration and args.scene:
        raise FluoInputError("give the calibrations once: --calibration or --scene",
                             field="--scene", value=args.scene)
    logic, lm, optics = _load(args)
    calibration = args.calibration or args.scene
    with TqdmProgress("acquire") as bar:
        acq, rows, info = logic.acquireRecording(lm, optics, args.recording, args.out,
                                                 calibration, args.spot_tolerance_mm,
                                                 sourceFrom=args.source_from, progress=bar)
    return {"output": str(args.out), "frames": info["frames"],
            "frames_used": info["frames_used"], "frames_rejected": info["frames_rejected"],
            "rejected": [{k: r[k] for k in ("frame", "reason", "detail")} for r in rows
                         if not r["used"]],
            "sources": len(acq.sources_ras_mm), "detectors": len(acq.detectors_ras_mm),
            "measurements": acq.n_measurements, "noise_pct": info["noise_pct"],
            "source_from": args.source_from,
            "spot_tolerance_mm": info["spot_tolerance_mm"],
            "time_sync_tolerance_s": info["time_sync_tolerance_s"],
            "warnings": info["warnings"], "seconds": time.perf_counter() - t0}


def _register_simulate(tomo):
    """Declare `fluo tomo simulate`: the acquisition simulated on a label map."""
    p = tomo.add_parser(
        "simulate", help="simulate an acquisition of a label map (whole-map FEM mesh)",
        description="Simulate what a tracked laser scan and camera would measure on a label "
        "map: a mesh of the whole label map (finer than any reconstruction's), the optical "
        "properties of optics.json per label (plus the fluorophore's absorption), the yields "
        "of --yield, relative Gaussian noise. Writes an acquisition folder "
        "(docs/tomography-own-scene.md).")
    p.add_argument("--labels", required=True, help="label map: .nrrd, .nii(.gz), .seg.nrrd "
                   "(segment n -> label n+1) or .mrml (its CBCTLabels); any direction, spacing "
                   "and origin")
    p.add_argument("--optics", required=True, help="optics.json: n, excitation and emission "
                   "mua_per_mm / musp_per_mm per label, optional fluorophore")
    p.add_argument("--yield", dest="yield_spec", required=True, metavar="LABEL:VALUE[,...]",
                   help="fluorescence yield eta*mua_f [1/mm] per label, e.g. 7:0.0026 "
                   "(labels not named: 0)")
    p.add_argument("--noise-pct", type=float, default=1.0,
                   help="relative Gaussian noise per measurement [%%] (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--sources", default=None, help="CSV of source points x,y,z (RAS mm) on the "
                   "tissue surface (default: a 4 x 4 grid, 3 mm pitch, over each target)")
    p.add_argument("--detectors", default=None, help="CSV of detector points x,y,z (RAS mm) "
                   "(default: a 7 x 7 grid, 1.5 mm pitch, over each target)")
    p.add_argument("--target", type=int, default=None, help="label meshed finely around (and "
                   "the default scan's only target when --scan-targets is not given; default: "
                   "the smallest region that is not the largest)")
    p.add_argument("--scan-targets", default=None, metavar="LABEL[,...]|inclusions",
                   help="labels the default scan lays one patch over each (at most 4; "
                   "default: --target, or else every inclusion: each label under a tenth of "
                   "the tissue's volume). The JSON's scan_coverage says what the scan sees "
                   "of every region")
    p.add_argument("--exclude-mm", type=float, default=None, help="pairs closer than this to "
                   "their source are marked unused (default 3)")
    p.add_argument("--engine", choices=["fem", "mc"], default="fem",
                   help="the light-transport engine (default fem: diffusion FEM on a mesh of "
                   "the whole label map; mc: Monte Carlo photon transport on the label map's "
                   "voxels with MCX-CL/MCX, the 'mc' extra; needs cubic voxels)")
    p.add_argument("--photons", type=int, default=None,
                   help="--engine mc: photons per run, each source and detector run twice "
                   "(default 100000; the time grows in proportion, the photon noise, reported "
                   "in the output, falls as 1/sqrt(photons))")
    p.add_argument("--accuracy", choices=["fast", "balanced", "fine"], default="balanced",
                   help=_simulate_accuracy_help())
    p.add_argument("--element-mm", type=float, default=None, help="simulation element size "
                   "near the optodes and target [mm] (default: from --accuracy)")
    p.add_argument("--mc-runs", default=None, metavar="DIR",
                   help="--engine mc: record every Monte Carlo run here as it finishes (a "
                   "killed simulation continues with --resume; default: not recorded)")
    add_run_options(p)
    p.add_argument("--out", required=True, help="acquisition folder to write "
                   "(acquisition.json, sources.csv, detectors.csv, data.csv)")
    add_json_flag(p)
    p.set_defaults(func=_simulate)


def _register_plan(tomo):
    """Declare `fluo tomo plan`: the scan planner."""
    p = tomo.add_parser(
        "plan", help="plan a scan: the laser entry points that narrow the targets' intervals",
        description="Choose the tracked laser's entry points on the skin the camera can see "
        "near the targets, to minimise the targets' predicted hard-prior (HP) 95 %% intervals "
        "under the noise model (a greedy A-optimal design with exchange passes, on the scan "
        "coverage's half-space sensitivities; docs/physics.md section 8.6). The detectors are "
        "the default scan's grid over each target. Writes OUT/sources.csv and "
        "OUT/detectors.csv (for fluo tomo simulate --sources/--detectors) and OUT/plan.json "
        "(the predicted interval per target, each source's approach direction, the default "
        "grid's prediction with as many positions; docs/tomography-own-scene.md).")
    p.add_argument("--labels", required=True, help="label map (.nrrd, .nii(.gz), .seg.nrrd, "
                   ".mrml)")
    p.add_argument("--optics", required=True, help="optics.json (every label of the map)")
    p.add_argument("--target", required=True, metavar="LABEL[,LABEL...]",
                   help="the labels the scan is for (at most 4)")
    p.add_argument("--positions", type=int, required=True,
                   help="laser positions to choose (the default scan lays 16 per target)")
    p.add_argument("--detectors-per-side", type=int, default=None,
                   help="detector grid per target, N x N at 1.5 mm pitch (default 7)")
    p.add_argument("--min-spacing-mm", type=float, default=2.0,
                   help="no two entry points closer than this [mm] (default %(default)s)")
    p.add_argument("--noise-pct", type=float, default=1.0, help="relative noise per "
                   "measurement [%%] of the noise model (default %(default)s)")
    p.add_argument("--yield", dest="yield_spec", default=None, metavar="LABEL:VALUE[,...]",
                   help="assumed yields [1/mm] (default: every label but the largest 1, the "
                   "largest 0.01: only ratios matter)")
    p.add_argument("--visible-from", default=None, metavar="X,Y,Z",
                   help="RAS direction towards the camera: entry points whose outward normal "
                   "is within --max-angle-deg of it (default: the mean outward normal of "
                   "the skin over the targets)")
    p.add_argument("--camera-at", default=None, metavar="X,Y,Z",
                   help="RAS position of the camera instead: within --max-angle-deg of the "
                   "direction to it and not hidden behind other tissue (default: none, "
                   "--visible-from's direction)")
    p.add_argument("--max-angle-deg", type=float, default=60.0,
                   help="the visibility cone's half-angle [deg] (default %(default)s)")
    p.add_argument("--exclude-mm", type=float, default=3.0, help="pairs closer than this are "
                   "not measured, as fluo tomo simulate's (default %(default)s)")
    p.add_argument("--time-budget-s", type=float, default=60.0,
                   help="the planner's time [s]: the exchange passes stop when it is spent "
                   "(default %(default)s)")
    p.add_argument("--out", required=True, help="plan folder (sources.csv, detectors.csv, "
                   "plan.json)")
    add_json_flag(p)
    p.set_defaults(func=_plan)


def _register_reconstruct(tomo):
    """Declare `fluo tomo reconstruct`: the yield reconstruction."""
    p = tomo.add_parser(
        "reconstruct", help="reconstruct the fluorescence yield of a label map",
        description="NP / SP / HP reconstruction of the yield on a label map from an "
        "acquisition folder; the region of interest is chosen from the light's decay length "
        "and its truncation error estimated; writes OUT/yield.nrrd on the label map's grid "
        "(same origin, spacing and direction) and OUT/reconstruction.json. "
        + _accuracy_help("%", "Accuracy levels: "))
    p.add_argument("--labels", required=True, help="label map (.nrrd, .nii(.gz), .seg.nrrd, "
                   ".mrml); its labels are the priors' regions")
    p.add_argument("--optics", required=True, help="optics.json (every label of the map)")
    p.add_argument("--acquisition", required=True, help="acquisition folder (acquisition.json: "
                   "sources, detectors, data; or tracked camera frames)")
    p.add_argument("--method", choices=["NP", "SP", "HP"], default="HP",
                   help="no, soft or hard priors from the labels (default HP)")
    p.add_argument("--lambda", dest="lam", type=float, default=None,
                   help="regularisation lambda (default 10)")
    p.add_argument("--target", type=int, default=None, help="label graded and refined across "
                   "(default: the smallest region that is not the largest)")
    p.add_argument("--accuracy", choices=["fast", "balanced", "fine"], default="balanced",
                   help=ACCURACY_HELP)
    p.add_argument("--element-mm", type=float, default=None,
                   help="reconstruction element size [mm] (default: from --accuracy)")
    p.add_argument("--truncation-pct", type=float, default=None, help="largest change of the "
                   "data by the region-of-interest cut [%%] (default: from --accuracy, "
                   "1 for balanced)")
    p.add_argument("--roi", default=None, help="x0,x1,y0,y1,z0,z1 (RAS mm) instead of the "
                   "automatic region of interest (default: chosen; write --roi=-10,... when "
                   "the first value is negative)")
    p.add_argument("--data-model", choices=["linear", "log"], default="linear",
                   help="fit the data (linear, default) or their logarithm (log: every used "
                   "measurement must be > 0)")
    p.add_argument("--noise-pct", type=float, default=None,
                   help="the data's relative noise, one SD per measurement [%%]: the fit is "
                   "tested against it and the intervals widen when the model explains the "
                   "data worse (default: the acquisition's noise_pct, or its simulation's; "
                   "else judged from the residual)")
    p.add_argument("--segmentation-mm", type=float, default=None,
                   help="how far the label map's boundaries may be off [mm] (the CBCT "
                   "segmentation's accuracy): the regions are solved again with their "
                   "boundaries moved by it and the 95 %% intervals reach the values found "
                   "(default: half the largest voxel; 0: exact)")
    p.add_argument("--grading", choices=["none", "grid", "bisection"], default="bisection",
                   help="the reconstruction mesh: bisection (default), refined only near the "
                   "optodes and the regions' boundaries and growing away from them "
                   "(docs/physics.md section 8.1; on the scene family: docs/validation.md); "
                   "none, a uniform grid refined in bands through the optodes and the target; "
                   "grid, that grid's cells twice as large away from them")
    p.add_argument("--no-self-absorption", dest="self_absorption", action="store_false",
                   help="do not feed the fluorophore's absorption back (default: fed back for "
                   "HP and SP when optics.json names a fluorophore)")
    p.add_argument("--out", required=True, help="output folder (yield.nrrd, "
                   "reconstruction.json)")
    add_json_flag(p)
    p.set_defaults(func=_reconstruct)


def _register_acquire(tomo):
    """Declare `fluo tomo acquire`: the recording-to-acquisition conversion."""
    p = tomo.add_parser(
        "acquire", help="turn a recorded tracked laser scan into an acquisition folder",
        description="Read a recording (docs/recording.md: 16-bit frames, frames.csv, "
        "poses.csv, recording.json; or FluoNav's recorder folder with a recording.json) and "
        "the calibrations (camera intrinsics, hand-eye, TrackerToReference, laser beam line, "
        "radiometric gain); per frame: the tool poses at the frame's time, the tracked beam "
        "on the label map's surface (the source), the laser spot in the frame checked "
        "against it, saturation away from the source. Frames that cannot be used are "
        "listed with their reason in OUT/frames.json and the output, never used; the others "
        "give OUT/acquisition.json, sources.csv, detectors.csv, data.csv (boundary fluence "
        "per watt) for fluo tomo reconstruct.")
    p.add_argument("--recording", required=True, help="recording folder (recording.json)")
    p.add_argument("--labels", required=True, help="label map (.nrrd, .nii(.gz), .seg.nrrd, "
                   ".mrml): its tissue surface places the sources and the camera's pixels")
    p.add_argument("--optics", required=True, help="optics.json (the tissue's refractive "
                   "index turns exitance into boundary fluence)")
    p.add_argument("--calibration", default=None, help="calibration JSON file (FluoCalib's; "
                   "default: the one recording.json names)")
    p.add_argument("--scene", default=None, help="scene.mrml holding the calibrations "
                   "(FluoCalibration node, CameraToCameraTool, TrackerToReference) instead of "
                   "--calibration (default: not used)")
    p.add_argument("--spot-tolerance-mm", type=float, default=None,
                   help="how far the laser spot seen by the camera may lie from the tracked "
                   "beam's surface point [mm] (default 2; docs/recording.md)")
    p.add_argument("--source-from", choices=("spot", "beam"), default="spot",
                   help="each source's surface point: the laser spot the camera sees (the "
                   "same camera pose as the frame's readings, so tracking and hand-eye errors "
                   "move both together) or the tracked beam's (default spot; docs/recording.md)")
    p.add_argument("--out", required=True, help="acquisition folder to write")
    add_json_flag(p)
    p.set_defaults(func=_acquire)


def _register_record_scan(tomo):
    """Declare `fluo tomo record-scan`: the rendered recording of a laser scan."""
    p = tomo.add_parser(
        "record-scan", help="render a recording of a tracked laser scan from a label map's "
        "truth (to check fluo tomo acquire against)",
        description="Render what a tracked laser raster scan over the label map's inclusions "
        "would record (docs/recording.md): the FEM emission light of each laser position on a "
        "mesh of the whole label map, 16-bit frames from the camera's true pose with the "
        "laser spot, shot and read noise; the tool poses as a tracker with the chosen error "
        "reports them, the hand-eye calibration off by the chosen error; the calibrations in "
        "OUT/calibration.json.")
    p.add_argument("--labels", required=True, help="label map (.nrrd, .nii(.gz), .seg.nrrd, "
                   ".mrml)")
    p.add_argument("--optics", required=True, help="optics.json (every label of the map)")
    p.add_argument("--yield", dest="yield_spec", required=True, metavar="LABEL:VALUE[,...]",
                   help="true fluorescence yield eta*mua_f [1/mm] per label, e.g. 7:0.0026")
    p.add_argument("--tracking-error-mm", type=float, default=0.5,
                   help="3D RMS position error of each reported tool pose [mm] (default "
                   "%(default)s)")
    p.add_argument("--tracking-error-deg", type=float, default=0.1,
                   help="rotation error of each reported tool pose, per axis about the tool's "
                   "origin [deg] (default %(default)s)")
    p.add_argument("--hand-eye-error-mm", type=float, default=0.3,
                   help="displacement of the written hand-eye calibration from the true one "
                   "[mm] (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="noise and error seed (default 0)")
    p.add_argument("--accuracy", choices=["fast", "balanced", "fine"], default="fast",
                   help=_simulate_accuracy_help())
    p.add_argument("--missing-pose", default=None, metavar="N[,N...]",
                   help="frames whose laser tool the tracker reports missing (a test fault; "
                   "default: none)")
    p.add_argument("--saturated-frames", default=None, metavar="N[,N...]",
                   help="frames exposed 20 times too long (a test fault; default: none)")
    p.add_argument("--spot-off", default=None, metavar="N[,N...]",
                   help="frames whose reported laser pose is 5 mm from where the light went "
                   "(a test fault; default: none)")
    p.add_argument("--out", required=True, help="recording folder to write")
    add_json_flag(p)
    p.set_defaults(func=_record_scan)


def _register_batch(tomo):
    """Declare `fluo tomo batch`: the batch reconstruction."""
    p = tomo.add_parser(
        "batch", help="reconstruct many (label map, optics, acquisition) cases: yield volumes "
        "and one table (serially or on Dask)",
        description="A batch file (CSV with a header, or JSON/YAML with 'cases': a list) names "
        "one case per row: labels, optics, acquisition (paths relative to the batch file's "
        "folder, inside it), optional name, methods, lambda, accuracy, target and truth (the "
        "target's true yield [1/mm]: the table then carries the errors). Every row and input is "
        "checked before any work; each case runs all its methods on one model (one mesh, one "
        "Jacobian). Writes OUT/table.csv (one row per case, as each finishes; --resume "
        "continues a killed run), OUT/cases/NAME/METHOD/yield.nrrd + reconstruction.json and "
        "OUT/batch.json. Exit 1 when a case failed (its row says why), 2 on bad input "
        "(docs/scale.md, docs/tomography-own-scene.md).")
    p.add_argument("batch", help="batch file (.csv, .json, .yaml, .yml)")
    p.add_argument("--methods", default=None, metavar="NP,SP,HP",
                   help="methods of the cases that name none (default NP,SP,HP)")
    p.add_argument("--lambda", dest="lam", type=float, default=None,
                   help="regularisation lambda of the cases that name none (default 10)")
    p.add_argument("--accuracy", choices=["fast", "balanced", "fine"], default=None,
                   help="accuracy of the cases that name none (default balanced): "
                   + ACCURACY_HELP.replace("accuracy level (default %(default)s): ", ""))
    p.add_argument("--out", required=True, help="run folder (table.csv, tasks/, cases/, "
                   "batch.json)")
    add_run_options(p)
    add_json_flag(p)
    p.set_defaults(func=_batch)


def register(subparsers):
    tomo = cli_group(subparsers, "tomo", "fluorescence tomography of any label map: simulate "
                     "an acquisition, reconstruct the yield")
    _register_simulate(tomo)
    _register_plan(tomo)
    _register_reconstruct(tomo)
    _register_acquire(tomo)
    _register_record_scan(tomo)
    _register_batch(tomo)
