"""``fluo calib camera | handeye | register | pivot | synth-boards``: geometric calibration CLI."""

from __future__ import annotations

from pathlib import Path

from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import module_logic, save_scene_to, scene_for
from fluoguide.errors import FluoInputError
# readers of the calibration inputs (image globs, poses, intrinsics, matrices, points)
from FluoCalibLib.geometry.files import (image_files, read_handeye_poses, read_intrinsics,
                                         read_matrix, read_points)

__all__ = ["register"]


def _calib(args):
    """The FluoCalib logic over the ``--scene`` scene (or a new one), after every
    output was checked: a refused run writes nothing."""
    from fluoguide import atomic

    if getattr(args, "yaml", None):
        atomic.check_writable(args.yaml, "--yaml")
    return module_logic("FluoCalib", scene_for(getattr(args, "scene", None)))


def _yaml(args, camera=None, camera_to_tool=None, rms=None):
    if getattr(args, "yaml", None) and (camera is not None or camera_to_tool is not None):
        module_logic("FluoCalib").writeCalibrationYaml(args.yaml, camera, camera_to_tool, rms)


def _camera(args):
    from fluoguide.progress import TqdmProgress

    logic = _calib(args)
    with TqdmProgress("calib camera") as prog:
        res = logic.calibrateCamera(image_files(args.images), args.board,
                                    "fisheye" if args.fisheye else "pinhole", args.holdout,
                                    fixK3=args.fix_k3, rejectOutliers=not args.keep_outliers,
                                    progress=prog)
    _yaml(args, camera=res.camera, rms=res.rms_px)
    save_scene_to(logic.scene, args.scene)
    return res.to_dict()


def _handeye(args):
    from fluoguide.progress import TqdmProgress

    images = image_files(args.images)
    doc = read_handeye_poses(args.poses)
    camera = read_intrinsics(args.intrinsics) if args.intrinsics else None
    if args.board_to_tracker:
        G = read_matrix(args.board_to_tracker, "--board-to-tracker", key="board_to_tracker")
    else:
        G = doc["board_to_tracker"]
    logic = _calib(args)
    with TqdmProgress("calib handeye") as prog:
        out = logic.calibrateHandEye(images, args.board, doc["tool_to_tracker"], camera=camera,
                                     boardToTracker=G, methods=args.method,
                                     storeMethod=args.store_method, holdout=args.holdout,
                                     truthCameraToTool=doc["camera_to_tool"], progress=prog)
    _yaml(args, camera_to_tool=out["camera_to_tool"])
    save_scene_to(logic.scene, args.scene)
    return {k: v for k, v in out.items() if k != "transform_node_id"}


def _register(args):
    moving = read_points(args.moving, "--moving")
    fixed = read_points(args.fixed, "--fixed")
    tm = read_points(args.targets_moving, "--targets-moving") if args.targets_moving else None
    tf_ = read_points(args.targets_fixed, "--targets-fixed") if args.targets_fixed else None
    logic = _calib(args)
    out = logic.registerTrackerToReference(moving, fixed, tm, tf_)
    save_scene_to(logic.scene, args.scene)
    return out


def _pivot(args):
    from fluoguide.jsonable import read_json

    doc = read_json(args.poses, expect=None, field="--poses")
    poses = doc.get("tool_to_tracker", doc) if isinstance(doc, dict) else doc
    if not isinstance(poses, list):
        raise FluoInputError("poses must be a list of 4x4 matrices", file=args.poses,
                             field="tool_to_tracker")
    try:
        return module_logic("FluoCalib").pivotCalibration(poses)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, FluoInputError):
            raise
        raise FluoInputError(f"poses must be 4x4 matrices of numbers ({exc})", file=args.poses,
                             field="tool_to_tracker") from None


def _synth(args):
    from fluoguide.progress import TqdmProgress

    with TqdmProgress("calib synth-boards") as prog:
        ds = module_logic("FluoCalib").writeSyntheticBoards(
            args.out, args.board, args.views, args.seed, args.width, args.height,
            fisheye=args.fisheye, blurPx=args.blur, noise=args.noise,
            trackerNoiseMm=args.tracker_noise_mm, motion=args.motion, progress=prog)
    return {"out": str(args.out), "images": ds["images"],
            "truth": str(Path(args.out) / "truth.json"),
            "camera": ds["camera"], "camera_to_tool": ds["camera_to_tool"]}


def register(subparsers):
    sub = cli_group(subparsers, "calib", "camera, hand-eye, radiometric and light calibrations")

    p = sub.add_parser("camera", help="intrinsic calibration from board images")
    p.add_argument("--images", required=True, help="glob of board images, e.g. 'cal/*.png'")
    p.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE_MM or charuco:COLSxROWS:SQ:MARKER:DICT")
    p.add_argument("--fisheye", action="store_true", help="fisheye (wide-angle) lens model")
    p.add_argument("--holdout", type=int, default=0,
                   help="views held out of the fit for validation (default %(default)s)")
    p.add_argument("--fix-k3", action="store_true", help="hold k3 at 0")
    p.add_argument("--keep-outliers", action="store_true",
                   help="do not reject views with RMS > max(1 px, 3 x median)")
    p.add_argument("--yaml", help="write OpenCV YAML here (default: not written)")
    p.add_argument("--scene", help="store in this MRML scene, created if missing (default: not "
                   "stored)")
    add_json_flag(p)
    p.set_defaults(func=_camera)

    p = sub.add_parser("handeye", help="hand-eye calibration (camera to tracked tool)")
    p.add_argument("--images", required=True,
                   help="glob of board images, e.g. 'cal/*.png' (sorted by name)")
    p.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE_MM or charuco:COLSxROWS:SQ:MARKER:DICT")
    p.add_argument("--poses", required=True,
                   help='JSON with "tool_to_tracker": one 4x4 per image (sorted by name); '
                        'optional "board_to_tracker"')
    p.add_argument("--intrinsics", help="YAML or JSON intrinsics (default: calibrate here)")
    p.add_argument("--board-to-tracker", help="JSON 4x4 grid registration (default: the poses "
                   "file's board_to_tracker, else estimated from the TSAI solution)")
    p.add_argument("--method", default="ALL", help="ALL or one of TSAI, PARK, HORAUD, ANDREFF, "
                   "DANIILIDIS, PAIRED_POINT (default %(default)s)")
    p.add_argument("--store-method", default="PAIRED_POINT",
                   help="method whose result is stored when several run (default %(default)s)")
    p.add_argument("--holdout", type=int, default=0,
                   help="views left out of the fit, errors reported separately (default "
                   "%(default)s)")
    p.add_argument("--yaml", help="write OpenCV YAML (intrinsics and hand-eye) here (default: "
                   "not written)")
    p.add_argument("--scene", help="store in this MRML scene, created if missing (default: not "
                   "stored)")
    add_json_flag(p)
    p.set_defaults(func=_handeye)

    p = sub.add_parser("register", help="paired-point rigid registration with FRE/TRE")
    p.add_argument("--moving", required=True, help="points in the moving frame (tracker)")
    p.add_argument("--fixed", required=True, help="the same points in the fixed frame (CBCT)")
    p.add_argument("--targets-moving", help="target points in the moving frame, for the target "
                   "registration error (TRE; default: none)")
    p.add_argument("--targets-fixed", help="the same targets in the fixed frame (default: none)")
    p.add_argument("--scene", help="store the registration in this MRML scene, created if "
                   "missing (default: not stored)")
    add_json_flag(p)
    p.set_defaults(func=_register)

    p = sub.add_parser("pivot", help="pivot calibration of a tracked pointer")
    p.add_argument("--poses", required=True, help='JSON list of 4x4 (or {"tool_to_tracker": ...})')
    add_json_flag(p)
    p.set_defaults(func=_pivot)

    p = sub.add_parser("synth-boards", help="render synthetic board images with known truth")
    p.add_argument("--out", required=True,
                   help="folder for view_NNN.png and truth.json (camera, hand-eye, tool poses)")
    p.add_argument("--board", default="chessboard:9x6:20",
                   help="board: chessboard:COLSxROWS:SQUARE_MM or "
                   "charuco:COLSxROWS:SQ:MARKER:DICT (default %(default)s)")
    p.add_argument("--views", type=int, default=12, help="images to render (default %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the poses and the noise (default %(default)s)")
    p.add_argument("--width", type=int, default=800, help="image width [px] (default %(default)s)")
    p.add_argument("--height", type=int, default=600,
                   help="image height [px] (default %(default)s)")
    p.add_argument("--fisheye", action="store_true",
                   help="a wide-angle camera with the fisheye lens model instead of the "
                   "distorted pinhole")
    p.add_argument("--noise", type=float, default=2.0,
                   help="sensor noise SD [grey levels] (default %(default)s)")
    p.add_argument("--blur", type=float, default=0.6, help="blur SD [px] (default %(default)s)")
    p.add_argument("--tracker-noise-mm", type=float, default=0.1,
                   help="SD of the tracked tool's position noise [mm] (default %(default)s)")
    p.add_argument("--motion", default="general", choices=("general", "translation", "parallel"),
                   help="camera motion between views: general; translation (one orientation: "
                   "degenerate for hand-eye and intrinsics); parallel (board always head-on: "
                   "degenerate for intrinsics) (default %(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_synth)
