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
        check_distances,
        log_robin_surface_fluence,
        spatially_resolved_reflectance,
        total_diffuse_fluorescence,
        total_diffuse_reflectance,
    )
    from FluoTomoLib.optics import (
        NEAR_SOURCE_MFP,
        check_properties,
        diffusion_coefficient,
        diffusion_validity,
        mueff,
        penetration_depth_mm,
        robin_A,
        transport_mfp_mm,
    )

    check_properties(args.mua, args.musp, args.n, where="--mua/--musp/--n", warn=False)
    rho = check_distances(_floats(args.rho, "--rho"), "--rho") if args.rho else None
    warnings = diffusion_validity(args.mua, args.musp, rho)
    out = {
        "mua_per_mm": args.mua, "musp_per_mm": args.musp, "n": args.n,
        "Rd": float(total_diffuse_reflectance(args.mua, args.musp, args.n)),
        "mueff": float(mueff(args.mua, args.musp)),
        "penetration_depth_mm": float(penetration_depth_mm(args.mua, args.musp)),
        "D": float(diffusion_coefficient(args.mua, args.musp)),
        "A": float(robin_A(args.n)),
        "diffusion_valid": args.musp >= 10 * args.mua,
    }
    if rho is not None:
        out["rho_mm"] = rho.tolist()
        out["R_rho"] = spatially_resolved_reflectance(rho, args.mua, args.musp, args.n).tolist()
        log_phi = log_robin_surface_fluence(rho, args.mua, args.musp, args.n)
        with np.errstate(under="ignore"):
            out["robin_surface_fluence"] = np.exp(log_phi).tolist()
        # values below the smallest double underflow to 0; their logs stay exact
        out["ln_robin_surface_fluence"] = log_phi.tolist()
        out["rho_diffusive"] = (rho >= NEAR_SOURCE_MFP * transport_mfp_mm(args.mua, args.musp)
                                ).tolist()
        if np.any(log_phi < np.log(np.finfo(float).tiny)):
            warnings.append(f"{int(np.sum(log_phi < np.log(np.finfo(float).tiny)))} fluence "
                            "value(s) are below 1e-308 and print as 0: use "
                            "ln_robin_surface_fluence")
    if args.yield_per_mm is not None:
        mua_m = args.mua_m if args.mua_m is not None else args.mua
        musp_m = args.musp_m if args.musp_m is not None else args.musp
        check_properties(mua_m, musp_m, args.n, where="--mua-m/--musp-m", warn=False)
        warnings += [f"emission: {w}" for w in diffusion_validity(mua_m, musp_m)]
        out["diffusion_valid"] = out["diffusion_valid"] and musp_m >= 10 * mua_m
        out["F"] = total_diffuse_fluorescence((args.mua, args.musp), (mua_m, musp_m),
                                              args.yield_per_mm, args.n,
                                              include_unscattered=args.unscattered)
        out["F_includes_unscattered_beam"] = bool(args.unscattered)
    out["warnings"] = warnings
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


def _read_forward_mesh(path):
    """The mesh of ``fluo forward``: elements of either orientation are turned
    positive (counted), degenerate ones refused naming the file."""
    from FluoTomoLib.meshing.vtu_io import read_mesh

    mesh = read_mesh(path)
    try:
        mesh.check_elements()
    except FluoInputError as exc:
        raise FluoInputError(exc.problem + " (only degenerate elements are refused; either "
                             "orientation is fine)", file=path, field=exc.field,
                             value=exc.value) from None
    flipped = int(np.sum(mesh.signed_measures < 0))
    return (mesh.oriented() if flipped else mesh), flipped


def _forward_optics(args, mesh):
    """(Optics, yields or None) from --optics or --mua/--musp/--n, and --yield."""
    from FluoTomoLib.optics import check_properties
    from FluoTomoLib.tomography import homogeneous_optics, read_optics

    if args.optics is not None:
        if args.mua is not None or args.musp is not None:
            raise FluoInputError("give --optics or --mua/--musp, not both", field="--optics")
        optics = read_optics(args.optics)
    else:
        if args.mua is None or args.musp is None:
            raise FluoInputError("give --optics optics.json (per region) or --mua and --musp "
                                 "(one material)", field="--mua" if args.mua is None else "--musp")
        check_properties(args.mua, args.musp, args.n, where="--mua/--musp/--n", warn=False)
        optics = homogeneous_optics(args.mua, args.musp, args.n, labels=mesh.regions)
    yields = None
    if args.yield_spec is not None:
        from fluoapp.commands.tomo import _parse_yields

        yields = _parse_yields(args.yield_spec)
    return optics, yields


def _forward_analytic(args, mesh, src, det, out, t0, want_jacobian):
    """The exact half-space answer when the check says the tissue under the
    optodes is one (one material, flat, far boundaries); None otherwise."""
    from FluoTomoLib.fem.forward import safe_log
    from FluoTomoLib.fem.halfspace import half_space_check, half_space_excitation_data
    from FluoTomoLib.optics import NEAR_SOURCE_MFP, diffusion_validity, transport_mfp_mm

    if args.model == "analytic":
        if want_jacobian:
            raise FluoInputError("the Jacobian needs the FEM (--model fem or auto)",
                                 field="--model", value=args.model)
        if args.optics is not None or args.yield_spec is not None:
            raise FluoInputError("the analytic half-space model takes one material (--mua/--musp) "
                                 "and no --yield: use --model fem or auto", field="--model",
                                 value=args.model)
    if args.optics is not None or args.yield_spec is not None:
        return None
    check = half_space_check(mesh, args.mua, args.musp, args.n, src, det)
    out["analytic_check"] = check
    if args.model == "analytic" and not check["usable"]:
        raise FluoInputError(f"the analytic half-space model does not apply: "
                             f"{check['reason']}", file=args.mesh, field="--model",
                             value="analytic")
    if not check["usable"] or want_jacobian:
        return None
    data = half_space_excitation_data(mesh, args.mua, args.musp, args.n, src, det)
    out["model"] = "analytic"
    out["detector_fluence"] = data.tolist()
    notes = diffusion_validity(args.mua, args.musp)
    rho = np.linalg.norm(src[:, None, :] - det[None, :, :], axis=2)
    near = rho < NEAR_SOURCE_MFP * transport_mfp_mm(args.mua, args.musp)
    if near.any():
        notes.append(f"{int(near.sum())} pair(s) are within {NEAR_SOURCE_MFP:g} transport "
                     "mean free paths: diffusion theory itself over-predicts there")
    out["accuracy"] = {"model_error_bound_rel": check["boundary_effect_bound"],
                       "what": "the exact Robin half-space solution; other boundaries of "
                               "the mesh change the data by at most this much"}
    out["warnings"] = notes
    out["log_valid_fraction"] = float(safe_log(data)[1].mean())
    out["seconds"] = time.perf_counter() - t0
    return out


def _forward(args):
    import warnings

    from FluoTomoLib.fem.forward import FluorescenceModel, safe_log

    from fluoguide import atomic
    from FluoTomoLib.fem.operators import check_solver

    t0 = time.perf_counter()
    # before any work: a solver name is checked even where the analytic path
    # would not use it (it was ignored, exit 0), and the outputs are writable
    check_solver(args.solver, field="--solver")
    for flag, path in (("--jacobian-out", args.jacobian_out),
                       ("--yield-jacobian-out", args.yield_jacobian_out)):
        if path:
            atomic.check_writable(path, flag)
    mesh, flipped = _read_forward_mesh(args.mesh)
    src = _read_points_csv(args.sources, "sources")
    det = _read_points_csv(args.detectors, "detectors")
    for name, pts in (("sources", src), ("detectors", det)):
        if pts.shape[1] != mesh.dim:
            raise FluoInputError(f"points are {pts.shape[1]}D but the mesh is {mesh.dim}D",
                                 file=getattr(args, name), field=name)
    optics, yields = _forward_optics(args, mesh)
    out = {"nodes": mesh.n_nodes, "elements": mesh.n_elements, "sources": len(src),
           "detectors": len(det), "regions": [int(r) for r in mesh.regions],
           "reoriented_elements": flipped}
    # a file to write implies computing it
    want_jacobian = bool(args.jacobian or args.jacobian_out or args.yield_jacobian_out)
    if args.yield_jacobian_out and yields is None:
        raise FluoInputError("the yield Jacobian needs --yield", field="--yield-jacobian-out")
    if args.model in ("auto", "analytic"):
        done = _forward_analytic(args, mesh, src, det, out, t0, want_jacobian)
        if done is not None:
            return done
    props_x, props_m, y_nodes = optics.nodal_from_mesh(mesh, yields)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fm = FluorescenceModel(mesh, props_x, props_m, src, det, solver=args.solver)
        acc = fm.accuracy()
    if acc["refuse"] and not args.force:
        raise FluoInputError("; ".join(acc["refuse"]) + _size_hint(acc) + " (--force to output "
                             "the data anyway, with these warnings)", file=args.mesh,
                             field="elements")
    data = fm.excitation_data()
    out["model"] = "fem"
    out["detector_fluence"] = data.tolist()
    if yields is not None:
        out["fluorescence"] = fm.emission_data(y_nodes).tolist()
        out["yield_by_region"] = {str(k): v for k, v in yields.items()}
    if want_jacobian:
        J = fm.jacobian_mua_x()
        out["jacobian_shape"] = list(J.shape)
        out["jacobian_mua_norm"] = float(np.linalg.norm(J))
        if args.jacobian_out:
            from fluoguide import atomic

            # exactly the path given (np.save would append .npy), complete or not at all
            out["jacobian_file"] = str(atomic.save_npy(args.jacobian_out, J,
                                                       field="--jacobian-out").resolve())
        if yields is not None:
            Jy = fm.jacobian_yield()
            out["jacobian_yield_shape"] = list(Jy.shape)
            out["jacobian_yield_norm"] = float(np.linalg.norm(Jy))
            if args.yield_jacobian_out:
                from fluoguide import atomic

                out["jacobian_yield_file"] = str(atomic.save_npy(
                    args.yield_jacobian_out, Jy, field="--yield-jacobian-out").resolve())
    out["log_valid_fraction"] = float(safe_log(data)[1].mean())
    out["accuracy"] = {k: acc[k] for k in ("target_rel_err", "estimated_rel_err",
                                            "element_size_needed_mm")}
    out["negative_nodes"] = acc["negative_nodes"]
    notes = acc["refuse"] + acc["warnings"]
    for w in caught:                      # the operators' own warnings, once each
        text = str(w.message)
        if text not in notes:
            notes.append(text)
    out["warnings"] = notes
    out["forced"] = bool(acc["refuse"]) and bool(args.force)
    out["solver"] = fm.solver_name
    out["timings"] = fm.timings
    out["seconds"] = time.perf_counter() - t0
    return out


def _size_hint(acc):
    size = acc.get("element_size_needed_mm")
    if size is None or not np.isfinite(size):
        return ""
    return f"; elements of at most {size:.3g} mm near the optodes would do"


def register(sub):
    p = sub.add_parser("analytic", help="closed-form diffusion theory: Rd, R(rho), F",
                       description="Homogeneous semi-infinite medium (docs/physics.md section 3): "
                       "Rd, mueff, D, A, R(rho) and the exact Robin-boundary surface fluence, "
                       "and total diffuse fluorescence F.")
    p.add_argument("--mua", type=float, required=True, help="absorption [1/mm] (excitation)")
    p.add_argument("--musp", type=float, required=True, help="reduced scattering [1/mm]")
    p.add_argument("--n", type=float, default=1.33, help="refractive index (default 1.33)")
    p.add_argument("--rho", default=None, help="source-detector distances [mm], comma-separated: "
                   "also compute R(rho) and the exact Robin surface fluence (default: none)")
    p.add_argument("--yield", dest="yield_per_mm", type=float, default=None,
                   help="fluorescence yield eta*mua_f [1/mm]: also compute F (default: none)")
    p.add_argument("--mua-m", type=float, default=None,
                   help="emission absorption [1/mm] (default: --mua)")
    p.add_argument("--musp-m", type=float, default=None,
                   help="emission reduced scattering [1/mm] (default: --musp)")
    p.add_argument("--unscattered", action="store_true",
                   help="include the unscattered excitation beam in F")
    add_json_flag(p)
    p.set_defaults(func=_analytic)

    p = sub.add_parser("forward", help="FEM forward model: boundary fluence for sources x detectors",
                       description="CW diffusion FEM on a .vtu mesh (one or several regions, "
                       "elements of either orientation). Sources/detectors: CSV of x,y[,z] mm; "
                       "sources snap to the nearest surface point and are buried one MFP'. "
                       "With --yield also the fluorescence data (and with --jacobian the yield "
                       "Jacobian).")
    p.add_argument("--mesh", required=True, help="mesh file (.vtu with a cell array 'region', "
                   "or NIRFAST .node/.elem stem)")
    p.add_argument("--optics", default=None, help="optics.json: mua/musp per region at "
                   "excitation and emission, n, fluorophore (docs/tomography-own-scene.md); default: "
                   "--mua/--musp for one material")
    p.add_argument("--mua", type=float, default=None, help="absorption [1/mm] of one material "
                   "at both wavelengths (instead of --optics; default: none)")
    p.add_argument("--musp", type=float, default=None, help="reduced scattering [1/mm] of one "
                   "material (instead of --optics; default: none)")
    p.add_argument("--n", type=float, default=1.33, help="refractive index with --mua/--musp "
                   "(default %(default)s)")
    p.add_argument("--yield", dest="yield_spec", default=None, metavar="LABEL:VALUE[,...]",
                   help="fluorescence yield [1/mm] per region: also the fluorescence data "
                   "(default: excitation only)")
    p.add_argument("--sources", required=True,
                   help="CSV of source points, x,y[,z] mm, one per line")
    p.add_argument("--detectors", required=True,
                   help="CSV of detector points, x,y[,z] mm, one per line")
    p.add_argument("--jacobian", action="store_true", help="also compute the mua Jacobian (and "
                   "the yield Jacobian with --yield)")
    p.add_argument("--jacobian-out", default=None,
                   help="save the mua Jacobian as .npy (default: not saved)")
    p.add_argument("--yield-jacobian-out", default=None, help="save the yield Jacobian as .npy "
                   "(with --yield --jacobian; default: not saved)")
    p.add_argument("--solver", default="auto",
                   help="linear solver: pardiso (MKL Cholesky), splu (SuperLU), amg (algebraic "
                   "multigrid CG, only for meshes too large to factorise: docs/fem.md); default "
                   "auto: PARDISO when MKL loads, else SuperLU")
    p.add_argument("--model", default="auto", choices=("auto", "fem", "analytic"),
                   help="auto (default): the exact half-space solution when the check in the "
                   "JSON's analytic_check says the tissue under the optodes is one (one material "
                   "from --mua/--musp, flat, other boundaries changing the data by < 1 %%) and no "
                   "Jacobian or --yield is asked for, else the FEM; fem or analytic to choose")
    p.add_argument("--force", action="store_true",
                   help="output FEM data even where they are unusable (negative fluence, "
                   "elements beyond the measured range), with the reasons in warnings (default: "
                   "refuse)")
    add_json_flag(p)
    p.set_defaults(func=_forward)
