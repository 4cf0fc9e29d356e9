"""OpenIGTLink servers that misbehave, on 127.0.0.1: every run ends on time, in
bounded memory, with a count or one clear device error; nothing reaches the
scene that is not a finite pose (issue #21)."""

import json
import os
import resource
import socket
import struct
import threading
import time

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoDeviceError
from FluoNavLib.devices.igtl_client import IGTLReceiver


def _message(device="CameraToTracker", matrix=None, seq=None, timestamp=1000.0, crc_ok=True):
    import pyigtl

    msg = pyigtl.TransformMessage(np.eye(4) if matrix is None else matrix,
                                  device_name=device, timestamp=timestamp)
    if seq is not None:
        msg.header_version = 2
        msg.metadata = {"seq": str(seq)}
    data = bytearray(msg.pack())
    if not crc_ok:
        data[-1] ^= 0xFF  # flip a body byte: the CRC no longer matches
    return bytes(data)


class Server:
    """A one-connection TCP server on 127.0.0.1 that runs ``script(conn)``."""

    def __init__(self, script):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(script,), daemon=True)
        self.thread.start()

    def _run(self, script):
        self.sock.settimeout(10)
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        with conn:
            try:
                script(conn, self.stop)
            except OSError:
                pass

    def close(self):
        self.stop.set()
        self.sock.close()
        self.thread.join(5)


def _run(script, seconds=1.5, **kw):
    srv = Server(script)
    rx = IGTLReceiver(mrml_io.new_scene(), "127.0.0.1", srv.port, **kw).connect(timeout_s=5)
    t0 = time.monotonic()
    try:
        out = rx.receive(seconds)
        err = None
    except FluoDeviceError as exc:
        out, err = None, str(exc)
    finally:
        rx.close()
        srv.close()
    return out, err, time.monotonic() - t0, rx


def test_half_a_header_then_silence_is_a_device_error_on_time():
    def script(conn, stop):
        conn.sendall(_message()[:20])
        stop.wait(10)

    out, err, took, _ = _run(script, seconds=1.0)
    # nothing usable in the run: an error naming what came, not an empty success
    assert out is None and "20 of the 58 bytes of a header, then nothing more" in err
    assert took < 3.0


def test_half_a_header_then_close_is_a_device_error():
    def script(conn, stop):
        conn.sendall(_message()[:20])

    out, err, took, _ = _run(script, seconds=5.0)
    assert out is None and "header, then closed the connection" in err and took < 3.0


def test_a_body_trickled_at_one_byte_per_second_ends_on_time():
    def script(conn, stop):
        data = _message()
        for b in data:
            if stop.is_set():
                return
            conn.sendall(bytes([b]))
            time.sleep(1.0)

    out, err, took, _ = _run(script, seconds=2.0)
    assert out is None and "bytes of a header, then nothing more" in err and took < 4.0


def test_a_header_announcing_a_gigabyte_is_refused_before_reading():
    def script(conn, stop):
        head = bytearray(_message()[:58])
        head[42:50] = struct.pack(">Q", 1000 * 2**20)
        conn.sendall(bytes(head))
        stop.wait(10)

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out, err, took, _ = _run(script)
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert err and "1048576000 bytes announced" in err
    assert grew_mb < 100


def test_wrong_crc_is_a_device_error():
    def script(conn, stop):
        conn.sendall(_message(crc_ok=False))
        stop.wait(10)

    out, err, took, _ = _run(script)
    assert err and "CRC mismatch" in err


def test_random_bytes_are_a_device_error_not_an_exit_0():
    rng = np.random.default_rng(0)

    def script(conn, stop):
        conn.sendall(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
        stop.wait(10)

    out, err, took, _ = _run(script)
    assert err and "OpenIGTLink" in err


def test_nan_pose_is_rejected_and_wild_seq_is_a_reset_not_billions_lost():
    def script(conn, stop):
        conn.sendall(_message(seq=0))
        conn.sendall(_message(seq=1, matrix=np.full((4, 4), np.nan)))
        conn.sendall(_message(seq=2))
        conn.sendall(_message(seq=4))                   # one lost
        conn.sendall(_message(seq=39_000_000_000_000_000))  # a wild jump
        conn.sendall(_message(seq=5))                   # and back: a reset too
        stop.wait(10)

    out, err, took, rx = _run(script, seconds=1.0)
    assert err is None
    assert out["received"]["CameraToTracker"] == 5
    assert out["rejected"]["CameraToTracker"] == 1
    assert out["lost"]["CameraToTracker"] == 1
    assert out["resets"]["CameraToTracker"] == 2
    # the NaN pose never reached the scene
    assert np.all(np.isfinite(mrml_io.get_transform(rx.scene, "CameraToTracker")))


def test_cli_track_igtl_garbage_is_one_line_exit_1(capsys):
    from fluoapp.cli import main

    def script(conn, stop):
        conn.sendall(os.urandom(2048))
        stop.wait(10)

    srv = Server(script)
    try:
        rc = main(["track", "--igtl", f"127.0.0.1:{srv.port}", "--seconds", "2", "--json"])
    finally:
        srv.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "OpenIGTLink" in err[0]


def test_cli_track_igtl_unresolvable_host_is_exit_2(capsys):
    from fluoapp.cli import main

    rc = main(["track", "--igtl", "no-such-host.invalid:18944", "--seconds", "1", "--json"])
    assert rc == 2 and "does not resolve" in capsys.readouterr().err


# ---------------------------------------------------------------- fluo track --igtl (issue #34)
# Each server below sent nothing usable and `fluo track --igtl ... --json` printed
# {"lost": {}, "received": {}} with exit 0; now one line, exit 1, on time.
def _header(body_size):
    head = bytearray(_message()[:58])
    head[42:50] = struct.pack(">Q", body_size)
    return bytes(head)


def _hold(conn, stop, data):
    conn.sendall(data)
    stop.wait(10)


@pytest.mark.parametrize("script, seconds, needle", [
    # announces a body of 2^64-1 bytes (the largest the field holds) and holds
    (lambda c, s: _hold(c, s, _header(2**64 - 1)), 5.0,
     "message body of 18446744073709551615 bytes announced (limit 67108864)"),
    # half a header, then holds the connection
    (lambda c, s: _hold(c, s, _message()[:29]), 1.0,
     "no usable message in 1.0 s: 29 of the 58 bytes of a header, then nothing more"),
    # a whole header (a 48-byte TRANSFORM body announced), then closes
    (lambda c, s: c.sendall(_message()[:58]), 5.0,
     "a TRANSFORM header announcing a 48-byte body of which 0 bytes arrived, then closed"),
    # a header and 10 of its 48 body bytes, then holds
    (lambda c, s: _hold(c, s, _message()[:68]), 1.0,
     "a TRANSFORM header announcing a 48-byte body of which 10 bytes arrived, then nothing"),
    # accepts and stays silent
    (lambda c, s: s.wait(10), 1.0, "sent nothing in 1.0 s"),
    # accepts and closes at once
    (lambda c, s: None, 5.0, "closed the connection after 0.0 s without sending anything"),
    # only NaN poses: every message rejected, none reaches the scene
    (lambda c, s: _hold(c, s, _message(matrix=np.full((4, 4), np.nan)) * 3), 1.0,
     "3 messages rejected (not a finite pose or image) from CameraToTracker"),
    # a header-version-2 TRANSFORM whose metadata is garbage (its CRC right): pyigtl
    # raised TypeError, an internal error instead of the peer's
    (lambda c, s: _hold(c, s, _v2_garbage_metadata()), 5.0, "malformed TRANSFORM body"),
], ids=["2^64-1 bytes announced", "half a header, held", "a header, then closed",
        "a short body, held", "silent", "closed at once", "only NaN poses",
        "garbage v2 metadata"])
def test_cli_track_igtl_nothing_usable_is_one_line_exit_1(fluo, script, seconds, needle):
    srv = Server(script)
    try:
        t0 = time.monotonic()
        r = fluo("track", "--igtl", f"127.0.0.1:{srv.port}", "--seconds", str(seconds),
                 "--json", timeout=60)
        took = time.monotonic() - t0
    finally:
        srv.close()
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and r.stdout.strip() == "", (r.returncode, r.stdout, r.stderr)
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith(f"fluo: error: OpenIGTLink server 127.0.0.1:{srv.port}: ")
    assert needle in lines[0], lines[0]
    assert took < seconds + 5.0, took


def _v2_garbage_metadata():
    """A header-version-2 TRANSFORM message whose metadata names a text encoding that
    does not exist (9999), with the CRC of that body."""
    from pyigtl.messages import CRC64

    data = _message(seq=1)
    head, body = bytearray(data[:58]), bytearray(data[58:])
    _, meta_head, meta_body, _ = struct.unpack(">HHII", bytes(body[:12]))
    first = len(body) - (meta_head + meta_body)          # the metadata index
    body[first + 4:first + 6] = struct.pack(">H", 9999)  # entry 1's value encoding
    head[50:58] = struct.pack(">Q", CRC64(bytes(body)))
    return bytes(head) + bytes(body)


def test_cli_track_igtl_a_good_message_then_close_is_a_count_not_an_error(fluo):
    """The counterpart: one usable pose, then the server closes: exit 0 with the count
    (the check above is on nothing usable, not on a peer that ends)."""
    srv = Server(lambda c, s: c.sendall(_message(seq=0) + _message(seq=1)))
    try:
        r = fluo("track", "--igtl", f"127.0.0.1:{srv.port}", "--seconds", "5", "--json",
                 timeout=60)
    finally:
        srv.close()
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["received"] == {"CameraToTracker": 2} and doc["closed_by_peer"] is True
