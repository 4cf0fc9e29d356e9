"""``fluo nav synth|correct`` and ``fluo bench mapping``: surface-flux mapping of
tracked fluorescence frames (docs/surface-mapping.md)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import module_logic
from fluoguide.progress import TqdmProgress, report
from fluoguide import atomic


def _synth(args):
    """Oral-cavity scene: TissueSurface, calibrations, tracked frames.  The frames
    are rendered on the phantom's analytic surface from the true poses; the scene
    holds the CBCT-derived surface, tracked poses and a hand-eye with errors."""
    from fluoguide import mrml_io

    from fluoguide.errors import check_number

    # a scene without frames is the logic's "room only" (the web app's stream); here it is
    # an empty result
    check_number("--views", args.views, 1, 64, integer=True)
    atomic.check_writable(Path(args.out) / "scene.mrml", "--out")   # before rendering
    logic = module_logic("FluoNav")
    with TqdmProgress("nav synth") as prog:
        info = logic.makeSyntheticAcquisition(views=args.views, binning=args.binning,
                                              triangles=args.triangles, transport=args.transport,
                                              trackingMm=args.tracking_mm,
                                              trackingDeg=args.tracking_deg,
                                              handEyeMm=args.hand_eye_mm,
                                              handEyeDeg=args.hand_eye_deg, progress=prog)
    path = mrml_io.save_scene(logic.scene, Path(args.out) / "scene.mrml")
    return {"scene": str(path), "frames": info["frames"], "transport_truth": args.transport,
            "triangles": info["triangles"], "image": info["image"],
            "rendered_on": info["rendered_on"], "scene_holds": info["scene_holds"],
            "tracking_sd": [args.tracking_mm, args.tracking_deg],
            "hand_eye_error": [args.hand_eye_mm, args.hand_eye_deg]}


def _factor_png(path, vm, frame, distance_mm):
    """The three factors of the illumination model in this frame's pixels, with the
    camera-to-surface distances [mm] of the lit pixels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    for ax, (name, a) in zip(axes, (("angular (cos theta)^alpha", vm.angular),
                                     ("foreshortening cos(beta)", vm.foreshortening),
                                     ("distance 1/(1+gamma d)^2", vm.distance))):
        im = ax.imshow(np.where(vm.lit, a, np.nan), cmap="viridis")
        ax.set_title(name, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, shrink=0.7, label="factor (dimensionless)")
    d = distance_mm[vm.lit] if vm.lit.any() else np.array([np.nan])
    fig.suptitle(f"frame {frame}: camera to surface {np.min(d):.0f}-{np.max(d):.0f} mm "
                 f"(median {np.median(d):.0f} mm) over the lit pixels", fontsize=10)
    atomic.save_figure(fig, path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return str(path)


def _correct(args):
    from fluoguide import mrml_io

    from FluoNavLib.mapping.contours import overlay_png

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)    # before the work, not after
    prog = TqdmProgress("nav correct")      # closed before the return (an error ends the run)
    report(prog, 0.0, "loading the scene and its surface")
    logic = module_logic("FluoNav", mrml_io.load_scene(args.scene))
    logic.correctionContext()
    # a first run compiles the ray caster here, reported, so frame_seconds is the frame's
    logic.prepareKernels(prog, 0.3)
    t1 = time.perf_counter()
    report(prog, 0.3, f"correcting frame {args.frame}")
    r = logic.correctFrame(args.frame)
    t_frame = time.perf_counter() - t1
    report(prog, 0.4, "mapping the frames onto the surface")
    mapped = logic.mapFrames(frames=None if args.all_frames else [args.frame], precomputed=[r],
                             progress=lambda f, m="": report(prog, 0.4 + 0.4 * f, m))
    report(prog, 0.8, "writing images and the scene")
    numbers = dict(r.numbers)
    out = Path(args.out)
    files = []
    if r.mapped.any():
        classes = logic.classifyContours(r)
        S = r.counts - r.offset_adu
        files += [overlay_png(out / "raw.png", S, classes["raw_contour"],
                              f"raw counts above offset, 40 % contour (miss "
                              f"{numbers['miss_rate_raw_pct']:.1f} %)", r.hits.visible),
                  overlay_png(out / "transport.png", r.transport, classes["corrected_contour"],
                              f"optical transport T, 40 % contour (miss "
                              f"{numbers['miss_rate_corrected_pct']:.1f} %)", r.mapped,
                              colorbar_label="optical transport T (dimensionless)")]
    files.append(_factor_png(out / "factors.png", r.vm, args.frame, r.hits.distance_mm))
    atomic.save_npy(out / "transport.npy", np.where(r.mapped, r.transport, np.nan))
    atomic.save_npy(out / "surface_flux_w_per_mm2.npy",
                    np.where(r.flux_valid, r.flux_w_per_mm2, np.nan))
    scene_path = mrml_io.save_scene(logic.scene, out / "scene.mrml")
    numbers.update({
        "frames_on_surface": mapped["frames_on_surface"], "frames_skipped": mapped["frames_skipped"],
        "faces_seen": mapped["faces_seen"], "faces": mapped["faces"],
        "surface_transport_median": mapped["surface_transport_median"],
        "frame_seconds": t_frame, "seconds": time.perf_counter() - t0,
        "scene": str(scene_path), "files": files + [str(out / "transport.npy"),
                                                    str(out / "surface_flux_w_per_mm2.npy")]})
    prog.close()
    return numbers


def _bench(args):
    with TqdmProgress("bench mapping") as prog:
        return module_logic("FluoNav").benchmarkMapping(args.repeats, args.binning,
                                                        progress=prog)


def register(subparsers):
    nav = cli_group(subparsers, "nav", "navigated fluorescence: surface-flux mapping of tracked frames")
    p = nav.add_parser("synth", help="synthetic oral-cavity scene with tracked frames of "
                       "homogeneous fluorescence")
    p.add_argument("--out", required=True, help="folder for scene.mrml and its data")
    p.add_argument("--views", type=int, default=4,
                   help="tracked camera views (frames) to render (default %(default)s)")
    p.add_argument("--binning", type=int, default=4,
                   help="camera pixel binning of the 1392 x 1040 sensor (default %(default)s: "
                   "348 x 260 px)")
    p.add_argument("--triangles", type=int, default=62000,
                   help="triangles of the tissue surface extracted from the CBCT "
                   "(default %(default)s)")
    p.add_argument("--transport", type=float, default=0.3,
                   help="optical transport T of the homogeneous tissue, dimensionless "
                   "(default %(default)s)")
    p.add_argument("--tracking-mm", type=float, default=0.25,
                   help="tracking error of the camera tool, SD per axis in mm (default %(default)s)")
    p.add_argument("--tracking-deg", type=float, default=0.1,
                   help="tracking error of the camera tool, SD per axis in degrees "
                   "(default %(default)s)")
    p.add_argument("--hand-eye-mm", type=float, default=0.3,
                   help="error of the stored hand-eye calibration, mm (default %(default)s)")
    p.add_argument("--hand-eye-deg", type=float, default=0.15,
                   help="error of the stored hand-eye calibration, degrees (default %(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_synth)
    p = nav.add_parser("correct", help="optical transport, surface flux and classification of one "
                       "tracked frame")
    p.add_argument("--scene", required=True,
                   help="MRML scene with TissueSurface, calibrations and tracked frames "
                   "(e.g. from nav synth)")
    p.add_argument("--frame", type=int, default=0,
                   help="index of the frame to correct, 0-based (default %(default)s)")
    p.add_argument("--out", required=True, help="folder for the PNGs, arrays and the updated scene")
    p.add_argument("--all-frames", action="store_true",
                   help="map every frame with a valid pose onto the surface (view-weighted)")
    add_json_flag(p)
    p.set_defaults(func=_correct)
    bench = cli_group(subparsers, "bench", "benchmarks: speed and accuracy together")
    p = bench.add_parser("mapping", help="per-pixel mapping speed and accuracy (full res, binned, "
                         "decimated)")
    p.add_argument("--repeats", type=int, default=5,
                   help="timed repeats; medians are printed (default %(default)s)")
    p.add_argument("--binning", type=int, default=10,
                   help="pixel binning of the binned runs (default %(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_bench)
