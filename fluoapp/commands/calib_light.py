"""``fluo calib radiometry|illumination|laser|synth-light``: radiometric
calibrations from image stacks and images (synthetic sets with known truth
from ``synth-light``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag, cli_group
from fluoguide.errors import FluoInputError


def _doc(folder, name):
    from fluoguide.jsonable import read_json

    p = Path(folder) / name
    if not Path(folder).is_dir():
        raise FluoInputError("folder not found", file=folder)
    if not p.is_file():
        raise FluoInputError(f"folder needs {name}", file=p)
    return read_json(p)


def _images(folder, doc, name):
    from FluoCalibLib.radiometry.camera_response import _read_image
    from fluoguide.paths import inside

    manifest = Path(folder) / name
    if not isinstance(doc.get("images"), list) or not doc["images"]:
        raise FluoInputError("needs a non-empty 'images' list", file=manifest, field="images")
    # a manifest names files in its own folder, never ../ or absolute paths
    return [_read_image(inside(folder, f, file=manifest, field=f"images[{i}]")).astype(float)
            for i, f in enumerate(doc["images"])]


def _preflight(args):
    """Check every output before any work: a refused run writes nothing.

    Returns the scene to store the result in (loaded, or new) or None.
    """
    from fluoguide import atomic, mrml_io
    from fluoguide.jsonable import read_json

    if getattr(args, "out", None):
        atomic.check_writable(args.out, "--out", folder=True)
    if getattr(args, "calibration", None):
        atomic.check_writable(args.calibration, "--calibration")
        if Path(args.calibration).exists():
            read_json(args.calibration, field="--calibration")   # never overwrite a damaged one
    if getattr(args, "scene", None):
        return mrml_io.scene_to_update(args.scene)
    return None


def _save(args, key, doc, scene=None):
    from FluoCalibLib.radiometry import scene as light_scene

    if getattr(args, "calibration", None):
        light_scene.write_calibration_json(args.calibration, key, doc)
    if getattr(args, "scene", None):
        from fluoguide import mrml_io

        light_scene.store_calibration(scene, key, doc)
        mrml_io.save_scene(scene, Path(args.scene))


def _radiometry(args):
    from FluoCalibLib.radiometry.camera_response import characterize, load_stack
    from FluoCalibLib.radiometry.scene import RADIOMETRY_KEY

    scene = _preflight(args)
    frames, meta = load_stack(args.stack)
    res = characterize(frames, bit_depth=args.bits)
    if args.out:
        from FluoCalibLib.radiometry.plots import plot_radiometry

        res["plots"] = plot_radiometry(res, args.out)
    keep = {k: v for k, v in res.items() if k not in ("ptc", "linearity", "dark")}
    _save(args, RADIOMETRY_KEY, keep, scene)
    if "truth" in meta:
        res["truth"] = meta["truth"]
    return {k: v for k, v in res.items() if k not in ("ptc", "linearity", "dark")} | (
        {"curves": {k: res[k] for k in ("ptc", "linearity", "dark")}} if args.curves else {})


def _illumination(args):
    from FluoCalibLib.geometry.camera_model import CameraModel
    from FluoCalibLib.radiometry.illumination_fit import calibrate_illumination
    from FluoCalibLib.radiometry.scene import ILLUMINATION_KEY

    scene = _preflight(args)
    doc = _doc(args.folder, "illumination.json")
    for k in ("camera", "phantom_to_camera", "rd"):
        if k not in doc:
            raise FluoInputError("missing key", file=Path(args.folder) / "illumination.json", field=k)
    images = _images(args.folder, doc, "illumination.json")
    res = calibrate_illumination(images, CameraModel.from_dict(doc["camera"]),
                                 [np.asarray(T, float) for T in doc["phantom_to_camera"]],
                                 float(doc["rd"]), float(doc.get("offset_adu", 0.0)),
                                 try_asymmetric=not args.axisymmetric,
                                 saturation_adu=float(doc.get("saturation_adu", 16383.0)))
    ratios = res.pop("ratio_images")
    cone = res.pop("cone")
    res["cone"] = cone.to_dict()
    if args.out:
        from FluoCalibLib.radiometry.plots import plot_ratio_images

        res["plots"] = plot_ratio_images(ratios, args.out)
    _save(args, ILLUMINATION_KEY, res, scene)
    if "truth" in doc:
        res["truth"] = doc["truth"]
    return res


def _laser(args):
    from FluoCalibLib.geometry.camera_model import CameraModel
    from FluoCalibLib.radiometry.laser_line import calibrate_laser
    from FluoCalibLib.radiometry.scene import LASER_KEY

    scene = _preflight(args)
    doc = _doc(args.folder, "laser.json")
    for k in ("camera", "camera_to_tracker", "laser_to_tracker", "phantom_to_tracker"):
        if k not in doc:
            raise FluoInputError("missing key", file=Path(args.folder) / "laser.json", field=k)
    images = _images(args.folder, doc, "laser.json")
    res = calibrate_laser(images, CameraModel.from_dict(doc["camera"]), doc["camera_to_tracker"],
                          doc["laser_to_tracker"], doc["phantom_to_tracker"],
                          doc.get("pointer_origin_tool_mm"), holdout=args.holdout)
    _save(args, LASER_KEY, {k: v for k, v in res.items() if k != "spots_px"}, scene)
    if "truth" in doc:
        res["truth"] = doc["truth"]
    return res


def _synth(args):
    from FluoCalibLib.radiometry.camera_response import write_stack
    from FluoCalibLib.radiometry.synthetic import (
        synthetic_illumination,
        synthetic_laser,
        synthetic_lens_spectral_frames,
        synthetic_stack,
        write_illumination_set,
        write_laser_set,
    )

    from fluoguide import atomic

    out = Path(args.out)
    atomic.check_writable(out, "--out", folder=True)   # three sets: refuse before the first
    frames, truth = synthetic_stack(seed=args.seed)
    # plus frames at several f-numbers and wavelengths (same default camera)
    extra, t_extra = synthetic_lens_spectral_frames(
        radiance_w_per_mm2_sr=truth["radiance_w_per_mm2_sr"], seed=args.seed + 1)
    frames = frames + extra
    write_stack(out / "stack", frames, {"truth": {**truth, **t_extra}})
    imgs, t_il = synthetic_illumination(seed=args.seed)
    write_illumination_set(out / "illumination", imgs, t_il)
    limgs, t_la = synthetic_laser(seed=args.seed)
    write_laser_set(out / "laser", limgs, t_la)
    return {"stack": str(out / "stack"), "illumination": str(out / "illumination"),
            "laser": str(out / "laser"), "frames": len(frames), "illumination_images": len(imgs),
            "laser_images": len(limgs)}


def _common(p):
    p.add_argument("--scene", help="MRML scene to store the result in (created if missing)")
    p.add_argument("--calibration", help="calibration JSON file to merge the result into")
    add_json_flag(p)


def register(subparsers):
    calib = cli_group(subparsers, "calib", "camera, hand-eye, radiometric and light calibrations")
    p = calib.add_parser("radiometry", help="camera response (gain, dark current, bias, read "
                         "noise, linearity) from an image stack (EMVA 1288 style)")
    p.add_argument("stack", help="folder with stack.json and the frames")
    p.add_argument("--bits", type=int, default=14, help="A/D bit depth")
    p.add_argument("--out", help="folder for PNG plots")
    p.add_argument("--curves", action="store_true", help="include the curves in the JSON")
    _common(p)
    p.set_defaults(func=_radiometry)
    p = calib.add_parser("illumination", help="broad-beam cone (origin, axis, half-angle, alpha, "
                         "gamma, system gain) from flat-phantom images")
    p.add_argument("folder", help="folder with illumination.json and the images")
    p.add_argument("--axisymmetric", action="store_true",
                   help="do not try the crescent (non-axisymmetric) term")
    p.add_argument("--out", help="folder for the ratio-image PNG")
    _common(p)
    p.set_defaults(func=_illumination)
    p = calib.add_parser("laser", help="laser beam line in laser-tool coordinates from spot images")
    p.add_argument("folder", help="folder with laser.json and the images")
    p.add_argument("--holdout", type=int, default=4, help="images kept out of the fit for accuracy")
    _common(p)
    p.set_defaults(func=_laser)
    p = calib.add_parser("synth-light", help="synthetic stack, illumination and laser data sets "
                         "with known truth")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0)
    add_json_flag(p)
    p.set_defaults(func=_synth)
