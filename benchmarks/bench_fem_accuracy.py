"""How accurate the FEM is, measured: the error table behind the resolution guard.

The discretisation error of the P1 diffusion FEM for a buried point source in
a half-space with the Robin boundary depends only on three dimensionless
numbers (the problem is scale-free: x -> l x, mua -> mua / l, musp -> musp / l
leaves them unchanged):

- ``mueff * h``: elements against the decay length,
- ``mut' * h``: elements against the burial depth 1/mut' of the source,
- ``rho / h``: source-detector distance in elements,

plus the refractive index (through zb / h) and, on a given mesh, the
direction and the position of the source within its element.  This benchmark
measures the error against the exact Robin half-space solution
(``analytic.robin_surface_fluence``) on Kuhn-cube meshes (``box_mesh``, the
fast mesher's elements) of unit h with the properties scaled, for six source
positions within a cell and 16 directions, and prints the worst |ln(FEM /
exact)| per (mueff h, mut' h, rho / h): the table ``fem/resolution.py``
interpolates.  It also counts negative nodes, and measures the lumped
absorption mass against the consistent one (docs/fem.md).

    python -m benchmarks fem_accuracy [-- --quick] [-- --json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

# source positions within a cell [h] (x, y): the worst over these is tabulated
OFFSETS = ((0.0, 0.0), (0.5, 0.0), (0.5, 0.5), (0.3, 0.7), (0.25, 0.1), (0.8, 0.4))
DIRECTIONS_DEG = tuple(range(0, 360, 30)) + (45, 135, 225, 315)
MUEFF_H = (0.2, 0.3, 0.5, 0.7, 1.0, 1.4)
MUTP_H = (1.0, 3.0, 10.0, 30.0, 100.0)
RHO_H = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 20.0)
N_INDEX = (1.0, 1.37, 1.6)


def kuhn_box(half_cells=24, depth_cells=18):
    """Unit-h Kuhn mesh [-L, L]^2 x [-Lz, 0] with the Robin boundary everywhere."""
    from FluoTomoLib.meshing.structured import box_mesh

    x = np.arange(-half_cells, half_cells + 0.5, 1.0)
    return box_mesh(x, x, np.arange(-depth_cells, 0.5, 1.0), name="kuhn-study")


def system(mesh, mua, musp, n, lumped=False):
    """Upper triangle of the Robin diffusion operator, the absorption term
    consistent (the FEM's, operators.py) or row-sum lumped."""
    from FluoTomoLib.fem.operators import DiffusionOperator, geometry, weighted_mass
    from FluoTomoLib.optics import robin_A

    if not lumped:
        return DiffusionOperator(mesh, mua, musp, n).K_upper
    g = geometry(mesh)
    D = np.full(mesh.n_nodes, 1.0 / (3.0 * (mua + musp)))
    lump = weighted_mass(mesh, np.full(mesh.n_nodes, mua)) @ np.ones(mesh.n_nodes)
    return g.upper(D, np.zeros(mesh.n_nodes), g.boundary_weight() / (2.0 * robin_A(n)) + lump)


def measure(mesh, mueff_h, mutp_h, rho_h=RHO_H, n=1.37, lumped=False, offsets=OFFSETS,
            directions_deg=DIRECTIONS_DEG, margin_decay=3.0):
    """Worst |ln(FEM/exact)| over source offsets and directions per rho/h.

    Detectors closer to a side of the box than ``margin_decay`` decay lengths
    are not used (the box's own boundary would be part of the error), and a
    distance only counts where every direction is usable.  Returns a dict
    with ``rho_h`` (used), ``worst_log_err``,
    ``signed`` (the signed relative error of the worst case), negative-node
    counts and seconds.
    """
    import warnings

    from FluoTomoLib.analytic import log_robin_surface_fluence
    from FluoTomoLib.fem.operators import detector_operator, geometry, point_source_rhs
    from FluoTomoLib.fem.pardiso import PardisoCholesky

    t0 = time.perf_counter()
    mua = mueff_h ** 2 / (3.0 * mutp_h)
    musp = mutp_h - mua
    z0 = 1.0 / mutp_h
    lo, hi = mesh.bounds()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        U = system(mesh, mua, musp, n, lumped)
    chol = PardisoCholesky(U, name="study", pattern=geometry(mesh).pardiso_pattern())
    src = np.array([[x, y, -z0] for x, y in offsets])
    phi = chol.solve(point_source_rhs(mesh, src).toarray())
    chol.release()
    rho = np.asarray(rho_h, float)
    ang = np.deg2rad(np.asarray(directions_deg, float))
    worst = np.full(len(rho), -np.inf)
    signed = np.zeros(len(rho))
    usable = np.zeros(len(rho), bool)
    every = []
    ref = log_robin_surface_fluence(rho, mua, musp, n)
    margin = margin_decay / mueff_h
    for k, (x, y) in enumerate(offsets):
        det = np.stack([x + np.outer(np.cos(ang), rho), y + np.outer(np.sin(ang), rho)], -1)
        dist_side = np.minimum.reduce([det[..., 0] - lo[0], hi[0] - det[..., 0],
                                       det[..., 1] - lo[1], hi[1] - det[..., 1]])
        ok = dist_side >= margin
        pts = np.concatenate([det.reshape(-1, 2), np.zeros((det[..., 0].size, 1))], axis=1)
        y_fem = np.full(ok.size, np.nan)
        y_fem[ok.ravel()] = detector_operator(mesh, pts[ok.ravel()]) @ phi[:, k]
        y_fem = y_fem.reshape(det.shape[:2])
        with np.errstate(divide="ignore", invalid="ignore"):
            logerr = np.where(y_fem > 0, np.log(np.abs(y_fem)) - ref, np.inf)
            rel = y_fem / np.exp(ref) - 1
        logerr = np.where(ok, np.abs(logerr), -np.inf)
        usable |= ok.all(axis=0)                  # a distance counts in every direction
        every.append(np.where(ok, logerr, np.nan))
        j = np.argmax(logerr, axis=0)
        better = logerr[j, np.arange(len(rho))] > worst
        worst = np.where(better, logerr[j, np.arange(len(rho))], worst)
        signed = np.where(better, rel[j, np.arange(len(rho))], signed)
    neg = np.sum(phi < 0, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")           # all-NaN columns (unusable rho)
        median = np.nanmedian(np.concatenate(every), axis=0)
    return {"mueff_h": mueff_h, "mutp_h": mutp_h, "n": n, "lumped": lumped,
            "rho_h": rho[usable].tolist(), "worst_log_err": worst[usable].tolist(),
            "median_log_err": median[usable].tolist(),
            "signed_rel_err": signed[usable].tolist(),
            "negative_nodes_max": int(neg.max()), "nodes": mesh.n_nodes,
            "min_over_max": float(np.min(phi.min(axis=0) / phi.max(axis=0))),
            "seconds": time.perf_counter() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks fem_accuracy")
    ap.add_argument("--quick", action="store_true", help="two cells of the table only")
    ap.add_argument("--lumped", action="store_true", help="also the lumped absorption mass")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--write-table", default=None,
                    help="write the table module (FluoTomo/FluoTomoLib/fem/_resolution_table.py)")
    ap.add_argument("--only-mueff-h", type=float, nargs="+", default=None,
                    help="measure only these mueff h values of the grid")
    ap.add_argument("--merge", default=None, help="JSON of earlier results to complete")
    ap.add_argument("--half-cells", type=int, default=30)
    ap.add_argument("--depth-cells", type=int, default=24)
    args = ap.parse_args(argv)
    meshes = {}

    def box_for(me):
        # wide enough that every direction reaches the last rho / h 3 decay
        # lengths from the sides (36 cells for mueff h = 0.2)
        half = max(args.half_cells, int(np.ceil(max(RHO_H) + 3.0 / me + 1)))
        if half not in meshes:
            meshes[half] = kuhn_box(half, args.depth_cells)
            print(f"Kuhn box {2 * half} x {2 * half} x {args.depth_cells} cells (h = 1), "
                  f"{meshes[half].n_nodes} nodes", flush=True)
        return meshes[half]

    print(f"{len(OFFSETS)} source offsets x {len(DIRECTIONS_DEG)} directions; worst "
          "|ln(FEM/exact)| in %", flush=True)
    cells = [(0.5, 1.0), (1.0, 10.0)] if args.quick else [
        (me, mt) for mt in MUTP_H for me in MUEFF_H
        if args.only_mueff_h is None or me in args.only_mueff_h]
    indices = (1.37,) if args.quick else N_INDEX
    results = []
    print(f"{'mueff h':>8} {'mut h':>6} {'n':>5} {'neg':>6} " + " ".join(f"{r:>6g}" for r in RHO_H))
    for me, mt in cells:
        for n in indices:
            for lumped in ((False, True) if args.lumped else (False,)):
                r = measure(box_for(me), me, mt, n=n, lumped=lumped)
                results.append(r)
                row = dict(zip(r["rho_h"], r["worst_log_err"]))
                print(f"{me:8.2f} {mt:6.1f} {n:5.2f} {r['negative_nodes_max']:6d} "
                      + " ".join(f"{100 * row[x]:6.1f}" if x in row else f"{'-':>6}" for x in RHO_H)
                      + ("  lumped" if lumped else "") + f"  ({r['seconds']:.1f} s)", flush=True)
    if args.merge:                        # earlier results for the cells not run now
        with open(args.merge) as f:
            done = {(r["mueff_h"], r["mutp_h"], r["n"], r["lumped"]) for r in results}
            results = [r for r in json.load(f)
                       if (r["mueff_h"], r["mutp_h"], r["n"], r["lumped"]) not in done] + results
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    if args.write_table:
        write_table(results, args.write_table)
    return 0


def write_table(results, path):
    """The Python module fem/_resolution_table.py from measured results:
    worst and median |ln(FEM/exact)| on the grid (n, mut' h, mueff h, rho/h),
    NaN where not measured, inf where a detector went negative."""
    ns = sorted({r["n"] for r in results})
    grid = [np.full((len(ns), len(MUTP_H), len(MUEFF_H), len(RHO_H)), np.nan) for _ in range(2)]
    for r in results:
        if r["lumped"]:
            continue
        a, b, c = ns.index(r["n"]), MUTP_H.index(r["mutp_h"]), MUEFF_H.index(r["mueff_h"])
        for rho, w, m in zip(r["rho_h"], r["worst_log_err"], r["median_log_err"]):
            grid[0][a, b, c, RHO_H.index(rho)] = w
            grid[1][a, b, c, RHO_H.index(rho)] = m

    def literal(arr):
        def fmt(v):
            return "nan" if np.isnan(v) else ("inf" if np.isinf(v) else f"{v:.4f}")
        lines = []
        for a in range(arr.shape[0]):
            lines.append("    [  # n = %g" % ns[a])
            for b in range(arr.shape[1]):
                lines.append("        [  # mut' h = %g" % MUTP_H[b])
                for c in range(arr.shape[2]):
                    lines.append("            [" + ", ".join(fmt(v) for v in arr[a, b, c]) + "],"
                                 + f"  # mueff h = {MUEFF_H[c]:g}")
                lines.append("        ],")
            lines.append("    ],")
        return "\n".join(lines)

    from FluoTomoLib import optics

    text = f'''"""Measured FEM error table (generated by benchmarks/bench_fem_accuracy.py
--write-table; do not edit by hand): |ln(FEM / exact)| for a buried point source
and a surface detector on Kuhn-cube meshes, worst case and median over
{len(OFFSETS)} source positions within a cell and {len(DIRECTIONS_DEG)} directions.
Axes: refractive index n, mut' h, mueff h, rho / h.  NaN: not measured (the
detector was too close to the test box's sides); inf: the FEM gave a
negative or zero value there.  Measured with the {optics.DEFAULT_BOUNDARY} boundary
constant (``BOUNDARY``).
"""

import numpy as np

nan, inf = np.nan, np.inf

BOUNDARY = {optics.DEFAULT_BOUNDARY!r}

N = np.array({list(ns)!r})
MUTP_H = np.array({list(MUTP_H)!r})
MUEFF_H = np.array({list(MUEFF_H)!r})
RHO_H = np.array({list(RHO_H)!r})

WORST = np.array([
{literal(grid[0])}
])

MEDIAN = np.array([
{literal(grid[1])}
])
'''
    with open(path, "w") as f:
        f.write(text)


if __name__ == "__main__":
    raise SystemExit(main())
