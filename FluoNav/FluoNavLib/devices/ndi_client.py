"""NDI tracker client over pyserial: set-up, tracking loop, fault recovery and
an exact account of every frame.

Every reply's CRC is checked (``ndi_protocol.check_reply``).  A bad CRC, a
time-out or a malformed reply is counted and the request retried; after
``max_failures`` failures in a row the client recovers: reset, INIT, tool
set-up, TSTART.  Frame numbers come from the device; every number between
the first and the last frame of a tracking session is either delivered or
counted as ``missing`` (reported), so ``lost_unreported`` is computed, not
assumed, and must be 0.

A device that misbehaves is reported as such, not as numbers (issue #34):

- replies are matched to their requests: each is checked for its CRC and its
  type (a TX reply parses as one, set-up commands get OKAY, a handle, a PHSR
  list), and bytes nobody asked for (a second reply to one request, found
  before the next request or right behind a reply) are counted as
  ``duplicate_replies``; the stream is drained until quiet (resynchronised)
  and a reply that may be stale is not used; the frames of the TX replies read
  and not used are remembered, so a late copy of one of them, taken for the answer
  to a later request, is not delivered (``stale_replies``: a drain that ends before
  the copy comes cannot tell). :data:`DUPLICATE_LIMIT` of them
  among :data:`DUPLICATE_WINDOW` requests refuse the device
  (``FluoDeviceError``): its replies cannot be matched to its requests;
- a frame counter that jumps further than the device could have counted in
  the time since the last frame (:data:`MAX_FRAME_RATE_HZ`), or goes back
  without a reset, is a ``counter_jumps`` (a new segment: no missing frames
  are counted across it); more than :data:`MAX_COUNTER_JUMPS` refuse the
  device, instead of reporting billions of missing frames;
- faults and recoveries are counted in ``stats``; the log gets at most one
  line per kind of fault every :data:`LOG_EVERY_S` seconds (a CRC storm of
  thousands of replies is a count, not thousands of lines).
"""

from __future__ import annotations

import collections
import logging
import math
import time
from dataclasses import dataclass, field

from fluoguide.errors import FluoDeviceError
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
# Unrequested replies among the last DUPLICATE_WINDOW requests that refuse the device:
# one is a glitch (counted, resynchronised); a device that answers twice does it to all
DUPLICATE_WINDOW = 10
DUPLICATE_LIMIT = 3
# Draining the stream after unrequested bytes: until this long without a byte [s],
# and at most RESYNC_MAX_S (a device that never stops is refused)
RESYNC_QUIET_S = 0.02
RESYNC_MAX_S = 0.5
# No NDI tracker counts frames faster (Polaris Vega 400 Hz, Aurora 40 Hz) [Hz]: a
# larger step of the frame counter than this rate allows is a counter fault
MAX_FRAME_RATE_HZ = 1000.0
# Counter faults a tracking session tolerates (a restart of the device's counter
# now and then); more and the frame numbers cannot be trusted
MAX_COUNTER_JUMPS = 3
# At most one log line per kind of fault in this time [s]; the rest are counted
LOG_EVERY_S = 10.0


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
    duplicate_replies: int = 0    # replies nobody asked for (a second reply to a request)
    late_replies: int = 0         # replies that came after their request had timed out
    stale_replies: int = 0        # replies with a frame the line already carried unused (a copy)
    counter_jumps: int = 0        # implausible steps of the device's frame counter
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
        self._last_frame_t = None     # when the request of the last new frame was sent [s]
        self._sent_at = None          # when the last request was sent [s, monotonic]
        self._segment_first = None
        self._roms = []
        self._answered = True         # the last request got its reply (not a time-out)
        self._expect_stray = False    # a serial break: the device's own RESET reply may come
        self._recent = collections.deque(maxlen=DUPLICATE_WINDOW)
        self._last_jump = None
        self._line_frame = None       # the highest frame of a TX reply read and not used
        self._logged = {}             # fault kind -> (last log time, events not logged)

    # -- transport -------------------------------------------------------------
    def open(self):
        import serial

        self.serial = serial.Serial(self.port_name, 9600, timeout=self.timeout_s)
        self._expect_stray = True    # what the device sent before we opened it is not a reply
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

    def _note(self, kind, message, *args):
        """Log a fault of ``kind``: at most one line per kind every LOG_EVERY_S seconds,
        with the number not logged since (the counts are in ``stats``)."""
        now = time.monotonic()
        last, skipped = self._logged.get(kind, (None, 0))
        if last is not None and now - last < LOG_EVERY_S:
            self._logged[kind] = (last, skipped + 1)
            return
        if skipped:
            message += f" ({skipped} more like it not logged)"
        self._logged[kind] = (now, 0)
        log.info(message, *args)

    def _drain(self):
        """Read and drop bytes until the line is quiet for RESYNC_QUIET_S; the number of
        bytes dropped. A device that keeps sending for RESYNC_MAX_S is refused."""
        dropped = 0
        data = b""
        t_end = time.monotonic() + RESYNC_MAX_S
        quiet_from = time.monotonic()
        while time.monotonic() - quiet_from < RESYNC_QUIET_S:
            n = self.serial.in_waiting
            if n:
                chunk = self.serial.read(min(n, MAX_REPLY_BYTES))
                dropped += len(chunk)
                data = (data + chunk)[-MAX_REPLY_BYTES:]
                quiet_from = time.monotonic()
                if time.monotonic() > t_end:
                    raise FluoDeviceError(f"tracker on {self.port_name} keeps sending without "
                                          f"a request ({dropped} bytes in {RESYNC_MAX_S:g} s)")
            else:
                time.sleep(0.002)
        self._unused(data)
        return dropped

    def _unused(self, data):
        """Remember the highest frame among the TX replies in ``data``, bytes read from
        the line and not used: a copy of one of them may still come, late, and be taken
        for the answer to a later request (``poll`` does not deliver it)."""
        for part in bytes(data).split(b"\r"):
            try:
                reply = parse_tx(check_reply(part + b"\r"))
            except NDIProtocolError:
                continue        # a set-up reply, a fragment or garbage: no frame to remember
            frames = [p.frame for p in reply.tools.values() if p.frame is not None]
            if frames and (self._line_frame is None or max(frames) > self._line_frame):
                self._line_frame = max(frames)

    def _unrequested(self, name, where):
        """Bytes nobody asked for were found ``where`` (before / right behind the reply to
        ``name``): counted, the stream resynchronised, the device refused when it keeps
        doing it (its replies cannot be matched to its requests)."""
        dropped = self._drain()
        self.stats.duplicate_replies += 1
        self._recent.append(True)
        self._note("duplicate", "%d bytes nobody asked for %s %s (resynchronised)", dropped,
                   where, name)
        if sum(self._recent) >= DUPLICATE_LIMIT:
            raise FluoDeviceError(
                f"tracker on {self.port_name} answers requests more than once "
                f"({sum(self._recent)} unrequested replies in the last {len(self._recent)} "
                f"checks, the last {where} {name}): its replies cannot be matched to its "
                f"requests")

    def _request(self, name, *args):
        """Send a command and return the checked reply body (raises NDIProtocolError;
        FluoDeviceError for a device that answers requests more than once)."""
        stray = self.serial.in_waiting
        if stray:
            if self._answered and not self._expect_stray:
                # a reply came after the one its request got: a second reply
                self._unrequested(name, "before the request for")
            else:
                # the reply of a request that timed out, or the device's own RESET after a
                # break: late, not a second one
                self.stats.late_replies += 1
                self._drain()
        else:
            self._recent.append(False)
        self._expect_stray = False
        late = self.serial.in_waiting
        if late:
            # what came since is dropped, but seen: a copy of it may follow
            self._unused(self.serial.read(min(late, MAX_REPLY_BYTES)))
        self._sent_at = time.monotonic()
        self.serial.write(command(name, *args))
        self._answered = False
        raw = self.serial.read_until(b"\r", MAX_REPLY_BYTES)
        if not raw:
            raise NDIProtocolError(f"no reply to {name} within {self.timeout_s} s", "timeout")
        self._answered = True
        if not raw.endswith(b"\r") and len(raw) >= MAX_REPLY_BYTES:
            self.serial.reset_input_buffer()
            raise NDIProtocolError(f"reply to {name} longer than {MAX_REPLY_BYTES} bytes "
                                   "without an end")
        body = check_reply(raw)
        if self.serial.in_waiting:
            # more right behind the reply: this one may be the stale answer to an earlier
            # request; not used, and the next request starts on a quiet line
            self._unused(raw)
            self._unrequested(name, "right behind the reply to")
            raise NDIProtocolError(f"{name}: a second reply right behind the first "
                                   "(resynchronised)", "duplicate", raw)
        return body

    def _request_retry(self, name, *args, tries=3):
        """A set-up command, retried on a corrupted, missing or unmatched reply (counted;
        an unmatched one in ``duplicate_replies`` already)."""
        for k in range(tries):
            try:
                return self._request(name, *args)
            except NDIProtocolError as exc:
                if exc.kind not in ("crc", "timeout", "duplicate"):
                    raise
                if exc.kind != "duplicate":
                    key = "crc_errors" if exc.kind == "crc" else "timeouts"
                    setattr(self.stats, key, getattr(self.stats, key) + 1)
                if k == tries - 1:
                    raise
                self._note(exc.kind, "%s: %s, retrying", name, exc)

    def _expect_okay(self, name, *args):
        body = self._request_retry(name, *args)
        if body != "OKAY":
            raise NDIProtocolError(f"{name}: expected OKAY, got {body[:40]!r}")

    # -- set-up ----------------------------------------------------------------
    def reset(self):
        """Serial break (real devices reset on it) then RESET; back at 9600 baud."""
        try:
            self.serial.send_break(0.25)
            self._expect_stray = True    # the device answers a break with RESET itself
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
            # a device already gone or in trouble: its faults are in the stats, and the
            # caller's own report is the one line a user sees
            self._note("tstop", "TSTOP failed: %s", exc)

    def _close_segment(self):
        if self._segment_first is not None and self._last_frame is not None:
            self.stats.segments.append((self._segment_first, self._last_frame))
        self._segment_first = self._last_frame = self._last_frame_t = None
        self._line_frame = None
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
            if exc.kind != "duplicate":     # counted as duplicate_replies already
                key = {"crc": "crc_errors", "timeout": "timeouts",
                       "error": "device_errors"}.get(exc.kind, "malformed")
                setattr(self.stats, key, getattr(self.stats, key) + 1)
            self._note(exc.kind, "TX failed (%s): %s", exc.kind, exc)
            raise
        frames = [p.frame for p in reply.tools.values() if p.frame is not None]
        if not frames:
            return reply
        f = max(frames)
        now = time.monotonic()
        if self._last_frame is not None and f == self._last_frame:
            self.stats.duplicates += 1
            return None
        if self._line_frame is not None and f <= self._line_frame and (
                self._last_frame is None or f > self._last_frame):
            # the line carried this frame, or a later one, in a reply not used: this is a
            # late copy of it (a device that answers twice), the answer to an earlier
            # request; a frame this device makes again is as old (counted missing if
            # never delivered)
            self.stats.stale_replies += 1
            self._note("stale", "TX: frame %d came before, in a reply not used (not "
                       "delivered)", f)
            return None
        if self._last_frame is not None and not self._plausible_step(f, now):
            # a counter fault: a new segment, no missing frames counted across it
            self._counter_jump(self._last_frame, f, now - self._last_frame_t)
            self._close_segment()
        if self._last_frame is not None and f > self._last_frame + 1:
            self.stats.missing += f - self._last_frame - 1
        if self._segment_first is None:
            self._segment_first = f
        # the device sampled this frame after the request went out: the bound on the
        # next step counts from here (a reply that was slow to come does not shrink it)
        self._last_frame, self._last_frame_t = f, self._sent_at
        self.stats.open_segment = (self._segment_first, f)
        self.stats.frames += 1
        for p in reply.tools.values():
            if p.state == "MISSING":
                self.stats.tool_missing += 1
                if p.out_of_volume:
                    self.stats.out_of_volume += 1
        return reply

    def _plausible_step(self, frame, now):
        """True when the counter went forward by no more than the device could count
        between the request of the last new frame and this reply (``now``), at
        MAX_FRAME_RATE_HZ with one frame of slack."""
        if frame < self._last_frame:
            return False        # back without a reset (recover() starts a new segment)
        elapsed = max(0.0, now - self._last_frame_t)
        return frame - self._last_frame <= math.ceil(elapsed * MAX_FRAME_RATE_HZ) + 1

    def _counter_jump(self, last, frame, elapsed_s):
        self.stats.counter_jumps += 1
        self._last_jump = (last, frame, elapsed_s)
        self._note("counter", "frame counter jumped from %d to %d in %.3f s", last, frame,
                   elapsed_s)
        if self.stats.counter_jumps > MAX_COUNTER_JUMPS:
            raise FluoDeviceError(
                f"tracker on {self.port_name}: its frame counter jumped implausibly "
                f"{self.stats.counter_jumps} times in {self.stats.frames + 1} frames (the last "
                f"from {last} to {frame} in {elapsed_s:.3f} s; at most "
                f"{MAX_FRAME_RATE_HZ:g} frames/s are possible): its frame numbers and "
                f"missing-frame counts cannot be trusted")

    def recover(self):
        """Re-establish tracking after repeated failures (reset, init, tools, start)."""
        self._close_segment()
        for attempt in range(5):
            try:
                self.initialize(self._roms)
                self.start()
                self.stats.recovered += 1
                self._note("recovered", "tracker recovered (attempt %d)", attempt + 1)
                return True
            except NDIProtocolError as exc:
                self._note("recovery", "recovery attempt %d failed: %s", attempt + 1, exc)
                time.sleep(0.2)
        return False

    def track(self, seconds, on_frame=None, rate_hz=60.0, stop=None):
        """Poll for ``seconds`` [s], or until ``stop()`` is true (asked before each
        poll); ``on_frame(reply, t_host)`` for each new frame."""
        t_end = time.monotonic() + float(seconds)
        failures = 0
        period = 1.0 / (2.0 * rate_hz)       # poll at twice the frame rate: no frame skipped
        while time.monotonic() < t_end and not (stop is not None and stop()):
            t0 = time.monotonic()
            try:
                reply = self.poll()
                failures = 0
            except NDIProtocolError as exc:
                if exc.kind == "duplicate":
                    continue        # resynchronised; a device that keeps it up is refused
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
