"""``fluo nav synth|correct`` and ``fluo bench mapping``: surface-flux mapping of
tracked fluorescence frames (docs/surface-mapping.md)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag, cli_group
from fluoguide import atomic
from fluoguide.errors import FluoInputError


def _synth(args):
    """Oral-cavity scene: TissueSurface, calibrations, tracked frames."""
    from fluoguide import mrml_io
    from FluoCalibLib.radiometry import scene as light_scene
    from FluoCalibLib.geometry.scene import store_intrinsics
    from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

    from FluoNavLib.devices import frame_store
    from FluoNavLib.mapping.synthetic import (
        coupled_light,
        open_field_camera,
        oral_cavity_surface,
        render_view,
        view_poses,
    )

    atomic.check_writable(Path(args.out) / "scene.mrml", "--out")   # before rendering
    cam = open_field_camera(args.binning)       # the cheap checks before the surface
    poses = view_poses(args.views)
    caster, poly = oral_cavity_surface(args.triangles)
    cone = coupled_light()
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    scene = mrml_io.new_scene()
    mrml_io.add_model(scene, "TissueSurface", poly)
    store_intrinsics(scene, cam, {"rms_px": 0.0})
    light_scene.store_calibration(scene, light_scene.ILLUMINATION_KEY, {"cone": cone.to_dict()})
    light_scene.store_calibration(scene, light_scene.RADIOMETRY_KEY, {"camera": rc.to_dict()})
    mrml_io.set_transform(scene, "TrackerToReference", np.eye(4))
    mrml_io.set_transform(scene, "CameraToTracker", np.eye(4))   # hand-eye: camera = tool frame
    frame_store.new_recording(scene)
    for k, pose in enumerate(poses):
        counts, _, _ = render_view(caster, cam, pose, cone, args.transport, rc, seed=k)
        frame_store.append_tracked_frame(scene, counts.astype(np.uint16), 1.0 + k / 10,
                                         {"CameraToolToTracker": pose}, exposure_s=rc.exposure_s)
    path = mrml_io.save_scene(scene, Path(args.out) / "scene.mrml")
    return {"scene": str(path), "frames": args.views, "transport_truth": args.transport,
            "triangles": caster.n_faces, "image": [cam.width, cam.height]}


def _factor_png(path, vm):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, (name, a) in zip(axes, (("angular (cos theta)^alpha", vm.angular),
                                     ("foreshortening cos(beta)", vm.foreshortening),
                                     ("distance 1/(1+gamma d)^2", vm.distance))):
        im = ax.imshow(np.where(vm.lit, a, np.nan), cmap="viridis")
        ax.set_title(name, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, shrink=0.7)
    atomic.save_figure(fig, path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return str(path)


def _correct(args):
    from fluoguide import mrml_io

    from FluoNavLib.devices import frame_store
    from FluoNavLib.mapping.contours import miss_rate, overlay_png
    from FluoNavLib.mapping.scene import write_frame_images, write_surface_flux
    from FluoNavLib.mapping.correct import correct_frame, load_context, map_frames_to_surface

    t0 = time.perf_counter()
    atomic.check_writable(args.out, "--out", folder=True)    # before the work, not after
    scene = mrml_io.load_scene(args.scene)
    ctx = load_context(scene)
    t1 = time.perf_counter()
    r = correct_frame(scene, ctx, args.frame)
    t_frame = time.perf_counter() - t1
    results = [r]
    skipped = []
    if args.all_frames:
        for n in range(frame_store.number_of_frames(scene)):
            if n == args.frame:
                continue
            try:
                results.append(correct_frame(scene, ctx, n))
            except FluoInputError as exc:          # no valid pose: not mapped, say so
                skipped.append({"frame": n, "reason": exc.problem})
    T_face, J_face, w_face, views = map_frames_to_surface(ctx, results)
    write_surface_flux(scene, ctx.polydata, T_face, J_face, w_face, views)
    S = r.counts - ctx.radiometric.offset_adu
    numbers = dict(r.numbers)
    write_frame_images(scene, r.transport, r.mapped, S, numbers)
    out = Path(args.out)
    files = []
    if r.mapped.any():
        _, raw_contour, _ = miss_rate(S, r.hits.visible & r.flux_valid)
        _, cor_contour, _ = miss_rate(r.transport, r.mapped)
        files += [overlay_png(out / "raw.png", S, raw_contour,
                              f"raw counts above offset, 40 % contour (miss "
                              f"{numbers['miss_rate_raw_pct']:.1f} %)", r.hits.visible),
                  overlay_png(out / "transport.png", r.transport, cor_contour,
                              f"optical transport T, 40 % contour (miss "
                              f"{numbers['miss_rate_corrected_pct']:.1f} %)", r.mapped)]
    files.append(_factor_png(out / "factors.png", r.vm))
    atomic.save_npy(out / "transport.npy", np.where(r.mapped, r.transport, np.nan))
    atomic.save_npy(out / "surface_flux_w_per_mm2.npy",
                    np.where(r.flux_valid, r.flux_w_per_mm2, np.nan))
    scene_path = mrml_io.save_scene(scene, out / "scene.mrml")
    seen = w_face > 0
    numbers.update({
        "frames_on_surface": [x.frame for x in results], "frames_skipped": skipped,
        "faces_seen": int(seen.sum()), "faces": int(len(w_face)),
        "surface_transport_median": float(np.median(T_face[seen])) if seen.any() else None,
        "frame_seconds": t_frame, "seconds": time.perf_counter() - t0,
        "scene": str(scene_path), "files": files + [str(out / "transport.npy"),
                                                    str(out / "surface_flux_w_per_mm2.npy")]})
    return numbers


def _bench(args):
    from FluoNavLib.mapping.benchmark import run_mapping_benchmark

    return run_mapping_benchmark(args.repeats, args.binning)


def register(subparsers):
    nav = cli_group(subparsers, "nav", "navigated fluorescence: surface-flux mapping of tracked frames")
    p = nav.add_parser("synth", help="synthetic oral-cavity scene with tracked frames of "
                       "homogeneous fluorescence")
    p.add_argument("--out", required=True)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--binning", type=int, default=4)
    p.add_argument("--triangles", type=int, default=62000)
    p.add_argument("--transport", type=float, default=0.3)
    add_json_flag(p)
    p.set_defaults(func=_synth)
    p = nav.add_parser("correct", help="optical transport, surface flux and classification of one "
                       "tracked frame")
    p.add_argument("--scene", required=True)
    p.add_argument("--frame", type=int, default=0)
    p.add_argument("--out", required=True, help="folder for the PNGs, arrays and the updated scene")
    p.add_argument("--all-frames", action="store_true",
                   help="map every frame with a valid pose onto the surface (view-weighted)")
    add_json_flag(p)
    p.set_defaults(func=_correct)
    bench = cli_group(subparsers, "bench", "benchmarks printed as JSON")
    p = bench.add_parser("mapping", help="per-pixel mapping speed and accuracy (full res, binned, "
                         "decimated)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--binning", type=int, default=10)
    add_json_flag(p)
    p.set_defaults(func=_bench)
