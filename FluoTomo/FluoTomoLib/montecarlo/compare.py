"""The diffusion FEM (and the closed forms) on the Monte Carlo's medium, and the
comparison table.

The FEM solves the same box as the Monte Carlo (tissue in air on every face), on a
quarter of it: the pencil beam's axis is where the planes x = 0 and y = 0 meet,
those planes reflect (zero flux), every other face carries the Robin condition, and
the quarter's solution for a quarter of the source power is the whole box's.  The
beam is the FEM's usual isotropic point source one transport mean free path deep.

What is compared, for each annulus and ring the Monte Carlo tallied:

- R(rho): the FEM's exitance J = Phi / (2A) averaged over the annulus (radial
  Gauss-Legendre points at five azimuths), against the MC's exiting weight per mm^2;
  also the closed forms (extrapolated-boundary dipole, exact Robin half-space).
- Interior fluence: the FEM interpolated at every voxel centre of the MC's ring and
  averaged like the MC's voxels.  A voxel's mean differs from its centre value by
  h^2 / 24 * laplacian(Phi) = h^2 mueff^2 / 24 Phi in a source-free homogeneous
  region: 0.1 % for 1 mm voxels at mueff 0.17 /mm.

``A`` may be given to solve with another boundary constant than the default
(``FluoTomoLib.optics.robin_A``): the boundary-constant study of docs/validation.md.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.optics import robin_A

# mesh grading for the quarter box, from the beam axis (and from the surface):
# (fine step [mm], extent of the fine zone [mm], growth per step, step up to
# mid_until [mm], mid_until [mm], coarsest step beyond [mm])
MESH_LEVELS = {
    # for fast tests: 1 mm out to 22 mm only
    "test": (0.35, 2.0, 1.2, 1.0, 22.0, 6.0),
    # about twice the normal steps everywhere: with "normal", a Richardson estimate of
    # the normal mesh's discretisation error (P1: error ~ h^2)
    "coarse": (0.5, 3.0, 1.25, 2.0, 35.0, 8.0),
    "normal": (0.25, 3.0, 1.12, 1.0, 35.0, 4.0),
}


def graded_from_zero(length, fine, until, grow, mid_step, mid_until, coarse):
    """Coordinates 0 .. length: ``fine`` steps up to ``until``, then growing by
    ``grow`` per step to at most ``mid_step`` up to ``mid_until``, then to ``coarse``."""
    x = [0.0]
    step = fine
    while x[-1] < length - 1e-9:
        if x[-1] >= until:
            step = min(step * grow, mid_step if x[-1] < mid_until else coarse)
        x.append(min(length, x[-1] + step))
    if len(x) > 2 and x[-1] - x[-2] < 0.3 * step:   # merge a sliver last step
        x.pop(-2)
    return np.array(x)


def quarter_box_mesh(size_mm, level="normal"):
    """Quarter of the box x in [0, X/2], y in [0, Y/2], z in [-Z, 0], graded towards
    the beam axis and the surface; returns (mesh, robin facet mask)."""
    from FluoTomoLib.meshing.structured import box_mesh

    if level not in MESH_LEVELS:
        raise FluoInputError(f"unknown mesh level; use one of {', '.join(MESH_LEVELS)}",
                             field="mesh_level", value=level)
    grading = MESH_LEVELS[level]
    X, Y, Z = (float(s) for s in size_mm)
    x = graded_from_zero(X / 2, *grading)
    y = graded_from_zero(Y / 2, *grading)
    z = -graded_from_zero(Z, *grading)[::-1]
    mesh = box_mesh(x, y, z, name="mc_quarter_box")
    f = mesh.boundary_facets
    xyz = mesh.nodes_mm[f]                       # (F, 3 nodes, 3)
    on_sym = np.all(np.abs(xyz[:, :, 0]) < 1e-9, axis=1) | np.all(np.abs(xyz[:, :, 1]) < 1e-9,
                                                                  axis=1)
    return mesh, ~on_sym


def diffusion_operator_with_A(mesh, mua, musp, n, A=None, robin_facets=None, name="operator"):
    """A DiffusionOperator whose Robin term uses boundary constant ``A`` (default:
    robin_A(n)); the operator is re-assembled with the given A."""
    from FluoTomoLib.fem.operators import DiffusionOperator, geometry

    op = DiffusionOperator(mesh, mua, musp, n, robin_facets=robin_facets, name=name)
    if A is not None and float(A) != op.A:
        if not (np.isfinite(A) and A >= 1.0):
            raise FluoInputError("boundary constant A must be >= 1", field="A", value=A)
        g = geometry(mesh)
        op.A = float(A)
        op.K_upper = g.upper(op.D, op.mua, g.boundary_weight(robin_facets) * (1.0 / (2.0 * op.A)))
        op._K = None
    return op


def _annulus_points(rho, width, n_r=6, n_phi=5):
    """Gauss-Legendre points in r (weight r) over the annulus at n_phi azimuths in the
    first quadrant; returns (points (P, 3) on z = 0, weights summing to 1)."""
    xg, wg = np.polynomial.legendre.leggauss(n_r)
    r = rho + 0.5 * width * xg
    w = wg * r
    phi = np.linspace(0.0, 0.5 * np.pi, n_phi)
    pts = np.array([[ri * np.cos(p), ri * np.sin(p), 0.0] for p in phi for ri in r])
    wts = np.tile(w, n_phi)
    return pts, wts / wts.sum()


def fem_halfspace(medium, A=None, level="normal"):
    """The FEM's R(rho) annulus means and fluence ring means for a HalfSpace.

    Returns a dict: ``J`` (per annulus), ``phi`` (layers x rings), ``A``, ``nodes``,
    ``seconds``.
    """
    from FluoTomoLib.fem.locate import locator

    t0 = time.perf_counter()
    mesh, robin = quarter_box_mesh(medium.size_mm, level)
    A_used = float(robin_A(medium.n)) if A is None else float(A)
    op = diffusion_operator_with_A(mesh, medium.mua, medium.musp, medium.n, A_used,
                                   robin_facets=robin, name="halfspace")
    depth = 1.0 / (medium.mua + medium.musp)
    loc = locator(mesh)
    q = loc.interpolation_matrix(np.array([[0.0, 0.0, -depth]]), what="source").T.tocsc()
    # the quarter box carries a quarter of the source's power
    phi = 0.25 * op.solve(q)[:, 0]
    J = np.empty(len(medium.rho_mm))
    for i, (rho, w) in enumerate(zip(medium.rho_mm, medium.width_mm)):
        pts, wts = _annulus_points(rho, w)
        J[i] = wts @ (loc.interpolation_matrix(pts, what="detector") @ phi) / (2.0 * A_used)
    fl = []
    for pts in medium.fluence_points_mm():
        p = np.abs(pts)
        p[:, 2] = pts[:, 2]
        fl.append(float(np.mean(loc.interpolation_matrix(p, what="fluence point") @ phi)))
    fl = np.array(fl).reshape(len(medium.fluence_depths_mm), len(medium.fluence_rho_mm))
    return {"J": J, "phi": fl, "A": A_used, "nodes": mesh.n_nodes, "level": level,
            "seconds": time.perf_counter() - t0}


def _graded_symmetric(half, fine_half, fine, coarse, grow=1.15):
    """Coordinates -half .. half: ``fine`` steps within |x| <= fine_half, growing outside."""
    pos = graded_from_zero(half, fine, fine_half, grow, coarse, half, coarse)
    return np.concatenate([-pos[::-1], pos[1:]])


def disc_points(centre, radius_mm, n_r=4, n_phi=8):
    """Gauss-Legendre (r, weight r) x uniform-azimuth points over a horizontal disc;
    returns (points (P, 3), weights summing to 1)."""
    xg, wg = np.polynomial.legendre.leggauss(n_r)
    r = 0.5 * radius_mm * (xg + 1.0)
    w = wg * r
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    pts = np.array([[centre[0] + ri * np.cos(p), centre[1] + ri * np.sin(p), centre[2]]
                    for p in phi for ri in r])
    wts = np.tile(w, n_phi)
    return pts, wts / wts.sum()


def fem_acquisition(case, A=None, detector_radius_mm=2.0, fine_mm=0.5):
    """The FEM's excitation and emission data for a label-map case on a flat-topped box
    (reference.fluorescence_case): excitation exitance Phi/(2A) averaged over the
    detector disc like the Monte Carlo's; emission exitance by the same voxel sum as
    the Monte Carlo's, sum yield(v) Phi_x,s(v) G_d(v) h^3 / (2A), with the FEM's
    excitation field and emission adjoint at the voxel centres.

    Returns a dict: ``excitation``, ``emission`` (S, D), ``A``, ``nodes``, ``seconds``.
    """
    from FluoTomoLib.fem.locate import locator
    from FluoTomoLib.fem.operators import detector_operator, source_positions
    from FluoTomoLib.meshing.structured import box_mesh
    from FluoTomoLib.montecarlo.acquisition import LabelMapGeometry

    t0 = time.perf_counter()
    geo = LabelMapGeometry(case["labels_kji"], case["ijk_to_ras"])
    lo = geo.to_ras(np.zeros(3))
    hi = geo.to_ras(np.array(geo.shape, float))
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    if not np.allclose(geo.R, np.eye(3)) or not np.isclose(hi[2], 0.0, atol=1e-6):
        raise FluoInputError("fem_acquisition needs an axis-aligned box with its top face at "
                             "z = 0", field="ijk_to_ras")
    cx, cy = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
    x = cx + _graded_symmetric(0.5 * (hi[0] - lo[0]), 14.0, fine_mm, 3.0)
    y = cy + _graded_symmetric(0.5 * (hi[1] - lo[1]), 5.0, fine_mm, 3.0)
    z = -graded_from_zero(hi[2] - lo[2], 0.25, 2.0, 1.15, fine_mm, 13.0, 3.0)[::-1]
    mesh = box_mesh(x, y, z, name="mc_case_box")
    # nodal optics from the voxel under each node (nodes on a voxel face: the lower one)
    g = geo.to_grid(mesh.nodes_mm)
    idx = np.clip(np.floor(g - 1e-9).astype(int), 0, np.array(geo.shape) - 1)
    node_label = geo.labels_ijk[idx[:, 0], idx[:, 1], idx[:, 2]]

    def nodal(optics):
        tab = np.zeros((256, 3))
        for lab, v in optics.items():
            tab[int(lab)] = v
        return tab[node_label]

    ox, om = nodal(case["optics_x"]), nodal(case["optics_m"])
    n = float(ox[0, 2])
    A_used = float(robin_A(n)) if A is None else float(A)
    op_x = diffusion_operator_with_A(mesh, ox[:, 0], ox[:, 1], n, A_used, name="excitation")
    op_m = diffusion_operator_with_A(mesh, om[:, 0], om[:, 1], n, A_used, name="emission")
    loc = locator(mesh)
    src = source_positions(mesh, case["sources_ras"], ox[:, 1], ox[:, 0])
    phi_x = op_x.solve(loc.interpolation_matrix(src, what="source").T.tocsc())
    det = np.asarray(case["detectors_ras"], float)
    G = op_m.solve(detector_operator(mesh, det).T.tocsc())
    S, D = phi_x.shape[1], G.shape[1]
    ex = np.zeros((S, D))
    for d in range(D):
        pts, wts = disc_points(det[d], detector_radius_mm)
        ex[:, d] = wts @ (loc.interpolation_matrix(pts, what="detector disc") @ phi_x) / (2 * A_used)
    gamma = np.zeros(256)
    for lab, y in case["yield_per_label"].items():
        gamma[int(lab)] = y
    vox = np.argwhere(gamma[geo.labels_ijk] > 0)
    centres = geo.to_ras(vox + 0.5)
    P = loc.interpolation_matrix(centres, what="voxel centre")
    yv = gamma[geo.labels_ijk[tuple(vox.T)]] * geo.h ** 3
    em = ((P @ phi_x) * yv[:, None]).T @ (P @ G) / (2 * A_used)
    return {"excitation": ex, "emission": em, "A": A_used, "nodes": mesh.n_nodes,
            "seconds": time.perf_counter() - t0}


# ---------------------------------------------------------------- the comparison table

# FEM vs MC: agreement means |FEM/MC - 1| <= AGREE_PCT + AGREE_SE MC standard errors.
# 3 standard errors: with ~26 annuli from 5 to 30 mm, a 2-sigma margin fails one of
# them by chance about half the time.
AGREE_PCT = 3.0
AGREE_SE = 3.0


def _pct(a, b):
    return None if not (np.isfinite(a) and np.isfinite(b) and b != 0) else float((a / b - 1) * 100)


def _annulus_mean(f, rho, width, n_r=4):
    xg, wg = np.polynomial.legendre.leggauss(n_r)
    r = rho + 0.5 * width * xg
    w = wg * r
    return float(np.dot(w, f(r)) / w.sum())


def agreement_from_mm(rows, value_key, mc_key="mc", se_key="mc_se", tol_pct=AGREE_PCT,
                      n_se=AGREE_SE):
    """Smallest rho from which every row agrees: ``|value/mc - 1| <= tol + n_se se/mc``."""
    ok = []
    for r in rows:
        mc, v, se = r[mc_key], r[value_key], r[se_key]
        if not (mc and np.isfinite(v)):
            ok.append(False)
            continue
        lim = tol_pct + 100.0 * n_se * (se / mc if np.isfinite(se) else 0.0)
        ok.append(abs(v / mc - 1) * 100 <= lim)
    start = None
    for i in range(len(rows) - 1, -1, -1):
        if not ok[i]:
            break
        start = rows[i]["rho_mm"]
    return start


def validate_halfspace(medium, merged, boundaries=("empirical", "fresnel"), level="normal",
                       reference=None, progress=None):
    """Compare a merged Monte Carlo half-space set with the FEM (one solve per boundary
    constant), the closed forms and, when given, an independent MC run of the same
    medium (reference.read_independent_reflectance).

    Returns a dict: ``rows`` (R per annulus), ``fluence_rows``, ``A`` (boundary ->
    value), ``agree_from_mm`` (boundary -> the smallest rho from which the FEM agrees
    with MC within AGREE_PCT % + AGREE_SE MC standard errors), ``reference`` summary,
    ``warnings``, ``fem_seconds``.
    """
    from fluoguide.progress import report

    from FluoTomoLib.analytic import robin_surface_fluence, spatially_resolved_reflectance

    from FluoTomoLib import optics

    default = optics.DEFAULT_BOUNDARY
    fems = {}
    for i, b in enumerate(boundaries):
        report(progress, i / max(len(boundaries), 1), f"FEM, boundary {b}")
        fems[b] = fem_halfspace(medium, A=robin_A(medium.n, b), level=level)
    report(progress, 1.0, "FEM done")
    main = default if default in fems else boundaries[0]
    mua, musp, n = medium.mua, medium.musp, medium.n
    A_main = fems[main]["A"]
    rows = []
    for i, r in enumerate(merged["R"]):
        rho, w = r["rho_mm"], r["width_mm"]
        # the larger of the runs' spread and the compound-Poisson error: a spread from
        # 3-4 runs is itself uncertain by +-40 %
        mc = r["R_per_mm2"]
        se = float(np.nanmax([r["se"], r["se_cp"]]))
        row = {"rho_mm": rho, "width_mm": w, "mc": mc, "mc_se": se, "mc_se_cp": r["se_cp"],
               "mc_rel_se_pct": float(se / mc * 100) if mc > 0 else None,
               "fem": float(fems[main]["J"][i]), "fem_vs_mc_pct": _pct(fems[main]["J"][i], mc),
               "fem_vs_mc_z": float((fems[main]["J"][i] - mc) / se) if se > 0 else None}
        for b, f in fems.items():
            row[f"fem_{b}"] = float(f["J"][i])
            row[f"fem_{b}_vs_mc_pct"] = _pct(f["J"][i], mc)
        dip = _annulus_mean(lambda x: spatially_resolved_reflectance(x, mua, musp, n), rho, w)
        rob = _annulus_mean(lambda x: robin_surface_fluence(x, mua, musp, n), rho,
                            w) / (2 * A_main)
        row.update({"dipole": dip, "dipole_vs_mc_pct": _pct(dip, mc),
                    "robin_exact": rob, "robin_exact_vs_mc_pct": _pct(rob, mc)})
        rows.append(row)
    warnings = []
    ref_summary = None
    if reference is not None:
        z = []
        for row in rows:
            j = np.flatnonzero(np.isclose(reference["rho_mm"], row["rho_mm"]) &
                               np.isclose(reference["width_mm"], row["width_mm"]))
            if len(j) == 0:
                continue
            j = j[0]
            ref, rse = float(reference["R"][j]), float(reference["se"][j])
            row["reference"] = ref
            row["reference_se"] = rse
            row["mc_vs_reference_pct"] = _pct(row["mc"], ref)
            zz = (row["mc"] - ref) / np.hypot(row["mc_se"], rse)
            row["mc_vs_reference_z"] = float(zz)
            z.append(zz)
        z = np.array(z)
        if len(z):
            ref_summary = {"annuli": int(len(z)), "max_abs_z": float(np.max(np.abs(z))),
                           "within_2se": float(np.mean(np.abs(z) <= 2)),
                           "chi2_per_dof": float(np.mean(z ** 2)),
                           "photons": reference.get("photons")}
            # with k annuli, |z| > 3.5 happens by chance with probability ~ k * 5e-4
            ref_summary["agrees"] = bool(ref_summary["max_abs_z"] <= 3.5 and
                                         ref_summary["chi2_per_dof"] <= 2.0)
            if not ref_summary["agrees"]:
                warnings.append(f"Monte Carlo disagrees with the independent run: max |z| "
                                f"{ref_summary['max_abs_z']:.1f}, chi2/dof "
                                f"{ref_summary['chi2_per_dof']:.2f}")
    frows = []
    for i, fr in enumerate(merged["fluence"]):
        a, b = divmod(i, len(medium.fluence_rho_mm))
        mc, se = fr["phi_per_mm2"], fr["se"]
        row = {"depth_mm": fr["depth_mm"], "rho_mm": fr["rho_mm"], "voxels": fr["voxels"],
               "mc": mc, "mc_se": se,
               "mc_rel_se_pct": float(se / mc * 100) if mc > 0 and np.isfinite(se) else None}
        for bnd, f in fems.items():
            row[f"fem_{bnd}"] = float(f["phi"][a, b])
            row[f"fem_{bnd}_vs_mc_pct"] = _pct(f["phi"][a, b], mc)
        row["fem"] = row[f"fem_{main}"]
        row["fem_vs_mc_pct"] = row[f"fem_{main}_vs_mc_pct"]
        frows.append(row)
    agree = {b: agreement_from_mm(rows, f"fem_{b}") for b in fems}
    near = [r for r in rows if agree[main] is None or r["rho_mm"] < agree[main]]
    if agree[main] is None:
        warnings.append(f"the FEM ({main}) does not agree with Monte Carlo within "
                        f"{AGREE_PCT:g} % + {AGREE_SE:g} MC errors at the far end of R(rho)")
    elif near:
        txt = ", ".join(f"{r['fem_vs_mc_pct']:+.1f} % at {r['rho_mm']:g} mm" for r in near[-3:])
        warnings.append(
            f"near the beam diffusion is not transport: the FEM ({main}) differs from Monte "
            f"Carlo by {txt}; it agrees within {AGREE_PCT:g} % (+ {AGREE_SE:g} MC errors) from "
            f"{agree[main]:g} mm outwards")
    noisy = [r["rho_mm"] for r in rows if r["mc_rel_se_pct"] and r["mc_rel_se_pct"] > AGREE_PCT]
    if noisy:
        warnings.append(f"Monte Carlo standard error above {AGREE_PCT:g} % at rho "
                        f"{min(noisy):g}-{max(noisy):g} mm: more photons for a sharper test")
    e = merged["energy"]
    if abs(e["lost"]) > 1e-3:
        warnings.append(f"energy balance: absorbed + exited = {e['balance']:.5f} (lost "
                        f"{e['lost']:.2e} at the time gate)")
    if merged.get("exit_records_truncated"):
        warnings.append("exit records hit MCX's limit: R(rho) is low; use fewer photons per run")
    return {"rows": rows, "fluence_rows": frows,
            "A": {b: f["A"] for b, f in fems.items()}, "boundary": main,
            "agree_from_mm": agree, "reference": ref_summary, "warnings": warnings,
            "fem_nodes": fems[main]["nodes"], "fem_level": level,
            "fem_seconds": float(sum(f["seconds"] for f in fems.values()))}
