"""``fluo study A|B|C|FILE``: the thesis's simulation studies, sweeps and grids,
serially or on Dask (thin caller of ``FluoTomoLib.studies``)."""

from __future__ import annotations

import time
from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoapp.commands import module_logic
from fluoapp.runopts import add_run_options, check_run_options, executor_for
from fluoguide.errors import FluoInputError
from fluoguide.progress import TqdmProgress

GRID_KEYS = ("methods", "lambdas", "noise_pct", "seeds", "forward_mm", "recon_mm", "data_mm",
             "roi_depth_mm", "diameters_mm", "depths_mm", "scheme", "hp_basis")


def _split(text, field):
    items = [t.strip() for t in str(text).split(",")]
    if not items or any(not t for t in items):
        raise FluoInputError("expected a comma-separated list of values", field=field, value=text)
    return items


def study_mapping(args):
    """The study's settings as a study-file mapping: the file (or A/B/C), then the options."""
    from fluoguide.runs.grid import load_study_file

    file = None
    if args.study in ("A", "B", "C"):
        doc = {"study": args.study}
    else:
        if Path(args.study).suffix.lower() not in (".json", ".yaml", ".yml"):
            raise FluoInputError("study must be A, B, C or a study file (.json, .yaml, .yml)",
                                 field="study", value=args.study)
        file = args.study
        doc = load_study_file(file)
    if args.sweep is not None or args.target is not None:
        doc.pop("study", None)
    if args.sweep is not None:
        doc["sweep"] = args.sweep
    if args.values is not None:
        doc["values"] = _split(args.values, "--values")
    if args.target is not None:
        parts = _split(args.target, "--target")
        if len(parts) != 2:
            raise FluoInputError("expected diameter_mm,depth_mm", field="--target", value=args.target)
        doc["targets"] = [parts]
        doc.pop("diameters_mm", None)
        doc.pop("depths_mm", None)
    if args.dim is not None:
        doc["dim"] = args.dim
    if args.seed is not None:
        doc["seeds"] = [args.seed]
    if args.scheme is not None:
        doc["scheme"] = args.scheme
    if args.hp_basis is not None:
        doc["hp_basis"] = args.hp_basis
    for item in args.grid or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or key not in GRID_KEYS:
            raise FluoInputError(f"expected KEY=V1,V2,... with KEY one of {', '.join(GRID_KEYS)}",
                                 field="--grid", value=item)
        doc[key] = _split(values, f"--grid {key}")
        if key in ("diameters_mm", "depths_mm"):
            doc.pop("targets", None)
            doc.pop("study", None)
    return doc, file


def _handler(args):
    threads = check_run_options(args)
    doc, file = study_mapping(args)
    logic = module_logic("FluoTomo")
    spec = logic.checkStudy(doc, file=file)     # every task checked before any work
    if args.out:          # refused before minutes of work, not after
        from fluoguide import atomic

        atomic.check_writable(args.out, "--out", folder=True)
    t0 = time.perf_counter()
    with TqdmProgress(f"study {spec.label}") as bar, executor_for(args, threads) as ex:
        out = logic.runStudy(spec, args.out, executor=ex, threads=threads, resume=args.resume,
                             progress=bar)
    out["seconds"] = time.perf_counter() - t0
    # every row's reconstruction warnings, where a reader of the JSON sees them
    # (after any the study itself reported)
    out["warnings"] = list(out.get("warnings", [])) + [
        f"{r['case']}, {r['method']} lambda {r['lambda']:g}: {w}"
        for r in out["rows"] for w in r.get("warnings", [])]
    from fluoguide.threads import current_threads

    out["library_threads"] = current_threads()      # fluo --threads / FLUO_THREADS
    if args.out:
        from fluoguide.jsonable import dumps

        from fluoguide import atomic

        atomic.write_text(Path(args.out) / "study.json", dumps(out))
        out["out"] = str(args.out)
    if out["failures"]:
        out["_exit_code"] = 1     # the table is written; the run is not a success
    return out


def register(sub):
    p = sub.add_parser(
        "study", help="simulation studies A, B, C of the thesis, sweeps and grids (serial or Dask)",
        description="Study A: disc diameter 2.5-15 mm at 2.5 mm depth; B: 6 mm disc at 2.5-6.5 mm; "
        "C: annulus with a filled-disc prior, SP lambda sweep. Or a study file (JSON/YAML: "
        "targets, methods, lambdas, noise_pct, seeds, forward_mm, recon_mm, data_mm, "
        "roi_depth_mm, ...; docs/scale.md). Rows: true vs reconstructed peak yield and centroid "
        "per target, method and lambda. With --out: table.csv (one row per task, written as each "
        "finishes; --resume continues a killed run), tasks/, error_vs_time.png, figures.")
    p.add_argument("study", help="A, B, C, or a study file (.json, .yaml)")
    p.add_argument("--dim", type=int, default=None,
                   help="2: discs in a 50 x 30 mm section (default); 3: spheres in a 50 x 30 x 20 mm slab")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default 0)")
    p.add_argument("--target", default=None, help="one custom case instead of the study's: "
                   "diameter_mm,top_depth_mm (default: the study's cases)")
    p.add_argument("--sweep", choices=["lambda", "noise", "mesh", "roi"], default=None,
                   help="error against time for one target (--target, default 6,3.5) as lambda, "
                   "noise [%%], the mesh sizes (reconstruction and forward; data from a finer "
                   "mesh) or the modelled depth below the surface (roi [mm]) varies "
                   "(default: no sweep)")
    p.add_argument("--values", default=None, metavar="V1,V2,...",
                   help="the sweep's values instead of its defaults (default: the sweep's own)")
    p.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                   help="one axis of the grid (repeatable; default: the study's own grid): "
                   + ", ".join(GRID_KEYS))
    p.add_argument("--scheme", choices=["nirfast", "reference"], default=None,
                   help="nirfast (default): the thesis's NIRFAST fluorescence reconstruction "
                   "(log-amplitude data, Jacobian normalised by the current yield, start at the "
                   "background); reference: the literal update of docs/physics.md section 8.3 "
                   "(linear data)")
    p.add_argument("--hp-basis", choices=["forward", "reconstruction"], default=None,
                   help="mesh on which HP's region basis is built (default forward: where the "
                   "data were simulated)")
    p.add_argument("--out", default=None,
                   help="run folder: table.csv, tasks/, study.json, PNG figures (default: no "
                   "files)")
    add_run_options(p)
    add_json_flag(p)
    p.set_defaults(func=_handler)
