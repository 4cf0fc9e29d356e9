"""The thesis's 2D simulation studies A, B and C (physics.md section 8).

50 x 30 mm tissue (top edge y = 0, depth downwards), forward mesh 0.5 mm,
reconstruction mesh 1.0 mm (structured triangles: 6,161 / 12,000 and
1,581 / 3,000, against the thesis's unstructured 7,504 / 14,652 and
1,848 / 3,520).  16 sources 2.5 mm apart across the top, detectors at the 15
other source positions (240 measurements).  mua 0.032, musp 1 /mm at both
wavelengths, n 1.33; background yield 0.04 * 0.003, target 0.04 * 0.03 /mm.

Noise: "Gaussian, max amplitude 1 %" is read as zero-mean Gaussian relative
noise with sigma = 1/3 % (so 99.7 % of values lie within +-1 %).

Data are simulated on the forward mesh with the exact target shape; the
Jacobian is computed on the forward mesh and mapped to the reconstruction
mesh (J_r = J_f P), as in the thesis.  Priors come from the target shape
(study C: a filled disc while the truth is an annulus) with volume-preserving
node regions.

Reconstruction scheme (``scheme``): "nirfast" (default) is what the thesis ran,
NIRFAST's fluorescence reconstruction: log-amplitude data, the Jacobian
normalised by the current yield, fixed lambda for NP and SP, started from the
known background yield.  "reference" is the literal update of physics.md
(linear data, zero start), kept for comparison.  HP's region basis
(``hp_basis``) is built on the forward mesh by default, where the data live
(NIRFAST's reconstruct_fl_region also works on the forward mesh).
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.progress import check_cancel, report

from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.fem.locate import locator
from FluoTomoLib.recon.metrics import depth_profile, peak_and_centroid
from FluoTomoLib.recon.solver import RegionPrior, reconstruct, region_jacobian
from FluoTomoLib.meshing.structured import box_mesh, rectangle_mesh

WIDTH_MM, DEPTH_MM = 50.0, 30.0
MUA, MUSP, N = 0.032, 1.0, 1.33
YIELD_BG, YIELD_TARGET = 0.04 * 0.003, 0.04 * 0.03


SLAB_Y_MM, SLAB_DEPTH_MM = 30.0, 20.0   # 3D: 50 x 30 x 20 mm slab


def study_meshes(fine_mm=None, coarse_mm=None, dim=2):
    """Forward and reconstruction meshes: 2D 50 x 30 mm at 0.5 / 1.0 mm; 3D slab
    50 x 30 x 20 mm at 1.0 / 1.5 mm (33k / 10k nodes)."""
    def axis(lo, hi, h):
        return np.linspace(lo, hi, int(round((hi - lo) / h)) + 1)

    def mesh(h, name):
        if dim == 2:
            m = rectangle_mesh(axis(-WIDTH_MM / 2, WIDTH_MM / 2, h), axis(-DEPTH_MM, 0.0, h),
                               name=name)
        else:
            m = box_mesh(axis(-WIDTH_MM / 2, WIDTH_MM / 2, h),
                         axis(-SLAB_Y_MM / 2, SLAB_Y_MM / 2, h), axis(-SLAB_DEPTH_MM, 0.0, h),
                         name=name)
        m.meta["size_mm"] = h
        return m
    if dim not in (2, 3):
        raise FluoInputError("dimension must be 2 or 3", field="dim", value=dim)
    fine_mm = fine_mm or (0.5 if dim == 2 else 1.0)
    coarse_mm = coarse_mm or (1.0 if dim == 2 else 1.5)
    return mesh(fine_mm, "forward"), mesh(coarse_mm, "reconstruction")


def disc(diameter_mm, top_depth_mm, inner_diameter_mm=0.0):
    """Indicator of a disc (2D) or sphere (3D), or their hollow versions, whose top
    lies ``top_depth_mm`` below the surface (the last coordinate is depth, surface 0)."""
    r = 0.5 * float(diameter_mm)
    ri = 0.5 * float(inner_diameter_mm)
    cy = -(float(top_depth_mm) + r)

    def inside(p):
        q = np.array(p, dtype=float, copy=True)
        q[:, -1] -= cy
        d = np.linalg.norm(q, axis=1)
        return (d <= r) & (d >= ri)
    return inside, -cy


def node_regions_from_shape(mesh, inside, supersample=8):
    """Volume-preserving node regions (2 = target, 1 = background) from an
    analytic shape: nodes ranked by the fraction of their h x h cell inside the
    shape, taken until their lumped areas equal the shape's area on the mesh."""
    from FluoTomoLib.meshing.voxel import nodal_volumes

    h = float(mesh.meta["size_mm"])
    d = mesh.dim
    ss = supersample if d == 2 else max(2, supersample // 2)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    grids = np.meshgrid(*([off * h] * d))
    offsets = np.stack([g.ravel() for g in grids], axis=1)
    pts = mesh.nodes_mm[:, None, :] + offsets[None]
    cover = inside(pts.reshape(-1, d)).reshape(len(mesh.nodes_mm), -1).mean(axis=1)
    area = nodal_volumes(mesh)
    target_area = float(np.sum(cover * area))
    order = np.argsort(-cover, kind="stable")
    order = order[cover[order] > 0]
    region = np.ones(mesh.n_nodes, dtype=np.int64)
    if len(order):
        cum = np.cumsum(area[order])
        k = int(np.argmin(np.abs(cum - target_area))) + 1
        region[order[:k]] = 2
    return region


# reconstruct() options per scheme; "start": the initial yield [1/mm] (None: zero)
SCHEMES = {
    "nirfast": dict(log_data=True, normalise=True, start=YIELD_BG),
    "reference": dict(log_data=False, normalise=False, start=None),
}
HP_BASES = ("forward", "reconstruction")

_CACHE = {}


def _forward_setup(fine, coarse):
    """Sources, detectors, Jacobian on the forward mesh, mapping to the coarse one
    (the same for every case of a study: computed once)."""
    key = (id(fine), id(coarse))
    if key not in _CACHE:
        xs = (np.arange(16) - 7.5) * 2.5
        src = np.stack([xs] + [np.zeros(16)] * (fine.dim - 1), axis=1)
        p = {"mua_per_mm": MUA, "musp_per_mm": MUSP, "n": N}
        fm = FluorescenceModel(fine, p, p, src, src)
        mask = ~np.eye(16, dtype=bool)
        J_f = fm.jacobian_yield()[mask.ravel()]
        P = locator(coarse).interpolation_matrix(fine.nodes_mm, what="forward node")
        _CACHE.clear()
        _CACHE[key] = (fm, mask, J_f, np.asarray((P.T @ J_f.T).T))
    return _CACHE[key]


def _recon_options(scheme, hp_basis):
    """reconstruct() keyword arguments for a scheme name (both names validated)."""
    if scheme not in SCHEMES:
        raise FluoInputError(f"scheme must be one of {', '.join(SCHEMES)}", field="scheme",
                             value=scheme)
    if hp_basis not in HP_BASES:
        raise FluoInputError(f"HP basis must be one of {', '.join(HP_BASES)}",
                             field="hp_basis", value=hp_basis)
    opts = dict(SCHEMES[scheme])
    opts["x0"] = opts.pop("start")
    return opts


def run_case(case, diameter_mm, top_depth_mm, inner_diameter_mm=0.0, prior_diameter_mm=None,
             methods=("NP", "SP", "HP"), lambdas=None, seed=0, noise_pct=1.0, meshes=None,
             scheme="nirfast", hp_basis="forward", progress=None, cancel=None):
    """One target through NP/SP/HP; returns (rows, figure data).

    ``scheme``: "nirfast" or "reference" (module docstring); ``hp_basis``:
    "forward" (HP's region Jacobian J_f K_f from node regions of the forward
    mesh) or "reconstruction" (J_f P K from those of the reconstruction mesh).
    """
    opts = _recon_options(scheme, hp_basis)
    fine, coarse = meshes or study_meshes()
    depth_max = (DEPTH_MM if fine.dim == 2 else SLAB_DEPTH_MM) - 2
    if not (0 < diameter_mm < depth_max) or top_depth_mm < 0 or top_depth_mm + diameter_mm > depth_max:
        raise FluoInputError("target must fit inside the 50 x 30 mm domain",
                             field="target", value=(diameter_mm, top_depth_mm))
    line = 0.0 if fine.dim == 2 else (0.0, 0.0)   # the depth profile through the target
    bottom = -(DEPTH_MM if fine.dim == 2 else SLAB_DEPTH_MM)
    fm, mask, J_f, J = _forward_setup(fine, coarse)
    inside, centre_depth = disc(diameter_mm, top_depth_mm, inner_diameter_mm)
    truth_f = np.where(inside(fine.nodes_mm), YIELD_TARGET, YIELD_BG)
    y_clean = J_f @ truth_f
    rng = seeded_rng(seed)
    y = y_clean * (1.0 + rng.normal(0.0, noise_pct / 300.0, y_clean.shape))
    prior_shape, _ = disc(prior_diameter_mm or diameter_mm, top_depth_mm)
    prior = RegionPrior(node_regions_from_shape(coarse, prior_shape))
    J_hp = (region_jacobian(J_f, node_regions_from_shape(fine, prior_shape), prior.labels)
            if hp_basis == "forward" else None)
    z_true, prof_true = depth_profile(fine, truth_f, line, 0.0, bottom)
    rows, fields = [], {"truth": (fine, truth_f)}
    for method in methods:
        for lam in (lambdas or {}).get(method, [10.0]):
            check_cancel(cancel)
            report(progress, 0.5, f"{case}: {method} lambda {lam:g}")
            t0 = time.perf_counter()
            res = reconstruct(J, y, method, lam=lam, prior=prior,
                              region_jacobian=J_hp if method == "HP" else None, **opts)
            sec = time.perf_counter() - t0
            z, prof = depth_profile(coarse, res.yield_per_mm, line, 0.0, bottom)
            peak, centroid = peak_and_centroid(z, prof)
            rows.append({
                "case": case, "method": method, "lambda": lam, "true_peak": YIELD_TARGET,
                "peak": peak, "peak_error_pct": 100 * (peak - YIELD_TARGET) / YIELD_TARGET,
                "true_centroid_mm": centre_depth, "centroid_mm": centroid,
                "centroid_error_pct": 100 * (centroid - centre_depth) / centre_depth,
                "seconds": sec, "iterations": res.iterations,
                "residual_ss": res.residual, "stop_reason": res.stop_reason,
            })
            fields[f"{method} (lambda {lam:g})"] = (coarse, res.yield_per_mm)
    return rows, fields


STUDIES = {
    "A": [(f"A: {d:g} mm disc", dict(diameter_mm=d, top_depth_mm=2.5)) for d in (2.5, 5, 10, 15)],
    "B": [(f"B: 6 mm disc, top {t:g} mm", dict(diameter_mm=6, top_depth_mm=t))
          for t in (2.5, 3.5, 4.5, 5.5, 6.5)],
    "C": [("C: annulus 15/13 mm, disc prior", dict(diameter_mm=15, top_depth_mm=2.5,
                                                    inner_diameter_mm=13, prior_diameter_mm=15,
                                                    lambdas={"NP": [10.0], "HP": [10.0],
                                                             "SP": [1e3, 10.0, 1e-1, 1e-3]}))],
}


def run_study(name, seed=0, target=None, out_dir=None, dim=2, scheme="nirfast",
              hp_basis="forward", progress=None, cancel=None):
    """Run study A, B or C (or one custom ``target`` = (diameter, top depth)), in 2D
    (discs in a 50 x 30 mm section) or 3D (spheres in a 50 x 30 x 20 mm slab),
    with a reconstruction ``scheme`` and ``hp_basis`` as in :func:`run_case`."""
    _recon_options(scheme, hp_basis)      # bad names fail before any mesh is built
    seeded_rng(seed)                      # and so does a bad seed
    if target is not None:
        cases = [(f"custom: {target[0]:g} mm disc, top {target[1]:g} mm",
                  dict(diameter_mm=target[0], top_depth_mm=target[1]))]
    elif name in STUDIES:
        cases = STUDIES[name]
    else:
        raise FluoInputError("study must be A, B or C", field="study", value=name)
    if dim == 3:
        cases = [(c.replace("disc", "sphere").replace("annulus", "spherical shell"), kw)
                 for c, kw in cases]
    meshes = study_meshes(dim=dim)
    rows, figures = [], []
    for i, (case, kw) in enumerate(cases):
        report(progress, i / len(cases), case)
        r, fields = run_case(case, seed=seed, meshes=meshes, scheme=scheme, hp_basis=hp_basis,
                             cancel=cancel, **kw)
        rows += r
        if out_dir is not None:
            from FluoTomoLib.studies.plots import plot_case

            figures.append(plot_case(out_dir, i, case, fields))
    report(progress, 1.0, "done")
    return {"study": name if target is None else "custom", "dim": dim, "rows": rows,
            "figures": figures,
            "forward_mesh": [meshes[0].n_nodes, meshes[0].n_elements],
            "reconstruction_mesh": [meshes[1].n_nodes, meshes[1].n_elements],
            "measurements": 240, "noise": "Gaussian, sigma = 1/3 % relative (max ~1 %)",
            "scheme": scheme, "hp_basis": hp_basis}


SWEEPS = {
    "lambda": [1e-3, 1e-1, 1.0, 10.0, 1e2, 1e3],
    "noise": [0.0, 0.5, 1.0, 2.0, 5.0],
    "mesh": [0.75, 1.0, 1.5, 2.0],
}


def run_sweep(kind, target=(6.0, 3.5), dim=2, seed=0, scheme="nirfast", hp_basis="forward",
              progress=None, cancel=None):
    """Error against time for one target as lambda, noise [% max amplitude] or the
    reconstruction mesh size [mm] varies: the speed/accuracy trade a user makes."""
    if kind not in SWEEPS:
        raise FluoInputError(f"sweep must be one of {', '.join(SWEEPS)}", field="--sweep",
                             value=kind)
    seeded_rng(seed)
    rows = []
    base = study_meshes(dim=dim)
    for i, value in enumerate(SWEEPS[kind]):
        report(progress, i / len(SWEEPS[kind]), f"{kind} = {value:g}")
        kw = dict(diameter_mm=target[0], top_depth_mm=target[1], seed=seed, scheme=scheme,
                  hp_basis=hp_basis, cancel=cancel)
        if kind == "lambda":
            kw["lambdas"] = {m: [value] for m in ("NP", "SP", "HP")}
            meshes = base
        elif kind == "noise":
            kw["noise_pct"] = value
            meshes = base
        else:
            h = value if dim == 2 else 1.5 * value
            meshes = study_meshes(coarse_mm=h, dim=dim)
        t0 = time.perf_counter()
        r, _ = run_case(f"{kind} = {value:g}", meshes=meshes, **kw)
        elapsed = time.perf_counter() - t0
        for row in r:
            row["sweep"] = kind
            row["value"] = value
            row["case_seconds_including_jacobian"] = elapsed
        rows += r
    return {"sweep": kind, "dim": dim, "target": list(target), "rows": rows, "scheme": scheme,
            "hp_basis": hp_basis}
