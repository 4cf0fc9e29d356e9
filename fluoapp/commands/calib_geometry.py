"""``fluo calib camera | handeye | register | pivot | synth-boards``: geometric calibration CLI."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from fluoapp.cli import add_json_flag, cli_group
from fluoguide.errors import FluoInputError

__all__ = ["register"]


def _images(pattern):
    files = sorted(glob.glob(pattern))
    if not files:
        raise FluoInputError("no files match", field="--images", value=pattern)
    return files


def _load_json(path, field, expect=None):
    from fluoguide.jsonable import read_json

    return read_json(path, expect=expect, field=field)


def _load_points(path, field):
    """(N, 3) points [mm] from JSON (list or {"points": list}) or CSV/TXT."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        doc = _load_json(p, field)
        doc = doc.get("points", doc) if isinstance(doc, dict) else doc
        try:
            arr = np.asarray(doc, dtype=float)
        except (TypeError, ValueError):
            raise FluoInputError('expected a list of [x, y, z] or {"points": [...]}', file=p,
                                 field=field) from None
    else:
        if not p.is_file():
            raise FluoInputError("file not found", file=p, field=field)
        try:
            arr = np.loadtxt(p, delimiter="," if p.suffix.lower() == ".csv" else None, ndmin=2)
        except (ValueError, UnicodeDecodeError) as exc:
            raise FluoInputError(f"cannot parse points ({str(exc)[:100]})", file=p,
                                 field=field) from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FluoInputError("points must be N rows of x, y, z [mm]", file=p, field=field,
                             value=arr.shape)
    return arr


def _preflight(args):
    """Check every output before any work (a refused run writes nothing); returns
    the scene to store the result in, or None."""
    from fluoguide import atomic, mrml_io

    if getattr(args, "yaml", None):
        atomic.check_writable(args.yaml, "--yaml")
    if getattr(args, "scene", None):
        return mrml_io.scene_to_update(args.scene)
    return None


def _store(args, scene, camera=None, camera_to_tool=None, info=None, rms=None, registration=None):
    if getattr(args, "yaml", None) and (camera is not None or camera_to_tool is not None):
        from FluoCalibLib.geometry.opencv_yaml import write_calibration_yaml

        write_calibration_yaml(args.yaml, camera, camera_to_tool, rms_px=rms)
    if scene is not None:
        from fluoguide import mrml_io

        from FluoCalibLib.geometry import scene as gs

        path = Path(args.scene)
        if camera is not None:
            gs.store_intrinsics(scene, camera, {"rms_px": rms})
        if camera_to_tool is not None:
            gs.store_handeye(scene, camera_to_tool, info)
        if registration is not None:
            gs.store_registration(scene, registration, info)
        mrml_io.save_scene(scene, path)


def _camera(args):
    from fluoguide.progress import TqdmProgress

    from FluoCalibLib.geometry.intrinsics import calibrate_camera

    scene = _preflight(args)
    with TqdmProgress("calib camera") as prog:
        res = calibrate_camera(_images(args.images), args.board,
                               "fisheye" if args.fisheye else "pinhole", args.holdout,
                               fix_k3=args.fix_k3, reject_outliers=not args.keep_outliers,
                               progress=prog)
    _store(args, scene, camera=res.camera, rms=res.rms_px)
    return res.to_dict()


def _intrinsics_from(args, images):
    if args.intrinsics:
        p = Path(args.intrinsics)
        if p.suffix.lower() in (".yaml", ".yml", ".xml"):
            from FluoCalibLib.geometry.opencv_yaml import read_calibration_yaml

            cam = read_calibration_yaml(p)["camera"]
            if cam is None:
                raise FluoInputError("no camera_matrix in file", file=p, field="--intrinsics")
            return cam
        from FluoCalibLib.geometry.camera_model import CameraModel

        doc = _load_json(p, "--intrinsics", expect=dict)
        return CameraModel.from_dict(doc.get("camera", doc))
    from FluoCalibLib.geometry.intrinsics import calibrate_camera

    return calibrate_camera(images, args.board).camera


def _handeye(args):
    from FluoCalibLib.geometry import handeye as he
    from FluoCalibLib.geometry.boards import parse_board
    from FluoCalibLib.geometry.intrinsics import detect_views, view_poses

    scene = _preflight(args)
    board = parse_board(args.board)
    images = _images(args.images)
    from FluoCalibLib.geometry.transforms import as_rigid, as_rigid_list

    doc = _load_json(args.poses, "--poses")
    if not isinstance(doc, dict) or "tool_to_tracker" not in doc:
        raise FluoInputError('poses file needs a "tool_to_tracker" list of 4x4 matrices',
                             file=args.poses, field="tool_to_tracker")
    poses = as_rigid_list(doc["tool_to_tracker"], "tool_to_tracker", file=args.poses)
    if len(poses) != len(images):
        raise FluoInputError(f"{len(images)} images but {len(poses)} tool poses: each image "
                             "needs one synchronised pose", file=args.poses,
                             field="tool_to_tracker", value=(len(images), len(poses)))
    camera = _intrinsics_from(args, images)
    views, _ = detect_views(images, board)
    keep = [i for i, v in enumerate(views) if v.status == "used"]
    rejected = [{"name": v.name, "reason": v.reason} for v in views if v.status != "used"]
    views = view_poses(camera, board, [views[i] for i in keep])
    poses = [poses[i] for i in keep]
    if args.board_to_tracker:
        g = _load_json(args.board_to_tracker, "--board-to-tracker")
        G = as_rigid(g.get("board_to_tracker", g) if isinstance(g, dict) else g,
                     "board_to_tracker", file=args.board_to_tracker)
    elif "board_to_tracker" in doc:
        G = as_rigid(doc["board_to_tracker"], "board_to_tracker", file=args.poses)
    else:
        G = None
    B = [v.board_to_camera for v in views]
    methods = he.METHODS if args.method.upper() == "ALL" else (args.method.upper(),)
    if G is None:
        # no grid registration: estimate it from the first method's solution
        X0 = he.solve_handeye(B, poses, "TSAI")
        G = he.estimate_board_to_tracker(B, poses, X0)
    truth = doc.get("camera_to_tool")
    cmp = he.compare_methods(camera, board, B, poses, [(v.ids, v.image_points) for v in views],
                             G, methods, truth_camera_to_tool=truth, holdout=args.holdout)
    best = methods[0] if len(methods) == 1 else args.store_method.upper()
    if best not in cmp:
        raise FluoInputError("stored method was not run", field="--store-method", value=best)
    X = cmp[best]["camera_to_tool"]
    info = {"method": best, **{k: v for k, v in cmp[best].items() if k != "camera_to_tool"}}
    _store(args, scene, camera_to_tool=X, info=info)
    return {"camera_to_tool": X, "method": best, "views_used": [v.name for v in views],
            "views_rejected": rejected, "methods": cmp}


def _register(args):
    from FluoCalibLib.geometry.registration import register_points, target_registration_error

    scene = _preflight(args)
    moving = _load_points(args.moving, "--moving")
    fixed = _load_points(args.fixed, "--fixed")
    res = register_points(moving, fixed)
    out = {"transform": res.transform, "fre_mm": res.fre_mm, "residuals_mm": res.residuals_mm}
    if args.targets_moving or args.targets_fixed:
        if not (args.targets_moving and args.targets_fixed):
            raise FluoInputError("give both --targets-moving and --targets-fixed",
                                 field="--targets-fixed")
        tre = target_registration_error(res.transform,
                                        _load_points(args.targets_moving, "--targets-moving"),
                                        _load_points(args.targets_fixed, "--targets-fixed"))
        out["tre_mm"] = tre
        out["tre_mean_mm"] = float(tre.mean())
    info = {k: v for k, v in out.items() if k in ("fre_mm", "tre_mean_mm")}
    _store(args, scene, registration=res.transform, info=info)
    return out


def _pivot(args):
    from FluoCalibLib.geometry.registration import pivot_calibration

    from FluoCalibLib.geometry.transforms import as_rigid_list

    doc = _load_json(args.poses, "--poses")
    poses = doc.get("tool_to_tracker", doc) if isinstance(doc, dict) else doc
    return pivot_calibration(as_rigid_list(poses, "tool_to_tracker", file=args.poses))


def _synth(args):
    from fluoguide.progress import TqdmProgress

    from FluoCalibLib.geometry.camera_model import CameraModel
    from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

    cam = default_camera(args.width, args.height)
    if args.fisheye:
        cam = CameraModel(cam.fx * 0.7, cam.fy * 0.7, cam.cx, cam.cy,
                          (0.03, -0.01, 0.002, -0.0005), cam.width, cam.height, "fisheye")
    with TqdmProgress("synth boards") as prog:
        ds = make_dataset(args.out, cam, args.board, args.views, args.seed,
                          blur_sigma_px=args.blur, noise_sigma=args.noise,
                          tracker_noise_mm=args.tracker_noise_mm, motion=args.motion,
                          progress=prog)
    return {"out": str(args.out), "images": ds["images"],
            "truth": str(Path(args.out) / "truth.json"),
            "camera": ds["camera"], "camera_to_tool": ds["camera_to_tool"]}


def register(subparsers):
    sub = cli_group(subparsers, "calib", "camera and laser calibration")

    p = sub.add_parser("camera", help="intrinsic calibration from board images")
    p.add_argument("--images", required=True, help="glob of board images, e.g. 'cal/*.png'")
    p.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE_MM or charuco:COLSxROWS:SQ:MARKER:DICT")
    p.add_argument("--fisheye", action="store_true", help="fisheye (wide-angle) lens model")
    p.add_argument("--holdout", type=int, default=0, help="views held out for validation")
    p.add_argument("--fix-k3", action="store_true", help="hold k3 at 0")
    p.add_argument("--keep-outliers", action="store_true",
                   help="do not reject views with RMS > max(1 px, 3 x median)")
    p.add_argument("--yaml", help="write OpenCV YAML here")
    p.add_argument("--scene", help="store in this MRML scene (created if missing)")
    add_json_flag(p)
    p.set_defaults(func=_camera)

    p = sub.add_parser("handeye", help="hand-eye calibration (camera to tracked tool)")
    p.add_argument("--images", required=True)
    p.add_argument("--board", required=True)
    p.add_argument("--poses", required=True,
                   help='JSON with "tool_to_tracker": one 4x4 per image (sorted by name); '
                        'optional "board_to_tracker"')
    p.add_argument("--intrinsics", help="YAML or JSON intrinsics (default: calibrate here)")
    p.add_argument("--board-to-tracker", help="JSON 4x4 grid registration")
    p.add_argument("--method", default="ALL", help="ALL or one of TSAI, PARK, HORAUD, ANDREFF, "
                   "DANIILIDIS, PAIRED_POINT")
    p.add_argument("--store-method", default="PAIRED_POINT", help="method whose result is stored")
    p.add_argument("--holdout", type=int, default=0,
                   help="views left out of the fit, errors reported separately")
    p.add_argument("--yaml")
    p.add_argument("--scene")
    add_json_flag(p)
    p.set_defaults(func=_handeye)

    p = sub.add_parser("register", help="paired-point rigid registration with FRE/TRE")
    p.add_argument("--moving", required=True, help="points in the moving frame (tracker)")
    p.add_argument("--fixed", required=True, help="the same points in the fixed frame (CBCT)")
    p.add_argument("--targets-moving")
    p.add_argument("--targets-fixed")
    p.add_argument("--scene")
    add_json_flag(p)
    p.set_defaults(func=_register)

    p = sub.add_parser("pivot", help="pivot calibration of a tracked pointer")
    p.add_argument("--poses", required=True, help='JSON list of 4x4 (or {"tool_to_tracker": ...})')
    add_json_flag(p)
    p.set_defaults(func=_pivot)

    p = sub.add_parser("synth-boards", help="render synthetic board images with known truth")
    p.add_argument("--out", required=True)
    p.add_argument("--board", default="chessboard:9x6:20")
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--fisheye", action="store_true")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise SD [grey levels]")
    p.add_argument("--blur", type=float, default=0.6, help="blur SD [px]")
    p.add_argument("--tracker-noise-mm", type=float, default=0.1)
    p.add_argument("--motion", default="general", choices=("general", "translation", "parallel"))
    add_json_flag(p)
    p.set_defaults(func=_synth)
