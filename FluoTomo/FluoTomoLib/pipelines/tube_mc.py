"""The cylinder-tube graded on Monte Carlo data: the honest accuracy figure.

The tube study of :mod:`FluoTomoLib.pipelines.tube` simulates its data with the
project's own diffusion FEM (on a finer, whole-phantom mesh).  Here the data come
from photon transport written outside the project (MCX-CL / MCX through
:mod:`FluoTomoLib.montecarlo`), on the phantom's 0.5 mm voxels, and the same
sources and detectors are also simulated by the diffusion FEM on the whole
phantom; both are reconstructed by the public label-map path
(``reconstruct_labelmap_methods``, as ``fluo tomo reconstruct``) on a 0.8 mm
label map of the phantom (another discretisation than either simulation).  The
difference between the two rows of a depth is what the diffusion model's own
error does to NP / SP / HP.

Layout: a line of ``SOURCES`` laser points across the tube (x = 0, along y,
``PITCH_MM`` apart) and ``SOURCES + 1`` detectors between and beyond them;
pairs closer than ``EXCLUDE_MM`` are unused.  The Monte Carlo acquisitions are
stored in ``FluoTomoLib/montecarlo/data/tube/depth_<d>mm/`` (a CPU needs
about 15-25 min per depth for ``PHOTONS`` photons x 2 runs per optode);
``fluo validate mc-tomography --simulate`` regenerates them.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.progress import check_cancel, report, scaled

SOURCES = 12
PITCH_MM = 3.0
EXCLUDE_MM = 3.0
MC_VOXEL_MM = 0.5          # MCX's grid (cubic voxels); the tube is 2.4 mm across
RECON_VOXEL_MM = 0.8       # the reconstruction's label map (the demo's CBCT voxel)
PHOTONS = 100_000
RUNS = 2
DEPTHS_MM = (2.7, 4.7, 6.7)
NOISE_PCT = 1.0            # relative Gaussian noise added to both data sets (same seed)
STORE = Path(__file__).resolve().parents[1] / "montecarlo" / "data" / "tube"
#: each depth's diffusion-FEM acquisition of the same optodes, beside its Monte Carlo one
FEM_FOLDER = "fem"


def depth_folder(depth_mm, root=None):
    """``root/depth_<d>mm`` (root None: the stored sets; an empty root is refused)."""
    if root is not None and not str(root).strip():
        raise FluoInputError("needs a folder of depth_<d>mm acquisitions", field="mc_root",
                             value=str(root))
    return Path(STORE if root is None else root) / f"depth_{float(depth_mm):.1f}mm"


def optode_line(n_sources=SOURCES, pitch_mm=PITCH_MM):
    """Sources (S, 3) and detectors (S + 1, 3) on the liquid surface (z = 0), RAS mm."""
    from FluoTomoLib.pipelines.tube_truth import raster_targets

    # the detectors: a line one longer, between and beyond the sources
    return raster_targets(n_sources, pitch_mm), raster_targets(n_sources + 1, pitch_mm)


def tube_scene(depth_mm, voxel_mm):
    """(LabelMap, Optics, {2: true yield}, truth) of the cylinder-tube phantom."""
    from fluoguide.phantoms import cylinder_tube
    from FluoTomoLib.tomography import LabelMap, optics_from_phantom

    ph = cylinder_tube(voxel_mm=voxel_mm, depth_mm=depth_mm)
    truth = ph.truth()
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    lm = LabelMap(ph.labels, ph.spacing_mm, ph.origin_mm,
                  source=f"cylinder-tube {voxel_mm:g} mm voxels, depth {depth_mm:g} mm")
    return lm, optics_from_phantom(optics), {2: float(optics[2]["yield_per_mm"])}, truth


def mc_seed(depth_mm):
    """The acquisition seed of a depth (the stored sets': 1, 1001, 2001)."""
    d = round(float(depth_mm), 1)
    if d in DEPTHS_MM:
        return 1 + 1000 * DEPTHS_MM.index(d)
    return 100_001 + int(round(1000 * d))


def simulate_tube(depth_mm, engine="mc", photons=PHOTONS, seed=None, accuracy="fine",
                  progress=None, cancel=None, executor=None, mc_store=None, threads=1):
    """Simulate the tube's acquisition (no added noise) with Monte Carlo on 0.5 mm
    voxels (``engine="mc"``) or the diffusion FEM on a mesh of the whole phantom
    (``engine="fem"``, ``accuracy``).  Returns (Acquisition, info)."""
    from FluoTomoLib.tomography import simulate_acquisition

    lm, optics, yields, _ = tube_scene(depth_mm, MC_VOXEL_MM)
    src, det = optode_line()
    kw = dict(photons=photons, executor=executor, mc_store=mc_store, threads=threads) \
        if engine == "mc" else dict(accuracy=accuracy)
    # the acquisition's seed; the MC engine seeds its runs from seed + 1 on
    # (tomography.simulate_mc), so the stored sets' runs start at 2, 1002, 2002
    seed = mc_seed(depth_mm) if seed is None else seed
    return simulate_acquisition(lm, optics, yields, src, det, noise_pct=0.0, seed=seed,
                                engine=engine, exclude_mm=EXCLUDE_MM, target=2,
                                progress=progress, cancel=cancel, **kw)


def _errors(result, truth_yield, depth_mm):
    """Yield and centroid errors of one method's result (the target label 2)."""
    s = result["summary"]
    reg = s["regions"]["2"]
    cen = s.get("target_centroid_ras_mm")
    row = {"yield_per_mm": reg["yield_per_mm"],
           "yield_error_pct": 100.0 * (reg["yield_per_mm"] - truth_yield) / truth_yield,
           "peak_yield_per_mm": s["peak_yield_per_mm"],
           "peak_error_pct": 100.0 * (s["peak_yield_per_mm"] - truth_yield) / truth_yield,
           "centroid_depth_mm": None if cen is None else -float(cen[2]),
           "warnings": list(s["warnings"]), "iterations": s["solver"]["iterations"]}
    row["centroid_error_pct"] = None if cen is None else \
        100.0 * (row["centroid_depth_mm"] - depth_mm) / depth_mm
    return row


def grade_depth(depth_mm, mc_acquisition, fem_acquisition=None, methods=("NP", "SP", "HP"),
                accuracy="fast", noise_pct=NOISE_PCT, seed=0, progress=None, cancel=None,
                grading="bisection"):
    """Reconstruct one depth from Monte Carlo data and from diffusion-FEM data of the
    same optodes (simulated here on the whole phantom unless given), on the 0.8 mm
    label map, and return the errors side by side.

    Both data sets get the same relative Gaussian noise (``noise_pct``, same seed)
    on top of what they carry (the Monte Carlo's photon noise).  ``grading``: the
    reconstruction mesh's (reconstruct_labelmap's).
    """
    from FluoTomoLib.tomography import reconstruct_labelmap_methods
    from FluoTomoLib.tomography.simulate import add_noise

    t0 = time.perf_counter()
    lm, optics, yields, _ = tube_scene(depth_mm, RECON_VOXEL_MM)
    truth_yield = yields[2]
    if fem_acquisition is None:
        report(progress, 0.0, f"diffusion FEM data, depth {depth_mm:g} mm (whole phantom)")
        fem_acquisition, _ = simulate_tube(depth_mm, "fem", progress=scaled(
            progress, 0.0, 0.3, "FEM data"), cancel=cancel)
    rows, mesh = {}, None
    for k, (name, acq) in enumerate((("diffusion FEM", fem_acquisition),
                                     ("Monte Carlo", mc_acquisition))):
        check_cancel(cancel)
        acq = type(acq)(acq.sources_ras_mm, acq.detectors_ras_mm,
                        np.where(acq.mask, add_noise(acq.data, noise_pct, seeded_rng(seed)),
                                 0.0),
                        acq.mask, acq.units, dict(acq.meta))
        solved = reconstruct_labelmap_methods(
            lm, optics, acq, methods, target=2, accuracy=accuracy, grading=grading,
            progress=scaled(progress, 0.3 + 0.35 * k, 0.65 + 0.35 * k, f"{name} data"),
            cancel=cancel, mesh=mesh)
        rows[name] = {m: _errors(r, truth_yield, depth_mm) for m, r in solved.items()}
        # both data sets on one reconstruction mesh (the optodes and the label map
        # are the same): the rows then differ by the data alone, and the second
        # set does not mesh again
        mesh = next(iter(solved.values()))["mesh"]
    return {"depth_mm": float(depth_mm), "true_yield_per_mm": truth_yield,
            "noise_pct": noise_pct, "accuracy": accuracy, "rows": rows,
            "seconds": time.perf_counter() - t0}


def regenerate_command(depth_mm, photons=PHOTONS):
    """The command that makes a depth's Monte Carlo acquisition (as stored)."""
    return (f"fluo validate mc-tomography --simulate --depths {float(depth_mm):g} --photons "
            f"{int(photons)} --out DIR (writes DIR/mc/{depth_folder(depth_mm, '.').name})")


def regenerate_fem_command(depth_mm):
    """The command that makes a depth's diffusion-FEM acquisition (as stored)."""
    return (f"fluo validate mc-tomography --simulate-fem --depths {float(depth_mm):g} --out DIR "
            f"(writes DIR/mc/{depth_folder(depth_mm, '.').name}/{FEM_FOLDER})")


def read_stored_fem(depth_mm, root=None):
    """The stored diffusion-FEM acquisition of a depth (:func:`simulate_tube` with
    ``engine="fem"``: no noise, the whole phantom at the ``fine`` level), checked
    to be that depth's and the optode line's; None when the folder holds none."""
    from FluoTomoLib.tomography import read_acquisition

    folder = depth_folder(depth_mm, root) / FEM_FOLDER
    if not (folder / "acquisition.json").is_file():
        return None
    acq = read_acquisition(folder)
    sim = acq.meta.get("simulation") or {}
    if sim.get("engine") != "fem" or sim.get("tube_depth_mm") is None or \
            abs(float(sim["tube_depth_mm"]) - float(depth_mm)) > 1e-6:
        raise FluoInputError(f"is not this depth's diffusion-FEM acquisition (regenerate: "
                             f"{regenerate_fem_command(depth_mm)})",
                             file=str(folder / "acquisition.json"),
                             field="simulation.tube_depth_mm", value=sim.get("tube_depth_mm"))
    _check_line(acq, folder)
    return acq


def _check_line(acq, folder):
    src, det = optode_line()
    if acq.sources_ras_mm.shape != src.shape or acq.detectors_ras_mm.shape != det.shape or \
            not (np.allclose(acq.sources_ras_mm, src, atol=1e-3)
                 and np.allclose(acq.detectors_ras_mm, det, atol=1e-3)):
        raise FluoInputError("holds other sources or detectors than the tube's optode line",
                             file=str(folder), field="sources/detectors")


def read_stored(depth_mm, root=None):
    """The stored Monte Carlo acquisition of a depth, checked to be that depth's: the
    optode line of :func:`optode_line` and ``tube_depth_mm`` in its simulation record
    (refused with the command that makes it when missing or another scene's)."""
    from FluoTomoLib.tomography import read_acquisition

    folder = depth_folder(depth_mm, root)
    if not (folder / "acquisition.json").is_file():
        raise FluoInputError(f"no Monte Carlo acquisition for this depth (make it with "
                             f"{regenerate_command(depth_mm)})", file=str(folder),
                             field="depth_mm", value=float(depth_mm))
    acq = read_acquisition(folder)
    sim = acq.meta.get("simulation") or {}
    made_for = sim.get("tube_depth_mm")
    if made_for is None or abs(float(made_for) - float(depth_mm)) > 1e-6:
        raise FluoInputError(f"is not this depth's Monte Carlo acquisition (made for "
                             f"{made_for} mm; regenerate: {regenerate_command(depth_mm)})",
                             file=str(folder / "acquisition.json"),
                             field="simulation.tube_depth_mm", value=made_for)
    _check_line(acq, folder)
    return acq


def validate_tube_mc(depths_mm=DEPTHS_MM, mc_root=None, simulate=False, photons=PHOTONS,
                     out_dir=None, methods=("NP", "SP", "HP"), accuracy="fast", executor=None,
                     threads=1, resume=False, progress=None, cancel=None, simulate_fem=False,
                     grading="bisection"):
    """NP / SP / HP of the cylinder-tube from Monte Carlo data next to diffusion data.

    ``simulate``: run the Monte Carlo here (its runs on ``executor``, recorded in
    ``out_dir/mc_runs/`` and resumable), writing the acquisitions to
    ``out_dir/mc/``; otherwise read the stored ones (``mc_root``, default
    :data:`STORE`).  The diffusion-FEM data are the stored ones beside them
    (``depth_<d>mm/fem``, :func:`read_stored_fem`) unless ``simulate`` or
    ``simulate_fem`` (computed here on the whole phantom and written to
    ``out_dir/mc/depth_<d>mm/fem``) or none is stored (computed here).  Returns
    the rows (depth x data x method) and per-depth details (``fem_data``: where
    the diffusion data came from).  ``grading``: the reconstruction mesh's
    (reconstruct_labelmap's).
    """
    from FluoTomoLib.tomography import write_acquisition

    depths = [float(d) for d in depths_mm]
    if not depths or any(not (2.0 <= d <= 16.0) for d in depths):
        raise FluoInputError("tube depths must be within 2..16 mm", field="depths_mm",
                             value=depths_mm)
    if (simulate or simulate_fem) and out_dir is None:
        raise FluoInputError("simulating needs an output folder", field="out_dir")
    acqs, mc_info, fem = {}, {}, {}
    n = len(depths)
    for d in depths:          # inputs first: a missing set fails before work
        if not simulate:
            acqs[d] = read_stored(d, mc_root)
            mc_info[d] = acqs[d].meta.get("simulation", {})
        if not (simulate or simulate_fem):
            fem[d] = read_stored_fem(d, mc_root)
    rows, details = [], []
    for i, d in enumerate(depths):
        check_cancel(cancel)
        lo, hi = i / n, (i + 1) / n
        if simulate:
            from fluoguide.runs.store import RunStore

            store = RunStore(Path(out_dir) / "mc_runs" / depth_folder(d).name, resume=resume)
            acq, info = simulate_tube(d, "mc", photons, executor=executor, mc_store=store,
                                      threads=threads,
                                      progress=scaled(progress, lo, lo + 0.5 * (hi - lo),
                                                      f"Monte Carlo, depth {d:g} mm"),
                                      cancel=cancel)
            info["regenerate"] = regenerate_command(d, photons)
            info["tube_depth_mm"] = d
            write_acquisition(depth_folder(d, Path(out_dir) / "mc"), acq, simulation=info)
            acqs[d], mc_info[d] = acq, info
            lo = lo + 0.5 * (hi - lo)
        fem_from = "stored: " + str(depth_folder(d, mc_root) / FEM_FOLDER)
        if fem.get(d) is None:
            fem_from = "computed here (whole phantom, fine)"
            fem[d], info = simulate_tube(d, "fem", progress=scaled(
                progress, lo, lo + 0.3 * (hi - lo), f"diffusion FEM data, depth {d:g} mm"),
                cancel=cancel)
            if simulate or simulate_fem:
                info.update(regenerate=regenerate_fem_command(d), tube_depth_mm=d,
                            engine="fem")
                target = depth_folder(d, Path(out_dir) / "mc") / FEM_FOLDER
                write_acquisition(target, fem[d], simulation=info)
                fem_from = "computed here, written to " + str(target)
            lo = lo + 0.3 * (hi - lo)
        g = grade_depth(d, acqs[d], fem[d], methods=methods, accuracy=accuracy,
                        progress=scaled(progress, lo, hi, f"depth {d:g} mm"), cancel=cancel,
                        grading=grading)
        g["fem_data"] = fem_from
        g["fem_regenerate"] = regenerate_fem_command(d)
        info = mc_info[d]
        g["mc"] = {k: info.get(k) for k in ("photons_per_run", "runs", "photon_noise_pct",
                                            "mc_engine", "device", "seconds", "regenerate")}
        details.append(g)
        for data_name, per_method in g["rows"].items():
            for m, r in per_method.items():
                rows.append({"depth_mm": d, "data": data_name, "method": m,
                             "yield_error_pct": r["yield_error_pct"],
                             "peak_error_pct": r["peak_error_pct"],
                             "centroid_error_pct": r["centroid_error_pct"],
                             "yield_per_mm": r["yield_per_mm"],
                             "centroid_depth_mm": r["centroid_depth_mm"],
                             "iterations": r["iterations"], "warnings": len(r["warnings"])})
    report(progress, 1.0, "done")
    # every reconstruction's warnings, where a reader of the JSON sees them
    warnings = [f"depth {g['depth_mm']:g} mm, {m} from {name} data: {w}" for g in details
                for name, per in g["rows"].items() for m, r in per.items()
                for w in r["warnings"]]
    return {"rows": rows, "depths": details, "warnings": warnings, "true_yield_per_mm": details[0]["true_yield_per_mm"],
            "layout": {"sources": SOURCES, "detectors": SOURCES + 1, "pitch_mm": PITCH_MM,
                       "exclude_mm": EXCLUDE_MM, "mc_voxel_mm": MC_VOXEL_MM,
                       "reconstruction_voxel_mm": RECON_VOXEL_MM},
            "noise_pct": NOISE_PCT, "accuracy": accuracy, "grading": grading or "none"}


def figure(result, path):
    """Yield and centroid errors per depth and method, from diffusion-FEM data
    (hatched) and Monte Carlo data (solid) of the same optodes: grouped bars with
    their values written on them (one PNG).  NP's errors (no prior: -90..-100 %)
    would flatten SP and HP, so the axis is set by SP and HP and a bar beyond it
    is cut and labelled with its value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    depths = sorted({r["depth_mm"] for r in result["rows"]})
    methods = [m for m in ("NP", "SP", "HP") if any(r["method"] == m for r in result["rows"])]
    colours = {"NP": "tab:red", "SP": "tab:orange", "HP": "tab:blue"}
    data_names = (("diffusion FEM", "//"), ("Monte Carlo", None))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    for ax, key, label in ((axes[0], "yield_error_pct", "mean yield in the tube: error [%]"),
                           (axes[1], "centroid_error_pct", "centroid depth: error [%]")):
        vals = [r[key] for r in result["rows"] if r[key] is not None and r["method"] != "NP"]
        span = max([5.0] + [abs(v) for v in vals]) * 1.35
        width = 0.8 / (len(methods) * 2)
        for i, d in enumerate(depths):
            for j, m in enumerate(methods):
                for k, (name, hatch) in enumerate(data_names):
                    row = next((r for r in result["rows"] if r["depth_mm"] == d
                                and r["method"] == m and r["data"] == name), None)
                    if row is None or row[key] is None:
                        continue
                    v = row[key]
                    x = i + (2 * j + k - len(methods) + 0.5) * width
                    shown = float(np.clip(v, -span, span))
                    ax.bar(x, shown, width, color=colours[m], hatch=hatch, edgecolor="k",
                           lw=0.5, alpha=0.55 if hatch else 0.95,
                           label=f"{m}, {name} data" if i == 0 else None)
                    if abs(v) > span:       # cut: the value inside the bar's end
                        ax.text(x, 0.9 * shown, f"{v:+.0f}", ha="center", va="center",
                                fontsize=7, color="white", fontweight="bold")
                    else:
                        ax.text(x, shown + (0.02 if shown >= 0 else -0.02) * span,
                                f"{v:+.1f}", ha="center", va="bottom" if shown >= 0 else "top",
                                fontsize=7)
        ax.set_ylim(-span * 1.15, span * 1.15)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(range(len(depths)))
        ax.set_xticklabels([f"tube at {d:g} mm" for d in depths])
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, ncol=len(methods) * 2, loc="lower center")
    fig.suptitle("Cylinder-tube reconstructed from Monte Carlo data (solid) and from "
                 "diffusion-FEM data (hatched): same 12 sources and 13 detectors, same 1 % "
                 "noise", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    from fluoguide import atomic

    atomic.save_figure(fig, path, field="--out", dpi=110)   # whole, or nothing
    plt.close(fig)
    return str(path)
