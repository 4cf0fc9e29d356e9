"""``fluo devices``, ``fluo track``, ``fluo record``, ``fluo replay``: find trackers and
cameras, track poses, record and replay tracked frames."""

from __future__ import annotations

from pathlib import Path

from fluoapp.cli import add_json_flag
from fluoapp.commands import module_logic
from fluoguide.errors import FluoInputError


def _seconds(value):
    """``--seconds``: finite, positive and at most a day (inf and NaN never end or never start)."""
    from FluoNavLib.devices.tracker import check_seconds

    return check_seconds(value)


def _devices(args):
    from FluoNavLib.devices.usb import discover

    return discover()


def _track(args):
    from fluoguide.errors import check_number

    _seconds(args.seconds)
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
        from FluoNavLib.devices.ndi_simulator import Faults

        Faults.named(args.inject_faults)    # an unknown kind: refused before the simulator
    if args.igtl:
        source, address, options = "igtl", args.igtl, {"rate_hz": args.rate}
    elif args.sim:
        source, address = "ndi-sim", None
        options = {"inject_faults": args.inject_faults, "seed": args.seed}
    elif args.serial:
        source, address, options = "ndi", args.serial, {"tools": args.tools or 1}
    else:
        raise FluoInputError("choose --sim or --serial PORT", field="source")
    logic = module_logic("FluoNav")
    logic.connectTracker(source, address, **options)
    try:
        return logic.trackFor(args.seconds)
    finally:
        logic.disconnect()


def _frame_source(args):
    from FluoNavLib.devices import frame_sources as fs

    if args.frames:
        return fs.ImageSequenceSource(args.frames, fps=args.fps, realtime=True)
    if args.camera is not None:
        return fs.OpenCVSource(args.camera, fps=args.fps)
    return fs.SyntheticSource(fps=args.fps, width=args.width, height=args.height, seed=args.seed)


def _record(args):
    """Simulated tracker + synthetic, image-sequence or camera frames -> a recording
    folder, through the live loop (the same path the mapping takes)."""
    from FluoNavLib.devices.live_loop import LiveLoop
    from FluoNavLib.devices.ndi_client import NDIClient
    from FluoNavLib.devices.ndi_simulator import Faults, NDISimulator
    from FluoNavLib.devices.recorder import Recorder

    _seconds(args.seconds)
    if not (args.fps > 0 and args.fps <= 1000):
        raise FluoInputError("must be a frame rate in (0, 1000] Hz", field="--fps", value=args.fps)
    sim = NDISimulator(faults=Faults.named(args.inject_faults), seed=args.seed)
    port = sim.start()
    try:
        # the camera first: a refused source must not leave a recording folder behind
        with _frame_source(args) as frames, NDIClient(port) as client, Recorder(args.out) as rec:
            client.initialize([b"camera tool rom " * 4])
            client.start()

            def write(image, info, poses):
                rec.add(image, info["timestamp_s"], poses, exposure_s=info["exposure_s"],
                        pose_valid=info["pose_valid"], pose_status=info["pose_status"])

            # a recording keeps every frame the camera gave (no "latest" dropping);
            # a slow disk shows as latency, or as camera-side gaps (dropped_upstream)
            loop = LiveLoop(frames, write, tracker=client, tools={"CameraToolToTracker": 1},
                            camera_latency_s=0.5 / args.fps, drop_policy="none")
            out = loop.run(seconds=args.seconds)
            client.stop()
            stats = client.stats
    finally:
        sim.stop()
    return {"frames": out["delivered"], "frames_without_pose": out["pose_invalid"],
            "pose_status": out["pose_status"], "dropped_slow": out["dropped_slow"],
            "dropped_upstream": out["dropped_upstream"],
            "frames_lost_unreported": out["lost_unreported"], "latency_ms": out["latency_ms"],
            "tracker_frames": stats.frames, "tracker_missing": stats.missing,
            "crc_errors": stats.crc_errors, "recovered": stats.recovered,
            "lost_unreported": stats.lost_unreported(),
            "folder": str(Path(args.out).resolve())}


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
    from FluoNavLib.devices.ndi_simulator import FAULT_KINDS

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
