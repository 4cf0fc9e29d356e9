"""``fluo validate mc`` and ``fluo validate mc-fluorescence``: the diffusion model
against Monte Carlo (MCX, written by others), docs/validation.md."""

from __future__ import annotations

import shlex
import sys
import time

import numpy as np

from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import GRADINGS, module_logic
from fluoapp.runopts import add_run_options, check_run_options, executor_for
from fluoguide.errors import FluoInputError
from fluoguide.progress import TqdmProgress

QUICK = {"photons": 25_000, "runs": 4}
FULL = {"photons": 250_000, "runs": 4}


def _command_line():
    return "fluo " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _out_dir(path):
    from fluoguide import atomic

    if path is None:
        raise FluoInputError("needs an output folder", field="--out")
    # checked now, created at the first write: a refused run leaves no folder
    return atomic.check_writable(path, "--out", folder=True)


def _check_budget(args):
    """The Monte Carlo options: in range, and refused where no Monte Carlo runs
    (with --mc-in they would be silently ignored)."""
    from fluoguide.errors import check_number

    check_number("--seed", args.seed, 0, 2**32 - 1, integer=True)
    run_opts = (("--workers", getattr(args, "workers", None)),
                ("--scheduler", getattr(args, "scheduler", None)),
                ("--resume", getattr(args, "resume", False) or None))
    given = [name for name, v in (("--photons", args.photons), ("--runs", args.runs),
                                  ("--quick", args.quick or None), *run_opts) if v is not None]
    if args.mc_in is not None and given:
        raise FluoInputError("applies when Monte Carlo runs (drop --mc-in)", field=given[0],
                             value=getattr(args, given[0][2:]))
    if args.photons is not None:
        check_number("--photons", args.photons, 1, 1e9, integer=True)
    if args.runs is not None:
        check_number("--runs", args.runs, 1, 1000, integer=True)


def _positive(value, field, upper=None):
    if value is None:
        return None
    if not np.isfinite(value) or value <= 0 or (upper is not None and value > upper):
        raise FluoInputError(f"must be > 0{'' if upper is None else f' and <= {upper:g}'}",
                             field=field, value=value)
    return float(value)


def _write_csv(path, rows, keys):
    import csv

    import io

    from fluoguide import atomic

    fh = io.StringIO(newline="")
    w = csv.writer(fh)
    w.writerow(keys)
    for r in rows:
        w.writerow(["" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float)
                                                  else r[k]) for k in keys])
    atomic.write_text(path, fh.getvalue(), field="--out")


def _write_json(path, result):
    from fluoguide import atomic
    from fluoguide.jsonable import dumps

    atomic.write_text(path, dumps(result), field="--out")


def _mc(args):
    _check_budget(args)
    threads = check_run_options(args)
    out = _out_dir(args.out)
    t0 = time.perf_counter()
    budget = dict(QUICK if args.quick else FULL)
    if args.photons is not None:
        budget["photons"] = args.photons
    if args.runs is not None:
        budget["runs"] = args.runs
    logic = module_logic("FluoTomo")
    medium = {"mua": args.mua, "musp": args.musp, "n": args.n, "g": args.g}
    if args.mc_in is not None:
        mc = logic.halfSpaceMonteCarlo(out, mcIn=args.mc_in, **medium)
    else:
        medium.update(mua=_positive(args.mua, "--mua", 10),
                      musp=_positive(args.musp, "--musp", 100))
        # missing engine: one line before any cluster starts
        logic.checkMonteCarloEngine(args.engine)
        # every run is a task of the run engine: written to OUT/mc_runs as it finishes
        # (--resume continues a killed set), split across Dask workers with --workers
        # or --scheduler
        with TqdmProgress("Monte Carlo") as bar, executor_for(args, threads) as ex:
            mc = logic.halfSpaceMonteCarlo(
                out, **medium, photons=budget["photons"], runs=budget["runs"], seed=args.seed,
                engine=args.engine, executor=ex, threads=threads, resume=args.resume,
                commandLine=_command_line(), progress=bar)
    boundaries = ("empirical", "fresnel") if args.boundary == "both" else (args.boundary,)
    with TqdmProgress("FEM") as bar:
        result = logic.validateHalfSpace(out, mc, boundaries, args.mesh_level, args.reference,
                                         progress=bar)
    _write_csv(out / "validate_mc_reflectance.csv", result["rows"], list(result["rows"][0]))
    _write_csv(out / "validate_mc_fluence.csv", result["fluence_rows"],
               list(result["fluence_rows"][0]))
    result["tables"] = [str(out / "validate_mc_reflectance.csv"),
                        str(out / "validate_mc_fluence.csv")]
    result["seconds"] = time.perf_counter() - t0
    _write_json(out / "validate_mc.json", result)
    if not args.json:
        _print_table(result)
        return {"agree_from_mm": result["agree_from_mm"], "reference": result["reference"],
                "energy_balance": result["energy"]["balance"], "photons": result["photons"],
                "device": result["device"], "seconds": round(result["seconds"], 1),
                "warnings": result["warnings"], "out": str(out)}
    return result


def _print_table(result):
    b = result["boundary_default"]
    print(f"{'rho':>5} {'MC R':>11} {'SE %':>6} {'FEM %':>7} " +
          " ".join(f"{k[:9]:>9}" for k in result["A"]) + f" {'dipole %':>9} {'vs indep':>9}",
          file=sys.stderr)
    for r in result["rows"]:
        alt = " ".join(f"{r[f'fem_{k}_vs_mc_pct']:+9.2f}" for k in result["A"])
        ref = r.get("mc_vs_reference_pct")
        print(f"{r['rho_mm']:5g} {r['mc']:11.4e} {r['mc_rel_se_pct']:6.2f} "
              f"{r['fem_vs_mc_pct']:+7.2f} {alt} {r['dipole_vs_mc_pct']:+9.2f} "
              f"{'' if ref is None else f'{ref:+9.2f}'}", file=sys.stderr)
    print(f"(FEM % = FEM with A of '{b}' minus MC; columns per boundary constant A)",
          file=sys.stderr)


def _mc_fluorescence(args):
    from fluoguide import atomic

    _check_budget(args)
    threads = check_run_options(args)
    out = _out_dir(args.out)
    t0 = time.perf_counter()
    logic = module_logic("FluoTomo")
    if args.mc_in is not None:
        mc = logic.fluorescenceMonteCarlo(out, mcIn=args.mc_in)
    else:
        # missing engine: one line before any cluster starts
        logic.checkMonteCarloEngine(args.engine)
        with TqdmProgress("Monte Carlo") as bar, executor_for(args, threads) as ex:
            mc = logic.fluorescenceMonteCarlo(
                out, photons=args.photons or (20_000 if args.quick else 100_000),
                runs=args.runs or (2 if args.quick else 3), seed=args.seed, engine=args.engine,
                executor=ex, threads=threads, resume=args.resume, commandLine=_command_line(),
                progress=bar)
    boundaries = ("empirical", "fresnel") if args.boundary == "both" else (args.boundary,)
    result = logic.validateFluorescence(mc, boundaries)
    atomic.make_folder(out)
    _write_csv(out / "validate_mc_fluorescence.csv", result["rows"], list(result["rows"][0]))
    result["seconds"] = time.perf_counter() - t0
    return result


def _mc_tomography(args):
    from fluoguide.runs.grid import parse_values

    # an empty --depths is a mistake, not "the default depths"
    depths = parse_values(args.depths, "--depths") if args.depths is not None else None
    for d in depths or ():
        if not 2.0 <= d <= 16.0:
            raise FluoInputError("tube depths must be within 2..16 mm", field="--depths", value=d)
    for name, v in (("--photons", args.photons), ("--workers", args.workers),
                    ("--scheduler", args.scheduler), ("--resume", args.resume or None)):
        if v is not None and not args.simulate:
            raise FluoInputError("applies when Monte Carlo runs (--simulate)", field=name,
                                 value=v)
    if args.mc_in is not None and not args.mc_in.strip():
        raise FluoInputError("needs a folder of depth_<d>mm acquisitions", field="--mc-in",
                             value=args.mc_in)
    if args.simulate and args.mc_in is not None:
        raise FluoInputError("--simulate makes the Monte Carlo data; --mc-in reads stored ones",
                             field="--mc-in", value=args.mc_in)
    if args.photons is not None:
        from fluoguide.errors import check_number

        check_number("--photons", args.photons, 1, 1e9, integer=True)
    threads = check_run_options(args)
    methods = [m.strip().upper() for m in args.methods.split(",")]
    if not methods or any(m not in ("NP", "SP", "HP") for m in methods) or \
            len(set(methods)) != len(methods):
        raise FluoInputError("expected methods from NP, SP, HP, each once", field="--methods",
                             value=args.methods)
    out = _out_dir(args.out)
    logic = module_logic("FluoTomo")
    if args.simulate:
        logic.checkMonteCarloEngine("auto")
    t0 = time.perf_counter()
    with TqdmProgress("mc-tomography") as bar, executor_for(args, threads) as ex:
        res = logic.validateTubeMonteCarlo(
            out, depths, mcIn=args.mc_in, simulate=args.simulate, photons=args.photons,
            methods=methods, accuracy=args.accuracy, executor=ex, threads=threads,
            resume=args.resume, progress=bar, simulateFem=args.simulate_fem,
            grading=GRADINGS[args.grading])
    _write_csv(out / "validate_mc_tomography.csv", res["rows"], list(res["rows"][0].keys()))
    res["table"] = str(out / "validate_mc_tomography.csv")
    res["seconds"] = time.perf_counter() - t0
    _write_json(out / "validate_mc_tomography.json", res)
    if not args.json:
        print(f"{'depth':>5} {'method':>6} {'FEM data: yield %':>18} {'centroid %':>10} "
              f"{'MC data: yield %':>17} {'centroid %':>10}", file=sys.stderr)
        for g in res["depths"]:
            for m in methods:
                f, c = g["rows"]["diffusion FEM"][m], g["rows"]["Monte Carlo"][m]
                print(f"{g['depth_mm']:5g} {m:>6} {f['yield_error_pct']:+18.1f} "
                      f"{_fmt(f['centroid_error_pct']):>10} {c['yield_error_pct']:+17.1f} "
                      f"{_fmt(c['centroid_error_pct']):>10}", file=sys.stderr)
        return {"table": res["table"], "figure": res["figure"],
                "seconds": round(res["seconds"], 1), "warnings": res["warnings"]}
    return res


def _fmt(v):
    return "-" if v is None else f"{v:+.1f}"


def register(sub):
    grp = cli_group(sub, "validate", "the diffusion model against independent references "
                    "(Monte Carlo)")
    p = grp.add_parser(
        "mc", help="FEM vs Monte Carlo (MCX) on a semi-infinite medium",
        description="Pencil beam on a 160 x 160 x 80 mm box of tissue (1 mm voxels): spatially "
        "resolved reflectance R(rho) and interior fluence by Monte Carlo (MCX-CL on the CPU, "
        "MCX on a CUDA GPU), standard errors from independent runs, the energy balance; the "
        "FEM (both boundary constants A), the dipole and the exact Robin half-space on the "
        "same medium; the independent stored run where the medium matches it. Writes "
        "mc_halfspace.json (the MC set), validate_mc_*.csv, validate_mc.png and "
        "validate_mc.json to --out.")
    p.add_argument("--quick", action="store_true",
                   help=f"{QUICK['runs']} runs x {QUICK['photons']} photons (a few minutes on 2 "
                   f"cores) instead of {FULL['runs']} x {FULL['photons']}")
    p.add_argument("--n", type=float, default=None,
                   help="refractive index of the tissue, outside air (default 1.37)")
    p.add_argument("--n-index", dest="n", type=float, default=None,
                   help="same as --n (default 1.37)")
    p.add_argument("--mua", type=float, default=None, help="absorption [1/mm] (default 0.01)")
    p.add_argument("--musp", type=float, default=None,
                   help="reduced scattering [1/mm] (default 1.0)")
    p.add_argument("--g", type=float, default=None,
                   help="anisotropy of the phase function, mus = musp/(1-g) (default 0.9)")
    p.add_argument("--photons", type=int, default=None,
                   help="photons per run (default 250000; --quick 25000)")
    p.add_argument("--runs", type=int, default=None,
                   help="independent runs, each with its own seed (default 4)")
    p.add_argument("--seed", type=int, default=1, help="seed of the first run (default 1)")
    p.add_argument("--engine", choices=["auto", "mcxcl", "mcx"], default="auto",
                   help="auto (default): MCX on a CUDA GPU if one answers, else MCX-CL")
    p.add_argument("--boundary", choices=["both", "empirical", "fresnel"], default="both",
                   help="boundary constant(s) A for the FEM: empirical Reff polynomial, exact "
                   "Fresnel integrals, or both (default)")
    p.add_argument("--mesh-level", choices=["test", "coarse", "normal"], default="normal",
                   help="FEM mesh of the quarter box (default normal: 0.25 mm at the beam, "
                   "1 mm to 35 mm)")
    p.add_argument("--mc-in", default=None,
                   help="compare a stored MC set (JSON) instead of running Monte Carlo "
                   "(default: run it)")
    p.add_argument("--reference", default=None,
                   help="independent R(rho) CSV to check the MC against (default: the stored "
                   "independent run when the medium is its own)")
    p.add_argument("--out", required=True, help="output folder (created if missing); the "
                   "Monte Carlo runs' records go to OUT/mc_runs (--resume continues them)")
    add_run_options(p)
    add_json_flag(p)
    p.set_defaults(func=_mc)

    p = grp.add_parser(
        "mc-fluorescence", help="FEM vs Monte Carlo on a buried fluorescent inclusion",
        description="The stored fluorescence case (reference.fluorescence_case): three optodes "
        "over a 4 mm sphere 7 mm deep; excitation by MC from each source, emission by "
        "reciprocity (an MC run from each detector combined with the excitation fluence and "
        "the yield); the FEM on the same label map with both boundary constants.")
    p.add_argument("--quick", action="store_true",
                   help="2 runs x 20000 photons per optode and wavelength (default 3 x 100000)")
    p.add_argument("--photons", type=int, default=None,
                   help="photons per run (default 100000; --quick 20000)")
    p.add_argument("--runs", type=int, default=None, help="independent runs (default 3; --quick 2)")
    p.add_argument("--seed", type=int, default=3001, help="seed of the first run (default 3001)")
    p.add_argument("--engine", choices=["auto", "mcxcl", "mcx"], default="auto",
                   help="auto (default): MCX on a CUDA GPU if one answers, else MCX-CL")
    p.add_argument("--boundary", choices=["both", "empirical", "fresnel"], default="both",
                   help="boundary constant(s) A for the FEM (default both)")
    p.add_argument("--mc-in", default=None,
                   help="compare a stored fluorescence set (JSON) instead of running Monte Carlo "
                   "(default: run it)")
    p.add_argument("--out", required=True, help="output folder (created if missing); the "
                   "Monte Carlo runs' records go to OUT/mc_runs (--resume continues them)")
    add_run_options(p)
    add_json_flag(p)
    p.set_defaults(func=_mc_fluorescence)

    p = grp.add_parser(
        "mc-tomography", help="NP/SP/HP of the cylinder-tube from Monte Carlo data",
        description="The cylinder-tube phantom reconstructed (NP/SP/HP, fluo tomo reconstruct's "
        "path, a 0.8 mm label map) from Monte Carlo data (MCX on 0.5 mm voxels: stored in "
        "FluoTomoLib/montecarlo/data/tube, or made here with --simulate) and from "
        "diffusion-FEM data of the same 12 sources and 13 detectors (whole phantom, its own "
        "mesh), with the same 1 %% noise: the yield and centroid errors side by side "
        "(docs/validation.md). Writes validate_mc_tomography.{csv,json,png} to --out.")
    p.add_argument("--depths", default=None, metavar="D1,D2,...",
                   help="tube depths [mm] (default 2.7,4.7,6.7, the stored sets)")
    p.add_argument("--simulate", action="store_true",
                   help="run the Monte Carlo here (minutes per depth: docs/validation.md "
                   "gives the measured time; its runs go where --workers/--scheduler say, recorded in OUT/mc_runs) and "
                   "write the acquisitions to OUT/mc (default: read the stored ones)")
    p.add_argument("--simulate-fem", action="store_true",
                   help="compute the diffusion-FEM data here (the whole phantom at the fine "
                   "level) and write them to OUT/mc/depth_<d>mm/fem (default: read the stored "
                   "ones beside the Monte Carlo sets; --simulate computes them too)")
    p.add_argument("--photons", type=int, default=None,
                   help="--simulate: photons per run, 2 runs per optode (default 100000)")
    p.add_argument("--mc-in", default=None, metavar="DIR",
                   help="folder of depth_<d>mm acquisitions to read (default: the stored ones)")
    p.add_argument("--methods", default="NP,SP,HP", help="methods (default NP,SP,HP)")
    p.add_argument("--accuracy", choices=["fast", "balanced", "fine"], default="fast",
                   help="the reconstruction's accuracy level (default fast)")
    p.add_argument("--grading", choices=list(GRADINGS), default="bisection",
                   help="the reconstruction mesh, as fluo tomo reconstruct's --grading "
                   "(default bisection, the demo's)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    add_run_options(p)
    add_json_flag(p)
    p.set_defaults(func=_mc_tomography)
