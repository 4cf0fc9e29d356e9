"""``fluo calib radiometry|illumination|laser|synth-light``: radiometric
calibrations from image stacks and images (synthetic sets with known truth
from ``synth-light``)."""

from __future__ import annotations

from pathlib import Path

from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import module_logic, save_scene_to, scene_for
from fluoguide.progress import TqdmProgress


def _calib(args):
    """The FluoCalib logic over the ``--scene`` scene (or a new one), after every
    output was checked: a refused run writes nothing."""
    from fluoguide import atomic
    from fluoguide.jsonable import read_json

    if getattr(args, "out", None):
        atomic.check_writable(args.out, "--out", folder=True)
    if getattr(args, "calibration", None):
        atomic.check_writable(args.calibration, "--calibration")
        if Path(args.calibration).exists():
            read_json(args.calibration, field="--calibration")   # never overwrite a damaged one
    return module_logic("FluoCalib", scene_for(getattr(args, "scene", None)))


def _outputs(args):
    return {"calibrationJson": getattr(args, "calibration", None)}


def _radiometry(args):
    logic = _calib(args)
    res = logic.characterizeCamera(args.stack, bitDepth=args.bits, plotsFolder=args.out,
                                   **_outputs(args))
    save_scene_to(logic.scene, args.scene)
    return {k: v for k, v in res.items() if k not in ("ptc", "linearity", "dark")} | (
        {"curves": {k: res[k] for k in ("ptc", "linearity", "dark")}} if args.curves else {})


def _illumination(args):
    logic = _calib(args)
    with TqdmProgress("calib illumination") as prog:
        res = logic.calibrateIllumination(args.folder, tryAsymmetric=not args.axisymmetric,
                                          plotsFolder=args.out, progress=prog, **_outputs(args))
    save_scene_to(logic.scene, args.scene)
    return {k: v for k, v in res.items() if k != "ratio_images"}


def _laser(args):
    logic = _calib(args)
    res = logic.calibrateLaser(args.folder, holdout=args.holdout, **_outputs(args))
    save_scene_to(logic.scene, args.scene)
    return res


def _synth(args):
    from fluoguide import atomic

    out = Path(args.out)
    atomic.check_writable(out, "--out", folder=True)   # three sets: refuse before the first
    with TqdmProgress("calib synth-light") as prog:
        return module_logic("FluoCalib").writeSyntheticLight(out, seed=args.seed,
                                                             lensSpectral=True, progress=prog)


def _common(p):
    p.add_argument("--scene", help="MRML scene to store the result in, created if missing "
                   "(default: not stored)")
    p.add_argument("--calibration", help="calibration JSON file to merge the result into "
                   "(default: none)")
    add_json_flag(p)


def register(subparsers):
    calib = cli_group(subparsers, "calib", "camera, hand-eye, radiometric and light calibrations")
    p = calib.add_parser("radiometry", help="camera response (gain, dark current, bias, read "
                         "noise, linearity) from an image stack (EMVA 1288 style)")
    p.add_argument("stack", help="folder with stack.json and the frames")
    p.add_argument("--bits", type=int, default=14, help="A/D bit depth (default %(default)s)")
    p.add_argument("--out", help="folder for PNG plots (default: no plots)")
    p.add_argument("--curves", action="store_true", help="include the curves in the JSON")
    _common(p)
    p.set_defaults(func=_radiometry)
    p = calib.add_parser("illumination", help="broad-beam cone (origin, axis, half-angle, alpha, "
                         "gamma, system gain) from flat-phantom images")
    p.add_argument("folder", help="folder with illumination.json and the images")
    p.add_argument("--axisymmetric", action="store_true",
                   help="do not try the crescent (non-axisymmetric) term")
    p.add_argument("--out", help="folder for the ratio-image PNG (default: no plot)")
    _common(p)
    p.set_defaults(func=_illumination)
    p = calib.add_parser("laser", help="laser beam line in laser-tool coordinates from spot images")
    p.add_argument("folder", help="folder with laser.json and the images")
    p.add_argument("--holdout", type=int, default=4,
                   help="images kept out of the fit to measure accuracy (default %(default)s)")
    _common(p)
    p.set_defaults(func=_laser)
    p = calib.add_parser("synth-light", help="synthetic stack, illumination and laser data sets "
                         "with known truth")
    p.add_argument("--out", required=True,
                   help="folder for the three sets: stack/, illumination/, laser/")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default %(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_synth)
