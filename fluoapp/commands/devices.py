"""``fluo devices``, ``fluo track``, ``fluo record``, ``fluo replay``: find trackers and
cameras, track poses, record and replay tracked frames."""

from __future__ import annotations

from fluoapp.cli import add_json_flag
from fluoapp.commands import as_flags, module_logic
from fluoguide.errors import FluoInputError
# the simulator's fault kinds, named in --help
from FluoNavLib.devices.ndi_simulator import FAULT_KINDS


def _devices(args):
    return module_logic("FluoNav").discoverDevices()


def _track(args):
    from fluoguide.errors import check_number

    logic = module_logic("FluoNav")
    logic.checkSeconds(args.seconds)
    # an option that would be ignored is refused: the user meant something by it
    if args.rate is not None and not args.igtl:
        raise FluoInputError("applies to --igtl only", field="--rate", value=args.rate)
    if args.tools is not None:
        if not args.serial:
            raise FluoInputError("applies to --serial only", field="--tools", value=args.tools)
        check_number("--tools", args.tools, 1, 16, integer=True)  # an NDI tracker's passive ports
    if args.inject_faults is not None:
        if not args.sim:
            raise FluoInputError("applies to --sim only", field="--inject-faults",
                                 value=args.inject_faults)
        logic.checkFaults(args.inject_faults)    # an unknown kind: refused before the simulator
    if args.igtl:
        source, address, options = "igtl", args.igtl, {"rate_hz": args.rate}
    elif args.sim:
        source, address = "ndi-sim", None
        options = {"inject_faults": args.inject_faults, "seed": args.seed}
    elif args.serial:
        source, address, options = "ndi", args.serial, {"tools": args.tools or 1}
    else:
        raise FluoInputError("choose --sim or --serial PORT", field="source")
    logic.connectTracker(source, address, **options)
    try:
        return logic.trackFor(args.seconds)
    finally:
        logic.disconnect()


def _record(args):
    """Simulated tracker + synthetic, image-sequence or camera frames -> a recording
    folder, through the live loop (the same path the mapping takes)."""
    with as_flags({"fps": "--fps"}):
        return module_logic("FluoNav").recordFrames(
            args.out, args.seconds, args.fps, frames=args.frames, camera=args.camera,
            width=args.width, height=args.height, injectFaults=args.inject_faults,
            seed=args.seed)


def _replay(args):
    from fluoguide import mrml_io

    if args.scene:       # refused before the replay, not after it
        mrml_io.scene_to_update(args.scene)
    logic = module_logic("FluoNav")
    logic.connectTracker("replay", args.folder, speed="max" if args.max_speed else "recorded")
    try:
        out = logic.trackFor(None, applyPoses=False)
    finally:
        logic.disconnect()
    if args.scene:
        logic.importRecording(args.folder)
        out["scene"] = str(mrml_io.save_scene(logic.scene, args.scene))
    return out


def _add_inject_faults(p, what):
    kinds = "; ".join(f"{k}: {v[0]}" for k, v in FAULT_KINDS.items())
    p.add_argument("--inject-faults", nargs="?", const="typical", default=None,
                   metavar="KIND,...", help=f"{what}: inject faults, the kinds named "
                   f"(comma-separated; without a value: typical) - {kinds} (default: none)")


def register(subparsers):
    p = subparsers.add_parser("devices", help="list attached trackers and cameras (USB / serial)")
    add_json_flag(p)
    p.set_defaults(func=_devices)
    p = subparsers.add_parser("track", help="track tool poses from an NDI tracker or the simulator")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", action="store_true", help="protocol-faithful simulator on a pty")
    src.add_argument("--serial", metavar="PORT", help="serial port of a real NDI tracker "
                     "(default: none; one of --sim, --serial, --igtl is needed)")
    src.add_argument("--igtl", metavar="HOST:PORT", help="OpenIGTLink server, e.g. PLUS "
                     "(default: none)")
    p.add_argument("--rate", type=float, default=None,
                   help="--igtl: nominal message rate [Hz], to count losses by timestamps when "
                   "messages carry no sequence numbers (default: not counted that way)")
    p.add_argument("--seconds", type=float, default=5.0,
                   help="how long to track [s] (default %(default)s)")
    _add_inject_faults(p, "simulator")
    p.add_argument("--tools", type=int, default=None,
                   help="passive tools to request (--serial only; default 1)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the simulator's faults (default %(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_track)
    p = subparsers.add_parser("record", help="record tracked camera frames (simulated tracker; "
                              "synthetic, image-folder or camera frames) incrementally to a folder")
    p.add_argument("--out", required=True, help="new or empty folder")
    cam = p.add_mutually_exclusive_group()
    cam.add_argument("--frames", metavar="FOLDER", help="images played as a camera at --fps "
                     "(default: synthetic frames)")
    cam.add_argument("--camera", type=int, metavar="INDEX", help="OpenCV/UVC camera index "
                     "(default: synthetic frames)")
    p.add_argument("--seconds", type=float, default=5.0,
                   help="how long to record [s] (default %(default)s)")
    p.add_argument("--fps", type=float, default=20.0,
                   help="camera frame rate [frames/s] (default %(default)s)")
    p.add_argument("--width", type=int, default=348,
                   help="synthetic frames: width [px] (default %(default)s)")
    p.add_argument("--height", type=int, default=260,
                   help="synthetic frames: height [px] (default %(default)s)")
    _add_inject_faults(p, "simulated tracker")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the synthetic frames and the tracker's faults (default "
                   "%(default)s)")
    add_json_flag(p)
    p.set_defaults(func=_record)
    p = subparsers.add_parser("replay", help="replay a recording (poses bit-exact), optionally as "
                              "an MRML scene")
    p.add_argument("folder", help="recording folder (from fluo record)")
    p.add_argument("--max-speed", action="store_true",
                   help="as fast as possible (default: at the recorded pace)")
    p.add_argument("--scene", help="also write the recording as an MRML scene (.mrml; default: "
                   "no scene)")
    add_json_flag(p)
    p.set_defaults(func=_replay)
