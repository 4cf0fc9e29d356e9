"""NDI tracker client over pyserial: set-up, tracking loop, fault recovery and
an exact account of every frame.

Every reply's CRC is checked (``ndi_protocol.check_reply``).  A bad CRC, a
time-out or a malformed reply is counted and the request retried; after
``max_failures`` failures in a row the client recovers: reset, INIT, tool
set-up, TSTART.  Frame numbers come from the device; every number between
the first and the last frame of a tracking session is either delivered or
counted as ``missing`` (reported), so ``lost_unreported`` is computed, not
assumed, and must be 0.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from FluoNavLib.devices.ndi_protocol import (
    NDIProtocolError,
    check_reply,
    command,
    parse_phsr,
    parse_tx,
)

__all__ = ["NDIClient", "TrackingStats", "parse_handle"]

log = logging.getLogger("fluoguide.ndi")

# The longest reply read [bytes]: a TX reply for 16 tools in text mode is under
# 2 KB; a device streaming bytes without a CR must not grow the buffer forever
MAX_REPLY_BYTES = 64 * 1024


def parse_handle(body):
    """The port handle of a PHRQ reply: two hex digits (raises NDIProtocolError)."""
    if len(body) != 2 or any(c not in "0123456789ABCDEFabcdef" for c in body):
        raise NDIProtocolError(f"PHRQ reply is not a port handle: {body[:40]!r}")
    return int(body, 16)


@dataclass
class TrackingStats:
    frames: int = 0               # distinct device frames delivered
    missing: int = 0              # device frames skipped between deliveries (reported gaps)
    tool_missing: int = 0         # tool records MISSING (occluded / out of volume) in delivered frames
    out_of_volume: int = 0
    crc_errors: int = 0
    timeouts: int = 0
    malformed: int = 0
    device_errors: int = 0
    recovered: int = 0
    duplicates: int = 0           # polls that returned an already delivered frame
    segments: list = field(default_factory=list)   # (first, last) frame per tracking session
    open_segment: tuple = None    # (first, last) of the session still running

    def lost_unreported(self):
        spans = self.segments + ([self.open_segment] if self.open_segment else [])
        expected = sum(last - first + 1 for first, last in spans)
        return expected - self.frames - self.missing


class NDIClient:
    """Talk to an NDI tracker (or the simulator) on ``port``."""

    def __init__(self, port, timeout_s=0.25, baud=115200, max_failures=3):
        self.port_name = port
        self.timeout_s = float(timeout_s)
        self.baud = int(baud)
        self.max_failures = int(max_failures)
        self.serial = None
        self.handles = []
        self.stats = TrackingStats()
        self._last_frame = None
        self._segment_first = None
        self._roms = []

    # -- transport -------------------------------------------------------------
    def open(self):
        import serial

        self.serial = serial.Serial(self.port_name, 9600, timeout=self.timeout_s)
        return self

    def close(self):
        if self.serial is not None:
            self._close_segment()
            try:
                self.serial.close()
            finally:
                self.serial = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    def _request(self, name, *args):
        """Send a command and return the checked reply body (raises NDIProtocolError)."""
        self.serial.reset_input_buffer()
        self.serial.write(command(name, *args))
        raw = self.serial.read_until(b"\r", MAX_REPLY_BYTES)
        if not raw:
            raise NDIProtocolError(f"no reply to {name} within {self.timeout_s} s", "timeout")
        if not raw.endswith(b"\r") and len(raw) >= MAX_REPLY_BYTES:
            self.serial.reset_input_buffer()
            raise NDIProtocolError(f"reply to {name} longer than {MAX_REPLY_BYTES} bytes "
                                   "without an end")
        return check_reply(raw)

    def _request_retry(self, name, *args, tries=3):
        """A set-up command, retried on a corrupted or missing reply (counted)."""
        for k in range(tries):
            try:
                return self._request(name, *args)
            except NDIProtocolError as exc:
                if exc.kind not in ("crc", "timeout") or k == tries - 1:
                    raise
                setattr(self.stats, "crc_errors" if exc.kind == "crc" else "timeouts",
                        getattr(self.stats, "crc_errors" if exc.kind == "crc" else "timeouts") + 1)
                log.info("%s: %s, retrying", name, exc)

    def _expect_okay(self, name, *args):
        body = self._request_retry(name, *args)
        if body != "OKAY":
            raise NDIProtocolError(f"{name}: expected OKAY, got {body[:40]!r}")

    # -- set-up ----------------------------------------------------------------
    def reset(self):
        """Serial break (real devices reset on it) then RESET; back at 9600 baud."""
        try:
            self.serial.send_break(0.25)
        except Exception:  # a pty or some adapters cannot send a break
            pass
        self.serial.baudrate = 9600
        body = self._request_retry("RESET", "0")
        if body != "RESET":
            raise NDIProtocolError(f"RESET: got {body[:40]!r}")

    def initialize(self, roms=()):
        """RESET, INIT, COMM (115200 8N1), then request, load, initialise and enable tools.

        ``roms``: passive-tool definition files (bytes), one handle each.
        """
        self._roms = [bytes(r) for r in roms]
        self.reset()
        self._expect_okay("INIT")
        self._expect_okay("COMM", "50000")       # 115200 baud, 8N1, no handshake
        self.serial.baudrate = self.baud
        self.handles = []
        for rom in self._roms:
            h = parse_handle(self._request_retry("PHRQ", "*********1****"))
            for off in range(0, len(rom), 64):
                chunk = rom[off:off + 64].ljust(64, b"\x00")
                self._expect_okay("PVWR", f"{h:02X}{off:04X}{chunk.hex().upper()}")
            self.handles.append(h)
        for h in parse_phsr(self._request_retry("PHSR", "02")):
            self._expect_okay("PINIT", f"{h:02X}")
        for h in parse_phsr(self._request_retry("PHSR", "03")):
            self._expect_okay("PENA", f"{h:02X}D")
        return self.handles

    def start(self):
        self._close_segment()
        self._expect_okay("TSTART")

    def stop(self):
        self._close_segment()
        try:
            self._expect_okay("TSTOP")
        except NDIProtocolError as exc:
            log.warning("TSTOP failed: %s", exc)

    def _close_segment(self):
        if self._segment_first is not None and self._last_frame is not None:
            self.stats.segments.append((self._segment_first, self._last_frame))
        self._segment_first = self._last_frame = None
        self.stats.open_segment = None

    # -- tracking --------------------------------------------------------------
    def poll(self):
        """One TX request: a TXReply with a new frame, or None (duplicate frame).

        Raises NDIProtocolError after counting it; the caller retries or recovers.
        """
        try:
            body = self._request("TX", "0001")
            reply = parse_tx(body)
        except NDIProtocolError as exc:
            key = {"crc": "crc_errors", "timeout": "timeouts", "error": "device_errors"}.get(
                exc.kind, "malformed")
            setattr(self.stats, key, getattr(self.stats, key) + 1)
            log.info("TX failed (%s): %s", exc.kind, exc)
            raise
        frames = [p.frame for p in reply.tools.values() if p.frame is not None]
        if not frames:
            return reply
        f = max(frames)
        if self._last_frame is not None and f <= self._last_frame:
            if f < self._last_frame:        # counter went back: the device restarted
                self._close_segment()
            else:
                self.stats.duplicates += 1
                return None
        if self._last_frame is not None and f > self._last_frame + 1:
            self.stats.missing += f - self._last_frame - 1
        if self._segment_first is None:
            self._segment_first = f
        self._last_frame = f
        self.stats.open_segment = (self._segment_first, f)
        self.stats.frames += 1
        for p in reply.tools.values():
            if p.state == "MISSING":
                self.stats.tool_missing += 1
                if p.out_of_volume:
                    self.stats.out_of_volume += 1
        return reply

    def recover(self):
        """Re-establish tracking after repeated failures (reset, init, tools, start)."""
        self._close_segment()
        for attempt in range(5):
            try:
                self.initialize(self._roms)
                self.start()
                self.stats.recovered += 1
                log.warning("tracker recovered (attempt %d)", attempt + 1)
                return True
            except NDIProtocolError as exc:
                log.info("recovery attempt %d failed: %s", attempt + 1, exc)
                time.sleep(0.2)
        return False

    def track(self, seconds, on_frame=None, rate_hz=60.0):
        """Poll for ``seconds``; ``on_frame(reply, t_host)`` for each new frame."""
        t_end = time.monotonic() + float(seconds)
        failures = 0
        period = 1.0 / (2.0 * rate_hz)       # poll at twice the frame rate: no frame skipped
        while time.monotonic() < t_end:
            t0 = time.monotonic()
            try:
                reply = self.poll()
                failures = 0
            except NDIProtocolError:
                failures += 1
                if failures >= self.max_failures:
                    if not self.recover():
                        raise
                    failures = 0
                continue
            if reply is not None and on_frame is not None:
                on_frame(reply, t0)
            dt = period - (time.monotonic() - t0)
            if dt > 0:
                time.sleep(dt)
        # the session stays open: a later track() call continues it, so a frame
        # skipped between two calls is still counted as missing
        return self.stats
