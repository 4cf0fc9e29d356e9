"""Find attached NDI trackers and cameras: serial ports (pyserial's
``list_ports``) and USB devices (pyusb), by vendor/product id and USB class.

Works without any device and without a libusb backend: what could not be
listed is said in ``notes``, never raised.
"""

from __future__ import annotations

__all__ = ["NDI_USB_IDS", "CAMERA_VENDORS", "UVC_CLASS", "discover", "classify_usb"]

# NDI Polaris / Aurora system control units connect through FTDI USB-serial
# converters (the common case) or, on newer units, with NDI's own vendor id.
NDI_USB_IDS = {(0x0403, 0x6001): "FTDI USB-serial (NDI Polaris/Aurora SCU)",
               (0x0403, 0x6015): "FTDI USB-serial (NDI)",
               (0x28E7, None): "NDI"}
# Cameras are recognised by the video interface class (UVC, 0x0E); these
# vendor ids only name them (and catch vendor-class machine-vision cameras).
CAMERA_VENDORS = {0x046D: "Logitech", 0x045E: "Microsoft", 0x05A3: "ARC (generic UVC)",
                  0x0C45: "Microdia (generic UVC)", 0x2676: "Basler", 0x1E10: "FLIR/Point Grey",
                  0x1409: "IDS", 0x199E: "The Imaging Source", 0x20F7: "XIMEA",
                  0x2A0B: "Hamamatsu"}
MACHINE_VISION_VENDORS = {0x2676, 0x1E10, 0x1409, 0x199E, 0x20F7, 0x2A0B}
UVC_CLASS = 0x0E


def _ndi_kind(vid, pid):
    return NDI_USB_IDS.get((vid, pid)) or NDI_USB_IDS.get((vid, None))


def classify_usb(vid, pid, interface_classes):
    """"tracker", "camera" or None for a USB device."""
    if _ndi_kind(vid, pid):
        return "tracker"
    if UVC_CLASS in interface_classes or vid in MACHINE_VISION_VENDORS:
        return "camera"
    return None


def discover(usb_backend=None):
    """{serial_ports, trackers, cameras, notes} of what is attached now."""
    out = {"serial_ports": [], "trackers": [], "cameras": [], "notes": []}
    try:
        from serial.tools import list_ports

        for p in list_ports.comports():
            entry = {"port": p.device, "description": p.description, "vid": p.vid, "pid": p.pid}
            out["serial_ports"].append(entry)
            kind = _ndi_kind(p.vid, p.pid)
            if kind:
                out["trackers"].append({**entry, "kind": kind})
    except Exception as exc:  # reported, not fatal
        out["notes"].append(f"serial ports not listed: {exc}")
    try:
        import usb.core

        for d in usb.core.find(find_all=True, backend=usb_backend):
            classes = {d.bDeviceClass}
            try:
                for cfg in d:
                    classes |= {intf.bInterfaceClass for intf in cfg}
            except Exception:     # configuration unreadable without permission
                pass
            if classify_usb(d.idVendor, d.idProduct, classes) == "camera":
                out["cameras"].append({"vid": d.idVendor, "pid": d.idProduct, "bus": d.bus,
                                       "address": d.address,
                                       "vendor": CAMERA_VENDORS.get(d.idVendor, "UVC")})
    except Exception as exc:  # no libusb backend, no permission
        out["notes"].append(f"USB devices not listed ({type(exc).__name__}: {exc}); install "
                            "libusb-1.0 for camera discovery")
    if not out["trackers"] and not out["cameras"]:
        out["notes"].append("no tracker or camera found (use `fluo track --sim` for the simulator)")
    return out
