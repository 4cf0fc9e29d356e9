"""The stages of ``fluo demo`` (``fluoapp/demo/run.py`` runs them).

Each stage is ``fn(ctx)``: it reads what earlier stages left in ``ctx.state``,
writes files into ``ctx.out``, records numbers in ``ctx.metrics[stage]`` and
figures with ``ctx.figure``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoapp.commands import module_logic
from fluoguide import atomic, mrml_io
from fluoguide.phantoms import add_phantom_to_scene, make_phantom, write_phantom
from fluoguide.progress import report, scaled

TUBE_DEPTHS_MM = [2.7, 3.7, 4.7, 5.7, 6.7]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _colorbar_beside(fig, ax, im, label, **kw):
    """A colour bar as tall as the image next to it, with its label (unit)."""
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08)
    fig.colorbar(im, cax=cax, label=label, **kw)


def stage_phantoms(ctx):
    """Digital phantoms: cylinder-tube at the thesis's tube depths, oral cavity, slab."""
    depths = TUBE_DEPTHS_MM[::2] if ctx.quick else TUBE_DEPTHS_MM
    ctx.metrics["tube_depths_mm"] = depths
    out = {}
    tubes = {}
    for d in depths:
        ph = make_phantom("cylinder-tube", depth_mm=d, seed=ctx.seed)
        write_phantom(ph, ctx.out / "phantoms" / f"cylinder-tube-{d:.1f}mm")
        tubes[d] = ph
        out[f"cylinder-tube {d:.1f} mm: tube volume error %"] = ph.truth()["regions"]["2"]["volume_error_pct"]
    others = {}
    for name in ("oral-cavity", "slab"):
        ph = make_phantom(name, seed=ctx.seed)
        write_phantom(ph, ctx.out / "phantoms" / name)
        others[name] = ph
        for label, r in ph.truth()["regions"].items():
            out[f"{name} region {r['name']}: volume error %"] = r["volume_error_pct"]
    ctx.state["tube_phantoms"] = tubes
    ctx.state["phantoms"] = others
    # The demo's own scene starts from the cylinder-tube phantom at the first depth.
    scene = mrml_io.new_scene()
    add_phantom_to_scene(scene, tubes[depths[0]])
    ctx.state["scene"] = scene
    mrml_io.save_scene(scene, ctx.out / "scene.mrml")
    ctx.metrics["phantoms"] = out

    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4))
    ph = tubes[depths[0]]
    i = ph.labels.shape[2] // 2
    ext = [ph.origin_mm[1], ph.origin_mm[1] + ph.spacing_mm[1] * ph.labels.shape[1],
           ph.origin_mm[2], ph.origin_mm[2] + ph.spacing_mm[2] * ph.labels.shape[0]]
    im = axes[0].imshow(ph.cbct_hu[:, :, i], cmap="gray", vmin=-300, vmax=300, origin="lower",
                        extent=ext)
    _colorbar_beside(fig, axes[0], im, "CT number [HU]")
    axes[0].set_title(f"cylinder-tube CBCT, y-z slice\n(tube at {depths[0]} mm)")
    axes[0].set_xlabel("y [mm]")
    axes[0].set_ylabel("z [mm]")
    oc = others["oral-cavity"]
    j = oc.labels.shape[1] // 2 + 5
    ext = [oc.origin_mm[0], oc.origin_mm[0] + oc.spacing_mm[0] * oc.labels.shape[2],
           oc.origin_mm[2], oc.origin_mm[2] + oc.spacing_mm[2] * oc.labels.shape[0]]
    im = axes[1].imshow(oc.cbct_hu[:, j, :], cmap="gray", vmin=-300, vmax=300, origin="lower",
                        extent=ext)
    _colorbar_beside(fig, axes[1], im, "CT number [HU]")
    axes[1].set_title("oral-cavity CBCT, x-z slice")
    axes[1].set_xlabel("x [mm]")
    im = axes[2].imshow(oc.labels[:, j, :], cmap="viridis", origin="lower", extent=ext,
                        interpolation="nearest")
    _colorbar_beside(fig, axes[2], im, "region label", ticks=[0, 1, 2])
    axes[2].set_title("oral-cavity labels (0 air, 1 agar, 2 tongue)")
    axes[2].set_xlabel("x [mm]")
    fig.tight_layout(w_pad=4.0)
    atomic.save_figure(fig, ctx.out / "phantoms.png", dpi=90)
    plt.close(fig)
    ctx.figure("phantoms", "phantoms.png", "Digital phantoms: synthetic CBCT (HU) and label maps.")




def _tomo_figures(ctx, runs):
    """Profiles per depth, error summary, and y-z sections (truth | NP | SP | HP)."""
    plt = _plt()
    methods = ["NP", "SP", "HP"]
    colors = {"truth": "k", "NP": "tab:red", "SP": "tab:blue", "HP": "tab:green"}
    depths = sorted(runs)
    fig, axes = plt.subplots(1, len(depths), figsize=(3.2 * len(depths), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, d in zip(axes, depths):
        run = runs[d]
        z = run["profile_depth_mm"]
        for key in ["truth"] + methods:
            ax.plot(z, 1e3 * run["profiles"][key], color=colors[key], lw=1.6 if key == "truth" else 1.2,
                    label=key)
        ax.set_title(f"tube at {d:.1f} mm")
        ax.set_xlabel("depth [mm]")
        ax.set_xlim(0, 12)
    axes[0].set_ylabel("yield [1e-3 / mm]")
    axes[0].legend(fontsize=8)
    fig.suptitle("Depth profiles through the tube (x = y = 0)")
    fig.tight_layout()
    atomic.save_figure(fig, ctx.out / "tomo_profiles.png", dpi=90)
    plt.close(fig)
    ctx.figure("tomography", "tomo_profiles.png",
               "Reconstructed yield along the depth profile through the tube, per depth.")

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    for k, m in enumerate(methods):
        axes[0].plot(depths, [runs[d]["results"][m]["peak_error_pct"] for d in depths], "o-",
                     color=colors[m], label=m)
        axes[2].plot(depths, [runs[d]["results"][m]["centroid_error_pct"] for d in depths], "o-",
                     color=colors[m], label=m)
        # the tube region's value and its stated 95 % interval, against the truth
        # (NP's intervals can span hundreds of %: clipped by the axis, not dropped)
        err, lo, hi, x = _region_errors(runs, depths, m)
        axes[1].errorbar(x + 0.08 * (k - 1), err, yerr=[err - lo, hi - err], fmt="o",
                         color=colors[m], capsize=3, label=m)
    axes[1].set_ylim(-110, 110)
    for ax, title in zip(axes, ["peak yield error [%]",
                                "tube region's yield error, 95 % interval [%]",
                                "centroid depth error [%]"]):
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xlabel("tube depth [mm]")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    atomic.save_figure(fig, ctx.out / "tomo_errors.png", dpi=90)
    plt.close(fig)
    ctx.figure("tomography", "tomo_errors.png",
               "Errors vs tube depth (NP, SP, HP): the profile's peak, the tube region's value "
               "with its stated 95 % interval (an interval that misses zero missed the truth), "
               "and the half-maximum centroid.")

    d = depths[0]
    run = runs[d]
    geometry = ctx.state["tube_phantoms"][d].truth()["geometry"]
    centre = geometry["tube_centre_mm"]
    _section_figure(ctx.out / "tomo_sections.png", run["sections"],
                    true_circle=((centre[1], centre[2]), geometry["tube_radius_mm"]))
    ctx.figure("tomography", "tomo_sections.png",
               f"Cross-section through the tube at {d:.1f} mm (x = 0): truth | NP | SP | HP, "
               "same colour scale; cyan: the true tube (2.4 mm circle); the truth panel is the "
               "tube as the simulation mesh holds it.")

    # one rendered camera frame (laser at the middle of the raster), log counts
    frame = run["frame_example"]
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    im = ax.imshow(np.log10(np.maximum(frame, 1.0)), cmap="gray")
    fig.colorbar(im, ax=ax, label="log10 counts [ADU]")
    ax.set_title(f"camera frame, laser at source {run['frame_example_source'] + 1} "
                 f"(tube at {d:.1f} mm)")
    ax.set_xlabel("x [px, 4x4 binned]")
    ax.set_ylabel("y [px]")
    fig.tight_layout()
    atomic.save_figure(fig, ctx.out / "tomo_frame.png", dpi=90)
    plt.close(fig)
    ctx.figure("tomography", "tomo_frame.png",
               "A rendered fluorescence frame (every pixel ray-cast onto the surface, emission "
               "exitance from the FEM field, shot and read noise); the bright spot is the laser "
               "position, the detectors are ~1 mm^2 ROIs of such frames.")


def _section_figure(path, sections, sources_mm=None, true_circle=None):
    """y-z section at x = 0 of truth | NP | SP | HP on one colour scale (blank
    where there is no tissue), from the images the case sampled
    (``FluoTomoLib.pipelines.cases.section_images``); the true target outlined
    in cyan on every panel: ``true_circle`` ((y, z) centre, radius; mm) where its
    geometry is a circle, else the half-way contour of the simulated true
    yield; ``sources_mm``: mark where the laser entered."""
    plt = _plt()
    y_mm, z_mm = tuple(sections["y_mm"]), tuple(sections["z_mm"])
    panels = [("forward model (truth)", sections["truth"])]
    panels += [(m, sections[m]) for m in ("NP", "SP", "HP")]
    vmax = max(float(np.nanmax(img)) for _, img in panels)
    cmap = plt.get_cmap("inferno").with_extremes(bad="white")
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.4), constrained_layout=True)
    truth = sections["truth"]
    yy, zz = np.meshgrid(np.linspace(*y_mm, truth.shape[1]), np.linspace(*z_mm, truth.shape[0]))
    for ax, (title, img) in zip(axes, panels):
        im = ax.imshow(1e3 * img, extent=(*y_mm, min(z_mm), max(z_mm)), origin="upper",
                       cmap=cmap, vmin=0, vmax=1e3 * vmax, aspect="equal")
        if true_circle is not None:
            (cy, cz), radius = true_circle
            t = np.linspace(0, 2 * np.pi, 181)
            ax.plot(cy + radius * np.cos(t), cz + radius * np.sin(t), color="cyan", lw=0.9)
        else:
            # half-way between the tissue's lowest and highest true yield
            level = 0.5 * (np.nanmin(truth) + np.nanmax(truth))
            ax.contour(yy, zz, truth, levels=[level], colors="cyan", linewidths=0.9)
        if sources_mm is not None:
            ax.plot(sources_mm[:, 1], sources_mm[:, 2], "c.", ms=3)
        ax.set_title(title)
        ax.set_xlabel("y [mm]")
    axes[0].set_ylabel("z [mm]")
    fig.colorbar(im, ax=axes, shrink=0.9, fraction=0.02, label="yield [1e-3 / mm]")
    atomic.save_figure(fig, path, dpi=90)
    plt.close(fig)


def _region_errors(runs, depths, method):
    """The tube region's (label 2) value and 95 % interval as errors against the
    true yield [%], at the depths where the result has them: (err, lo, hi, depths)."""
    rows = []
    for d in depths:
        res = runs[d]["results"][method]
        r = (res.get("regions") or {}).get("2") or {}
        ci, v, t = r.get("ci95_per_mm"), r.get("yield_per_mm"), res["true_peak"]
        if ci is not None and v is not None:
            rows.append([100 * (v / t - 1), 100 * (ci[0] / t - 1), 100 * (ci[1] / t - 1), d])
    a = np.array(rows, float).reshape(-1, 4)
    return a[:, 0], a[:, 1], a[:, 2], a[:, 3]


def _run_cases(ctx, name, tasks):
    """The tomography cases of a stage on the run engine (``fluo demo --workers`` /
    ``--scheduler``; serial in this process by default), recorded in
    OUT/runs/NAME (``--resume`` reuses the finished ones); the cases as
    ``FluoTomoLogic.runTomographyCases`` returns them, in task order.  A failed
    case fails the stage, naming it."""
    from fluoguide.errors import FluoError

    run = module_logic("FluoTomo").runTomographyCases(
        tasks, ctx.out / "runs" / name, resume=ctx.resume, executor=ctx.executor,
        threads=ctx.threads, progress=ctx.progress, cancel=ctx.cancel,
        label=f"fluo demo: {name}")
    ctx.metrics.setdefault("runs", {})[name] = {
        k: run[k] for k in ("tasks", "computed", "reused", "failures", "seconds", "executor",
                            "workers")}
    if run["failed"]:
        f = run["failed"][0]
        raise FluoError(f"{len(run['failed'])} of {len(tasks)} cases failed; the first "
                        f"({f['params']}): {f['error']} (records in {run['store']})")
    return run["cases"]


#: the tube cases' and the Monte Carlo stage's reconstruction mesh
#: (reconstruct_labelmap's ``grading``)
TUBE_GRADING = "bisection"


def stage_tomography(ctx):
    """Tracked non-contact acquisition and NP/SP/HP reconstruction at each tube depth."""

    # The public label-map path (fluo tomo reconstruct's): the simulation meshes
    # the whole phantom, the region of interest is chosen from the decay length
    # and its truncation error is reported (it was graded by itself before:
    # 30 x 50 mm, 7.9 % median / 29 % max change of the data).  Quick: the
    # "fast" accuracy level, same tube resolution.  One run-engine task per
    # depth: each builds its phantom (the one stage_phantoms wrote, from the
    # same depth and seed) and returns plain arrays, so the depths can go to
    # Dask workers side by side.  The reconstruction mesh is graded by bisection
    # (fine at the optodes and the tube only): a laptop's memory and minutes,
    # the tube's errors as on the uniform grid (docs/validation.md).
    depths = sorted(ctx.state["tube_phantoms"])
    tasks = module_logic("FluoTomo").tomographyCaseTasks(
        depths, seed=ctx.seed,
        tubeOptions={"accuracy": "fast" if ctx.quick else "balanced", "grading": TUBE_GRADING,
                     **ctx.case_options})
    runs = dict(zip(depths, _run_cases(ctx, "tomography", tasks)))
    for d in depths:            # fluo demo --simulate-truth: what the stored sets are made of
        if runs[d].get("surface_truth") is not None:
            module_logic("FluoTomo").writeTubeTruth(runs[d]["surface_truth"],
                                                    ctx.out / "tube_truth")
    methods = ["NP", "SP", "HP"]
    ctx.metrics["yield_error_pct"] = {m: [runs[d]["results"][m]["peak_error_pct"] for d in depths]
                                      for m in methods}
    ctx.metrics["centroid_error_pct"] = {m: [runs[d]["results"][m]["centroid_error_pct"]
                                             for d in depths] for m in methods}
    summary = {}
    for m in methods:
        summary[f"{m} mean |yield error| %"] = float(np.mean(np.abs(ctx.metrics["yield_error_pct"][m])))
        summary[f"{m} mean |centroid error| %"] = float(
            np.mean(np.abs(ctx.metrics["centroid_error_pct"][m])))
    r0 = runs[depths[0]]
    summary.update({
        "forward mesh nodes / tets": [r0["mesh_nodes"]["forward"], r0["mesh_elements"]["forward"]],
        "reconstruction mesh nodes / tets": [r0["mesh_nodes"]["reconstruction"],
                                             r0["mesh_elements"]["reconstruction"]],
        "measurements per case": r0["measurements"],
        "mean source position error from tracking [mm]": float(
            np.mean([runs[d]["source_error_mm"] for d in depths])),
        "solver": r0["solver"],
        "region of interest: estimated truncation max % (per case)": [
            runs[d]["region_of_interest"].get("truncation_max_pct") for d in depths],
        "region of interest: margin around the optodes and tube [mm]": float(
            runs[depths[0]]["region_of_interest"].get("margin_mm", float("nan"))),
        "camera pose error from tracking [mm] (mean)": float(
            np.mean([runs[d]["camera_pose_error_mm"] for d in depths])),
        "pixels per detector ROI (median)": float(
            np.median([runs[d]["roi_pixels_median"] for d in depths])),
        "true fields (whole-phantom FEM), per case": [
            "simulated" if runs[d]["truth"]["source"] == "simulated" else "stored"
            for d in depths],
        "simulated acquisition per case [s] (median): true fields + rendered frames": float(
            np.median([runs[d]["timings"]["forward_simulation"]
                       + runs[d]["timings"]["camera_frames"] for d in depths])),
        "processing per case [s] (median): meshing + Jacobian + NP/SP/HP": float(np.median(
            [runs[d]["timings"]["total"] - runs[d]["timings"]["forward_simulation"]
             - runs[d]["timings"]["camera_frames"] for d in depths])),
        "thesis FEM processing per case [s]": "300-600",
    })
    summary["reconstruction warnings"] = [
        f"tube {d:g} mm, {m}: {w}" for d in depths for m in methods
        for w in runs[d]["results"][m].get("warnings", [])]
    summary["speed-up vs thesis (300 s, median case)"] = 300.0 / summary[
        "processing per case [s] (median): meshing + Jacobian + NP/SP/HP"]
    ctx.metrics["tomography"] = summary
    ctx.metrics["tomography_cases"] = {
        f"{d:.1f}": {m: {k: v for k, v in runs[d]["results"][m].items() if k != "yield"}
                     for m in methods} | {"timings": runs[d]["timings"]} for d in depths}
    ctx.note("tomography", "Thesis phantom experiment (real data): mean |yield error| NP 85 %, "
             "SP 18 %, HP 16 %; centroid 1.8 % (SP), 1.2 % (HP). Here: the same pipeline on the "
             "digital cylinder-tube phantom: tracked laser and camera, rendered camera frames "
             "with shot and read noise; HP feeds the absorption of the ICG it reconstructs back "
             "into its model (docs/tomography.md).")
    _tomo_figures(ctx, runs)
    _tomo_to_scene(ctx, runs[depths[0]], ctx.state["tube_phantoms"][depths[0]])


def _tomo_to_scene(ctx, run, phantom):
    """Reconstructions as volumes on the CBCT grid (for fusion) and the mesh surface."""
    scene = ctx.state["scene"]
    tomo = module_logic("FluoTomo", scene)
    results = {m: run["results"][m] for m in ("NP", "SP", "HP")}
    tomo.storeReconstruction({"coarse": run["coarse"], "results": results},
                             (phantom.labels.shape, {"spacing": phantom.spacing_mm,
                                                     "origin": phantom.origin_mm}))
    tomo.writeReconstructionMesh(run, ctx.out / "reconstruction_mesh.vtu")
    mrml_io.save_scene(scene, ctx.out / "scene.mrml")


def stage_tomography_mc(ctx):
    """The cylinder-tube reconstructed from Monte Carlo data (stored MCX acquisitions,
    photon transport written outside the project) next to diffusion-FEM data of the
    same optodes: the honest accuracy figure (docs/validation.md)."""
    # Quick: the middle stored depth; full: all of them.  Nothing here simulates:
    # the Monte Carlo and the diffusion-FEM acquisitions are stored, each with the
    # command that regenerates it (test_tube_mc checks the FEM's against a rerun).
    res = module_logic("FluoTomo").validateTubeMonteCarlo(
        ctx.out, depths=[4.7] if ctx.quick else None, figureName="tomography_mc.png",
        progress=ctx.progress, grading=TUBE_GRADING)
    depths = [g["depth_mm"] for g in res["depths"]]
    ctx.figure("tomography_mc", Path(res["figure"]).name,
               "Tube yield and centroid errors from Monte Carlo data (solid) and from "
               "diffusion-FEM data (dashed) of the same 12 sources and 13 detectors")
    summary = {}
    for data_name in ("diffusion FEM", "Monte Carlo"):
        for m in ("NP", "SP", "HP"):
            rows = [r for r in res["rows"] if r["data"] == data_name and r["method"] == m]
            summary[f"{m} from {data_name} data: tube yield error % per depth"] = [
                round(r["yield_error_pct"], 1) for r in rows]
            summary[f"{m} from {data_name} data: centroid error % per depth"] = [
                None if r["centroid_error_pct"] is None else round(r["centroid_error_pct"], 1)
                for r in rows]
    summary["depths [mm]"] = [float(d) for d in depths]
    summary["Monte Carlo photons per run x runs per optode"] = [
        res["depths"][0]["mc"]["photons_per_run"], res["depths"][0]["mc"]["runs"]]
    summary["Monte Carlo photon noise % (median per depth)"] = [
        round(g["mc"]["photon_noise_pct"]["median"], 2) for g in res["depths"]]
    summary["diffusion FEM data (per depth)"] = [g["fem_data"] for g in res["depths"]]
    summary["reconstruction warnings"] = res["warnings"]
    ctx.metrics["tomography_mc"] = summary
    ctx.note("tomography_mc", "Both data sets carry the same 1 % Gaussian noise; the Monte "
             "Carlo data also carry their photon noise. The reconstruction (fluo tomo "
             "reconstruct's path, accuracy fast, a mesh graded by bisection, a 0.8 mm label "
             "map) is the same for both, so the difference between the rows is what the "
             "diffusion model's own error does to NP/SP/HP. Regenerate the stored Monte Carlo data: "
             + str(res["depths"][0]["mc"].get("regenerate"))
             + "; the diffusion-FEM data: " + str(res["depths"][0]["fem_regenerate"]))


def stage_camera_calibration(ctx):
    """Camera intrinsics and hand-eye from rendered board images with known truth."""
    calib = module_logic("FluoCalib", ctx.state["scene"])
    board = "chessboard:9x6:20"
    n_views = 10 if ctx.quick else 16
    data = calib.writeSyntheticBoards(ctx.out / "calibration-images", board, n_views, ctx.seed,
                                      progress=scaled(ctx.progress, 0.0, 0.6,
                                                      "rendering board views"))
    images = [str(ctx.out / "calibration-images" / n) for n in data["images"]]
    res = calib.calibrateCamera(images, board, holdout=2,
                                progress=scaled(ctx.progress, 0.6, 0.9, "intrinsics"))
    report(ctx.progress, 0.9, "hand-eye, six methods")
    cam = res.camera
    true = data["camera"]
    out = {
        "views used / held out / rejected": [len(res.used), len(res.holdout), len(res.rejected)],
        "rms reprojection [px]": res.rms_px,
        "held-out rms [px]": res.holdout_rms_px,
        "fx error %": 100 * (cam.fx - true["fx"]) / true["fx"],
        "fy error %": 100 * (cam.fy - true["fy"]) / true["fy"],
        "cx, cy error [px]": [cam.cx - true["cx"], cam.cy - true["cy"]],
    }
    # every method on the same views, graded against the true hand-eye; TSAI's is stored
    he = calib.calibrateHandEye(images, board, data["tool_to_tracker"], camera=cam,
                                boardToTracker=np.asarray(data["board_to_tracker"]),
                                methods="ALL", storeMethod="TSAI", holdout=2,
                                truthCameraToTool=data["camera_to_tool"])
    for method, r in he["methods"].items():
        out[f"hand-eye {method}: translation error [mm]"] = r["translation_error_mm"]
        out[f"hand-eye {method}: held-out 3D [mm] / 2D [px] error"] = [
            r.get("holdout_err3d_mean_mm"), r.get("holdout_err2d_mean_px")]
    mrml_io.save_scene(ctx.state["scene"], ctx.out / "scene.mrml")
    ctx.metrics["camera_calibration"] = out
    ctx.note("camera_calibration", f"{n_views} synthetic 9x6 chessboard views rendered for a "
             "known camera and tracked tool; thesis: 3D error 0.17 mm, 2D error 2.77 px "
             "(31 mm open-field lens).")


def _angle_deg(a, b):
    """Angle [deg] between two unit vectors."""
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1, 1))))


def stage_light_calibration(ctx):
    """Camera response, broad-beam illumination and laser line from synthetic
    images with known truth (docs/physics.md sections 5-7): the sets ``fluo calib
    synth-light`` writes, calibrated as ``fluo calib`` does, kept in
    OUT/light-calibration."""
    import shutil

    calib = module_logic("FluoCalib", ctx.state["scene"])
    root = ctx.out / "light-calibration"
    plots = root / "plots"
    report(ctx.progress, 0.0, "synthetic camera stack, illumination and laser images")
    sets = calib.writeSyntheticLight(root, ctx.seed, progress=scaled(ctx.progress, 0.0, 0.1))
    report(ctx.progress, 0.1, "camera response")
    rad = calib.characterizeCamera(sets["stack"], plotsFolder=plots)
    cam = rad["truth"]["camera"]
    out = {f"{k} (truth {cam[k]:g})": rad[k] for k in ("gain_adu_per_e", "dark_current_e_per_s",
                                                      "bias_e", "read_noise_e")}
    out.update({"linearity R^2": rad["linearity_r2"], "nonlinearity %": rad["nonlinearity_pct"],
                "dynamic range": rad["dynamic_range"]})
    for src, name in zip(rad["plots"], ("radiometry_ptc.png", "radiometry_linearity.png",
                                        "radiometry_dark.png")):
        shutil.copyfile(src, ctx.out / name)
    ctx.figure("light_calibration", "radiometry_ptc.png",
               "Photon-transfer curve of the synthetic camera stack (slope = gain).")
    report(ctx.progress, 0.3, "illumination images")
    il = calib.calibrateIllumination(sets["illumination"], plotsFolder=plots,
                                     progress=scaled(ctx.progress, 0.3, 0.8, "illumination cone"))
    c = il["truth"]["cone"]
    out["illumination: axis error [deg]"] = _angle_deg(il["axis"], c["axis"])
    out["illumination: half-angle [deg] (truth 35)"] = il["half_angle_deg"]
    for k in ("alpha", "gamma_per_mm", "system_gain_adu"):
        out[f"illumination: {k} error %"] = 100 * (il[k] - c[k]) / c[k]
    out["illumination: ratio mean (SD)"] = [il["ratio_mean"], il["ratio_sd"]]
    out["illumination: model"] = il["model"]
    shutil.copyfile(il["plots"][0], ctx.out / "illumination_ratio.png")
    ctx.figure("light_calibration", "illumination_ratio.png",
               "Measured / fitted cone model for the five phantom poses (endoscope light; the "
               "cone leaves the image in the nearest view).")
    report(ctx.progress, 0.8, "laser line")
    la = calib.calibrateLaser(sets["laser"])
    out["laser: direction error [deg]"] = _angle_deg(la["direction"], la["truth"]["direction"])
    out["laser: held-out 3D error [mm] / 2D [px]"] = [la["error_3d_mm"], la["error_2d_px"]]
    mrml_io.save_scene(ctx.state["scene"], ctx.out / "scene.mrml")
    ctx.metrics["light_calibration"] = out
    ctx.note("light_calibration", "Targets: gain, dark current, bias, read noise within 3 %; cone "
             "axis < 0.5 deg, half-angle < 0.2 deg, alpha/gamma/gain within 3 %, ratio 1.00 +- "
             "0.01; laser direction < 0.3 deg, 3D error < 0.5 mm (thesis 0.92 mm).")


def stage_surface_mapping(ctx):
    """Tracked views of the oral-cavity phantom (homogeneous fluorescence): per-pixel
    ray casting, optical-transport correction, 40 % contour miss rates; graded on
    frames the software did not make (analytic surface, true poses) as well as on
    its own mesh (the self-consistent figure earlier versions reported alone)."""
    from FluoNavLib.mapping.contours import overlay_png

    nav = module_logic("FluoNav")
    views = 2 if ctx.quick else 4
    mm = nav.validateSurfaceMapping(views=views, binning=4, seed=ctx.seed,
                                    figureFile=ctx.out / "mapping_mismatch.png",
                                    progress=scaled(ctx.progress, 0.0, 0.8))
    indep, indep_raw = mm["cases"]["all (CBCT intensities)"], mm["cases_unguarded"]["all (CBCT intensities)"]
    labels_g = mm["cases"]["all (label map)"]
    own = mm["cases_unguarded"]["self-consistent"]
    raw, cor = mm["view_contours"]["raw"], mm["view_contours"]["self-consistent"]
    overlay_png(ctx.out / "mapping_raw.png", raw["image"], raw["contour"],
                f"raw counts above offset, 40 % contour: miss {raw['miss_rate_pct']:.1f} %",
                raw["mask"], colorbar_label="counts above offset [ADU]")
    overlay_png(ctx.out / "mapping_corrected.png", cor["image"], cor["contour"],
                f"corrected T on its own mesh, exact poses (truth 0.3): miss "
                f"{cor['miss_rate_pct']:.1f} %", cor["mask"],
                colorbar_label="optical transport T (dimensionless)")
    report(ctx.progress, 0.8, "timing the per-pixel cast")
    cast = nav.timeSurfaceCast(62000, seed=ctx.seed, repeats=3, binnedRepeats=10, binning=10,
                               progress=scaled(ctx.progress, 0.8, 0.95,
                                               "timing the per-pixel cast"))
    ctx.metrics["surface_mapping"] = {
        "views": views, "triangles": cast["triangles"],
        "miss rate raw % (per view)": mm["miss_rate_raw_pct"],
        "self-consistent: visible pixels with transport within 5 %":
            own["within_5pct"],
        "self-consistent: miss rate corrected %": own["miss_rate_corrected_pct"],
        "independent: visible pixels within 5 %, no guard": indep_raw["within_5pct"],
        "independent: miss rate corrected %, no guard": indep_raw["miss_rate_corrected_pct"],
        "independent: visible pixels corrected (guard)": indep["accepted_fraction"],
        "independent: corrected pixels within 5 % (guard)": indep["within_5pct_of_accepted"],
        "independent: visible pixels within 5 % (guard)": indep["within_5pct"],
        "independent: miss rate corrected % (guard)": indep["miss_rate_corrected_pct"],
        "independent: mapping error median / p95 [mm]": [indep["mapping_error_mm"]["median"],
                                                         indep["mapping_error_mm"]["p95"]],
        "label-map mesh instead: visible pixels within 5 % (guard)": labels_g["within_5pct"],
        "label-map mesh instead: corrected pixels within 5 % (guard)":
            labels_g["within_5pct_of_accepted"],
        "frames/s full resolution 1392x1040 (median)": cast["frames_per_s_full"],
        "frames/s 10x binned (median)": cast["frames_per_s_binned"],
    }
    ctx.figure("surface_mapping", "mapping_raw.png",
               "Raw fluorescence of homogeneous tissue seen by the tracked camera (rendered on the "
               "phantom's analytic surface): the 40 % contour misses the cavity walls "
               "(illumination and angle).")
    ctx.figure("surface_mapping", "mapping_corrected.png",
               "Self-consistent: frames rendered on the same mesh that corrects them, with exact "
               "poses. This is what earlier versions reported; it grades the model on data it "
               "made.")
    ctx.figure("surface_mapping", "mapping_mismatch.png",
               "Independent: frames rendered on the analytic surface from the true poses, "
               "corrected with the CBCT-intensity mesh and tracked poses (tracking 0.25 mm / "
               "0.1 deg, hand-eye 0.3 mm / 0.15 deg). Without a guard, pixels at the cavity rim "
               "(normals the 0.8 mm CBCT cannot resolve) are off by up to several times and set "
               "the contour's peak; the model-error guard leaves them uncorrected (white).")
    ctx.note("surface_mapping", "Targets: transport within 5 % over >= 90 % of the corrected "
             "pixels, corrected miss rate < 5 %, >= 30 frames/s at full resolution and >= 300 "
             "binned (the cast; the full illumination model adds to it). Independent validation "
             "and the guard: docs/surface-mapping.md.")


def stage_oral_tomography(ctx):
    """The same acquisition and reconstruction on the oral cavity: a curved surface,
    beams and camera looking into the cavity, the ICG-rich tongue as the target."""

    # a run-engine task like the tube's depths (its phantom is stage_phantoms' oral
    # cavity, rebuilt from the seed); quick mode reconstructs at "fast", as the tubes do
    run, = _run_cases(ctx, "oral_tomography", module_logic("FluoTomo").tomographyCaseTasks(
        oral=True, seed=ctx.seed, oralOptions={"accuracy": "fast"} if ctx.quick else None))
    methods = ["NP", "SP", "HP"]
    out = {}
    for m in methods:
        r = run["results"][m]
        out[f"{m} tongue yield error %"] = r["tongue_yield_error_pct"]
        out[f"{m} agar yield error %"] = r["agar_yield_error_pct"]
        out[f"{m} 95 % intervals hold the truth (tongue, agar)"] = [
            r["tongue_ci95_covers_truth"], r["agar_ci95_covers_truth"]]
    out.update({"measurements": run["measurements"],
                "mean source position error from tracking [mm]": run["source_error_mm"],
                "mesh nodes forward / reconstruction": [run["mesh_nodes"]["forward"],
                                                        run["mesh_nodes"]["reconstruction"]],
                "stage times [s]": {k: round(v, 2) for k, v in run["timings"].items()}})
    out["reconstruction warnings"] = [f"{m}: {w}" for m in methods
                                      for w in run["results"][m].get("warnings", [])]
    ctx.metrics["oral_tomography"] = out

    _section_figure(ctx.out / "oral_sections.png", run["sections"],
                    sources_mm=run["sources_true_mm"])
    ctx.figure("oral_tomography", "oral_sections.png",
               "Oral cavity, section x = 0 through the tongue (the cavity is white: not tissue): "
               "truth | NP | SP | HP, same colour scale; cyan line: the true tongue; cyan dots: "
               "where the laser entered.")
    ctx.note("oral_tomography", "A bulk, optically thick target (2 ug/mL ICG: ~2 mm "
             "penetration) on a curved surface, through the same label-map path as the tube "
             "cases: the yields here are far from the tube study's, and the reconstruction "
             "warnings say why each may be off; docs/tomography.md says more.")
    return out


# stage name -> its function; the order, titles and what each stage needs from the
# others are the runner's (fluoapp/demo/run.py:STAGE_TABLE), which the CLI reads
# without importing the stages
STAGE_FUNCTIONS = {
    "phantoms": stage_phantoms,
    "camera_calibration": stage_camera_calibration,
    "light_calibration": stage_light_calibration,
    "surface_mapping": stage_surface_mapping,
    "tomography": stage_tomography,
    "tomography_mc": stage_tomography_mc,
    "oral_tomography": stage_oral_tomography,
}
