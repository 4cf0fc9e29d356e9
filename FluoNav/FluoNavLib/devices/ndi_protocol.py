"""NDI Combined API (Polaris/Aurora) serial protocol: commands, replies, CRC.

Only the text forms are implemented (commands as ``NAME args<CR>``, the ``TX``
tracking reply); ``BX`` binary replies are not.  Every reply ends with a
CRC-16 (polynomial 0x8005, reflected, initial 0: "OKAY" -> ``A896``) and a
carriage return; :func:`check_reply` verifies it before anything is parsed.

TX reply (option 0001, transforms), per handle, one line each::

    hh Q0 Qx Qy Qz Tx Ty Tz Err Status Frame      (sign + digits, implied decimals)
    hh MISSING Status Frame
    hh DISABLED

then the 4-hex-digit system status.  Quaternion components carry 4 implied
decimals (+10000 = 1.0), translations 2 (mm), the RMS error 4.

This module is pure (no I/O): the client and the simulator share it, so the
simulator is protocol-faithful by construction and the parsers are fuzzed in
the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoError

__all__ = ["NDIProtocolError", "crc16", "with_crc", "check_reply", "command", "ToolPose",
           "TXReply", "parse_tx", "format_tx", "parse_phsr", "format_phsr", "ERROR_CODES",
           "PORT_OCCUPIED", "PORT_ENABLED", "PORT_OUT_OF_VOLUME", "PORT_PARTIAL_OUT_OF_VOLUME"]

PORT_OCCUPIED = 0x01
PORT_INITIALIZED = 0x10
PORT_ENABLED = 0x20
PORT_OUT_OF_VOLUME = 0x40
PORT_PARTIAL_OUT_OF_VOLUME = 0x80

ERROR_CODES = {
    "01": "invalid command", "02": "command too long", "03": "command too short",
    "04": "invalid CRC calculated for command", "05": "time-out on command execution",
    "06": "unable to set up new communication parameters", "07": "incorrect number of parameters",
    "08": "invalid port handle selected", "09": "invalid mode selected",
    "0A": "invalid LED selected", "0B": "invalid LED state selected",
    "0C": "command invalid in current operating mode", "0D": "no tool detected in port",
    "0E": "port not initialized", "0F": "port already initialized",
    "10": "system not initialized", "14": "internal system error",
}


class NDIProtocolError(FluoError):
    """A reply that cannot be used (bad CRC, malformed, ERROR); ``kind`` says which."""

    def __init__(self, message, kind="malformed", reply=b""):
        super().__init__(message)
        self.kind = kind
        self.reply = bytes(reply)


def crc16(data):
    """NDI CRC-16 of ``data`` (bytes)."""
    crc = 0
    for b in bytes(data):
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(body):
    """``body`` + 4 hex CRC digits + CR (how the device sends a reply)."""
    body = body.encode("ascii") if isinstance(body, str) else bytes(body)
    return body + f"{crc16(body):04X}".encode("ascii") + b"\r"


def command(name, *args):
    """One command line: ``NAME args<CR>`` (space form, no CRC)."""
    text = name if not args else name + " " + "".join(str(a) for a in args)
    return (text + "\r").encode("ascii")


def check_reply(raw):
    """Body of a reply after checking its CRC; raises NDIProtocolError.

    ``ERRORxx`` replies raise with kind ``"error"`` and the decoded message.
    """
    raw = bytes(raw)
    if not raw.endswith(b"\r"):
        raise NDIProtocolError("reply not terminated by CR (truncated)", "truncated", raw)
    text = raw[:-1]
    if len(text) < 4:
        raise NDIProtocolError("reply shorter than its CRC", "truncated", raw)
    body, crc = text[:-4], text[-4:]
    try:
        want = int(crc.decode("ascii"), 16)
    except (UnicodeDecodeError, ValueError):
        raise NDIProtocolError("CRC field is not hexadecimal", "crc", raw) from None
    if crc16(body) != want:
        raise NDIProtocolError("CRC mismatch", "crc", raw)
    try:
        body_text = body.decode("ascii")
    except UnicodeDecodeError:
        raise NDIProtocolError("reply is not ASCII", "malformed", raw) from None
    if body_text.startswith("ERROR"):
        code = body_text[5:7]
        raise NDIProtocolError(f"device error {code}: {ERROR_CODES.get(code, 'unknown')}",
                               "error", raw)
    return body_text


@dataclass
class ToolPose:
    """One handle in one TX reply.  ``state`` is OK, MISSING or DISABLED."""

    handle: int
    state: str
    quaternion: np.ndarray | None = None     # (q0, qx, qy, qz), unit
    translation_mm: np.ndarray | None = None
    rms_error_mm: float | None = None
    port_status: int = 0
    frame: int | None = None

    @property
    def out_of_volume(self):
        return bool(self.port_status & PORT_OUT_OF_VOLUME)

    def matrix(self):
        """4x4 ToolToTracker (None unless state is OK)."""
        if self.state != "OK":
            return None
        from FluoCalibLib.geometry.transforms import quaternion_to_matrix

        m = np.eye(4)
        m[:3, :3] = quaternion_to_matrix(self.quaternion)
        m[:3, 3] = self.translation_mm
        return m


@dataclass
class TXReply:
    tools: dict
    system_status: int


def _signed(s, decimals, what):
    if len(s) < 2 or s[0] not in "+-" or not s[1:].isdigit():
        raise NDIProtocolError(f"bad number for {what}: {s!r}")
    return int(s) / 10 ** decimals


def parse_tx(body):
    """Parse the body (CRC already checked) of a ``TX 0001`` reply."""
    lines = body.split("\n")
    head = lines[0]
    if len(head) < 2:
        raise NDIProtocolError("TX reply too short")
    try:
        n = int(head[:2], 16)
    except ValueError:
        raise NDIProtocolError(f"bad handle count {head[:2]!r}") from None
    # the first handle's record follows the count on the same line
    records = [head[2:]] + lines[1:]
    if len(records) != n + 1:
        raise NDIProtocolError(f"TX reply announces {n} handles but has {len(records) - 1}")
    tools = {}
    for rec in records[:n]:
        if len(rec) < 2:
            raise NDIProtocolError("empty handle record")
        try:
            h = int(rec[:2], 16)
        except ValueError:
            raise NDIProtocolError(f"bad handle {rec[:2]!r}") from None
        rest = rec[2:]
        if rest.startswith("DISABLED"):
            tools[h] = ToolPose(h, "DISABLED")
            continue
        if rest.startswith("MISSING"):
            tail = rest[7:]
            if len(tail) != 16:
                raise NDIProtocolError("MISSING record needs status and frame")
            try:
                status, frame = int(tail[:8], 16), int(tail[8:], 16)
            except ValueError:
                raise NDIProtocolError("bad status/frame in MISSING record") from None
            tools[h] = ToolPose(h, "MISSING", port_status=status, frame=frame)
            continue
        if len(rest) != 4 * 6 + 3 * 7 + 6 + 8 + 8:
            raise NDIProtocolError(f"transform record has {len(rest)} characters")
        q = np.array([_signed(rest[6 * i:6 * i + 6], 4, "quaternion") for i in range(4)])
        t = np.array([_signed(rest[24 + 7 * i:31 + 7 * i], 2, "translation") for i in range(3)])
        err = _signed(rest[45:51], 4, "error")
        try:
            status, frame = int(rest[51:59], 16), int(rest[59:67], 16)
        except ValueError:
            raise NDIProtocolError("bad status/frame in transform record") from None
        norm = float(np.linalg.norm(q))
        if not 0.9 < norm < 1.1:
            raise NDIProtocolError(f"quaternion norm {norm:.3f} is not 1")
        tools[h] = ToolPose(h, "OK", q / norm, t, err, status, frame)
    tail = records[n]
    if len(tail) != 4:
        raise NDIProtocolError("TX reply lacks the system status")
    try:
        system = int(tail, 16)
    except ValueError:
        raise NDIProtocolError("bad system status") from None
    return TXReply(tools, system)


def _fmt(v, decimals, width):
    n = int(round(float(v) * 10 ** decimals))
    limit = 10 ** (width - 1) - 1
    n = max(-limit, min(limit, n))  # the device saturates the field
    return f"{'+' if n >= 0 else '-'}{abs(n):0{width - 1}d}"


def format_tx(tools, frame, system_status=0):
    """Body of a TX reply (the simulator's side).  ``tools``: list of
    (handle, state, quaternion, translation_mm, rms_mm, port_status)."""
    recs = []
    for h, state, q, t, err, status in tools:
        if state == "DISABLED":
            recs.append(f"{h:02X}DISABLED")
        elif state == "MISSING":
            recs.append(f"{h:02X}MISSING{status:08X}{frame:08X}")
        else:
            qs = "".join(_fmt(c, 4, 6) for c in q)
            ts = "".join(_fmt(c, 2, 7) for c in t)
            recs.append(f"{h:02X}{qs}{ts}{_fmt(err, 4, 6)}{status:08X}{frame:08X}")
    return f"{len(tools):02X}" + "\n".join(recs) + "\n" + f"{system_status:04X}"


def parse_phsr(body):
    """Handles and their 3-hex-digit status from a PHSR reply."""
    try:
        n = int(body[:2], 16)
    except ValueError:
        raise NDIProtocolError(f"bad PHSR count {body[:2]!r}") from None
    if len(body) != 2 + 5 * n:
        raise NDIProtocolError("PHSR reply length does not match its count")
    out = {}
    for i in range(n):
        rec = body[2 + 5 * i:7 + 5 * i]
        try:
            out[int(rec[:2], 16)] = int(rec[2:], 16)
        except ValueError:
            raise NDIProtocolError(f"bad PHSR record {rec!r}") from None
    return out


def format_phsr(handles):
    return f"{len(handles):02X}" + "".join(f"{h:02X}{s:03X}" for h, s in handles.items())
