"""Tracked frames in the scene: exact round trip through a saved .mrml, flags kept."""

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError
from FluoNavLib.devices import frame_store as fs


def _pose(k):
    rng = np.random.default_rng(k)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    m = np.eye(4)
    m[:3, :3] = q
    m[:3, 3] = rng.normal(size=3) * 100
    return m


def test_recording_round_trip_is_bit_exact(tmp_path):
    scene = mrml_io.new_scene()
    fs.new_recording(scene, tools=("CameraToolToTracker", "LaserToolToTracker"))
    rng = np.random.default_rng(0)
    images, poses = [], []
    for k in range(4):
        img = rng.integers(0, 2 ** 14, size=(26, 35)).astype(np.uint16)
        p = {"CameraToolToTracker": _pose(k), "LaserToolToTracker": None if k == 2 else _pose(10 + k)}
        fs.append_tracked_frame(scene, img, 1.0 + k / 60.0, p, exposure_s=0.05, pose_valid=k != 3,
                                pose_status="OK" if k != 3 else "MISSING")
        images.append(img)
        poses.append(p)
    mrml_io.save_scene(scene, tmp_path / "rec.mrml")
    back = mrml_io.load_scene(tmp_path / "rec.mrml")
    assert fs.number_of_frames(back) == 4
    assert fs.recording_tools(back) == ["CameraToolToTracker", "LaserToolToTracker"]
    for k in range(4):
        img, info, got = fs.read_tracked_frame(back, k)
        assert np.array_equal(img, images[k]) and img.dtype == np.uint16
        assert info["timestamp_s"] == 1.0 + k / 60.0
        if k == 3:
            assert info["pose_valid"] is False and info["pose_status"] == "MISSING"
            assert got["CameraToolToTracker"] is None
            continue
        assert np.array_equal(got["CameraToolToTracker"], poses[k]["CameraToolToTracker"])
        if k == 2:
            assert got["LaserToolToTracker"] is None
        else:
            assert np.array_equal(got["LaserToolToTracker"], poses[k]["LaserToolToTracker"])


def test_bad_frames_are_refused_and_leave_the_recording_as_it_was():
    scene = mrml_io.new_scene()
    fs.new_recording(scene)
    fs.append_tracked_frame(scene, np.zeros((4, 5)), 2.0, {"CameraToolToTracker": np.eye(4)})
    with pytest.raises(FluoInputError, match="increase"):
        fs.append_tracked_frame(scene, np.zeros((4, 5)), 2.0, {"CameraToolToTracker": np.eye(4)})
    with pytest.raises(FluoInputError, match="2D"):
        fs.append_tracked_frame(scene, np.zeros((4, 5, 3)), 3.0, {})
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(FluoInputError, match="CameraToolToTracker"):
        fs.append_tracked_frame(scene, np.zeros((4, 5)), 3.0, {"CameraToolToTracker": bad})
    with pytest.raises(FluoInputError, match="not in this recording"):
        fs.append_tracked_frame(scene, np.zeros((4, 5)), 3.0, {"Pointer": np.eye(4)})
    assert fs.number_of_frames(scene) == 1
    with pytest.raises(FluoInputError, match="no such frame"):
        fs.read_tracked_frame(scene, 1)
