"""Monte Carlo of a pencil beam on a (near) semi-infinite medium: spatially resolved
reflectance R(rho) and interior fluence, with standard errors from independent runs.

The medium is a box of tissue (default 160 x 160 x 80 mm, 1 mm voxels: the size of
the independent stored run) in air; the beam enters normally at the centre of the
top face (z = 0).  One run (:func:`run_halfspace`) is one MCX simulation with its
own seed and returns raw tallies (sums of weights, sums of squared weights, photon
counts); :func:`merge_halfspace` pools any number of runs - made here, in another
process, or by a Dask worker - into means and standard errors:

- R per annulus [rho - w/2, rho + w/2) from the exit records of the top face:
  exiting weight per entering photon per mm^2 (no specular loss: the FEM's source
  is the power that enters).  ``se``: spread of the runs' estimates (batch means);
  ``se_cp``: compound-Poisson error sqrt(sum w^2) / (N area) of the pooled estimate.
- Fluence per ring of voxels (voxel centres with rho in [r - 0.5, r + 0.5) mm) in
  chosen voxel layers: E / (mua V) averaged over the ring's voxels [1/mm^2 per
  unit power]; the FEM is averaged over the same voxel centres (compare.py).
- The energy balance: absorbed + exited through the top + exited elsewhere + lost
  at the time gate = 1.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import report

from FluoTomoLib.montecarlo.engine import (
    check_photons,
    check_seed,
    load_engine,
    max_exit_records,
    mcx_props,
    time_gate_ns,
)
from FluoTomoLib.optics import check_properties

# the independent stored run's annuli: 0.1 rho wide below 10 mm, 1 mm beyond
DEFAULT_RHO_MM = tuple(float(r) for r in range(1, 31))
DEFAULT_FLUENCE_DEPTHS_MM = (1.5, 2.5, 5.5, 10.5, 15.5)
DEFAULT_FLUENCE_RHO_MM = (1.0, 2.0, 3.0, 5.0, 8.0, 10.0, 15.0, 20.0)
DEFAULT_SIZE_MM = (160.0, 160.0, 80.0)


def annulus_widths(rho_mm):
    """The stored run's annulus widths: 0.1 rho, at most 1 mm."""
    rho = np.asarray(rho_mm, float)
    return np.minimum(0.1 * rho, 1.0)


class HalfSpace:
    """The simulated medium and what is tallied (shared by every run of a set).

    Parameters
    ----------
    mua_per_mm, musp_per_mm, n : tissue optics (outside: air, n = 1)
    g : anisotropy of the Henyey-Greenstein phase function (mus = musp / (1 - g))
    size_mm : (x, y, z) extent of the tissue box
    voxel_mm : voxel edge
    rho_mm : annulus centres for R(rho) (widths: :func:`annulus_widths`)
    fluence_depths_mm : depths of the voxel layers where fluence is tallied
        (rounded to the voxel centre below)
    fluence_rho_mm : ring centres for the interior fluence (rings 1 mm wide; each
        must hold at least one voxel centre)
    """

    def __init__(self, mua_per_mm, musp_per_mm, n, g=0.9, size_mm=DEFAULT_SIZE_MM, voxel_mm=1.0,
                 rho_mm=DEFAULT_RHO_MM, fluence_depths_mm=DEFAULT_FLUENCE_DEPTHS_MM,
                 fluence_rho_mm=DEFAULT_FLUENCE_RHO_MM):
        check_properties(mua_per_mm, musp_per_mm, n, where="medium", warn=False)
        if not (np.isfinite(g) and 0 <= g < 1):
            raise FluoInputError("anisotropy must be in [0, 1)", field="g", value=g)
        if float(mua_per_mm) <= 0:
            raise FluoInputError("Monte Carlo fluence needs absorption > 0", field="mua_per_mm",
                                 value=mua_per_mm)
        self.mua = float(mua_per_mm)
        self.musp = float(musp_per_mm)
        self.n = float(n)
        self.g = float(g)
        self.voxel_mm = float(voxel_mm)
        if not (np.isfinite(self.voxel_mm) and 0.05 <= self.voxel_mm <= 5):
            raise FluoInputError("voxel size must be 0.05-5 mm", field="voxel_mm", value=voxel_mm)
        size = np.asarray(size_mm, float)
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size < 4 * self.voxel_mm):
            raise FluoInputError("needs three extents of at least 4 voxels", field="size_mm",
                                 value=tuple(np.atleast_1d(size).tolist()))
        # an even voxel count across puts the beam on a grid corner, centred
        self.shape = tuple(int(2 * round(s / (2 * self.voxel_mm))) if i < 2
                           else int(round(s / self.voxel_mm)) for i, s in enumerate(size))
        self.size_mm = tuple(float(s * self.voxel_mm) for s in self.shape)
        self.rho_mm = np.asarray(rho_mm, float)
        if self.rho_mm.ndim != 1 or len(self.rho_mm) == 0 or np.any(self.rho_mm <= 0) or \
                np.any(~np.isfinite(self.rho_mm)):
            raise FluoInputError("needs positive finite distances", field="rho_mm")
        if self.rho_mm.max() + 1 > 0.5 * min(self.size_mm[:2]):
            raise FluoInputError("annuli reach the side of the box", field="rho_mm",
                                 value=float(self.rho_mm.max()))
        self.width_mm = annulus_widths(self.rho_mm)
        self.area_mm2 = 2 * np.pi * self.rho_mm * self.width_mm
        self.fluence_rho_mm = np.asarray(fluence_rho_mm, float)
        depths = np.asarray(fluence_depths_mm, float)
        self.layers = np.clip(np.floor(depths / self.voxel_mm).astype(int), 0, self.shape[2] - 1)
        self.fluence_depths_mm = (self.layers + 0.5) * self.voxel_mm
        self._ring_index = None
        empty = [float(r) for r, idx in zip(self.fluence_rho_mm, self.ring_voxels()) if len(idx) == 0]
        if empty:
            raise FluoInputError("fluence ring holds no voxel centre", field="fluence_rho_mm",
                                 value=empty[0])

    # ---------------------------------------------------------------- geometry
    @property
    def source_grid(self):
        return (self.shape[0] / 2.0, self.shape[1] / 2.0, 0.0)

    def voxel_centres_xy_mm(self):
        """(nx, ny, 2) voxel-centre x, y relative to the beam [mm]."""
        h = self.voxel_mm
        x = (np.arange(self.shape[0]) + 0.5 - self.shape[0] / 2.0) * h
        y = (np.arange(self.shape[1]) + 0.5 - self.shape[1] / 2.0) * h
        return np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1)

    def ring_voxels(self):
        """For each fluence ring: flat (nx*ny) indices of its voxels in a layer."""
        if self._ring_index is None:
            xy = self.voxel_centres_xy_mm().reshape(-1, 2)
            r = np.hypot(xy[:, 0], xy[:, 1])
            self._ring_index = [np.flatnonzero((r >= max(rc - 0.5, 0.0)) & (r < rc + 0.5))
                                for rc in self.fluence_rho_mm]
        return self._ring_index

    def fluence_points_mm(self):
        """Voxel centres of every (layer, ring) bin: list of (P, 3) arrays [mm], z < 0
        inside the tissue (the FEM's frame: surface at z = 0)."""
        xy = self.voxel_centres_xy_mm().reshape(-1, 2)
        out = []
        for z in self.fluence_depths_mm:
            for idx in self.ring_voxels():
                out.append(np.column_stack([xy[idx], np.full(len(idx), -z)]))
        return out

    def params(self):
        """The constructor's arguments as plain values (a run-engine task's parameters:
        ``HalfSpace(**m.params())`` is the same medium)."""
        return {"mua_per_mm": self.mua, "musp_per_mm": self.musp, "n": self.n, "g": self.g,
                "size_mm": list(self.size_mm), "voxel_mm": self.voxel_mm,
                "rho_mm": self.rho_mm.tolist(),
                "fluence_depths_mm": self.fluence_depths_mm.tolist(),
                "fluence_rho_mm": self.fluence_rho_mm.tolist()}

    def metadata(self):
        return {
            "medium": {"mua_per_mm": self.mua, "musp_per_mm": self.musp, "g": self.g,
                       "mus_per_mm": self.musp / (1 - self.g), "n_inside": self.n,
                       "n_outside": 1.0},
            "volume_mm": list(self.size_mm), "voxel_mm": self.voxel_mm,
            "grid": list(self.shape),
            "source": "pencil beam, normal incidence, centre of the top face (z = 0)",
            "R_units": "exiting weight per entering photon per mm^2 (no specular loss)",
            "fluence_units": "1/mm^2 per unit entering power, mean over the ring's voxels",
        }

    # ---------------------------------------------------------------- one run
    def config(self, photons, seed):
        nx, ny, nz = self.shape
        prop = mcx_props([(self.mua, self.musp, self.n)], self.g)
        tend = time_gate_ns(self.mua, self.n) * 1e-9
        centre = np.array([nx, ny, nz], float) / 2.0
        return {
            "nphoton": int(photons), "seed": int(seed),
            "vol": np.ones(self.shape, dtype=np.uint8), "prop": prop,
            "unitinmm": self.voxel_mm,
            "tstart": 0.0, "tend": tend, "tstep": tend,
            "srcpos": list(self.source_grid), "srcdir": [0.0, 0.0, 1.0], "issrcfrom0": 1,
            # one detector sphere around the whole box: every exit is recorded
            "detpos": np.array([[*centre, float(np.linalg.norm(centre)) + 2.0]]),
            "savedetflag": "dpx", "maxdetphoton": max_exit_records(photons),
            "isreflect": 1, "outputtype": "energy", "autopilot": 1,
        }


def run_halfspace(medium, photons, seed, engine="auto"):
    """One independent MCX run: raw tallies of ``medium`` (a :class:`HalfSpace`).

    Returns a dict of plain arrays and numbers (picklable, JSON-able), for
    :func:`merge_halfspace`.
    """
    photons = check_photons(photons)
    seed = check_seed(seed)
    eng = load_engine(engine) if isinstance(engine, str) else engine
    t0 = time.perf_counter()
    res = eng.run(medium.config(photons, seed))
    seconds = time.perf_counter() - t0
    stat = res["stat"]
    det = res.get("detp") or {}
    h = medium.voxel_mm
    if "p" in det and len(det["p"]):
        p = det["p"]
        ppath_mm = det["ppath"][:, 0] * h
        w = np.exp(-medium.mua * ppath_mm)
        top = p[:, 2] < 1e-3
    else:
        p = np.zeros((0, 3))
        w = np.zeros(0)
        top = np.zeros(0, bool)
    n_rec = len(w)
    cx, cy, _ = medium.source_grid
    rho = np.hypot(p[top, 0] - cx, p[top, 1] - cy) * h
    wt = w[top]
    lo = medium.rho_mm - medium.width_mm / 2
    hi = medium.rho_mm + medium.width_mm / 2
    W = np.zeros(len(lo))
    W2 = np.zeros(len(lo))
    cnt = np.zeros(len(lo), int)
    order = np.argsort(rho)
    rs, ws = rho[order], wt[order]
    c1 = np.concatenate([[0.0], np.cumsum(ws)])
    c2 = np.concatenate([[0.0], np.cumsum(ws ** 2)])
    a = np.searchsorted(rs, lo, side="left")
    b = np.searchsorted(rs, hi, side="left")
    W[:] = c1[b] - c1[a]
    W2[:] = c2[b] - c2[a]
    cnt[:] = b - a
    E = np.asarray(res["flux"], float)
    E = E.reshape(medium.shape + (-1,)).sum(axis=3)     # one time gate; sum to be safe
    phi_voxel = E / (medium.mua * h ** 3)
    rings = medium.ring_voxels()
    fl = np.array([[phi_voxel[:, :, k].reshape(-1)[idx].mean() for idx in rings]
                   for k in medium.layers])
    absorbed = float(stat["energyabs"]) / float(stat["energytot"])
    return {
        "photons": photons, "seed": seed, "seconds": seconds,
        "engine": eng.name, "engine_version": eng.version, "device": eng.device,
        "W": W, "W2": W2, "count": cnt,
        "exit_top": float(wt.sum()) / photons, "exit_other": float(w[~top].sum()) / photons,
        "absorbed": absorbed, "absorbed_voxels": float(E.sum()),
        "records": int(n_rec), "records_max": max_exit_records(photons),
        "fluence": fl,
    }


def _batch_se(values, weights):
    """Standard error of the weighted mean of per-run estimates (batch means)."""
    v = np.asarray(values, float)
    wts = np.asarray(weights, float)
    k = len(wts)
    if k < 2:
        return np.full(v.shape[1:], np.nan)
    wn = wts / wts.sum()
    mean = np.tensordot(wn, v, axes=1)
    var = np.tensordot(wn ** 2, (v - mean) ** 2, axes=1) * k / (k - 1)
    return np.sqrt(var)


def merge_halfspace(medium, runs):
    """Pool independent runs (same medium, different seeds) into means and errors.

    Returns a dict: ``R`` rows (rho_mm, width_mm, R_per_mm2, se, se_cp, rel_se,
    n_exits), ``fluence`` rows (depth_mm, rho_mm, voxels, phi_per_mm2, se, rel_se),
    ``energy`` (absorbed, exit_top (total diffuse reflectance), exit_other, lost,
    each with its spread), ``photons``, ``seeds``, ``seconds``.
    """
    if not runs:
        raise FluoInputError("no runs to merge", field="runs")
    seeds = [r["seed"] for r in runs]
    if len(set(seeds)) != len(seeds):
        raise FluoInputError("runs share a seed: they are not independent", field="runs.seed",
                             value=seeds)
    N = np.array([r["photons"] for r in runs], float)
    Ntot = N.sum()
    area = medium.area_mm2
    W = np.array([r["W"] for r in runs])
    W2 = np.array([r["W2"] for r in runs])
    R_runs = W / (N[:, None] * area)
    R = W.sum(0) / (Ntot * area)
    se = _batch_se(R_runs, N)
    se_cp = np.sqrt(W2.sum(0)) / (Ntot * area)
    cnt = np.array([r["count"] for r in runs]).sum(0)
    rows = []
    for i, rho in enumerate(medium.rho_mm):
        rows.append({"rho_mm": float(rho), "width_mm": float(medium.width_mm[i]),
                     "R_per_mm2": float(R[i]), "se": float(se[i]), "se_cp": float(se_cp[i]),
                     "rel_se": float(se[i] / R[i]) if R[i] > 0 else None,
                     "n_exits": int(cnt[i])})
    F = np.array([r["fluence"] for r in runs])
    phi = np.tensordot(N / Ntot, F, axes=1)
    phi_se = _batch_se(F, N)
    nvox = [len(idx) for idx in medium.ring_voxels()]
    frows = []
    for a, z in enumerate(medium.fluence_depths_mm):
        for b, rc in enumerate(medium.fluence_rho_mm):
            frows.append({"depth_mm": float(z), "rho_mm": float(rc), "voxels": int(nvox[b]),
                          "phi_per_mm2": float(phi[a, b]), "se": float(phi_se[a, b]),
                          "rel_se": float(phi_se[a, b] / phi[a, b]) if phi[a, b] > 0 else None})
    energy = {}
    for key in ("absorbed", "exit_top", "exit_other"):
        vals = np.array([r[key] for r in runs])
        energy[key] = float(np.dot(N / Ntot, vals))
        energy[key + "_se"] = float(_batch_se(vals[:, None], N)[0])
    energy["lost"] = 1.0 - energy["absorbed"] - energy["exit_top"] - energy["exit_other"]
    energy["balance"] = energy["absorbed"] + energy["exit_top"] + energy["exit_other"]
    truncated = any(r["records"] >= r["records_max"] for r in runs)
    return {
        "R": rows, "fluence": frows, "energy": energy,
        "photons": int(Ntot), "runs": len(runs), "seeds": seeds,
        "seconds": float(sum(r["seconds"] for r in runs)),
        "engine": runs[0]["engine"], "engine_version": runs[0]["engine_version"],
        "device": runs[0]["device"], "exit_records_truncated": bool(truncated),
    }


RUN_ARRAYS = ("W", "W2", "count", "fluence")


def halfspace_task(params):
    """One run as a run-engine task (``fluoguide.runs``): ``params`` = ``medium``
    (:meth:`HalfSpace.params`), ``photons``, ``seed``, ``engine``.  The tallies go to
    the task's arrays, the rest to its row."""
    medium = HalfSpace(**params["medium"])
    run = run_halfspace(medium, params["photons"], params["seed"], params.get("engine", "auto"))
    run["arrays"] = {k: np.asarray(run.pop(k)) for k in RUN_ARRAYS}
    return run


def halfspace_tasks(medium, photons_per_run, runs=4, seed=1, engine="auto"):
    """The run-engine tasks of ``runs`` independent runs (seeds seed, seed + 1, ...)."""
    from fluoguide.runs.tasks import Task

    photons = check_photons(photons_per_run)
    if not (isinstance(runs, (int, np.integer)) and 1 <= runs <= 1000):
        raise FluoInputError("must be a whole number from 1 to 1000", field="runs", value=runs)
    seed = check_seed(seed)
    check_seed(seed + runs - 1)
    if not isinstance(engine, str):
        engine = engine.name
    return [Task(halfspace_task, {"medium": medium.params(), "photons": photons,
                                  "seed": seed + i, "engine": engine}) for i in range(runs)]


def runs_of_records(records, arrays_of):
    """The per-run dicts :func:`merge_halfspace` pools, from run-engine records
    (``arrays_of(record)`` -> the task's arrays); a failed run raises its error."""
    from fluoguide.errors import FluoError

    out = []
    for rec in records:
        if rec["status"] != "ok":
            raise FluoError(f"Monte Carlo run (seed {rec['params']['seed']}) failed: "
                            f"{rec['error']}")
        run = dict(rec["result"])
        run.update(arrays_of(rec))
        out.append(run)
    return out


def simulate_halfspace(medium, photons_per_run, runs=4, seed=1, engine="auto", progress=None,
                       cancel=None, executor=None, store=None, threads=1):
    """``runs`` independent MCX runs (seeds seed, seed+1, ...) of ``medium``, merged.

    The runs are tasks of the run engine (``fluoguide.runs``): serial in this
    process by default, or split across a Dask cluster's workers
    (``executor``); with a ``store`` (a RunStore) each finished run is written
    at once and a killed set resumes without redoing them.  A seed draws the
    same photons wherever it runs (Engine.run's fixed launch shape), so the
    merged result does not depend on the number of workers.

    Parameters
    ----------
    medium : HalfSpace
    photons_per_run : photons launched per run
    runs : number of independent runs (>= 2 for a spread-based standard error)
    seed : first seed
    engine : "auto", "mcxcl", "mcx" (or a loaded Engine: its name is used)
    executor, store, threads : as :func:`fluoguide.runs.run_tasks`
    """
    from fluoguide.runs.engine import run_tasks

    tasks = halfspace_tasks(medium, photons_per_run, runs, seed, engine)
    out = run_tasks(tasks, store=store, executor=executor, threads=threads, progress=progress,
                    cancel=cancel, label="Monte Carlo half-space")
    arrays_of = store.arrays if store is not None else (lambda rec: rec.get("_arrays") or {})
    merged = merge_halfspace(medium, runs_of_records(out["records"], arrays_of))
    merged["executor"] = {k: out[k] for k in ("executor", "workers", "computed", "reused")}
    report(progress, 1.0, "Monte Carlo done")
    return merged
