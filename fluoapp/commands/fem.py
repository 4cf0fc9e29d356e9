"""``fluo analytic`` and ``fluo forward``: diffusion theory and the FEM from the shell."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag
from fluoguide.errors import FluoInputError


def _floats(text, field):
    try:
        return [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise FluoInputError("must be a comma-separated list of numbers", field=field,
                             value=text) from None


def _analytic(args):
    from FluoTomoLib.analytic import (
        robin_surface_fluence,
        spatially_resolved_reflectance,
        total_diffuse_fluorescence,
        total_diffuse_reflectance,
    )
    from FluoTomoLib.optics import (
        check_properties,
        diffusion_coefficient,
        mueff,
        penetration_depth_mm,
        robin_A,
    )

    check_properties(args.mua, args.musp, args.n, where="--mua/--musp/--n")
    out = {
        "mua_per_mm": args.mua, "musp_per_mm": args.musp, "n": args.n,
        "Rd": float(total_diffuse_reflectance(args.mua, args.musp, args.n)),
        "mueff": float(mueff(args.mua, args.musp)),
        "penetration_depth_mm": float(penetration_depth_mm(args.mua, args.musp)),
        "D": float(diffusion_coefficient(args.mua, args.musp)),
        "A": float(robin_A(args.n)),
    }
    if args.rho:
        rho = np.array(_floats(args.rho, "--rho"))
        out["rho_mm"] = rho.tolist()
        out["R_rho"] = spatially_resolved_reflectance(rho, args.mua, args.musp, args.n).tolist()
        out["robin_surface_fluence"] = robin_surface_fluence(rho, args.mua, args.musp,
                                                             args.n).tolist()
    if args.yield_per_mm is not None:
        mua_m = args.mua_m if args.mua_m is not None else args.mua
        musp_m = args.musp_m if args.musp_m is not None else args.musp
        out["F"] = total_diffuse_fluorescence((args.mua, args.musp), (mua_m, musp_m),
                                              args.yield_per_mm, args.n,
                                              include_unscattered=args.unscattered)
        out["F_includes_unscattered_beam"] = bool(args.unscattered)
    return out


def _read_points_csv(path, field):
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("file not found", file=p, field=field)
    rows = []
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FluoInputError("not UTF-8 text", file=p, field=field) from None
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [v for v in line.replace(";", ",").split(",") if v.strip()]
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            if not rows and i == 1:  # header line
                continue
            raise FluoInputError(f"line {i} is not numeric", file=p, field=field,
                                 value=line) from None
        if len(vals) not in (2, 3) or not np.all(np.isfinite(vals)):
            raise FluoInputError(f"line {i} needs 2 or 3 finite coordinates (x,y[,z] mm)", file=p,
                                 field=field, value=line)
        rows.append(vals)
    if not rows:
        raise FluoInputError("no points", file=p, field=field)
    if len({len(r) for r in rows}) != 1:
        raise FluoInputError("mixed 2D and 3D points", file=p, field=field)
    return np.array(rows)


def _forward(args):
    from FluoTomoLib.fem.forward import FluorescenceModel, safe_log
    from FluoTomoLib.meshing.vtu_io import read_mesh

    t0 = time.perf_counter()
    mesh = read_mesh(args.mesh)
    src = _read_points_csv(args.sources, "sources")
    det = _read_points_csv(args.detectors, "detectors")
    for name, pts in (("sources", src), ("detectors", det)):
        if pts.shape[1] != mesh.dim:
            raise FluoInputError(f"points are {pts.shape[1]}D but the mesh is {mesh.dim}D",
                                 file=getattr(args, name), field=name)
    props = dict(mua_per_mm=args.mua, musp_per_mm=args.musp, n=args.n)
    fm = FluorescenceModel(mesh, props, props, src, det, solver=args.solver)
    data = fm.excitation_data()
    out = {"nodes": mesh.n_nodes, "elements": mesh.n_elements, "sources": len(src),
           "detectors": len(det), "detector_fluence": data.tolist()}
    if args.jacobian or args.jacobian_out:   # a file to write implies computing it
        J = fm.jacobian_mua_x()
        out["jacobian_shape"] = list(J.shape)
        out["jacobian_mua_norm"] = float(np.linalg.norm(J))
        if args.jacobian_out:
            from fluoguide import atomic

            # exactly the path given (np.save would append .npy), complete or not at all
            out["jacobian_file"] = str(atomic.save_npy(args.jacobian_out, J,
                                                       field="--jacobian-out").resolve())
    out["log_valid_fraction"] = float(safe_log(data)[1].mean())
    out["solver"] = fm.solver_name
    out["timings"] = fm.timings
    out["seconds"] = time.perf_counter() - t0
    return out


def register(sub):
    p = sub.add_parser("analytic", help="closed-form diffusion theory: Rd, R(rho), F",
                       description="Homogeneous semi-infinite medium (physics.md section 3): "
                       "Rd, mueff, D, A, R(rho) and the exact Robin-boundary surface fluence, "
                       "and total diffuse fluorescence F.")
    p.add_argument("--mua", type=float, required=True, help="absorption [1/mm] (excitation)")
    p.add_argument("--musp", type=float, required=True, help="reduced scattering [1/mm]")
    p.add_argument("--n", type=float, default=1.33, help="refractive index (default 1.33)")
    p.add_argument("--rho", default=None, help="source-detector distances [mm], comma-separated")
    p.add_argument("--yield", dest="yield_per_mm", type=float, default=None,
                   help="fluorescence yield eta*mua_f [1/mm]: also compute F")
    p.add_argument("--mua-m", type=float, default=None, help="emission absorption [1/mm]")
    p.add_argument("--musp-m", type=float, default=None, help="emission reduced scattering [1/mm]")
    p.add_argument("--unscattered", action="store_true",
                   help="include the unscattered excitation beam in F")
    add_json_flag(p)
    p.set_defaults(func=_analytic)

    p = sub.add_parser("forward", help="FEM forward model: boundary fluence for sources x detectors",
                       description="CW diffusion FEM on a .vtu mesh. Sources/detectors: CSV of x,y[,z] "
                       "mm; sources snap to the nearest surface point and are buried one MFP'.")
    p.add_argument("--mesh", required=True, help="mesh file (.vtu, or NIRFAST .node/.elem stem)")
    p.add_argument("--mua", type=float, required=True, help="absorption [1/mm]")
    p.add_argument("--musp", type=float, required=True, help="reduced scattering [1/mm]")
    p.add_argument("--n", type=float, default=1.33, help="refractive index")
    p.add_argument("--sources", required=True, help="CSV of source points")
    p.add_argument("--detectors", required=True, help="CSV of detector points")
    p.add_argument("--jacobian", action="store_true", help="also compute the mua Jacobian")
    p.add_argument("--jacobian-out", default=None, help="save the Jacobian as .npy")
    p.add_argument("--solver", default="auto", help="auto, pardiso, splu or amg")
    add_json_flag(p)
    p.set_defaults(func=_forward)
