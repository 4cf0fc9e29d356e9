"""A fluorescence acquisition simulated by Monte Carlo on a label map.

Excitation: one MCX run per source (a pencil beam entering along the inward surface
normal), giving the excitation fluence in every voxel and the exit records; the
excitation datum of a source-detector pair is the exiting weight within
``detector_radius_mm`` of the detector per mm^2 (flat-surface disc area).

Emission, by reciprocity: one MCX run per detector at the emission wavelength,
launched from the detector into the tissue with the angular distribution of what
that detector accepts - internal directions weighted by cos(theta) times the Fresnel
transmission T(theta) (none beyond the critical angle).  Its fluence Phi*_d per
launched photon gives the exitance per mm^2 at the detector from a unit isotropic
source at r:

    J_d(r) = C / (4 pi) * Phi*_d(r),   C = int T(theta) cos(theta) dOmega = pi (1 - R_phi)

(R_phi: optics.fresnel_moments; C = pi for n = 1), so the emission datum is

    J_m(s, d) = C / (4 pi) * sum_voxels yield(v) Phi_x,s(v) Phi*_d(v) h^3.

The diffusion model's counterpart is its boundary fluence / (2A) at the detector.
Standard errors come from ``runs`` independent repeats of every run (different
seeds): the photon-statistics noise of the data.

Geometry: the label map's voxels must be cubes (MCX's grid has one voxel size);
the IJK-to-RAS matrix may rotate.  The surface normal is the gradient of the
smoothed tissue mask, which is exact for faces aligned with the grid and an
approximation on staircased curved surfaces.
"""

from __future__ import annotations

import json
import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import report

from FluoTomoLib.montecarlo.engine import (check_photons, check_seed, load_engine,
                                           max_exit_records, time_gate_ns)
from FluoTomoLib.optics import check_properties, fresnel_moments, fresnel_reflectance


def detector_launch_icdf(n, points=1001):
    """MCX ``angleinvcdf`` (zenith angle / pi at uniform probabilities) for launches
    with pdf proportional to T(theta) cos(theta) sin(theta) on the inward hemisphere."""
    n = float(n)
    theta_max = np.arcsin(1.0 / n) if n > 1.0 else 0.5 * np.pi
    th = np.linspace(0.0, theta_max, 20001)
    T = 1.0 - fresnel_reflectance(np.cos(th), n)
    pdf = np.clip(T, 0.0, None) * np.cos(th) * np.sin(th)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(th))])
    cdf /= cdf[-1]
    u = np.linspace(0.0, 1.0, points)
    icdf = np.interp(u, cdf, th) / np.pi
    return np.maximum.accumulate(icdf)


def detector_acceptance(n):
    """C = int T cos dOmega over the inward hemisphere = pi (1 - R_phi) [sr]."""
    r_phi, _ = fresnel_moments(n)
    return np.pi * (1.0 - r_phi)


class LabelMapGeometry:
    """A label map (K, J, I) with its IJK-to-RAS matrix, as MCX's grid."""

    def __init__(self, labels_kji, ijk_to_ras):
        lab = np.asarray(labels_kji)
        if lab.ndim != 3 or lab.size == 0:
            raise FluoInputError("needs a 3D label map", field="labels", value=lab.shape)
        if not np.issubdtype(lab.dtype, np.integer) or lab.min() < 0 or lab.max() > 255:
            raise FluoInputError("labels must be integers 0..255 (0: air)", field="labels")
        M = np.asarray(ijk_to_ras, float)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise FluoInputError("needs a finite 4x4 IJK-to-RAS matrix", field="ijk_to_ras")
        cols = M[:3, :3]
        h = np.linalg.norm(cols, axis=0)
        if np.any(h <= 0) or np.ptp(h) > 1e-6 * h.max():
            raise FluoInputError("Monte Carlo needs cubic voxels (one spacing on every axis)",
                                 field="ijk_to_ras.spacing", value=tuple(np.round(h, 6).tolist()))
        R = cols / h
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
            raise FluoInputError("IJK axes must be orthogonal", field="ijk_to_ras")
        self.h = float(h[0])
        self.R = R
        self.origin = M[:3, 3]
        self.labels_ijk = np.ascontiguousarray(np.transpose(lab, (2, 1, 0)).astype(np.uint8))
        self.shape = self.labels_ijk.shape
        self._normals = None

    def to_grid(self, ras):
        """RAS [mm] -> MCX grid coordinates (voxel i spans [i, i+1))."""
        return (np.asarray(ras, float) - self.origin) @ self.R / self.h + 0.5

    def to_ras(self, grid):
        return (np.asarray(grid, float) - 0.5) * self.h @ self.R.T + self.origin

    def tissue(self, g):
        i = np.floor(g).astype(int)
        if np.any(i < 0) or np.any(i >= self.shape):
            return False
        return self.labels_ijk[tuple(i)] > 0

    def inward_normal(self, g):
        """Unit inward normal (grid frame) at grid point g: gradient of the smoothed mask."""
        from scipy import ndimage

        if self._normals is None:
            mask = np.pad((self.labels_ijk > 0).astype(float), 3)
            sm = ndimage.gaussian_filter(mask, 1.5)
            self._normals = [np.asarray(x) for x in np.gradient(sm)]
        coords = (np.asarray(g, float) - 0.5 + 3.0)[:, None]
        v = np.array([ndimage.map_coordinates(gr, coords, order=1)[0] for gr in self._normals])
        nv = np.linalg.norm(v)
        if nv < 1e-6:
            return None
        return v / nv

    def launch(self, ras, what):
        """Launch point (grid) on the tissue surface nearest along the normal, and
        the inward normal, for a surface point in RAS."""
        g0 = self.to_grid(ras)
        n_in = self.inward_normal(g0)
        if n_in is None:
            raise FluoInputError("is not on the tissue surface (no surface normal there)",
                                 field=what, value=np.round(ras, 3).tolist())
        # from 3 voxels outside along the normal, march in until the first tissue voxel
        t = np.arange(-3.0, 3.0, 0.01)
        for ti in t:
            p = g0 + ti * n_in
            if self.tissue(p):
                if ti <= -3.0 + 1e-9:
                    break
                return p + 1e-3 * n_in, n_in
        raise FluoInputError("is more than 3 voxels from the tissue surface", field=what,
                             value=np.round(ras, 3).tolist())


def _props_table(optics, n_labels, what):
    """MCX property rows from {label: (mua, musp, n)} or a sequence indexed by label-1."""
    rows = []
    for lab in range(1, n_labels + 1):
        try:
            v = optics[lab] if isinstance(optics, dict) else optics[lab - 1]
        except (KeyError, IndexError):
            raise FluoInputError("no optical properties for this label", field=f"{what}[{lab}]") \
                from None
        mua, musp, n = (float(x) for x in v)
        check_properties(mua, musp, n, where=f"{what}[{lab}]", warn=False)
        if mua <= 0:
            raise FluoInputError("Monte Carlo fluence needs absorption > 0",
                                 field=f"{what}[{lab}].mua_per_mm", value=mua)
        rows.append((mua, musp, n))
    return rows


def _cfg(geo, rows, g, photons, seed, pos, direction, icdf=None):
    prop = [[0.0, 0.0, 1.0, 1.0]] + [[m, s / (1 - g), g, n] for m, s, n in rows]
    tend = time_gate_ns(min(r[0] for r in rows), max(r[2] for r in rows)) * 1e-9
    centre = np.array(geo.shape, float) / 2.0
    cfg = {
        "nphoton": int(photons), "seed": int(seed), "vol": geo.labels_ijk,
        "prop": np.array(prop), "unitinmm": geo.h,
        "tstart": 0.0, "tend": tend, "tstep": tend,
        "srcpos": [float(x) for x in pos], "srcdir": [float(x) for x in direction],
        "issrcfrom0": 1,
        "detpos": np.array([[*centre, float(np.linalg.norm(centre)) + 2.0]]),
        # room for every launched photon to exit (MCX-CL rounds the launch count up to
        # whole work items, and in weakly absorbing media nearly all of them exit)
        "savedetflag": "dpx", "maxdetphoton": max_exit_records(photons),
        "isreflect": 1, "outputtype": "energy", "autopilot": 1,
    }
    if icdf is not None:
        cfg["angleinvcdf"] = np.asarray(icdf, float)
    return cfg


def _fluence(res, geo, mua_of_label):
    E = np.asarray(res["flux"], float).reshape(geo.shape + (-1,)).sum(axis=3)
    mua = mua_of_label[geo.labels_ijk]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(mua > 0, E / (mua * geo.h ** 3), 0.0)


def _pack_scene(geo, rows_x, rows_m, gamma):
    """The scene as plain values (a Shared input's arguments: JSON-able, hashable)."""
    import base64
    import zlib

    return {"labels_ijk": base64.b64encode(zlib.compress(geo.labels_ijk.tobytes(), 6)).decode(),
            "shape": list(geo.shape), "h": geo.h, "R": geo.R.tolist(),
            "origin": geo.origin.tolist(), "rows_x": [list(r) for r in rows_x],
            "rows_m": [list(r) for r in rows_m], "gamma": [float(v) for v in gamma]}


def _fluorescing(geo, gamma):
    """Flat indices of the voxels with a yield > 0, and their yields [1/mm]."""
    y = gamma[geo.labels_ijk].ravel()
    glow = np.flatnonzero(y > 0)
    return glow, y[glow]


def scene_input(packed):
    """Shared input: the Monte Carlo scene (geometry, media, the fluorescing voxels)."""
    import base64
    import zlib

    lab_ijk = np.frombuffer(zlib.decompress(base64.b64decode(packed["labels_ijk"])),
                            np.uint8).reshape(packed["shape"])
    M = np.eye(4)
    M[:3, :3] = np.asarray(packed["R"]) * packed["h"]
    M[:3, 3] = packed["origin"]
    geo = LabelMapGeometry(np.transpose(lab_ijk, (2, 1, 0)), M)
    glow, yield_glow = _fluorescing(geo, np.asarray(packed["gamma"], float))
    return {"geo": geo, "rows_x": [tuple(r) for r in packed["rows_x"]],
            "rows_m": [tuple(r) for r in packed["rows_m"]],
            "mua_x": np.array([0.0] + [r[0] for r in packed["rows_x"]]),
            "mua_m": np.array([0.0] + [r[0] for r in packed["rows_m"]]),
            "glow": glow, "yield_glow": yield_glow}


def detector_task(params, scene):
    """One emission run from a detector (reciprocity): its adjoint fluence times
    C / (4 pi) on the fluorescing voxels only (``arrays["adjoint"]``)."""
    from FluoTomoLib.montecarlo.engine import load_engine

    geo = scene["geo"]
    pos, n_in = np.asarray(params["launch"][0]), np.asarray(params["launch"][1])
    lab = geo.labels_ijk[tuple(np.floor(pos).astype(int))]
    n_det = scene["rows_m"][lab - 1][2]
    res = load_engine(params["engine"]).run(
        _cfg(geo, scene["rows_m"], params["g"], params["photons"], params["seed"], pos, n_in,
             icdf=detector_launch_icdf(n_det)))
    adj = _fluence(res, geo, scene["mua_m"]).ravel()[scene["glow"]]
    return {"seed": params["seed"], "arrays": {
        "adjoint": adj * (detector_acceptance(n_det) / (4 * np.pi))}}


def source_task(params, scene):
    """One excitation run from a source: the excitation fluence on the fluorescing
    voxels (``arrays["phi"]``) and the excitation datum of every detector
    (``arrays["excitation"]``: exiting weight within the detector disc per mm^2)."""
    from FluoTomoLib.montecarlo.engine import load_engine

    geo, mua_x = scene["geo"], scene["mua_x"]
    photons = params["photons"]
    pos, n_in = np.asarray(params["launch"][0]), np.asarray(params["launch"][1])
    eng = load_engine(params["engine"])
    res = eng.run(_cfg(geo, scene["rows_x"], params["g"], photons, params["seed"], pos, n_in))
    phi = _fluence(res, geo, mua_x).ravel()[scene["glow"]]
    dp = res.get("detp") or {}
    full = False
    if "p" in dp and len(dp["p"]):
        ppath = dp["ppath"] * geo.h
        w = np.exp(-(ppath * mua_x[1:][None, :ppath.shape[1]]).sum(axis=1))
        exit_ras = geo.to_ras(dp["p"])
        full = len(dp["p"]) >= max_exit_records(photons)
    else:
        w = np.zeros(0)
        exit_ras = np.zeros((0, 3))
    r = float(params["detector_radius_mm"])
    det = np.asarray(params["detectors_ras"], float)
    ex = np.array([w[np.linalg.norm(exit_ras - d, axis=1) <= r].sum() for d in det])
    return {"seed": params["seed"], "exit_records_full": bool(full),
            "engine": eng.name, "engine_version": eng.version, "device": eng.device,
            "arrays": {"phi": phi, "excitation": ex / (photons * np.pi * r ** 2)}}


def _checked_media(labels_kji, ijk_to_ras, optics_x, optics_m, yield_per_label):
    """The label map's geometry, the MCX property rows at excitation and emission, and
    the yield of every label [1/mm] (index 0: air), refused in one line when unusable."""
    geo = LabelMapGeometry(labels_kji, ijk_to_ras)
    L = int(geo.labels_ijk.max())
    if L < 1:
        raise FluoInputError("the label map holds no tissue (all 0)", field="labels")
    rows_x = _props_table(optics_x, L, "optics_x")
    rows_m = _props_table(optics_m, L, "optics_m")
    gamma = np.zeros(L + 1)
    for lab, y in dict(yield_per_label).items():
        lab = int(lab)
        if not (1 <= lab <= L) or not np.isfinite(y) or y < 0:
            raise FluoInputError("needs labels 1..L and yields >= 0", field=f"yield_per_label[{lab}]",
                                 value=y)
        gamma[lab] = float(y)
    return geo, rows_x, rows_m, gamma


def _checked_points(sources_ras, detectors_ras):
    """The sources and detectors as (S, 3) and (D, 3) arrays [mm], refused when they
    are not finite points."""
    src = np.atleast_2d(np.asarray(sources_ras, float))
    det = np.atleast_2d(np.asarray(detectors_ras, float))
    for name, pts in (("sources_ras", src), ("detectors_ras", det)):
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
            raise FluoInputError("needs finite (N, 3) points [mm]", field=name, value=pts.shape)
    return src, det


def _acquisition_tasks(geo, rows_x, rows_m, gamma, launch_s, launch_d, det, *, photons, seed,
                       runs, g, engine_name, detector_radius_mm):
    """Every MCX run as a task of the run engine, sharing one scene input: per repeat r
    the detectors' runs, then the sources', seeds counting up from ``seed + r (S + D)``."""
    import hashlib

    from fluoguide.runs.tasks import Shared, Task

    S, D = len(launch_s), len(launch_d)
    packed = _pack_scene(geo, rows_x, rows_m, gamma)
    scene_hash = hashlib.sha1(json.dumps(packed, sort_keys=True).encode()).hexdigest()[:16]
    scene = Shared(f"Monte Carlo scene {scene_hash}", scene_input, (packed,))
    common = {"scene": scene_hash, "photons": photons, "g": float(g), "engine": engine_name}
    tasks = []
    for r in range(runs):
        base = seed + r * (S + D)
        for d, (pos, n_in) in enumerate(launch_d):
            tasks.append(Task(detector_task, {**common, "kind": "detector", "index": d,
                                              "repeat": r, "seed": base + d,
                                              "launch": [pos.tolist(), n_in.tolist()]},
                              {"scene": scene}))
        for s, (pos, n_in) in enumerate(launch_s):
            tasks.append(Task(source_task, {**common, "kind": "source", "index": s, "repeat": r,
                                            "seed": base + D + s,
                                            "launch": [pos.tolist(), n_in.tolist()],
                                            "detectors_ras": det.tolist(),
                                            "detector_radius_mm": float(detector_radius_mm)},
                              {"scene": scene}))
    return tasks


def _gathered(out, store, runs, S, D):
    """The finished runs' arrays by repeat: the detectors' adjoint fluences (runs, D),
    the sources' excitation fluences (runs, S) and excitation data (runs, S, D), and
    the warnings they raise; a failed run raises FluoError naming it."""
    from fluoguide.errors import FluoError

    arrays_of = store.arrays if store is not None else (lambda rec: rec.get("_arrays") or {})
    warnings = []
    adj = np.zeros((runs, D), object)
    phi = np.zeros((runs, S), object)
    ex = np.zeros((runs, S, D))
    for rec in out["records"]:
        p = rec["params"]
        if rec["status"] != "ok":
            raise FluoError(f"Monte Carlo run ({p['kind']} {p['index']}, repeat {p['repeat']}, "
                            f"seed {p['seed']}) failed: {rec['error']}")
        a = arrays_of(rec)
        if p["kind"] == "detector":
            adj[p["repeat"], p["index"]] = a["adjoint"]
        else:
            phi[p["repeat"], p["index"]] = a["phi"]
            ex[p["repeat"], p["index"]] = a["excitation"]
            if rec["result"].get("exit_records_full"):
                warnings.append("exit records hit their limit; excitation data may be low")
    return adj, phi, ex, warnings


def _emission(geo, gamma, phi, adj):
    """The emission datum of every repeat and pair (runs, S, D): the sum over the
    fluorescing voxels of yield x h^3 x excitation fluence x the detector's adjoint
    (its C / (4 pi) already applied by detector_task)."""
    runs, S = phi.shape
    D = adj.shape[1]
    yg = _fluorescing(geo, gamma)[1] * geo.h ** 3
    em = np.zeros((runs, S, D))
    for r in range(runs):
        for s in range(S):
            src_emit = yg * phi[r, s]
            for d in range(D):
                em[r, s, d] = float(np.sum(src_emit * adj[r, d]))
    return em


def simulate_acquisition(labels_kji, ijk_to_ras, optics_x, optics_m, sources_ras, detectors_ras,
                         yield_per_label, photons, seed=1, runs=2, g=0.9, detector_radius_mm=1.0,
                         engine="auto", progress=None, cancel=None, executor=None, store=None,
                         threads=1):
    """Excitation and emission data of every source-detector pair by Monte Carlo.

    Every MCX run (each detector's and each source's, per repeat) is a task of the
    run engine (``fluoguide.runs``): serial here by default, split across Dask
    workers with ``executor``, written as it finishes and resumable with ``store``.
    A task returns only the fluence on the fluorescing voxels, so what travels back
    is small whatever the volume; the same seeds give the same data wherever the
    runs ran (Engine.run's fixed launch shape).

    Parameters
    ----------
    labels_kji : (K, J, I) integer label map, 0 = air, 1..L tissue labels
    ijk_to_ras : (4, 4) IJK-to-RAS matrix [mm] (cubic voxels)
    optics_x, optics_m : {label: (mua_per_mm, musp_per_mm, n)} at excitation (mua
        includes the fluorophore's absorption) and emission
    sources_ras, detectors_ras : (S, 3), (D, 3) points on the tissue surface, RAS [mm]
    yield_per_label : {label: eta * mua_f [1/mm]} (missing labels: 0)
    photons : photons per run
    seed : first seed; every run gets its own (repeat r: the detectors' runs, then the
        sources', seeds counting up from ``seed + r (S + D)``)
    runs : independent repeats of every run (>= 2 for standard errors)
    g : Henyey-Greenstein anisotropy (mus = musp / (1 - g))
    detector_radius_mm : radius of the disc over which excitation exits are counted
    executor, store, threads : as :func:`fluoguide.runs.run_tasks`

    Returns
    -------
    dict with ``excitation`` and ``excitation_se`` (S, D) [exiting power per mm^2 per
    unit entering excitation power], ``emission`` and ``emission_se`` (S, D) [emitted
    exitance per mm^2 per unit excitation power], ``photons_per_run``, ``runs``,
    ``seeds``, ``seconds``, ``engine``, ``device``, ``warnings``, ``executor``.
    """
    from fluoguide.runs.engine import run_tasks

    photons = check_photons(photons)
    seed = check_seed(seed)
    if not (isinstance(runs, (int, np.integer)) and 1 <= runs <= 100):
        raise FluoInputError("must be a whole number from 1 to 100", field="runs", value=runs)
    if not (np.isfinite(detector_radius_mm) and detector_radius_mm > 0):
        raise FluoInputError("must be > 0", field="detector_radius_mm", value=detector_radius_mm)
    geo, rows_x, rows_m, gamma = _checked_media(labels_kji, ijk_to_ras, optics_x, optics_m,
                                                yield_per_label)
    src, det = _checked_points(sources_ras, detectors_ras)
    launch_s = [geo.launch(p, f"sources_ras[{i}]") for i, p in enumerate(src)]
    launch_d = [geo.launch(p, f"detectors_ras[{i}]") for i, p in enumerate(det)]
    eng = load_engine(engine) if isinstance(engine, str) else engine
    S, D = len(src), len(det)
    check_seed(seed + runs * (S + D) - 1)
    tasks = _acquisition_tasks(geo, rows_x, rows_m, gamma, launch_s, launch_d, det,
                               photons=photons, seed=seed, runs=runs, g=g, engine_name=eng.name,
                               detector_radius_mm=detector_radius_mm)
    t0 = time.perf_counter()
    out = run_tasks(tasks, store=store, executor=executor, threads=threads, progress=progress,
                    cancel=cancel, label="Monte Carlo acquisition")
    adj, phi, ex, warnings = _gathered(out, store, runs, S, D)
    em = _emission(geo, gamma, phi, adj)
    report(progress, 1.0, "Monte Carlo acquisition done")
    if runs < 2:
        warnings.append("one run per source and detector: no standard errors")
    se = (lambda a: a.std(axis=0, ddof=1) / np.sqrt(runs)) if runs >= 2 else \
        (lambda a: np.full(a.shape[1:], np.nan))
    return {
        "excitation": ex.mean(axis=0), "excitation_se": se(ex),
        "emission": em.mean(axis=0), "emission_se": se(em),
        "photons_per_run": photons, "runs": runs, "seeds": [t.params["seed"] for t in tasks],
        "detector_radius_mm": float(detector_radius_mm), "g": float(g),
        "seconds": time.perf_counter() - t0, "engine": eng.name,
        "engine_version": eng.version, "device": eng.device, "warnings": sorted(set(warnings)),
        "executor": {k: out[k] for k in ("executor", "workers", "computed", "reused")},
        "units": {"excitation": "exiting power per mm^2 per unit entering excitation power "
                                "(disc of detector_radius_mm)",
                  "emission": "emitted exitance per mm^2 per unit entering excitation power"},
    }
