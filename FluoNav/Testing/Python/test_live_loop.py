"""Camera frame sources (OpenCV video, image folders, recordings), USB discovery,
and the live loop: simulated tracker on a pty + frames -> callback, with exact
frame accounting and poses checked against the simulator's motion."""

import json
import time

import cv2
import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoNavLib.devices import frame_sources as fs
from FluoNavLib.devices.live_loop import LiveLoop
from FluoNavLib.devices.ndi_client import NDIClient
from FluoNavLib.devices.ndi_simulator import Faults, NDISimulator
from FluoNavLib.devices.recorder import Recorder
from FluoNavLib.devices.usb import classify_usb, discover


def test_image_sequence_keeps_16_bit_counts_and_order(tmp_path):
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 65535, (12, 17), dtype=np.uint16) for _ in range(4)]
    for k, img in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), img)
    colour = rng.integers(0, 255, (12, 17, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "f004.png"), colour)
    np.save(tmp_path / "f005.npy", imgs[0])
    (tmp_path / "notes.txt").write_text("ignored")
    frames = list(fs.ImageSequenceSource(tmp_path, fps=10))
    assert [f.sequence for f in frames] == list(range(6))
    assert [f.timestamp_s for f in frames] == pytest.approx([0, 0.1, 0.2, 0.3, 0.4, 0.5])
    for f, img in zip(frames, imgs):
        assert f.image.dtype == np.uint16 and np.array_equal(f.image, img)
    assert np.array_equal(frames[4].image, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    assert np.array_equal(frames[5].image, imgs[0])
    with pytest.raises(FluoInputError):
        fs.ImageSequenceSource(tmp_path / "none")
    with pytest.raises(FluoInputError):
        fs.ImageSequenceSource(tmp_path, fps=0)


def test_opencv_source_reads_a_video_file_with_its_times(tmp_path):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (32, 24))
    assert w.isOpened()
    for k in range(10):
        w.write(np.full((24, 32, 3), 20 * k, np.uint8))
    w.release()
    with fs.OpenCVSource(path) as src:
        frames = list(src)
    assert len(frames) == 10
    assert frames[0].image.shape == (24, 32)
    # grey levels survive MJPG within a few counts; times advance by 1/25 s
    assert [int(round(f.image.mean())) for f in frames] == pytest.approx(
        [20 * k for k in range(10)], abs=3)
    assert np.diff([f.timestamp_s for f in frames]) == pytest.approx(0.04, abs=1e-3)
    with pytest.raises(FluoInputError):
        fs.OpenCVSource(tmp_path / "missing.avi")


def test_usb_classification_and_discovery_without_devices():
    assert classify_usb(0x0403, 0x6001, {0xFF}) == "tracker"        # FTDI in an NDI SCU
    assert classify_usb(0x28E7, 0x1234, set()) == "tracker"
    assert classify_usb(0x046D, 0x0825, {0xEF, 0x0E, 0x01}) == "camera"   # UVC webcam
    assert classify_usb(0x2676, 0xBA02, {0xEF}) == "camera"        # Basler (vendor class)
    assert classify_usb(0x8087, 0x0024, {0x09}) is None             # a hub
    out = discover()
    assert set(out) == {"serial_ports", "trackers", "cameras", "notes"}
    if not out["trackers"] and not out["cameras"]:
        assert any("no tracker or camera" in n for n in out["notes"])


def _truth_translation(sim, t_host):
    """Noise-free position of the simulator's first tool at host time ``t_host``."""
    tool = sim.tools[0]
    t = t_host - sim._t0
    w = 2 * np.pi / np.asarray(tool.period_s, float)
    return np.asarray(tool.centre_mm) + np.asarray(tool.amplitude_mm) * np.sin(w * t)


def test_live_loop_matches_poses_to_frames_and_accounts_for_every_frame(tmp_path):
    for k in range(12):
        np.save(tmp_path / f"img{k:02d}.npy", np.full((8, 9), k, np.uint16))
    got = []
    with NDISimulator(seed=2) as sim:
        with NDIClient(sim.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            time.sleep(0.1)                           # some poses before the first frame
            src = fs.ImageSequenceSource(tmp_path, fps=20, realtime=True)
            loop = LiveLoop(src, lambda img, info, poses: got.append((img, info, poses)),
                            tracker=client, drop_policy="none")
            rep = loop.run(seconds=10)
            client.stop()
    assert rep["delivered"] == 12 and rep["lost_unreported"] == 0
    assert [int(img[0, 0]) for img, _, _ in got] == list(range(12))
    assert rep["tracker"]["lost_unreported"] == 0
    valid = [(info, poses) for _, info, poses in got if info["pose_valid"]]
    assert len(valid) >= 11
    for info, poses in valid:
        m = poses["CameraToolToTracker"]
        assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
        # interpolated to the frame time: within 2 mm of the simulator's path
        # (tool speed <= 75 mm/s, host stamping jitter of a few ms, 0.05 mm noise)
        err = np.linalg.norm(m[:3, 3] - _truth_translation(sim, info["timestamp_s"]))
        assert err < 2.0, err
    for _, info, poses in got:
        if not info["pose_valid"]:
            assert poses["CameraToolToTracker"] is None and info["pose_status"] != "OK"
    assert rep["latency_ms"]["median"] >= 0


def test_slow_callback_drops_are_counted_and_faulty_tracker_frames_flagged():
    seen = []

    def slow(img, info, poses):
        seen.append(info)
        assert (poses["CameraToolToTracker"] is None) != info["pose_valid"]
        time.sleep(0.12)                               # slower than the 25 fps camera

    faults = Faults(crc_error_rate=0.05, dropout_rate_per_s=3.0, dropout_s=0.3)
    with NDISimulator(faults=faults, seed=3) as sim:
        with NDIClient(sim.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            src = fs.SyntheticSource(fps=25, width=16, height=12, seed=1)
            rep = LiveLoop(src, slow, tracker=client).run(seconds=2.5)
            client.stop()
    assert rep["dropped_slow"] > 10 and rep["lost_unreported"] == 0
    assert rep["frames_in"] == rep["delivered"] + rep["dropped_slow"]
    assert rep["delivered"] == len(seen)
    assert rep["tracker"]["crc_errors"] > 0 and rep["tracker"]["lost_unreported"] == 0
    assert rep["pose_invalid"] == sum(not i["pose_valid"] for i in seen)
    assert sum(rep["pose_status"].values()) == rep["pose_invalid"]


def test_replayed_recording_through_the_loop_gives_recorded_poses_bit_exact(tmp_path):
    rng = np.random.default_rng(4)
    poses = []
    with Recorder(tmp_path / "r") as rec:
        for k in range(5):
            m = np.eye(4)
            m[:3, 3] = rng.normal(0, 100, 3) / 3.0          # non-round floats
            poses.append(m if k != 2 else None)
            rec.add(np.full((4, 5), k, np.uint16), 0.1 * k + 1 / 3, {"CameraToolToTracker":
                    poses[-1]}, pose_valid=k != 2, pose_status="OK" if k != 2 else "MISSING")
    out = []
    rep = LiveLoop(fs.RecordingSource(tmp_path / "r"), lambda i, info, p: out.append((info, p)),
                   drop_policy="none").run(live=False)
    assert rep["delivered"] == 5 and rep["pose_invalid"] == 1 and rep["latency_ms"] is None
    for (info, p), m in zip(out, poses):
        if m is None:
            assert not info["pose_valid"] and p["CameraToolToTracker"] is None
        else:
            assert np.array_equal(p["CameraToolToTracker"], m)   # bit for bit


def test_frames_skipped_between_track_calls_are_reported_missing():
    with NDISimulator(seed=6) as sim:
        with NDIClient(sim.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            client.track(0.3)
            time.sleep(0.25)                 # ~15 device frames nobody polled
            stats = client.track(0.3)
            client.stop()
    assert stats.missing >= 10
    assert len(stats.segments) == 1 and stats.lost_unreported() == 0


def test_cli_record_from_an_image_folder(tmp_path, capsys):
    from fluoapp.cli import main

    for k in range(6):
        cv2.imwrite(str(tmp_path / f"{k}.png"), np.full((10, 11), 1000 + k, np.uint16))
    assert main(["record", "--out", str(tmp_path / "rec"), "--frames", str(tmp_path),
                 "--fps", "10", "--seconds", "3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 6 and out["frames_lost_unreported"] == 0
    assert out["lost_unreported"] == 0
    frames = list(fs.RecordingSource(tmp_path / "rec"))
    assert [int(f.image[0, 0]) for f in frames] == [1000 + k for k in range(6)]


def test_latest_policy_delivers_every_frame_of_a_finite_source_when_keeping_up(tmp_path):
    for k in range(10):
        np.save(tmp_path / f"{k:02d}.npy", np.full((3, 3), k, np.uint16))
    got = []
    loop = LiveLoop(fs.ImageSequenceSource(tmp_path, fps=50, realtime=True),
                    lambda img, info, poses: got.append((int(img[0, 0]), info["pose_valid"])))
    rep = loop.run(seconds=10)
    assert [g[0] for g in got] == list(range(10))       # the last frame too
    assert rep["dropped_slow"] == 0 and rep["lost_unreported"] == 0
    assert rep["pose_invalid"] == 10 and not any(v for _, v in got)   # no tracker: no pose
    with pytest.raises(FluoInputError):
        LiveLoop(fs.ImageSequenceSource(tmp_path), "not callable")
