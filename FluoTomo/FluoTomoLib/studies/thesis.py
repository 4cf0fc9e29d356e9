"""The thesis's 2D simulation studies A, B and C (docs/physics.md section 8.5).

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
known background yield.  "reference" is the literal update of docs/physics.md section 8.3
(linear data, zero start), kept for comparison.  HP's region basis
(``hp_basis``) is built on the forward mesh by default, where the data live
(NIRFAST's reconstruct_fl_region also works on the forward mesh).
"""

from __future__ import annotations

import functools
import time

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.fem.locate import locator
from FluoTomoLib.recon.metrics import depth_profile, peak_and_centroid
from FluoTomoLib.recon.solver import RegionPrior, reconstruct, region_jacobian
from FluoTomoLib.meshing.structured import box_mesh, rectangle_mesh

WIDTH_MM, DEPTH_MM = 50.0, 30.0
MUA, MUSP, N = 0.032, 1.0, 1.33
YIELD_BG, YIELD_TARGET = 0.04 * 0.003, 0.04 * 0.03
# NIRFAST's boundary constant (the empirical Reff(n) polynomial): the studies reproduce
# the thesis's NIRFAST runs.  The rest of the project defaults to the Fresnel constant
# that Monte Carlo supports (docs/validation.md); at n 1.33 the two are 2.79 and 2.52.
BOUNDARY = "empirical"


SLAB_Y_MM, SLAB_DEPTH_MM = 30.0, 20.0   # 3D: 50 x 30 x 20 mm slab
N_SOURCES, SOURCE_PITCH_MM = 16, 2.5    # 240 measurements: every source to the 15 others


def full_depth_mm(dim):
    """Depth of the whole domain: 30 mm (2D section), 20 mm (3D slab)."""
    return DEPTH_MM if dim == 2 else SLAB_DEPTH_MM


def default_sizes_mm(dim):
    """(forward, reconstruction) element sizes: 0.5 / 1.0 mm in 2D, 1.0 / 1.5 mm in 3D."""
    return (0.5, 1.0) if dim == 2 else (1.0, 1.5)


def _axis(lo, hi, h):
    return np.linspace(lo, hi, int(round((hi - lo) / h)) + 1)


@functools.lru_cache(maxsize=16)
def domain_mesh(dim, size_mm, depth_mm=None, name="mesh"):
    """Structured mesh of the study domain (or of its top ``depth_mm``: a region of
    interest cut below the target). Cached: tasks on one worker share it."""
    if dim not in (2, 3):
        raise FluoInputError("dimension must be 2 or 3", field="dim", value=dim)
    depth = full_depth_mm(dim) if depth_mm is None else float(depth_mm)
    h = float(size_mm)
    if dim == 2:
        m = rectangle_mesh(_axis(-WIDTH_MM / 2, WIDTH_MM / 2, h), _axis(-depth, 0.0, h), name=name)
    else:
        m = box_mesh(_axis(-WIDTH_MM / 2, WIDTH_MM / 2, h), _axis(-SLAB_Y_MM / 2, SLAB_Y_MM / 2, h),
                     _axis(-depth, 0.0, h), name=name)
    m.meta["size_mm"] = h
    m.meta["depth_mm"] = depth
    return m


def study_meshes(fine_mm=None, coarse_mm=None, dim=2):
    """Forward and reconstruction meshes: 2D 50 x 30 mm at 0.5 / 1.0 mm; 3D slab
    50 x 30 x 20 mm at 1.0 / 1.5 mm (33k / 10k nodes)."""
    if dim not in (2, 3):
        raise FluoInputError("dimension must be 2 or 3", field="dim", value=dim)
    f, c = default_sizes_mm(dim)
    return (domain_mesh(dim, float(fine_mm or f), name="forward"),
            domain_mesh(dim, float(coarse_mm or c), name="reconstruction"))


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


def true_yield(mesh, inside):
    """The true yield [1/mm] at the nodes of ``mesh``: the background's plus the
    target's excess by each node's share of the shape (``meshing.shares``), so
    that the interpolated truth holds the shape's true area (volume in 3D).
    Sampling the shape at the 0.25 mm data mesh's nodes missed a disc's area by
    -3.3 to +2.6 % (diameters 2-10 mm, depending on where the nodes fell)."""
    from FluoTomoLib.meshing.shares import analytic_fractions

    return YIELD_BG + (YIELD_TARGET - YIELD_BG) * analytic_fractions(mesh, inside)


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


def recon_options(scheme, hp_basis):
    """``reconstruct()`` keyword arguments of a reconstruction scheme.

    Parameters
    ----------
    scheme : str
        A key of :data:`SCHEMES` ("nirfast" or "reference").
    hp_basis : str
        One of :data:`HP_BASES`; checked here so that a study's parameters are
        refused before any task runs (:func:`FluoTomoLib.studies.spec.check_params`).

    Returns
    -------
    dict
        ``log_data``, ``normalise`` and ``x0`` (the initial yield [1/mm], None: zero).

    Raises
    ------
    FluoInputError
        An unknown scheme or basis.
    """
    if scheme not in SCHEMES:
        raise FluoInputError(f"scheme must be one of {', '.join(SCHEMES)}", field="scheme",
                             value=scheme)
    if hp_basis not in HP_BASES:
        raise FluoInputError(f"HP basis must be one of {', '.join(HP_BASES)}",
                             field="hp_basis", value=hp_basis)
    opts = dict(SCHEMES[scheme])
    opts["x0"] = opts.pop("start")
    return opts


# --- shared inputs: computed once per distinct model, whatever number of tasks use them

def optodes_mm(dim):
    """The 16 source (= detector) positions across the top surface, 2.5 mm apart."""
    xs = (np.arange(N_SOURCES) - 0.5 * (N_SOURCES - 1)) * SOURCE_PITCH_MM
    return np.stack([xs] + [np.zeros(N_SOURCES)] * (dim - 1), axis=1)


def forward_jacobian(dim, size_mm, depth_mm):
    """The 240 x N Jacobian d(emission data)/d(nodal yield) on the forward mesh of
    the domain cut at ``depth_mm`` (the full depth: no cut).

    Returns a dict of plain arrays (a Dask worker sends it to the tasks that
    share it): ``J`` (240, N), ``nodes``, ``elements`` (counts), ``seconds``.
    """
    t0 = time.perf_counter()
    mesh = domain_mesh(dim, size_mm, depth_mm)
    src = optodes_mm(dim)
    p = {"mua_per_mm": MUA, "musp_per_mm": MUSP, "n": N, "boundary": BOUNDARY}
    fm = FluorescenceModel(mesh, p, p, src, src)
    mask = ~np.eye(N_SOURCES, dtype=bool)
    J = np.ascontiguousarray(fm.jacobian_yield()[mask.ravel()])
    return {"J": J, "nodes": mesh.n_nodes, "elements": mesh.n_elements,
            "seconds": time.perf_counter() - t0}


def mapped_jacobian(forward, dim, forward_mm, recon_mm, depth_mm):
    """J_r = J_f P: the forward Jacobian mapped to the reconstruction mesh (the
    thesis's scheme); P interpolates reconstruction nodes at the forward nodes."""
    t0 = time.perf_counter()
    fine = domain_mesh(dim, forward_mm, depth_mm)
    coarse = domain_mesh(dim, recon_mm, depth_mm)
    P = locator(coarse).interpolation_matrix(fine.nodes_mm, what="forward node")
    J = np.ascontiguousarray((P.T @ forward["J"].T).T)
    return {"J": J, "nodes": coarse.n_nodes, "elements": coarse.n_elements,
            "seconds": forward["seconds"] + time.perf_counter() - t0}


def reconstruction_task(params, data, forward, recon):
    """One target, one method, one lambda: simulate the data, reconstruct, score.

    ``params`` (study spec, :mod:`FluoTomoLib.studies.spec`): ``dim``,
    ``diameter_mm``, ``top_depth_mm``, ``inner_diameter_mm``,
    ``prior_diameter_mm``, ``method``, ``lambda``, ``noise_pct``, ``seed``,
    ``forward_mm``, ``recon_mm``, ``data_mm``, ``roi_depth_mm``, ``scheme``,
    ``hp_basis``. ``data``: the Jacobian of the mesh the measurements are
    simulated on (full domain); ``forward``/``recon``: the reconstruction
    model's forward and mapped Jacobians (on the region of interest).

    The noise comes from ``seed`` alone, so every method of one target sees the
    same measurements and a re-run (anywhere) gives the same numbers.
    """
    p = params
    dim, roi = int(p["dim"]), float(p["roi_depth_mm"])
    opts = recon_options(p["scheme"], p["hp_basis"])
    data_mesh = domain_mesh(dim, p["data_mm"], full_depth_mm(dim))
    fine = domain_mesh(dim, p["forward_mm"], roi)
    coarse = domain_mesh(dim, p["recon_mm"], roi)
    inside, centre_depth = disc(p["diameter_mm"], p["top_depth_mm"], p["inner_diameter_mm"])
    truth = true_yield(data_mesh, inside)
    y_clean = data["J"] @ truth
    rng = np.random.default_rng(int(p["seed"]))
    y = y_clean * (1.0 + rng.normal(0.0, p["noise_pct"] / 300.0, y_clean.shape))
    prior_shape, _ = disc(p["prior_diameter_mm"] or p["diameter_mm"], p["top_depth_mm"])
    prior = RegionPrior(node_regions_from_shape(coarse, prior_shape))
    J_hp = None
    if p["method"] == "HP" and p["hp_basis"] == "forward":
        J_hp = region_jacobian(forward["J"], node_regions_from_shape(fine, prior_shape),
                               prior.labels)
    # the noise model grades the fit (diagnostics), it does not weight it
    res = reconstruct(recon["J"], y, p["method"], lam=p["lambda"], prior=prior,
                      region_jacobian=J_hp,
                      noise_rel=p["noise_pct"] / 300.0 if p["noise_pct"] > 0 else None, **opts)
    line = 0.0 if dim == 2 else (0.0, 0.0)   # the depth profile through the target
    z, prof = depth_profile(coarse, res.yield_per_mm, line, 0.0, -roi)
    peak, centroid = peak_and_centroid(z, prof)
    row = {
        "true_peak": YIELD_TARGET, "peak": peak,
        "peak_error_pct": 100 * (peak - YIELD_TARGET) / YIELD_TARGET,
        "true_centroid_mm": centre_depth, "centroid_mm": centroid,
        "centroid_error_pct": 100 * (centroid - centre_depth) / centre_depth,
    }
    # the solver's own summary (iterations, residuals, diagnostics), scalars only
    for k, v in res.summary().items():
        if k not in ("method", "lambda") and (v is None or isinstance(v, (int, float, str, bool,
                                                                           np.generic))):
            row.setdefault(k, v)
    row["warnings"] = list(res.warnings)
    row["diagnostics"] = res.diagnostics
    row.update({"forward_nodes": fine.n_nodes, "recon_nodes": coarse.n_nodes,
                "jacobian_seconds": recon["seconds"],
                "arrays": {"yield_per_mm": res.yield_per_mm}})
    return row


# --- the thesis's studies and sweeps (expanded into tasks by FluoTomoLib.studies.spec)

# name -> [(case title, target keywords)]: the targets of studies A, B and C
STUDIES = {
    "A": [(f"A: {d:g} mm disc", dict(diameter_mm=d, top_depth_mm=2.5)) for d in (2.5, 5, 10, 15)],
    "B": [(f"B: 6 mm disc, top {t:g} mm", dict(diameter_mm=6, top_depth_mm=t))
          for t in (2.5, 3.5, 4.5, 5.5, 6.5)],
    "C": [("C: annulus 15/13 mm, disc prior", dict(diameter_mm=15, top_depth_mm=2.5,
                                                    inner_diameter_mm=13, prior_diameter_mm=15,
                                                    lambdas={"NP": [10.0], "HP": [10.0],
                                                             "SP": [1e3, 10.0, 1e-1, 1e-3]}))],
}

# named sweep -> its default values (lambda; noise [% max amplitude]; mesh, roi [mm])
SWEEPS = {
    "lambda": [1e-3, 1e-1, 1.0, 10.0, 1e2, 1e3],
    "noise": [0.0, 0.5, 1.0, 2.0, 5.0],
    "mesh": [0.75, 1.0, 1.5, 2.0],
    "roi": [12.0, 15.0, 20.0, 25.0, 30.0],
}
