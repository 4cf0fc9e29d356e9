"""``fluo analytic`` and ``fluo forward``: diffusion theory and the FEM from the shell."""

from __future__ import annotations

import time

import numpy as np

from fluoapp.cli import add_json_flag
from fluoapp.commands import as_flags, module_logic
from fluoguide.errors import FluoInputError


def _floats(text, field):
    try:
        return [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise FluoInputError("must be a comma-separated list of numbers", field=field,
                             value=text) from None


def _analytic(args):
    rho = _floats(args.rho, "--rho") if args.rho else None
    with as_flags({"properties": "--mua/--musp/--n", "rho": "--rho",
                   "emission": "--mua-m/--musp-m"}):
        return module_logic("FluoTomo").analytic(
            args.mua, args.musp, args.n, rho=rho, yieldPerMm=args.yield_per_mm,
            muaM=args.mua_m, muspM=args.musp_m, unscattered=args.unscattered)


def _check_forward_options(args, want_jacobian):
    """The flags that exclude each other: one material or optics.json, and the
    analytic model's one material, no yield, no Jacobian."""
    if args.optics is not None:
        if args.mua is not None or args.musp is not None:
            raise FluoInputError("give --optics or --mua/--musp, not both", field="--optics")
    elif args.mua is None or args.musp is None:
        raise FluoInputError("give --optics optics.json (per region) or --mua and --musp "
                             "(one material)", field="--mua" if args.mua is None else "--musp")
    if args.yield_jacobian_out and args.yield_spec is None:
        raise FluoInputError("the yield Jacobian needs --yield", field="--yield-jacobian-out")
    if args.model == "analytic":
        if want_jacobian:
            raise FluoInputError("the Jacobian needs the FEM (--model fem or auto)",
                                 field="--model", value=args.model)
        if args.optics is not None or args.yield_spec is not None:
            raise FluoInputError("the analytic half-space model takes one material (--mua/--musp) "
                                 "and no --yield: use --model fem or auto", field="--model",
                                 value=args.model)


def _forward(args):
    from fluoapp.commands.tomo import _parse_yields
    from fluoguide import atomic

    t0 = time.perf_counter()
    # before any work: the outputs are writable (the solver's name is checked first
    # thing by the logic, even where the analytic path would not use it)
    for flag, path in (("--jacobian-out", args.jacobian_out),
                       ("--yield-jacobian-out", args.yield_jacobian_out)):
        if path:
            atomic.check_writable(path, flag)
    # a file to write implies computing it
    want_jacobian = bool(args.jacobian or args.jacobian_out or args.yield_jacobian_out)
    _check_forward_options(args, want_jacobian)
    yields = _parse_yields(args.yield_spec) if args.yield_spec is not None else None
    with as_flags({"solver": "--solver", "model": "--model",
                   "properties": "--mua/--musp/--n"}):
        data = module_logic("FluoTomo").forwardMesh(
            args.mesh, args.sources, args.detectors, optics=args.optics, mua=args.mua,
            musp=args.musp, n=args.n, yieldByLabel=yields, model=args.model,
            solver=args.solver, jacobian=want_jacobian, force=args.force, forceName="--force")
    out = {}
    for key, value in data.items():       # the Jacobians: their size, norm and file
        if key == "jacobian_mua":
            out["jacobian_shape"] = list(value.shape)
            out["jacobian_mua_norm"] = float(np.linalg.norm(value))
            if args.jacobian_out:
                # exactly the path given (np.save would append .npy), complete or not at all
                out["jacobian_file"] = str(atomic.save_npy(args.jacobian_out, value,
                                                           field="--jacobian-out").resolve())
        elif key == "jacobian_yield":
            out["jacobian_yield_shape"] = list(value.shape)
            out["jacobian_yield_norm"] = float(np.linalg.norm(value))
            if args.yield_jacobian_out:
                out["jacobian_yield_file"] = str(atomic.save_npy(
                    args.yield_jacobian_out, value, field="--yield-jacobian-out").resolve())
        else:
            out[key] = value
    out["seconds"] = time.perf_counter() - t0
    return out


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
