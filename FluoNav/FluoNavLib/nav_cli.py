"""``fluo nav synth|correct`` and ``fluo bench mapping``: surface-flux mapping of
tracked fluorescence frames (docs/surface-mapping.md)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoguide.cli import add_json_flag, cli_group
from fluoguide.errors import FluoInputError


def _synth(args):
    """Oral-cavity scene: TissueSurface, calibrations, tracked frames."""
    from fluoguide import mrml_io
    from FluoCalibLib import light_scene
    from FluoCalibLib.geometry_scene import store_intrinsics
    from FluoCalibLib.radiometric_model import RadiometricCamera

    from . import frame_store
    from .nav_synth import coupled_light, open_field_camera, oral_cavity_surface, render_view, view_poses

    caster, poly = oral_cavity_surface(args.triangles)
    cam = open_field_camera(args.binning)
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
    for k, pose in enumerate(view_poses(args.views)):
        counts, _, _ = render_view(caster, cam, pose, cone, args.transport, rc, seed=k)
        frame_store.append_tracked_frame(scene, counts.astype(np.uint16), 1.0 + k / 10,
                                         {"CameraToolToTracker": pose}, exposure_s=rc.exposure_s)
    path = mrml_io.save_scene(scene, Path(args.out) / "scene.mrml")
    return {"scene": str(path), "frames": args.views, "transport_truth": args.transport,
            "triangles": caster.n_faces, "image": [cam.width, cam.height]}


def _correct(args):
    from fluoguide import mrml_io
    from FluoCalibLib import light_scene
    from FluoCalibLib.geometry_scene import load_intrinsics
    from FluoCalibLib.illumination_model import IlluminationCone
    from FluoCalibLib.radiometric_model import RadiometricCamera

    from . import frame_store
    from .contour_classify import miss_rate, overlay_png
    from .flux_map import surface_flux, transport_image, view_model
    from .pixel_cast import SurfaceCaster, cast_camera

    t0 = time.perf_counter()
    scene = mrml_io.load_scene(args.scene)
    img, info, poses = frame_store.read_tracked_frame(scene, args.frame)
    tool = poses.get("CameraToolToTracker")
    if tool is None or not info.get("pose_valid", True):
        raise FluoInputError("frame has no valid camera pose: not mapped", field="frame",
                             value=args.frame)
    cam = load_intrinsics(scene)
    if (cam.width, cam.height) != (img.shape[1], img.shape[0]):
        raise FluoInputError("frame size differs from the camera intrinsics", field="frame",
                             value=(img.shape, cam.width, cam.height))
    il = light_scene.load_calibration(scene, light_scene.ILLUMINATION_KEY)
    rad = light_scene.load_calibration(scene, light_scene.RADIOMETRY_KEY)
    if not il or "cone" not in il:
        raise FluoInputError("scene has no illumination calibration", field="FluoCalib.Illumination")
    cone = IlluminationCone.from_dict(il["cone"])
    rc = RadiometricCamera.from_dict((rad or {}).get("camera", {}))
    world = mrml_io.get_transform(scene, "TrackerToReference") @ tool @ \
        mrml_io.get_transform(scene, "CameraToTracker")
    model = mrml_io.get_node(scene, "TissueSurface", "vtkMRMLModelNode")
    caster = SurfaceCaster.from_polydata(model.GetPolyData())
    t_cast = time.perf_counter()
    hits = cast_camera(caster, cam, world)
    vm = view_model(hits, cone, world)
    t_cast = time.perf_counter() - t_cast
    S = img.astype(float) - rc.offset_adu
    _, valid, saturated, _ = rc.radiance_from_counts(img.astype(float), min_snr=3.0)
    T, ok = transport_image(S, vm, cone, valid=valid)
    J, jvalid = surface_flux(img.astype(float), rc)
    raw_rate, raw_contour, _ = miss_rate(S, hits.visible & valid)
    cor_rate, cor_contour, _ = miss_rate(T, ok)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    files = [overlay_png(out / "raw.png", S, raw_contour, f"raw counts, 40 % contour (miss {raw_rate:.1f} %)",
                         hits.visible),
             overlay_png(out / "transport.png", T, cor_contour,
                         f"optical transport T, 40 % contour (miss {cor_rate:.1f} %)", ok)]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, (name, a) in zip(axes, (("angular", vm.angular), ("foreshortening cos(beta)", vm.foreshortening),
                                     ("distance 1/(1+gamma d)^2", vm.distance))):
        im = ax.imshow(np.where(vm.lit, a, np.nan), cmap="viridis")
        ax.set_title(name, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, shrink=0.7)
    fig.savefig(out / "factors.png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    files.append(str(out / "factors.png"))
    np.save(out / "transport.npy", np.where(ok, T, np.nan))
    np.save(out / "surface_flux_w_per_mm2.npy", np.where(jvalid, J, np.nan))
    return {"frame": int(args.frame), "pixels": int(img.size), "visible": int(hits.visible.sum()),
            "mapped": int(ok.sum()), "saturated": int(saturated.sum()),
            "transport_median": float(np.median(T[ok])) if ok.any() else None,
            "transport_iqr": [float(np.percentile(T[ok], 25)), float(np.percentile(T[ok], 75))] if ok.any() else None,
            "surface_flux_median_w_per_mm2": float(np.median(J[jvalid & hits.visible])) if (jvalid & hits.visible).any() else None,
            "miss_rate_raw_pct": raw_rate, "miss_rate_corrected_pct": cor_rate,
            "cast_seconds": t_cast, "seconds": time.perf_counter() - t0, "files": files}


def _bench(args):
    from .mapping_bench import run_mapping_benchmark

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
    p.add_argument("--out", required=True)
    add_json_flag(p)
    p.set_defaults(func=_correct)
    bench = cli_group(subparsers, "bench", "benchmarks printed as JSON")
    p = bench.add_parser("mapping", help="per-pixel mapping speed and accuracy (full res, binned, "
                         "decimated)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--binning", type=int, default=10)
    add_json_flag(p)
    p.set_defaults(func=_bench)
