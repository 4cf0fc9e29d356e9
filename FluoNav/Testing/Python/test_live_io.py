"""Time sync (SLERP + linear, watchdog), incremental recording with bit-exact
replay, and OpenIGTLink from a real pyigtl server on 127.0.0.1."""

import json
import socket
import time

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import transforms as tf
from FluoNavLib.devices import frame_store
from FluoNavLib.devices.recorder import (
    Recorder,
    read_recording,
    replay,
    to_scene,
)
from FluoNavLib.devices.timesync import PoseBuffer, estimate_latency


def _pose(t):
    R = tf.rotation_matrix([0.3, 1.0, 0.2], 0.8 * t)
    return tf.make_rigid(R, [10 * t, -5 * t, 100 + 2 * t])


def test_pose_interpolation_and_watchdog():
    buf = PoseBuffer(latency_s=0.02, max_gap_s=0.05, max_age_s=0.1)
    for k in range(61):                      # 60 Hz, source clock 0.02 s late
        t = k / 60
        buf.add(t + 0.02, None if 30 <= k <= 31 else _pose(t))
    m, status = buf.at(0.105)
    assert status == "OK"
    np.testing.assert_allclose(m[:3, 3], _pose(0.105)[:3, 3], atol=1e-9)   # linear motion
    ang = tf.rotation_angle(m[:3, :3].T @ _pose(0.105)[:3, :3])
    assert ang < 1e-9                                                      # rotation about one axis
    assert buf.at(30.5 / 60)[1] == "MISSING"
    assert buf.at(1.0 + 0.5)[1] == "STALE"                                 # watchdog: too old
    assert buf.at(1.0 + 0.05)[1] == "EXTRAPOLATION"
    sparse = PoseBuffer(max_gap_s=0.05)
    sparse.add(0.0, _pose(0))
    sparse.add(0.2, _pose(0.2))
    assert sparse.at(0.1)[1] == "STALE"                                    # gap too long
    assert not buf.add(0.0, _pose(0))                                      # out of order: ignored


def test_latency_estimate_from_motion():
    t = np.arange(0, 10, 1 / 60)
    speed = np.sin(2 * np.pi * 0.7 * t) + 0.5 * np.sin(2 * np.pi * 1.9 * t)
    tb = np.arange(0, 10, 1 / 30)
    delayed = np.interp(tb - 0.083, t, speed)
    assert abs(estimate_latency(t, speed, tb, delayed) - 0.083) < 0.003


def test_recording_is_incremental_and_replays_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    frames = []
    rec = Recorder(tmp_path / "rec", tools=("CameraToolToTracker", "LaserToolToTracker"))
    for k in range(5):
        img = rng.integers(0, 2 ** 14, (24, 32)).astype(np.uint16)
        poses = {"CameraToolToTracker": _pose(k * 0.1) + rng.normal(0, 1e-7, (4, 4)),
                 "LaserToolToTracker": None if k == 2 else _pose(-k)}
        rec.add(img, 10.0 + k / 60, poses, exposure_s=0.03, pose_valid=k != 2,
                pose_status="OK" if k != 2 else "MISSING")
        frames.append((img, poses))
    # a crash: the log is not closed and a half-written line is at its end
    with open(tmp_path / "rec" / "log.jsonl", "a") as f:
        f.write('{"frame": 5, "file": "frame_0000')
    out = list(replay(tmp_path / "rec", speed="max"))
    assert len(out) == 5
    for (img, info, poses), (img0, poses0) in zip(out, frames):
        assert np.array_equal(img, img0)
        for tool, m0 in poses0.items():
            assert (poses[tool] is None) == (m0 is None)
            if m0 is not None:
                assert np.array_equal(poses[tool], m0)           # bit for bit
    assert out[2][1]["pose_status"] == "MISSING"
    scene = to_scene(tmp_path / "rec")
    mrml_io.save_scene(scene, tmp_path / "scene" / "rec.mrml")
    back = mrml_io.load_scene(tmp_path / "scene" / "rec.mrml")
    img, info, poses = frame_store.read_tracked_frame(back, 4)
    assert np.array_equal(img, frames[4][0])
    assert np.array_equal(poses["CameraToolToTracker"], frames[4][1]["CameraToolToTracker"])
    with pytest.raises(FluoInputError, match="not empty"):
        Recorder(tmp_path / "rec")
    rec2 = Recorder(tmp_path / "rec2")
    rec2.add(np.zeros((2, 2)), 1.0, {})
    with pytest.raises(FluoInputError, match="increase"):
        rec2.add(np.zeros((2, 2)), 1.0, {})
    (tmp_path / "rec2" / "frame_000000.npy").unlink()
    with pytest.raises(FluoInputError, match="missing"):
        read_recording(tmp_path / "rec2")


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_openigtlink_transforms_and_images_arrive_in_mrml():
    import pyigtl

    from FluoNavLib.devices.igtl_client import TIMESTAMP_ATTRIBUTE, IGTLReceiver

    port = _free_port()
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    scene = mrml_io.new_scene()
    try:
        rx = IGTLReceiver(scene, "127.0.0.1", port).connect(timeout_s=10)
        t_end = time.monotonic() + 10
        while not server.is_connected() and time.monotonic() < t_end:
            time.sleep(0.02)
        sent = 0
        for k in range(40):                  # bounded: 40 messages at ~100 Hz
            m = _pose(k / 100)
            msg = pyigtl.TransformMessage(m, device_name="CameraToTracker", timestamp=1000.0 + k / 100)
            msg.header_version = 2            # metadata travels in header v2 only
            msg.metadata = {"seq": str(k)}
            server.send_message(msg, wait=True)
            sent += 1
            if k % 10 == 0:
                img = (np.arange(2 * 3 * 4, dtype=np.uint16) + k).reshape(2, 3, 4)
                server.send_message(pyigtl.ImageMessage(img, device_name="Image_Reference",
                                                        timestamp=1000.0 + k / 100), wait=True)
            time.sleep(0.01)
            rx.poll()
        for k in range(40, 60):              # a burst nobody polls: our loop keeps every message
            if k in (45, 46, 47):            # ... and three the sender never sent: lost
                continue
            msg = pyigtl.TransformMessage(_pose(k / 100), device_name="CameraToTracker",
                                          timestamp=1000.0 + k / 100)
            msg.header_version = 2
            msg.metadata = {"seq": str(k)}
            server.send_message(msg, wait=True)
            sent += 1
        time.sleep(0.2)
        rx.poll(budget_s=1.0)
        assert rx.lost["CameraToTracker"] == 3          # seen from the seq numbers
        node = mrml_io.get_node(scene, "CameraToTracker")
        np.testing.assert_allclose(mrml_io.get_transform(scene, "CameraToTracker"), _pose(0.59),
                                   atol=1e-4)
        assert float(node.GetAttribute(TIMESTAMP_ATTRIBUTE)) == pytest.approx(1000.59)
        vol = mrml_io.get_node(scene, "Image_Reference")
        arr = mrml_io.volume_array(vol)
        assert arr.shape == (2, 3, 4) and int(arr.max()) == 23 + 30
        # every message sent was applied; the three never sent are the only losses
        assert rx.received["CameraToTracker"] == sent == 57
    finally:
        rx.close()
        server.stop()


def test_cli_track_record_replay(tmp_path, capsys):
    from fluoapp.cli import main

    assert main(["track", "--sim", "--seconds", "1.5", "--inject-faults", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["lost_unreported"] == 0 and out["frames"] > 30
    assert main(["record", "--out", str(tmp_path / "r"), "--seconds", "1.5", "--fps", "10",
                 "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["frames"] >= 10 and rec["lost_unreported"] == 0
    assert main(["replay", str(tmp_path / "r"), "--max-speed", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["frames"] == rec["frames"]
    assert rep["frames_with_pose"] == rec["frames"] - rec["frames_without_pose"]
    assert main(["track", "--sim", "--seconds", "0"]) == 2
    assert main(["track", "--igtl", "nonsense"]) == 2
    assert main(["devices", "--json"]) == 0
    dev = json.loads(capsys.readouterr().out)
    assert "serial_ports" in dev and dev["notes"]
