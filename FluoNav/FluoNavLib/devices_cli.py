"""``fluo devices`` and ``fluo track``: find trackers and cameras, track poses."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fluoguide.cli import add_json_flag
from fluoguide.errors import FluoInputError

# USB ids: NDI Polaris/Aurora connect through FTDI USB-serial converters (or
# NDI's own id on newer units); UVC cameras are USB class 0x0E (video).
NDI_USB_IDS = {(0x0403, 0x6001): "FTDI USB-serial (NDI Polaris/Aurora SCU)",
               (0x0403, 0x6015): "FTDI USB-serial (NDI)",
               (0x28E7, 0x0001): "NDI"}


def _devices(args):
    out = {"serial_ports": [], "trackers": [], "cameras": [], "notes": []}
    try:
        from serial.tools import list_ports

        for p in list_ports.comports():
            entry = {"port": p.device, "description": p.description,
                     "vid": p.vid, "pid": p.pid}
            out["serial_ports"].append(entry)
            if (p.vid, p.pid) in NDI_USB_IDS:
                out["trackers"].append({**entry, "kind": NDI_USB_IDS[(p.vid, p.pid)]})
    except Exception as exc:  # reported, not fatal
        out["notes"].append(f"serial ports not listed: {exc}")
    try:
        import usb.core

        for d in usb.core.find(find_all=True):
            classes = {d.bDeviceClass}
            try:
                for cfg in d:
                    classes |= {intf.bInterfaceClass for intf in cfg}
            except Exception:
                pass
            if 0x0E in classes:
                out["cameras"].append({"vid": d.idVendor, "pid": d.idProduct,
                                       "bus": d.bus, "address": d.address})
    except Exception as exc:  # no libusb backend, no permission
        out["notes"].append(f"USB devices not listed ({type(exc).__name__}: {exc}); install "
                            "libusb-1.0 for camera discovery")
    if not out["trackers"] and not out["cameras"]:
        out["notes"].append("no tracker or camera found (use `fluo track --sim` for the simulator)")
    return out


def _track(args):
    from .ndi_client import NDIClient
    from .ndi_simulator import Faults, NDISimulator

    if args.seconds <= 0:
        raise FluoInputError("must be > 0", field="--seconds", value=args.seconds)
    if args.igtl:
        return _track_igtl(args)
    sim = None
    if args.sim:
        sim = NDISimulator(faults=Faults.typical() if args.inject_faults else Faults(),
                           seed=args.seed)
        port = sim.start()
    elif args.serial:
        port = args.serial
    else:
        raise FluoInputError("choose --sim or --serial PORT", field="source")
    try:
        try:
            client = NDIClient(port).open()
        except Exception as exc:
            raise FluoInputError(f"cannot open serial port ({exc})", field="--serial",
                                 value=port) from None
        with client:
            client.initialize([b"FluoGuide sim tool " * 4] * (2 if args.sim else args.tools))
            client.start()
            t0 = time.monotonic()
            stats = client.track(args.seconds)
            elapsed = time.monotonic() - t0
            client.stop()
    finally:
        if sim is not None:
            sim.stop()
    return {"frames": stats.frames, "rate_hz": stats.frames / elapsed, "seconds": elapsed,
            "missing": stats.missing, "tool_missing": stats.tool_missing,
            "out_of_volume": stats.out_of_volume, "crc_errors": stats.crc_errors,
            "timeouts": stats.timeouts, "malformed": stats.malformed,
            "device_errors": stats.device_errors, "recovered": stats.recovered,
            "lost_unreported": stats.lost_unreported(), "segments": stats.segments,
            "simulator": sim.counters if sim is not None else None}


def _track_igtl(args):
    from fluoguide import mrml_io

    from .igtl_client import IGTLReceiver

    host, _, port = args.igtl.rpartition(":")
    if not host or not port.isdigit():
        raise FluoInputError("expected HOST:PORT", field="--igtl", value=args.igtl)
    with IGTLReceiver(mrml_io.new_scene(), host, int(port), nominal_rate_hz=args.rate) as rx:
        out = rx.receive(args.seconds)
    out["seconds"] = args.seconds
    return out


def _record(args):
    """Simulated tracker + synthetic camera frames -> a recording folder."""
    from .ndi_client import NDIClient
    from .ndi_simulator import Faults, NDISimulator
    from .recorder import Recorder
    from .timesync import PoseBuffer

    if args.seconds <= 0 or args.fps <= 0:
        raise FluoInputError("seconds and fps must be > 0", field="--seconds/--fps",
                             value=(args.seconds, args.fps))
    rng = np.random.default_rng(args.seed)
    sim = NDISimulator(faults=Faults.typical() if args.inject_faults else Faults(), seed=args.seed)
    port = sim.start()
    buf = PoseBuffer(max_gap_s=0.05, max_age_s=0.1)
    t_start = None
    try:
        with NDIClient(port) as client, Recorder(args.out) as rec:
            client.initialize([b"camera tool rom " * 4])
            client.start()
            next_frame = time.monotonic() + 0.1
            t_end = time.monotonic() + args.seconds
            flagged = 0

            def on_pose(reply, t_host):
                pose = reply.tools.get(1)
                buf.add(t_host, pose.matrix() if pose is not None else None)

            while time.monotonic() < t_end:
                client.track(max(0.0, next_frame - time.monotonic()), on_frame=on_pose)
                t = next_frame - 0.5 / args.fps      # mid-exposure time of this frame
                m, status = buf.at(t)
                if m is None:
                    flagged += 1
                img = rng.poisson(200.0 + 50.0 * np.sin(t) ** 2, size=(args.height, args.width))
                rec.add(img.astype(np.uint16), t, {"CameraToolToTracker": m}, exposure_s=0.5 / args.fps,
                        pose_valid=m is not None, pose_status=status)
                t_start = t_start or t
                next_frame += 1.0 / args.fps
            client.stop()
            stats = client.stats
            n = rec.n
    finally:
        sim.stop()
    return {"frames": n, "frames_without_pose": flagged, "tracker_frames": stats.frames,
            "tracker_missing": stats.missing, "crc_errors": stats.crc_errors,
            "recovered": stats.recovered, "lost_unreported": stats.lost_unreported(),
            "folder": str(Path(args.out).resolve())}


def _replay(args):
    from .recorder import replay, to_scene

    n = valid = 0
    t0 = time.monotonic()
    for _, info, poses in replay(args.folder, "max" if args.max_speed else "recorded"):
        n += 1
        valid += bool(info["pose_valid"])
    out = {"frames": n, "frames_with_pose": valid, "seconds": time.monotonic() - t0}
    if args.scene:
        from fluoguide import mrml_io

        out["scene"] = str(mrml_io.save_scene(to_scene(args.folder), args.scene))
    return out


def register(subparsers):
    p = subparsers.add_parser("devices", help="list attached trackers and cameras (USB / serial)")
    add_json_flag(p)
    p.set_defaults(func=_devices)
    p = subparsers.add_parser("track", help="track tool poses from an NDI tracker or the simulator")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", action="store_true", help="protocol-faithful simulator on a pty")
    src.add_argument("--serial", metavar="PORT", help="serial port of a real NDI tracker")
    src.add_argument("--igtl", metavar="HOST:PORT", help="OpenIGTLink server (e.g. PLUS)")
    p.add_argument("--rate", type=float, default=None,
                   help="--igtl: nominal message rate [Hz] for loss counting by timestamps")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--inject-faults", action="store_true",
                   help="simulator: CRC errors, slow replies, dropouts and a disconnect")
    p.add_argument("--tools", type=int, default=1, help="passive tools to request (--serial)")
    p.add_argument("--seed", type=int, default=0)
    add_json_flag(p)
    p.set_defaults(func=_track)
    p = subparsers.add_parser("record", help="record tracked camera frames (simulated tracker and "
                              "synthetic frames) incrementally to a folder")
    p.add_argument("--out", required=True, help="new or empty folder")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--fps", type=float, default=20.0)
    p.add_argument("--width", type=int, default=348)
    p.add_argument("--height", type=int, default=260)
    p.add_argument("--inject-faults", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    add_json_flag(p)
    p.set_defaults(func=_record)
    p = subparsers.add_parser("replay", help="replay a recording (poses bit-exact), optionally as "
                              "an MRML scene")
    p.add_argument("folder")
    p.add_argument("--max-speed", action="store_true", help="as fast as possible")
    p.add_argument("--scene", help="also write the recording as an MRML scene (.mrml)")
    add_json_flag(p)
    p.set_defaults(func=_replay)
