"""Simulated acquisitions of a label map: the scan, the engines, the noise.

``simulate_acquisition`` is what ``fluo tomo simulate`` and
``FluoTomoLogic.simulateAcquisition`` call.  The physics sits behind one seam,
an *engine*: a function

    engine(labelmap, optics, sources_ras_mm, detectors_ras_mm, yield_by_label,
           noise_pct, seed, settings, progress=None, cancel=None)
        -> {"data": (S, D) measured boundary fluence per watt [1/mm^2],
            "clean": (S, D) its noise-free value (or None),
            "info": dict (engine, domain, timings; "_mesh"/"_yield_nodes" optional)}

registered in :data:`ENGINES`: ``"fem"`` (below) and ``"mc"`` (Monte Carlo on
the label map's voxels, :func:`simulate_mc`, with its own photon noise).  The scan,
the checks of the input, the near-source exclusion and the file are the same
for every engine.

The FEM engine never shares a mesh with a reconstruction: it meshes the whole
label map (graded: ``simulate_mm`` around the optodes and the target,
``simulate_coarse_mm`` elsewhere), with the true properties of each label, the
fluorophore's absorption added where it is, and the yield as each node's
partial-volume share of the labels' yields.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

from FluoTomoLib.tomography.acquisition_file import Acquisition

#: default scan: sources on an n x n grid (pitch mm), detectors on a finer grid
DEFAULT_SCAN = {"sources_per_side": 4, "source_pitch_mm": 3.0, "detectors_per_side": 7,
                "detector_pitch_mm": 1.5, "exclude_mm": 3.0}


def _tangent_basis(n):
    n = np.asarray(n, float) / np.linalg.norm(n)
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, e)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


#: most patches a default scan lays (one per target); name the targets for more
MAX_SCAN_PATCHES = 4


def check_scan_targets(lm, target, field="scan targets", file=None):
    """The labels a default scan is to cover (:func:`default_scan`'s ``target``),
    checked: cheap, so a caller can refuse them before any work.

    Parameters
    ----------
    lm : LabelMap
    target : int, list of int or None
        A label, or one label per patch (at most ``MAX_SCAN_PATCHES``); None: the
        tissue's centre.
    field, file : str
        What a refusal names (default: ``"scan targets"`` of the label map's file).

    Returns
    -------
    list of int, or None
        The labels; None for no target.
    """
    if target is None:
        return None
    file = lm.source if file is None else file
    values = np.atleast_1d(np.asarray(target, dtype=object)).tolist()
    try:
        targets = [int(t) for t in values]
    except (TypeError, ValueError):
        raise FluoInputError("labels must be integers", file=file, field=field,
                             value=values) from None
    if not targets:
        raise FluoInputError("no target to scan over", file=file, field=field, value=[])
    if len(targets) > MAX_SCAN_PATCHES:
        raise FluoInputError(f"at most {MAX_SCAN_PATCHES} targets per default scan (give the "
                             "positions for more)", file=file, field=field, value=targets)
    missing = [t for t in targets if t not in lm.labels]
    if missing:
        raise FluoInputError("label is not in the label map", file=file, field=field,
                             value=missing[0] if len(missing) == 1 else missing)
    return targets


def default_scan(lm, target=None, sources_per_side=None, source_pitch_mm=None,
                 detectors_per_side=None, detector_pitch_mm=None):
    """Sources and detectors (RAS mm) on square grids in the tangent plane of the
    skin point nearest each target's centre (the tissue's centre without a
    target), dropped onto the skin along its normal. Skin only: a cut face of
    the label map (its border, where the tissue was cropped) is never scanned;
    where the grids centred there would run off the skin (past the tissue's edge
    or onto a cut), they move along the plane by the least amount that keeps
    them on it (steps of half the source pitch, up to the grids' span).

    ``target`` is a label, a list of labels (one patch each, at most
    MAX_SCAN_PATCHES; a target whose skin point lies within half a patch of an
    earlier patch's centre shares that patch) or None. The configuration
    returned lists the patches and, for each source and detector, its patch
    (``source_patch``, ``detector_patch``): a pair across patches is not a
    measurement of either target (:func:`scan_pairs`)."""
    cfg = dict(DEFAULT_SCAN)
    for k, v in (("sources_per_side", sources_per_side), ("source_pitch_mm", source_pitch_mm),
                 ("detectors_per_side", detectors_per_side),
                 ("detector_pitch_mm", detector_pitch_mm)):
        if v is not None:
            cfg[k] = v
    for k in ("sources_per_side", "detectors_per_side"):
        if int(cfg[k]) != cfg[k] or not 1 <= cfg[k] <= 32:
            raise FluoInputError("must be an integer 1..32", field=k, value=cfg[k])
    for k in ("source_pitch_mm", "detector_pitch_mm"):
        if not (np.isfinite(cfg[k]) and cfg[k] > 0):
            raise FluoInputError("must be a positive number", field=k, value=cfg[k])
    targets = check_scan_targets(lm, target) or [None]
    surf = lm.surface().skin_only()
    if len(surf.triangles) == 0:
        raise FluoInputError("the label map has no skin: its tissue fills every side of the "
                             "volume (every border is a cut face)", file=lm.source,
                             field="labels")
    span = max((cfg["sources_per_side"] - 1) * cfg["source_pitch_mm"],
               (cfg["detectors_per_side"] - 1) * cfg["detector_pitch_mm"])
    src, det, patches, skin, s_of, d_of = [], [], [], [], [], []
    for t in targets:
        if t is not None:
            c = lm.region_centroid_local(t)
        else:
            k, j, i = np.nonzero(lm.labels_kji > 0)
            c = np.array([i.mean(), j.mean(), k.mean()]) * lm.spacing_mm
        p, nrm, _ = surf.closest(c)
        p, nrm = p[0], nrm[0]
        near = [n for n, q in enumerate(skin) if np.linalg.norm(q - p) <= 0.5 * span]
        if near:
            patches[near[0]]["targets"].append(t)
            continue
        s_l, d_l, shift = _patch(surf, p, nrm, cfg, span)
        n = len(patches)
        patches.append({"targets": [t], "centre_ras_mm": lm.to_ras(p)[0].round(3).tolist(),
                        "shift_mm": shift})
        skin.append(p)
        src.append(s_l)
        det.append(d_l)
        s_of += [n] * len(s_l)
        d_of += [n] * len(d_l)
    cfg["shift_mm"] = max(q["shift_mm"] for q in patches)
    cfg["patches"] = patches
    cfg["source_patch"], cfg["detector_patch"] = s_of, d_of
    return lm.to_ras(np.vstack(src)), lm.to_ras(np.vstack(det)), cfg


def _patch(surf, p, nrm, cfg, span):
    """One patch's sources and detectors (local mm) around skin point ``p``
    (outward normal ``nrm``), moved the least amount that keeps it on skin."""
    u, v = _tangent_basis(nrm)

    def grid(centre, n, pitch):
        t = (np.arange(int(n)) - 0.5 * (int(n) - 1)) * pitch
        a, b = np.meshgrid(t, t, indexing="ij")
        pts = centre + a.ravel()[:, None] * u + b.ravel()[:, None] * v
        hit, face = surf.cast(pts + 30.0 * nrm, np.tile(-nrm, (len(pts), 1)))
        return None if np.any(face < 0) else hit

    step = 0.5 * cfg["source_pitch_mm"]
    reach = int(np.ceil(span / step))
    shifts = sorted(((a * step, b * step) for a in range(-reach, reach + 1)
                     for b in range(-reach, reach + 1)), key=lambda s: s[0] ** 2 + s[1] ** 2)
    for da, db in shifts:
        centre = p + da * u + db * v
        src = grid(centre, cfg["sources_per_side"], cfg["source_pitch_mm"])
        det = None if src is None else grid(centre, cfg["detectors_per_side"],
                                            cfg["detector_pitch_mm"])
        if det is not None:
            return src, det, float(np.hypot(da, db))
    raise FluoInputError("the scan does not fit on the skin near the target (past the tissue's "
                         "edge or onto a cut face of the label map, wherever it is moved): use "
                         "fewer or closer positions", field="scan",
                         value=float(cfg["source_pitch_mm"]))


def scan_pairs(cfg, n_sources, n_detectors):
    """(S, D) bool: the pairs of one patch (every pair for a scan without patches)."""
    if not cfg or "source_patch" not in cfg:
        return np.ones((n_sources, n_detectors), bool)
    s = np.asarray(cfg["source_patch"])
    d = np.asarray(cfg["detector_patch"])
    if len(s) != n_sources or len(d) != n_detectors:
        return np.ones((n_sources, n_detectors), bool)
    return s[:, None] == d[None, :]


def add_noise(y, noise_pct, rng):
    """Relative Gaussian noise of ``noise_pct`` % per measurement (shot noise of
    well-exposed ROIs is proportional to sqrt(signal); a fixed percentage is
    the stated, conservative model here)."""
    if not (np.isfinite(noise_pct) and 0 <= noise_pct < 100):
        raise FluoInputError("noise must be within 0..100 %", field="noise_pct", value=noise_pct)
    return y * (1.0 + 0.01 * noise_pct * rng.standard_normal(np.shape(y)))


def simulation_mesh(lm, points_local, target, size_mm, coarse_mm, margin_mm, burial_mm=None,
                    cancel=None):
    """Graded structured mesh of the whole tissue: ``size_mm`` cells in the box
    of the points and the target grown by ``margin_mm``, ``coarse_mm`` elsewhere;
    its tissue-air nodes moved onto the smooth surface (model.fit_to_surface)."""
    from FluoTomoLib.meshing.voxel import MeshFidelityWarning, mesh_labelmap_structured

    t_lo, t_hi = lm.tissue_bounds_local()
    lo, hi = points_local.min(axis=0), points_local.max(axis=0)
    roi = np.array([t_lo[0], t_hi[0], t_lo[1], t_hi[1], t_lo[2], t_hi[2]])
    if target is not None:          # where the target is compact (not a tube's length)
        b_lo, b_hi = lm.region_bounds_local(target)
        thin = (b_hi - b_lo) < 0.5 * (t_hi - t_lo)
        lo = np.where(thin, np.minimum(lo, b_lo), lo)
        hi = np.where(thin, np.maximum(hi, b_hi), hi)
    lo, hi = np.maximum(lo - margin_mm, t_lo), np.minimum(hi + margin_mm, t_hi)
    refine = [[(lo[a], hi[a], size_mm)] if coarse_mm > size_mm else [] for a in range(3)]
    if burial_mm is not None:
        from FluoTomoLib.tomography.model import surface_band

        band = surface_band(points_local, lm.surface().closest(points_local)[1], burial_mm,
                            size_mm)
        if band is not None and band[1][2] < size_mm:
            refine[band[0]].append(band[1])
    from FluoTomoLib.tomography.model import cap_grading

    coarse_mm = cap_grading(coarse_mm, refine, size_mm)
    refine = [None if not r else (r[0] if len(r) == 1 else r) for r in refine]
    if all(r is None for r in refine):
        refine = None
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshFidelityWarning)
        mesh = mesh_labelmap_structured(lm.labels_kji, lm.spacing_mm, np.zeros(3),
                                        max(coarse_mm, size_mm), roi=roi, refine=refine,
                                        name="simulation", cancel=cancel)
    from FluoTomoLib.tomography.model import fit_to_surface

    return fit_to_surface(mesh, lm.surface(), roi)


#: the peak memory of the coupled excitation/emission FEM per mesh node [bytes]:
#: assembly, the PARDISO factors of both operators (their fill grows a little
#: faster than the nodes), source and detector fields. Measured (``fluo tomo
#: simulate``, /usr/bin/time -v, peak less the 0.43 GB of imports; a 50 x 40 x
#: 24 mm ellipsoid at 0.5 mm voxels, accuracy fast, balanced and fine: 26,266,
#: 58,918 and 101,675 nodes; issue #17's scene at fine, 137,964 nodes): 9.3, 10.1,
#: 11.3 and 12.3 kB a node; 14 kB is 1.14-1.51x (docs/reliability.md, "Memory
#: estimates")
FEM_BYTES_PER_NODE = 14e3
#: the same for a reconstruction, besides its Jacobian-sized arrays
#: (``reconstruct._PEAK_JACOBIAN_COPIES`` of measurements x nodes doubles): the
#: tissue model, its fields, one factorisation at a time (``lean``), the prior and
#: the solver's other arrays. Measured (/usr/bin/time -v or the test suite's
#: memory report, less the 0.43 GB of imports): HP alone at balanced on a 70 x 60 x
#: 40 mm ellipsoid, 315,033 nodes: 3.43 GB (10.9 kB a node, no Jacobian); SP at fast
#: on the same, 228,371 nodes and 684 pairs: 7.27 GB; HP then SP at balanced on
#: issue #17's scene (``test_issue_scene_through_the_cli``): 5.16 GB. 14 kB a node
#: plus the method's Jacobians is 1.12-1.29x the measured (docs/reliability.md)
RECON_BYTES_PER_NODE = 14e3


def check_fem_memory(n_nodes, jacobian_bytes, size_mm, per_node=FEM_BYTES_PER_NODE):
    """Refuse a forward model (and a Jacobian of ``jacobian_bytes``) whose
    estimated peak does not fit, once its mesh is known and before any solve.

    Parameters
    ----------
    n_nodes : int
        Nodes of the mesh.
    jacobian_bytes : float
        The Jacobian arrays the solver will hold [bytes] (0 for a simulation).
    size_mm : float
        The element size, named in the message.
    per_node : float
        The estimate's bytes per node (:data:`FEM_BYTES_PER_NODE`, or
        :data:`RECON_BYTES_PER_NODE` for a reconstruction).
    """
    from fluoguide.memory import check_fits

    check_fits(per_node * n_nodes + jacobian_bytes,
               f"the diffusion model on {n_nodes:,} nodes ({size_mm:.2g} mm elements)"
               + (f" and its {jacobian_bytes / 1e9:.1f} GB Jacobian" if jacobian_bytes else ""),
               "use accuracy 'fast' or a larger element size" +
               (", or fewer source-detector pairs" if jacobian_bytes else ""),
               field="size_mm", value=round(float(size_mm), 4))


def check_yields(lm, yield_by_label):
    """Each label of ``yield_by_label`` in the label map, each yield a finite number
    >= 0 [1/mm]; refused in one line (FluoInputError, field ``yield``)."""
    for lab, v in yield_by_label.items():
        if int(lab) not in lm.labels:
            raise FluoInputError("label is not in the label map", field="yield",
                                 value=int(lab))
        if not (np.isfinite(v) and v >= 0):
            raise FluoInputError("yield must be a finite number >= 0 [1/mm]",
                                 field=f"yield {int(lab)}", value=v)


def whole_map_model(lm, optics, yield_by_label, src_local, det_local, settings, target,
                    progress=None, cancel=None):
    """The true tissue's FEM model on a mesh of the whole label map: the simulation
    engine's and a rendered recording's (``recording.record_scan``).

    Parameters
    ----------
    lm : LabelMap; optics : Optics; yield_by_label : {label: yield [1/mm]}
    src_local, det_local : (S, 3), (D, 3) sources and detectors in the label map's
        local frame [mm] (the fine band of the mesh follows them)
    settings : accuracy_settings' dict (``simulate_mm``, ``simulate_coarse_mm``)
    target : the label the mesh is refined around

    Returns
    -------
    (FluorescenceModel (lean: release() it when its fields are taken), Mesh, nodal
    yield [1/mm], element size h [mm], the fine band's margin [mm])
    """
    from FluoTomoLib.fem.forward import FluorescenceModel
    from FluoTomoLib.tomography.accuracy import cap_at_burial
    from FluoTomoLib.tomography.model import membership

    decay = 1.0 / max(optics.min_mueff(lm.labels), 1e-6)
    margin = max(4.0, 0.5 * decay)
    report(progress, 0.05, "simulation mesh (whole label map)")
    h, mfp = cap_at_burial(settings["simulate_mm"], optics, lm.labels)
    mesh = simulation_mesh(lm, np.vstack([src_local, det_local]), target, h,
                           max(settings["simulate_coarse_mm"], h), margin, mfp, cancel)
    check_fem_memory(mesh.n_nodes, 0, h)
    check_cancel(cancel)
    labs, F = membership(mesh, lm.labels_kji, lm.spacing_mm)
    y_nodes = F @ np.array([float(yield_by_label.get(int(v), 0.0)) for v in labs])
    px, pm = optics.nodal(labs, F, yield_nodes=y_nodes)
    report(progress, 0.3, f"forward model ({mesh.n_nodes} nodes)")
    fm = FluorescenceModel(mesh, px, pm, src_local, det_local,
                           source_normals=lm.surface().closest(src_local)[1],
                           cut_facets=lm.cut_facets(mesh), lean=True)
    return fm, mesh, y_nodes, h, margin


def simulate_fem(lm, optics, sources_ras, detectors_ras, yield_by_label, noise_pct, seed,
                 settings, progress=None, cancel=None):
    """The FEM engine: emission boundary fluence per watt on a mesh of the whole
    label map, with relative Gaussian noise (:func:`add_noise`)."""
    from FluoTomoLib.fem.kernels import prepare_kernels

    t0 = time.perf_counter()
    src = lm.to_local(sources_ras)
    det = lm.to_local(detectors_ras)
    prepare_kernels(progress, 0.02, cancel)     # first run: compiled, reported as it goes
    fm, mesh, y_nodes, h, margin = whole_map_model(lm, optics, yield_by_label, src, det,
                                                   settings, settings.get("target"),
                                                   progress, cancel)
    data = fm.emission_data(y_nodes)
    fm.release()
    check_cancel(cancel)
    info = {"engine": "fem", "mesh_nodes": mesh.n_nodes, "mesh_elements": mesh.n_elements,
            "element_mm": h, "coarse_element_mm":
            settings["simulate_coarse_mm"], "fine_band_margin_mm": margin,
            "domain": "whole label map", "solver": fm.solver_name,
            "mesh_warnings": list(mesh.meta.get("warnings", [])),
            "seconds": time.perf_counter() - t0, "_mesh": mesh, "_yield_nodes": y_nodes}
    noisy = add_noise(data, noise_pct, np.random.default_rng(seed))
    return {"data": noisy, "clean": data, "info": info}


#: photons per Monte Carlo run (per source and per detector, each repeated twice)
MC_PHOTONS = 100_000


def simulate_mc(lm, optics, sources_ras, detectors_ras, yield_by_label, noise_pct, seed,
                settings, progress=None, cancel=None):
    """The Monte Carlo engine (FluoTomoLib.montecarlo, MCX-CL / MCX): photon
    transport on the label map's own voxels, emission by reciprocity, turned
    into the boundary fluence per watt the diffusion model predicts (the
    Monte Carlo's exitance J times 2A, A the Robin constant of optics.json's
    ``boundary``), then the relative Gaussian noise of ``noise_pct`` on top of
    its photon noise.  Needs cubic voxels (MCX has one voxel size) and labels
    up to 255; ``settings["photons"]`` photons per run, two runs each (their
    spread is the photon noise, reported)."""
    from FluoTomoLib.montecarlo.acquisition import simulate_acquisition as mc_acquisition
    from FluoTomoLib.optics import robin_A

    t0 = time.perf_counter()
    labels = [int(v) for v in lm.labels]
    if max(labels) > 255:
        raise FluoInputError("the Monte Carlo engine takes labels up to 255", field="labels",
                             value=max(labels))
    # MCX's media are 1..L: the label map's labels in order
    remap = np.zeros(max(labels) + 1, np.uint8)
    remap[labels] = np.arange(1, len(labels) + 1)
    mx, sx, mm, sm = optics.per_label_arrays(labels)
    ys = np.array([float(yield_by_label.get(v, 0.0)) for v in labels])
    ox = {k + 1: (mx[k] + optics.mua_per_yield[0] * ys[k], sx[k], optics.n)
          for k in range(len(labels))}
    om = {k + 1: (mm[k] + optics.mua_per_yield[1] * ys[k], sm[k], optics.n)
          for k in range(len(labels))}
    photons = int(settings.get("photons") or MC_PHOTONS)
    # MCX launches each beam at the first tissue voxel along the normal: on a
    # staircase voxel surface that can be a step above the smooth surface the
    # FEM and the reconstruction use (1 mm voxels, curved top: a source 0.9 mm
    # up a step got 0.43x the FEM's data)
    from FluoTomoLib.montecarlo.acquisition import LabelMapGeometry

    geo = LabelMapGeometry(remap[lm.labels_kji], lm.ijk_to_ras)
    surf = lm.surface()
    step = []
    for what, pts in (("source", sources_ras), ("detector", detectors_ras)):
        for i, p in enumerate(np.atleast_2d(pts)):
            g, _ = geo.launch(p, f"{what}s[{i}]")
            d = float(surf.closest(lm.to_local(geo.to_ras(g[None])))[2][0])
            if d > 0.25 * geo.h:
                step.append((what, i, d))
    mc = mc_acquisition(remap[lm.labels_kji], lm.ijk_to_ras, ox, om, sources_ras, detectors_ras,
                        {k + 1: ys[k] for k in range(len(labels))}, photons=photons,
                        seed=int(seed) + 1, runs=2, engine="auto", progress=progress,
                        cancel=cancel, executor=settings.get("executor"),
                        store=settings.get("mc_store"), threads=settings.get("threads", 1))
    A = float(robin_A(optics.n, optics.boundary))
    clean = 2.0 * A * mc["emission"]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_se = np.where(mc["emission"] > 0, mc["emission_se"] / mc["emission"], np.inf)
    notes = list(mc["warnings"])
    if step:
        what, i, d = max(step, key=lambda t: t[2])
        notes.append(f"{len(step)} optode(s) enter the Monte Carlo's voxel surface more than a "
                     f"quarter voxel from the smooth tissue surface (worst: {what} {i}, "
                     f"{d:.2f} mm, a staircase step): their data can be off by a factor of "
                     "2; finer voxels make the steps smaller")
    if np.any(mc["emission"] <= 0):
        notes.append(f"{int(np.sum(mc['emission'] <= 0))} pair(s) received no emitted photon: "
                     "more photons are needed for them")
    info = {"engine": "mc", "mc_engine": mc["engine"], "device": mc["device"],
            "photons_per_run": photons, "runs": mc["runs"], "seeds": mc["seeds"],
            "mc_executor": mc["executor"],
            "robin_A": A, "domain": "the label map's voxels",
            "photon_noise_pct": {"median": float(100 * np.median(rel_se)),
                                 "max": float(100 * np.max(rel_se))},
            # per pair (sources x detectors), same units as the data: what a grader
            # compares a model's data against, with the photon noise it must allow
            "photon_se": (2.0 * A * mc["emission_se"]).tolist(),
            "mesh_warnings": notes, "seconds": time.perf_counter() - t0}
    noisy = add_noise(clean, noise_pct, np.random.default_rng(seed))
    return {"data": noisy, "clean": clean, "info": info}


ENGINES = {"fem": simulate_fem, "mc": simulate_mc}


def simulate_acquisition(lm, optics, yield_by_label, sources_ras=None, detectors_ras=None,
                         scan=None, noise_pct=1.0, seed=0, engine="fem", exclude_mm=None,
                         accuracy="balanced", simulate_mm=None, target=None, photons=None,
                         progress=None, cancel=None, executor=None, mc_store=None, threads=1,
                         scan_targets=None):
    """A simulated acquisition of a label map.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics (every label of the map must be listed)
    yield_by_label : {label: yield [1/mm]} (labels not listed: 0)
    sources_ras, detectors_ras : (S, 3), (D, 3) RAS mm, or None for the
        default scan (``scan``: DEFAULT_SCAN keys): one patch over each of
        ``scan_targets`` (None: every inclusion, LabelMap.inclusion_labels,
        at most MAX_SCAN_PATCHES of them), pairs within a patch
    noise_pct : relative Gaussian noise per measurement [%]
    seed : random seed of the noise
    engine : "fem" or "mc" (see ENGINES)
    exclude_mm : pairs closer than this to their source are marked unused
        (default DEFAULT_SCAN's 3 mm)
    accuracy, simulate_mm : the simulation mesh (accuracy.LEVELS)
    photons : photons per Monte Carlo run (engine "mc"; default MC_PHOTONS)
    executor, mc_store, threads : engine "mc": where its runs go (a run-engine
        executor: serial by default, or Dask workers), the RunStore that records
        each finished run (a killed simulation resumes), threads per run

    Returns
    -------
    (Acquisition, info dict: engine, mesh, timings, truth)
    """
    import warnings

    from FluoTomoLib.tomography.accuracy import accuracy_settings
    from FluoTomoLib.tomography.labelmap import place_on_surface

    t0 = time.perf_counter()
    if engine not in ENGINES:
        raise FluoInputError(f"engine must be one of {', '.join(ENGINES)}", field="engine",
                             value=engine)
    optics.check_labels(lm.labels)
    check_yields(lm, yield_by_label)
    if not any(v > 0 for v in yield_by_label.values()):
        raise FluoInputError("no label fluoresces: give a yield > 0 to at least one",
                             field="yield")
    if target is None:
        target = lm.default_target()
    settings = accuracy_settings(accuracy, simulate_mm=simulate_mm)
    settings["target"] = target
    settings.update(executor=executor, mc_store=mc_store, threads=threads)
    if photons is not None:
        from FluoTomoLib.montecarlo.engine import check_photons

        settings["photons"] = check_photons(photons)
    scan_cfg = None
    if sources_ras is None or detectors_ras is None:
        if scan_targets is None:
            scan_targets = lm.inclusion_labels()[:MAX_SCAN_PATCHES] or target
        sources_ras, detectors_ras, scan_cfg = default_scan(lm, scan_targets, **(scan or {}))
    sources_ras = np.atleast_2d(np.asarray(sources_ras, float))
    detectors_ras = np.atleast_2d(np.asarray(detectors_ras, float))
    src_l, d_src = place_on_surface(lm, sources_ras, "sources")
    det_l, d_det = place_on_surface(lm, detectors_ras, "detectors")
    sources_ras, detectors_ras = lm.to_ras(src_l), lm.to_ras(det_l)
    if not (np.isfinite(noise_pct) and 0 <= noise_pct < 100):
        raise FluoInputError("noise must be within 0..100 %", field="noise_pct", value=noise_pct)
    if not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2 ** 32:
        raise FluoInputError("seed must be an integer within 0..2**32-1", field="seed",
                             value=seed)
    ex = float(DEFAULT_SCAN["exclude_mm"] if exclude_mm is None else exclude_mm)
    if not (np.isfinite(ex) and 0 <= ex <= 100):
        raise FluoInputError("must be a distance within 0..100 mm", field="exclude_mm", value=ex)
    dist = np.linalg.norm(sources_ras[:, None] - detectors_ras[None], axis=2)
    mask = (dist > ex) & scan_pairs(scan_cfg, len(sources_ras), len(detectors_ras))
    if not mask.any():
        raise FluoInputError("every pair is closer than this to its source: no measurement "
                             "left", field="exclude_mm", value=ex)
    from FluoTomoLib.tomography.coverage import scan_coverage
    from FluoTomoLib.tomography.roi import label_map_cut

    coverage = scan_coverage(lm, optics, sources_ras, detectors_ras, mask, noise_pct)
    for w in coverage["warnings"]:
        report(progress, 0.0, w)
    cut_info = label_map_cut(lm, optics, src_l, det_l, mask, cancel=cancel)
    cut_warnings = cut_info.pop("warnings")
    if engine == "mc" and cut_info["sides"]:
        # MCX's photons leave the voxel grid at its border: a cut acts as air there
        cut_warnings = [w.replace("modelled as the same tissue going on, whose own error "
                                  "measured 0.2-0.5 of that", "the Monte Carlo's voxels end "
                                  "there: light crossing the cut is lost, as at air")
                        for w in cut_warnings]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = ENGINES[engine](lm, optics, sources_ras, detectors_ras, yield_by_label,
                              float(noise_pct), int(seed), settings, progress, cancel)
    info = out["info"]
    mesh, y_nodes = info.pop("_mesh", None), info.pop("_yield_nodes", None)
    info["warnings"] = (sorted({str(w.message) for w in caught}) + info.pop("mesh_warnings", [])
                        + cut_warnings + coverage.pop("warnings"))
    info["scan_coverage"] = coverage
    info["label_map_cut"] = cut_info
    noisy = np.asarray(out["data"], float)
    clean = noisy if out.get("clean") is None else np.asarray(out["clean"], float)
    if noisy.shape != (len(sources_ras), len(detectors_ras)) or not np.all(np.isfinite(noisy)):
        raise FluoInputError("the engine returned data of the wrong shape or not finite",
                             field="engine", value=engine)
    info.update({"noise_pct": float(noise_pct), "seed": int(seed), "exclude_mm": ex,
                 "yield_by_label": {str(int(k)): float(v) for k, v in yield_by_label.items()},
                 "accuracy": settings["level"], "target": target, "scan": scan_cfg,
                 "moved_to_surface_mm": {"sources_max": float(d_src.max()),
                                         "detectors_max": float(d_det.max())},
                 "seconds": time.perf_counter() - t0})
    acq = Acquisition(sources_ras, detectors_ras, np.where(mask, noisy, 0.0), mask, "1/mm^2",
                      {"simulation": info})
    acq.clean = np.where(mask, clean, 0.0)
    acq.simulation_mesh = mesh
    acq.simulation_yield_nodes = y_nodes
    return acq, info
