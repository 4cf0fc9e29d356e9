"""A protocol-faithful simulated NDI tracker on a pseudo-terminal.

The client opens the pty's slave path with pyserial exactly as it opens a real
serial port.  The simulator answers the commands of ``ndi_protocol`` with the
device's reply formats and CRCs, runs a 60 Hz frame counter, moves its tools
along smooth paths with measurement noise, and can inject the faults a real
setup has: tools MISSING (occlusion bursts) or out of volume, corrupted CRCs,
slow replies, and a disconnect (silence for a while, after which the device
has reset and must be initialised again, as after a power cycle or cable pull).
And the faults of a device that misbehaves (issue #34): a CRC storm (every
reply corrupted for a while), a chaotic frame counter (random 32-bit frame
numbers), and every reply sent twice (a loop-back or a confused adapter).

Serial break on a pty is a no-op, so a reset is asked for with the ``RESET``
command (which the real device also accepts).
"""

from __future__ import annotations

import os
import select
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng

from FluoNavLib.devices.ndi_protocol import (
    PORT_ENABLED,
    PORT_INITIALIZED,
    PORT_OCCUPIED,
    PORT_OUT_OF_VOLUME,
    format_phsr,
    format_tx,
    with_crc,
)

__all__ = ["Faults", "SimTool", "NDISimulator", "FAULT_KINDS"]


@dataclass
class Faults:
    """Fault injection rates (per reply / per second); all off by default."""

    crc_error_rate: float = 0.0          # fraction of replies with a corrupted CRC
    slow_reply_rate: float = 0.0         # fraction of replies delayed by slow_reply_s
    slow_reply_s: float = 0.05
    dropout_rate_per_s: float = 0.0      # occlusion bursts (tool MISSING) per second
    dropout_s: float = 0.2
    disconnect_at_s: tuple = ()          # times after TSTART of a disconnect
    disconnect_s: float = 0.5
    crc_storms: tuple = ()               # ((start, end), ...) after the first TSTART [s]:
                                         # every reply's CRC corrupted in these windows
    chaotic_frames: bool = False         # TX frame numbers drawn at random in [0, 2^32)
    duplicate_replies: tuple = ()        # commands whose replies are sent twice ("*": all) ...
    duplicate_delay_s: float = 0.002     # ... the copy this long after the first [s]

    @classmethod
    def typical(cls):
        return cls(crc_error_rate=0.01, slow_reply_rate=0.005, dropout_rate_per_s=0.5,
                   disconnect_at_s=(2.0,))

    @classmethod
    def named(cls, kinds, field="--inject-faults"):
        """The faults of ``kinds``: a comma-separated list of :data:`FAULT_KINDS` names
        (``fluo track --sim --inject-faults crc-storm,chaotic-frames``); True: typical;
        None, False or nothing: none."""
        if kinds is None or kinds is False:
            return cls()
        if kinds is True:
            kinds = "typical"
        names = [k.strip() for k in str(kinds).split(",")]
        bad = [k for k in names if k not in FAULT_KINDS]
        if bad or not names:
            raise FluoInputError(f"expected fault kinds from {', '.join(FAULT_KINDS)}, "
                                 f"comma-separated", field=field, value=kinds)
        settings = {}
        for k in names:
            settings.update(FAULT_KINDS[k][1])
        return cls(**settings)


#: The fault sets ``--inject-faults`` names: name -> (what, Faults fields).
FAULT_KINDS = {
    "typical": ("CRC errors, slow replies, occlusion bursts and a disconnect at 2 s",
                {"crc_error_rate": 0.01, "slow_reply_rate": 0.005, "dropout_rate_per_s": 0.5,
                 "disconnect_at_s": (2.0,)}),
    # 0.3 s in every second from 0.5 s on (for an hour): each one costs a recovery
    "crc-storm": ("every reply's CRC corrupted for 0.3 s in every second",
                  {"crc_storms": tuple((0.5 + k, 0.8 + k) for k in range(3600))}),
    "chaotic-frames": ("TX frame numbers at random in [0, 2^32)", {"chaotic_frames": True}),
    "duplicate-replies": ("every TX reply sent twice, the copy 2 ms after the first",
                          {"duplicate_replies": ("TX",)}),
}


@dataclass
class SimTool:
    """A tool moving on a Lissajous path around ``centre_mm`` (tracker frame)."""

    name: str
    centre_mm: tuple = (0.0, 0.0, -1500.0)
    amplitude_mm: tuple = (80.0, 60.0, 40.0)
    period_s: tuple = (7.0, 5.0, 11.0)
    noise_mm: float = 0.05
    volume_radius_mm: float = 1e9         # beyond this from the centre: out of volume
    rom: bytes = field(default=b"\x00" * 64, repr=False)

    def pose(self, t, rng):
        c = np.asarray(self.centre_mm, float)
        a = np.asarray(self.amplitude_mm, float)
        w = 2 * np.pi / np.asarray(self.period_s, float)
        p = c + a * np.sin(w * t) + rng.normal(0.0, self.noise_mm, 3)
        ang = 0.3 * np.sin(0.5 * t)
        axis = np.array([np.cos(0.2 * t), np.sin(0.2 * t), 0.3])
        axis /= np.linalg.norm(axis)
        q = np.r_[np.cos(ang / 2), np.sin(ang / 2) * axis]
        out = np.linalg.norm(p - c) > self.volume_radius_mm
        return q, p, out


class NDISimulator:
    """Run with ``start()`` (returns the serial port path), stop with ``stop()``."""

    def __init__(self, tools=None, rate_hz=60.0, faults=None, seed=0):
        self.tools = list(tools or [SimTool("CameraTool"),
                                    SimTool("LaserTool", centre_mm=(100.0, 20.0, -1400.0))])
        self.rate_hz = float(rate_hz)
        self.faults = faults or Faults()
        self.rng = seeded_rng(seed)
        self._master = self._slave = None
        self._thread = None
        self._stop = threading.Event()
        self.port = None
        self.counters = {"replies": 0, "crc_corrupted": 0, "slow": 0, "disconnects": 0,
                         "commands": 0, "duplicated": 0, "chaotic_frames": 0}
        self._done_disconnects = set()   # survives resets: each scheduled disconnect once
        self._first_start = None         # the first TSTART (the CRC storm's clock)
        self._reset_state()

    # -- device state ----------------------------------------------------------
    def _reset_state(self):
        self.initialized = False
        self.tracking = False
        self.handles = {}             # handle -> dict(tool, status flags)
        self._next_handle = 1
        self._t0 = None
        self._silent_until = 0.0
        self._dropouts = {}           # handle -> end time of the current burst

    def _frame(self, now):
        return int((now - self._t0) * self.rate_hz) + 1 if self._t0 is not None else 0

    # -- pty -------------------------------------------------------------------
    def start(self):
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._run, name="ndi-sim", daemon=True)
        self._thread.start()
        return self.port

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def _run(self):
        buf = b""
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self._master], [], [], 0.05)
            except (OSError, ValueError):
                return
            if not r:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                return
            buf += chunk
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                text = line.decode("ascii", "replace")
                reply = self._handle(text)
                if reply is not None:
                    self._send(reply, text.strip().partition(" ")[0].split(":")[0].upper())

    def _in_crc_storm(self):
        if not self.faults.crc_storms or self._first_start is None:
            return False
        t = time.monotonic() - self._first_start
        return any(start <= t < end for start, end in self.faults.crc_storms)

    def _send(self, reply, name=""):
        f = self.faults
        if f.slow_reply_rate and self.rng.random() < f.slow_reply_rate:
            self.counters["slow"] += 1
            time.sleep(f.slow_reply_s)
        if len(reply) > 5 and (self._in_crc_storm() or (
                f.crc_error_rate and self.rng.random() < f.crc_error_rate)):
            self.counters["crc_corrupted"] += 1
            b = bytearray(reply)
            k = len(b) - 2
            b[k] = ord("0") if b[k] != ord("0") else ord("1")
            reply = bytes(b)
        self.counters["replies"] += 1
        try:
            os.write(self._master, reply)
            if "*" in f.duplicate_replies or name in f.duplicate_replies:
                time.sleep(f.duplicate_delay_s)
                self.counters["duplicated"] += 1
                os.write(self._master, reply)
        except OSError:
            pass

    # -- commands ----------------------------------------------------------------
    def _handle(self, line):
        self.counters["commands"] += 1
        now = time.monotonic()
        if now < self._silent_until:
            return None                    # disconnected: nothing comes back
        if self._silent_until:
            self._silent_until = 0.0
            self._reset_state()            # the device comes back reset
        name, _, args = line.strip().partition(" ")
        name = name.split(":")[0].upper()
        if self.tracking and self._t0 is not None:
            for k, t_dis in enumerate(self.faults.disconnect_at_s):
                if k not in self._done_disconnects and now - self._t0 >= t_dis:
                    self._done_disconnects.add(k)
                    self.counters["disconnects"] += 1
                    self._silent_until = now + self.faults.disconnect_s
                    return None
        if name == "RESET":
            self._reset_state()
            return with_crc("RESET")
        if name == "INIT":
            self.initialized = True
            return with_crc("OKAY")
        if not self.initialized:
            return with_crc("ERROR10")     # system not initialised
        if name in ("COMM", "BEEP", "VER", "PHF"):
            return with_crc("OKAY" if name != "VER" else "FluoGuide NDI simulator 1.0")
        if name == "PHRQ":
            if len(self.handles) >= len(self.tools):
                return with_crc("ERROR0D")
            h = self._next_handle
            self._next_handle += 1
            self.handles[h] = {"tool": self.tools[len(self.handles)], "init": False, "enabled": False}
            return with_crc(f"{h:02X}")
        if name == "PVWR":
            return with_crc("OKAY") if self._handle_arg(args) in self.handles else with_crc("ERROR08")
        if name == "PHSR":
            which = args.strip() or "00"
            sel = {h: s for h, s in self.handles.items()
                   if which == "00" or (which == "02" and not s["init"])
                   or (which == "03" and s["init"] and not s["enabled"])}
            return with_crc(format_phsr({h: self._status(s) for h, s in sel.items()}))
        if name in ("PINIT", "PENA", "PDIS"):
            h = self._handle_arg(args)
            if h not in self.handles:
                return with_crc("ERROR08")
            s = self.handles[h]
            if name == "PINIT":
                s["init"] = True
            elif name == "PENA":
                if not s["init"]:
                    return with_crc("ERROR0E")
                s["enabled"] = True
            else:
                s["enabled"] = False
            return with_crc("OKAY")
        if name == "TSTART":
            self.tracking = True
            self._t0 = now
            if self._first_start is None:
                self._first_start = now
            return with_crc("OKAY")
        if name == "TSTOP":
            self.tracking = False
            return with_crc("OKAY")
        if name == "TX":
            if not self.tracking:
                return with_crc("ERROR0C")
            return with_crc(self._tx(now))
        return with_crc("ERROR01")

    @staticmethod
    def _handle_arg(args):
        try:
            return int(args.strip()[:2], 16)
        except ValueError:
            return -1

    @staticmethod
    def _status(s):
        return PORT_OCCUPIED | (PORT_INITIALIZED if s["init"] else 0) | (PORT_ENABLED if s["enabled"] else 0)

    def _tx(self, now):
        t = now - self._t0
        frame = self._frame(now)
        f = self.faults
        if f.chaotic_frames:
            self.counters["chaotic_frames"] += 1
            frame = int(self.rng.integers(0, 2**32))
        recs = []
        for h, s in sorted(self.handles.items()):
            if not s["enabled"]:
                recs.append((h, "DISABLED", None, None, None, 0))
                continue
            status = self._status(s)
            if f.dropout_rate_per_s and h not in self._dropouts and \
                    self.rng.random() < f.dropout_rate_per_s / self.rate_hz:
                self._dropouts[h] = now + f.dropout_s
            if self._dropouts.get(h, 0) > now:
                recs.append((h, "MISSING", None, None, None, status))
                continue
            self._dropouts.pop(h, None)
            q, p, out = s["tool"].pose(t, self.rng)
            if out:
                recs.append((h, "MISSING", None, None, None, status | PORT_OUT_OF_VOLUME))
                continue
            recs.append((h, "OK", q, p, 0.12, status))
        return format_tx(recs, frame)
