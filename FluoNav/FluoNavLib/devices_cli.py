"""``fluo devices`` and ``fluo track``: find trackers and cameras, track poses."""

from __future__ import annotations

import time

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


def register(subparsers):
    p = subparsers.add_parser("devices", help="list attached trackers and cameras (USB / serial)")
    add_json_flag(p)
    p.set_defaults(func=_devices)
    p = subparsers.add_parser("track", help="track tool poses from an NDI tracker or the simulator")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", action="store_true", help="protocol-faithful simulator on a pty")
    src.add_argument("--serial", metavar="PORT", help="serial port of a real NDI tracker")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--inject-faults", action="store_true",
                   help="simulator: CRC errors, slow replies, dropouts and a disconnect")
    p.add_argument("--tools", type=int, default=1, help="passive tools to request (--serial)")
    p.add_argument("--seed", type=int, default=0)
    add_json_flag(p)
    p.set_defaults(func=_track)
