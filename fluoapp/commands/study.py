"""``fluo study A|B|C``: the thesis's 2D simulation studies."""

from __future__ import annotations

import time
from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoguide.errors import FluoInputError
from fluoguide.progress import TqdmProgress


def _handler(args):
    if args.dim not in (2, 3):
        raise FluoInputError("dimension must be 2 or 3", field="--dim", value=args.dim)
    target = None
    if args.target:
        try:
            d, depth = (float(v) for v in args.target.split(","))
        except ValueError:
            raise FluoInputError("expected diameter_mm,depth_mm", field="--target",
                                 value=args.target) from None
        target = (d, depth)
    from FluoTomoLib.studies.thesis import run_study, run_sweep

    if args.out:          # refused before minutes of work, not after
        from fluoguide import atomic

        atomic.check_writable(args.out, "--out", folder=True)
    t0 = time.perf_counter()
    with TqdmProgress(f"study {args.study}", force=not args.json) as bar:
        if args.sweep:
            out = run_sweep(args.sweep, target=target or (6.0, 3.5), dim=args.dim,
                            seed=args.seed, scheme=args.scheme, hp_basis=args.hp_basis,
                            progress=bar)
        else:
            out = run_study(args.study, seed=args.seed, target=target, out_dir=args.out,
                            dim=args.dim, scheme=args.scheme, hp_basis=args.hp_basis,
                            progress=bar)
    out["seconds"] = time.perf_counter() - t0
    if args.out:
        import json

        from fluoapp.cli import dumps

        from fluoguide import atomic

        atomic.write_text(Path(args.out) / "study.json", dumps(out))
        json.loads((Path(args.out) / "study.json").read_text())
    return out


def register(sub):
    p = sub.add_parser("study", help="simulation studies A, B, C of the thesis (2D)",
                       description="Study A: disc diameter 2.5-15 mm at 2.5 mm depth; B: 6 mm disc "
                       "at 2.5-6.5 mm; C: annulus with a filled-disc prior, SP lambda sweep. "
                       "Rows: true vs reconstructed peak yield and centroid for NP, SP, HP.")
    p.add_argument("study", choices=["A", "B", "C"], help="which study")
    p.add_argument("--dim", type=int, default=2,
                   help="2: discs in a 50 x 30 mm section (default); 3: spheres in a 50 x 30 x 20 mm slab")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--target", default=None, help="one custom case: diameter_mm,depth_mm")
    p.add_argument("--sweep", choices=["lambda", "noise", "mesh"], default=None,
                   help="error against time for one target (--target, default 6,3.5) as "
                   "lambda, noise or the reconstruction mesh size varies")
    p.add_argument("--scheme", choices=["nirfast", "reference"], default="nirfast",
                   help="nirfast (default): the thesis's NIRFAST fluorescence reconstruction "
                   "(log-amplitude data, Jacobian normalised by the current yield, start at the "
                   "background); reference: the literal update of physics.md (linear data)")
    p.add_argument("--hp-basis", choices=["forward", "reconstruction"], default="forward",
                   help="mesh on which HP's region basis is built (default forward: where the "
                   "data were simulated)")
    p.add_argument("--out", default=None, help="folder for study.json and PNG figures")
    add_json_flag(p)
    p.set_defaults(func=_handler)
