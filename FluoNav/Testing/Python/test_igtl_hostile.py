"""OpenIGTLink servers that misbehave, on 127.0.0.1: every run ends on time, in
bounded memory, with a count or one clear device error; nothing reaches the
scene that is not a finite pose (issue #21)."""

import os
import resource
import socket
import struct
import threading
import time

import numpy as np

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


def test_half_a_header_then_silence_ends_on_time():
    def script(conn, stop):
        conn.sendall(_message()[:20])
        stop.wait(10)

    out, err, took, _ = _run(script, seconds=1.0)
    assert err is None and out["received"] == {} and took < 3.0


def test_half_a_header_then_close_is_reported():
    def script(conn, stop):
        conn.sendall(_message()[:20])

    out, err, took, _ = _run(script, seconds=5.0)
    assert out["closed_by_peer"] and took < 3.0


def test_a_body_trickled_at_one_byte_per_second_ends_on_time():
    def script(conn, stop):
        data = _message()
        for b in data:
            if stop.is_set():
                return
            conn.sendall(bytes([b]))
            time.sleep(1.0)

    out, err, took, _ = _run(script, seconds=2.0)
    assert err is None and out["received"] == {} and took < 4.0


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
