"""OpenIGTLink input (from PLUS or any server) into the MRML scene, as
SlicerOpenIGTLink maps it: a TRANSFORM message named ``CameraToolToTracker``
updates (or creates) the linear transform node of that name, an IMAGE message
updates the scalar volume node of its device name, and each node carries the
message time in the attribute ``FluoNav.IGTLTimestamp``.

The receive loop is our own (pyigtl only encodes and decodes message bodies):
it runs in the caller's thread, so a peer cannot leave threads behind, and it
trusts nothing the server sends:

- every read has a deadline: a server that sends half a header and goes quiet,
  or trickles a body byte by byte, ends the run on time;
- a header announcing a body larger than ``max_body_bytes`` is refused before
  any of it is read (memory stays bounded);
- the CRC-64 of every body is checked; a bad CRC, an unknown header version or
  bytes that are not a header end the connection (the framing is lost) and are
  reported as a device error, not as the user's bad input;
- a message whose content is not finite (NaN in a pose) is counted as rejected
  and never reaches the scene;
- a run (:meth:`IGTLReceiver.receive`) in which the server sent no usable
  message (it stayed silent, sent half a header and held, closed after a
  header or in a body, or sent only rejected or unmapped messages) is a device
  error saying what arrived, never an empty success (issue #34).

Every message is applied (nothing is dropped between polls). Messages the
sender lost are counted from a ``seq`` metadata field when the sender puts one
(OpenIGTLink header version 2), otherwise from timestamp gaps larger than 1.5
nominal periods; implausible jumps (a sequence reset, a clock jump) are counted
as such, not as millions of lost messages.
"""

from __future__ import annotations

import socket
import struct
import time

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoDeviceError, FluoInputError, check_number

__all__ = ["IGTLReceiver", "TIMESTAMP_ATTRIBUTE"]

TIMESTAMP_ATTRIBUTE = "FluoNav.IGTLTimestamp"
HEADER_SIZE = 58
_HEADER = struct.Struct("> H 12s 20s I I Q Q")
# A sequence or timestamp jump beyond this many messages is a reset, not a loss.
MAX_PLAUSIBLE_GAP = 10_000
# The message types that reach the scene (the others are counted as ignored).
MAPPED_TYPES = ("TRANSFORM", "IMAGE")


class IGTLReceiver:
    """Read an OpenIGTLink server and write what arrives into ``scene``.

    Parameters
    ----------
    scene : vtkMRMLScene
    host, port : server address
    nominal_rate_hz : float, optional
        Expected message rate per device, for loss counting by timestamps when
        the sender puts no ``seq`` metadata.
    max_body_bytes : int
        Largest message body accepted (default 64 MiB: a 4K RGB frame is 25 MB).
    """

    def __init__(self, scene, host="127.0.0.1", port=18944, nominal_rate_hz=None,
                 max_body_bytes=64 * 2**20):
        self.scene = scene
        check_number("port", port, 1, 65535, integer=True)
        if nominal_rate_hz is not None:
            check_number("nominal_rate_hz", nominal_rate_hz, 0.0, 10_000.0, lo_open=True)
        self.host, self.port = host, int(port)
        self.nominal_rate_hz = nominal_rate_hz
        self.max_body_bytes = int(max_body_bytes)
        self.sock = None
        self.received = {}       # device -> messages applied
        self.lost = {}           # device -> messages known to be lost
        self.rejected = {}       # device -> messages with unusable content (NaN, bad shape)
        self.resets = {}         # device -> implausible seq / timestamp jumps
        self.ignored_types = {}  # message type -> count (types we do not map)
        self.first_seq = {}      # device -> first sequence number seen (senders count from 0)
        self.closed_by_peer = False
        self._last_seq = {}
        self._last_ts = {}
        self._buffer = b""

    # ---------------------------------------------------------------- connection
    def connect(self, timeout_s=5.0):
        try:
            self.sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        except socket.gaierror:
            raise FluoInputError("host name does not resolve", field="--igtl",
                                 value=f"{self.host}:{self.port}") from None
        except OSError:
            raise FluoInputError("no OpenIGTLink server answered", field="--igtl",
                                 value=f"{self.host}:{self.port}") from None
        return self

    def close(self):
        if self.sock is not None:
            try:
                self.sock.close()
            finally:
                self.sock = None

    def __enter__(self):
        return self.connect()

    def __exit__(self, *exc):
        self.close()

    # ---------------------------------------------------------------- reading
    def _device_error(self, problem):
        self.close()
        raise FluoDeviceError(f"OpenIGTLink server {self.host}:{self.port}: {problem}")

    def _next_message(self, deadline):
        """One decoded pyigtl message, or None at the deadline / when the peer closed."""
        import pyigtl
        from pyigtl.messages import CRC64

        # a partial header or body stays in the buffer across calls
        if len(self._buffer) < HEADER_SIZE and self._read_exact_peek(HEADER_SIZE, deadline) is None:
            return None
        header = self._buffer[:HEADER_SIZE]
        version, mtype, device, sec, frac, body_size, crc = _HEADER.unpack(header)
        if version not in (1, 2, 3):
            self._device_error(f"not an OpenIGTLink header (version {version})")
        try:
            mtype = mtype.decode("ascii").rstrip(" \t\r\n\0")
            device = device.decode("utf-8").rstrip(" \t\r\n\0")
        except UnicodeDecodeError:
            self._device_error("header with undecodable type or device name")
        if not mtype.isprintable() or not mtype:
            self._device_error("header with an unprintable message type")
        if body_size > self.max_body_bytes:
            self._device_error(f"message body of {body_size} bytes announced "
                               f"(limit {self.max_body_bytes})")
        if self._read_exact_peek(HEADER_SIZE + body_size, deadline) is None:
            return None
        body = self._buffer[HEADER_SIZE:HEADER_SIZE + body_size]
        self._buffer = self._buffer[HEADER_SIZE + body_size:]
        if CRC64(body) != crc:
            self._device_error(f"CRC mismatch in a {mtype} message from {device!r}")
        # a type we do not map is counted, not decoded: pyigtl's decoders of other types
        # (STRING's text encodings, POINT) are code a hostile body need not reach
        message = pyigtl.MessageBase.create_message(mtype) if mtype in MAPPED_TYPES else None
        if message is None:
            self.ignored_types[mtype] = self.ignored_types.get(mtype, 0) + 1
            return False
        fields = {"header_version": version, "message_type": mtype, "device_name": device,
                  "timestamp": sec + frac / 2.0**32, "body_size": body_size}
        try:
            message.unpack(fields, body)
        except Exception as exc:  # noqa: BLE001 - pyigtl decoding untrusted bytes raises
            # anything (struct.error, ValueError, NotImplementedError for a sub-volume,
            # TypeError from its own `raise "text"` on bad metadata): the peer's fault
            self._device_error(f"malformed {mtype} body from {device!r} "
                               f"({type(exc).__name__}: {exc})")
        return message

    def _read_exact_peek(self, n, deadline):
        """Fill the buffer to ``n`` bytes without consuming; None at deadline or close."""
        while len(self._buffer) < n:
            left = deadline - time.monotonic()
            if left <= 0 or self.sock is None:
                return None
            self.sock.settimeout(min(left, 0.25))
            try:
                chunk = self.sock.recv(min(n - len(self._buffer), 1 << 20))
            except socket.timeout:
                continue
            except OSError as exc:
                raise FluoDeviceError(f"OpenIGTLink connection failed: {exc}") from None
            if not chunk:
                self.closed_by_peer = True
                return None
            self._buffer += chunk
        return True

    # ---------------------------------------------------------------- applying
    def poll(self, budget_s=0.05):
        """Apply every message that arrives within ``budget_s``; returns the devices updated."""
        if self.sock is None:
            raise FluoDeviceError("OpenIGTLink receiver is not connected")
        deadline = time.monotonic() + budget_s
        updated = []
        while not self.closed_by_peer:
            msg = self._next_message(deadline)
            if msg is None:
                break
            if msg is False:
                continue
            if self._apply(msg):
                updated.append(msg.device_name)
        return updated

    def _apply(self, msg):
        name = msg.device_name
        if msg.message_type in ("TRANSFORM", "IMAGE"):
            self._account(name, msg)  # it arrived: a rejected message is not a lost one
        if msg.message_type == "TRANSFORM":
            matrix = np.asarray(msg.matrix, float)
            if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
                self.rejected[name] = self.rejected.get(name, 0) + 1
                return False
            node = mrml_io.set_transform(self.scene, name, matrix)
        elif msg.message_type == "IMAGE":
            node = self._image(name, msg)
            if node is None:
                self.rejected[name] = self.rejected.get(name, 0) + 1
                return False
        else:
            self.ignored_types[msg.message_type] = self.ignored_types.get(msg.message_type, 0) + 1
            return False
        node.SetAttribute(TIMESTAMP_ATTRIBUTE, repr(float(msg.timestamp)))
        self.received[name] = self.received.get(name, 0) + 1
        return True

    def _account(self, name, msg):
        seq = (msg.metadata or {}).get("seq")
        try:
            seq = None if seq is None else int(seq)
        except (TypeError, ValueError):
            seq = None
        if seq is not None:
            last = self._last_seq.get(name)
            self.first_seq.setdefault(name, seq)
            if last is not None:
                gap = seq - last - 1
                if gap < 0 or gap > MAX_PLAUSIBLE_GAP:
                    self.resets[name] = self.resets.get(name, 0) + 1
                elif gap > 0:
                    self.lost[name] = self.lost.get(name, 0) + gap
            self._last_seq[name] = seq
        elif self.nominal_rate_hz:
            last = self._last_ts.get(name)
            period = 1.0 / self.nominal_rate_hz
            if last is not None:
                missing = int(round((msg.timestamp - last) / period)) - 1
                if msg.timestamp < last or missing > MAX_PLAUSIBLE_GAP:
                    self.resets[name] = self.resets.get(name, 0) + 1
                elif msg.timestamp - last > 1.5 * period:
                    self.lost[name] = self.lost.get(name, 0) + missing
            self._last_ts[name] = msg.timestamp

    def _image(self, name, msg):
        img = np.asarray(msg.image)
        if img.ndim == 2:
            img = img[None]
        m = np.asarray(msg.ijk_to_world_matrix, float)
        if img.ndim != 3 or m.shape != (4, 4) or not np.all(np.isfinite(m)):
            return None
        spacing = np.linalg.norm(m[:3, :3], axis=0)
        if np.any(spacing <= 0):
            return None
        direction = m[:3, :3] / spacing
        try:
            return mrml_io.add_volume(self.scene, name, img, spacing, m[:3, 3], direction=direction)
        except FluoInputError:  # a voxel type or shape MRML cannot hold: the device's fault
            return None

    def receive(self, seconds, stop=None):
        """Apply messages for ``seconds`` [s] (ends on time whatever the server
        does), or until ``stop()`` is true (asked between reads).

        Returns
        -------
        dict
            ``received``, ``lost``, ``rejected``, ``resets`` per device,
            ``ignored_types``, and ``closed_by_peer``.

        Raises
        ------
        FluoDeviceError
            The server sent no message that reached the scene within ``seconds``
            (or closed the connection before one did) and ``stop`` did not end
            it; the message says what arrived instead.
        """
        seconds = float(seconds)
        if not np.isfinite(seconds) or seconds <= 0 or seconds > 86400:
            raise FluoInputError("must be a number of seconds in (0, 86400]", field="--seconds",
                                 value=seconds)
        t0 = time.monotonic()
        t_end = t0 + seconds
        stopped = False
        while time.monotonic() < t_end and not self.closed_by_peer:
            if stop is not None and stop():
                stopped = True
                break
            self.poll(budget_s=max(0.0, min(0.1, t_end - time.monotonic())))
        if not self.received and not stopped:
            # nothing reached the scene: a peer failure, not an empty success
            self._device_error(self._nothing_usable(time.monotonic() - t0))
        return {"received": dict(self.received), "lost": dict(self.lost),
                "rejected": dict(self.rejected), "resets": dict(self.resets),
                "ignored_types": dict(self.ignored_types), "closed_by_peer": self.closed_by_peer}

    def _nothing_usable(self, elapsed_s):
        """What the server sent instead of a usable message, in words."""
        what = []
        if self.rejected:
            what.append(f"{sum(self.rejected.values())} messages rejected (not a finite pose "
                        f"or image) from {', '.join(sorted(self.rejected))}")
        if self.ignored_types:
            what.append("only message types that are not mapped (" + ", ".join(
                f"{k} x{v}" for k, v in sorted(self.ignored_types.items())) + ")")
        n = len(self._buffer)
        if n >= HEADER_SIZE:
            _, mtype, _, _, _, body_size, _ = _HEADER.unpack(self._buffer[:HEADER_SIZE])
            mtype = mtype.decode("ascii", "replace").rstrip(" \t\r\n\0")
            what.append(f"a {mtype} header announcing a {body_size}-byte body of which "
                        f"{n - HEADER_SIZE} bytes arrived")
        elif n:
            what.append(f"{n} of the {HEADER_SIZE} bytes of a header")
        if not what:
            return (f"closed the connection after {elapsed_s:.1f} s without sending anything"
                    if self.closed_by_peer else f"sent nothing in {elapsed_s:.1f} s")
        end = "then closed the connection" if self.closed_by_peer else "then nothing more"
        return f"no usable message in {elapsed_s:.1f} s: {'; '.join(what)}, {end}"
