"""FluoNavLogic's calls on their own: point data of the mapped surface, tracker
sessions (replay, bad sources, the tracking loop's callback and stop), input checks of correctFrame, and old scenes
whose hand-eye node has the old name."""

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError


def test_point_means_are_weighted_means_of_the_faces_around_each_point():
    from FluoNavLib.mapping.scene import point_means

    # two triangles sharing the edge (1, 2); point 4 belongs to no face
    tri = np.array([[0, 1, 2], [1, 3, 2]])
    values = np.array([1.0, 4.0])
    weights = np.array([1.0, 3.0])
    got = point_means(tri, 5, values, weights)
    # written out by hand: points 1 and 2 see both faces, (1*1 + 4*3) / (1 + 3)
    np.testing.assert_allclose(got, [1.0, 13.0 / 4.0, 13.0 / 4.0, 4.0, 0.0])
    # a face never seen (weight 0) does not pull its points to 0
    got = point_means(tri, 5, values, np.array([0.0, 2.0]))
    np.testing.assert_allclose(got, [0.0, 4.0, 4.0, 4.0, 0.0])


@pytest.fixture(scope="module")
def nav_scene():
    from FluoNav import FluoNavLogic

    scene = mrml_io.new_scene()
    FluoNavLogic(scene).makeSyntheticAcquisition(views=2, binning=8, triangles=8000)
    return scene


def test_correct_frame_refuses_what_it_cannot_use(nav_scene):
    from FluoNav import FluoNavLogic

    logic = FluoNavLogic(nav_scene)
    img = np.zeros((130, 174), np.uint16)
    with pytest.raises(FluoInputError, match="camera pose"):
        logic.correctFrame(img)                            # an image needs its pose
    with pytest.raises(FluoInputError, match="finite 4x4"):
        logic.correctFrame(img, np.full((4, 4), np.nan))
    with pytest.raises(FluoInputError, match="intrinsics"):
        logic.correctFrame(np.zeros((10, 10)), np.eye(4))  # not the calibrated camera's size
    with pytest.raises(FluoInputError, match="no such frame"):
        logic.correctFrame(7)


def test_a_changed_pose_chain_or_calibration_is_used_at_once(nav_scene):
    """The logic keeps what frames share between calls; a new hand-eye, registration
    or calibration must reach the next correction (a stale one is a wrong number)."""
    from FluoNav import FluoNavLogic
    from FluoCalibLib.geometry.scene import load_intrinsics, store_intrinsics

    logic = FluoNavLogic(nav_scene)
    first = logic.correctionContext()
    assert logic.correctionContext() is first                 # nothing changed: reused
    moved = np.eye(4)
    moved[:3, 3] = [0.0, 0.0, 5.0]
    mrml_io.set_transform_matrix(mrml_io.get_node(nav_scene, "TrackerToReference"), moved)
    try:
        ctx = logic.correctionContext()
        assert ctx is not first
        np.testing.assert_array_equal(ctx.tracker_to_reference, moved)
        cam = load_intrinsics(nav_scene)
        store_intrinsics(nav_scene, cam.binned(2), {"rms_px": 0.0})
        assert logic.correctionContext().camera.width == cam.width // 2
        store_intrinsics(nav_scene, cam, {"rms_px": 0.0})
    finally:
        mrml_io.set_transform_matrix(mrml_io.get_node(nav_scene, "TrackerToReference"), np.eye(4))


def test_a_scene_with_the_old_hand_eye_name_still_corrects(nav_scene, tmp_path):
    """Scenes saved before CameraToCameraTool call the hand-eye CameraToTracker."""
    from FluoNav import FluoNavLogic

    new = FluoNavLogic(nav_scene).correctFrame(1)
    path = mrml_io.save_scene(nav_scene, tmp_path / "new.mrml")
    text = path.read_text()
    assert 'name="CameraToCameraTool"' in text
    old = tmp_path / "old" / "scene.mrml"
    old.parent.mkdir()
    for f in path.parent.iterdir():
        if f.is_file() and f != path:
            (old.parent / f.name).write_bytes(f.read_bytes())
    old.write_text(text.replace('name="CameraToCameraTool"', 'name="CameraToTracker"'))
    scene = mrml_io.load_scene(old)
    assert mrml_io.get_node(scene, "CameraToCameraTool", required=False) is None
    r = FluoNavLogic(scene).correctFrame(1)
    # the hand-eye carries a calibration error (not the identity), and a saved scene
    # keeps its matrix to the last bit or so: the same pixels, the same values
    np.testing.assert_array_equal(r.mapped, new.mapped)
    np.testing.assert_allclose(r.transport, new.transport, rtol=1e-12, atol=0)


def test_replay_through_the_logic_puts_the_recorded_poses_in_the_scene(tmp_path):
    from FluoNav import FluoNavLogic
    from FluoNavLib.devices.recorder import Recorder

    poses = []
    with Recorder(tmp_path / "rec") as rec:
        for k in range(5):
            T = np.eye(4)
            T[:3, 3] = [k, 2.0 * k, 100.0 + 0.1 * k]
            poses.append(T)
            rec.add(np.full((4, 6), k, np.uint16), 0.05 * k, {"CameraToolToTracker": T},
                    pose_valid=k != 3, pose_status="OK" if k != 3 else "MISSING")
    logic = FluoNavLogic(mrml_io.new_scene())
    logic.connectTracker("replay", str(tmp_path / "rec"), speed="max")
    seen = []
    while (p := logic.updateTracker()) is not None:
        seen.append(p["CameraToolToTracker"])
    logic.disconnect()
    assert len(seen) == 5 and seen[3] is None          # the invalid frame has no pose
    # the node holds the last valid pose, bit for bit
    np.testing.assert_array_equal(mrml_io.get_transform(logic.scene, "CameraToolToTracker"),
                                  poses[4])
    assert logic.posesApplied == 4
    assert logic.importRecording(tmp_path / "rec") == 5


def test_the_tracking_loop_hands_on_each_frame_and_stops_when_asked():
    # the one live-tracking loop (fluo track, the web app's stream): a callback per
    # frame, and a stop the caller decides (the stream's Stop and its time window)
    from FluoNav import FluoNavLogic

    logic = FluoNavLogic(mrml_io.new_scene())
    logic.connectTracker("ndi-sim", phantomCamera=True)
    seen = []
    try:
        out = logic.trackFor(60.0, applyPoses=False,
                             onPoses=lambda poses, t: seen.append(
                                 (poses["CameraToolToTracker"], logic.tracker.last_frame)),
                             stop=lambda: len(seen) >= 5)
        stopped_at_once = logic.trackFor(60.0, stop=lambda: True)   # no frame: no error
    finally:
        logic.disconnect()
    assert len(seen) == 5 and out["frames"] == 5 and out["lost_unreported"] == 0
    # the phantom camera circles 120 mm above the cavity (z 100 +- 5 mm)
    assert all(abs(pose[2, 3] - 100.0) < 6.0 for pose, _ in seen)
    assert [f for _, f in seen] == sorted({f for _, f in seen})       # device frame numbers
    assert stopped_at_once["frames"] == 5
    assert mrml_io.get_node(logic.scene, "CameraToolToTracker", required=False) is None


@pytest.mark.parametrize("source, address, needle", [
    ("ndi", None, "serial port"),
    ("igtl", "nonsense", "HOST:PORT"),
    ("replay", "/nonexistent/recording", "recording"),
    ("carrier-pigeon", None, "unknown tracker source"),
])
def test_bad_tracker_sources_are_named(source, address, needle):
    from FluoNav import FluoNavLogic

    logic = FluoNavLogic(mrml_io.new_scene())
    with pytest.raises(FluoInputError, match=needle):
        logic.connectTracker(source, address)
    assert not logic.isConnected()
    with pytest.raises(FluoInputError, match="no tracker"):
        logic.updateTracker()


def test_synthetic_acquisition_saves_and_loads_with_its_nodes(nav_scene, tmp_path):
    """The synthetic scene (CLI ``nav synth``) saves and loads with its documented nodes."""
    path = mrml_io.save_scene(nav_scene, tmp_path / "s.mrml")
    names = {n["name"] for n in mrml_io.node_summary(mrml_io.load_scene(path))}
    assert {"TissueSurface", "FluoCalibration", "TrackerToReference", "CameraToCameraTool",
            "CameraFrame-Sequence", "FluoNavRecordingLog"} <= names
    assert "CameraToTracker" not in names
