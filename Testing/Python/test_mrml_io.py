"""MRML scene helpers: every node kind the modules use survives save and load."""

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError


def _scene():
    scene = mrml_io.new_scene()
    arr = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5)
    direction = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
    mrml_io.add_volume(scene, "CBCT", arr, (0.8, 0.7, 1.2), (1, 2, 3), direction)
    mrml_io.add_volume(scene, "CBCTLabels", (arr > 30).astype(np.uint8), (0.8, 0.7, 1.2), (1, 2, 3),
                       direction, labelmap=True)
    mrml_io.set_transform(scene, "TrackerToReference", np.diag([1.0, 1.0, 1.0, 1.0]))
    m = np.eye(4)
    m[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    m[:3, 3] = [5.0, -7.5, 100.25]
    mrml_io.set_transform(scene, "CameraToTracker", m, parent="TrackerToReference")
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], float)
    mrml_io.add_model(scene, "TissueSurface", pts, np.array([[0, 1, 2], [0, 2, 3]]))
    mrml_io.set_table(scene, "Results", {"depth_mm": [2.7, 3.7], "error_pct": [1.5, -2.0]})
    mrml_io.set_json_attribute(mrml_io.get_node(scene, "CBCT"), "FluoGuide.Info", {"a": [1, 2]})
    return scene, arr, m, pts


def test_round_trip(tmp_path):
    scene, arr, m, pts = _scene()
    path = mrml_io.save_scene(scene, tmp_path / "s" / "scene.mrml")
    text = path.read_text()
    assert str(tmp_path) not in text  # storage files referenced relatively
    loaded = mrml_io.load_scene(path)
    assert [(n["name"], n["class"]) for n in mrml_io.node_summary(loaded)] == \
        [(n["name"], n["class"]) for n in mrml_io.node_summary(scene)]
    cbct = mrml_io.get_node(loaded, "CBCT")
    assert np.array_equal(mrml_io.volume_array(cbct), arr)
    geo = mrml_io.volume_geometry(cbct)
    np.testing.assert_allclose(geo["spacing"], (0.8, 0.7, 1.2))
    np.testing.assert_allclose(geo["direction"], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(mrml_io.get_transform(loaded, "CameraToTracker"), m)
    np.testing.assert_allclose(mrml_io.get_transform_to_world(loaded, "CameraToTracker"), m)
    got_pts, got_tri = mrml_io.model_arrays(mrml_io.get_node(loaded, "TissueSurface"))
    np.testing.assert_allclose(got_pts, pts)
    assert got_tri.tolist() == [[0, 1, 2], [0, 2, 3]]
    np.testing.assert_allclose(mrml_io.get_table(mrml_io.get_node(loaded, "Results"))["error_pct"],
                               [1.5, -2.0])
    assert mrml_io.get_json_attribute(cbct, "FluoGuide.Info") == {"a": [1, 2]}


def test_moved_scene_folder_still_loads(tmp_path):
    scene, arr, _, _ = _scene()
    mrml_io.save_scene(scene, tmp_path / "a" / "scene.mrml")
    (tmp_path / "a").rename(tmp_path / "b")
    loaded = mrml_io.load_scene(tmp_path / "b" / "scene.mrml")
    assert np.array_equal(mrml_io.volume_array(mrml_io.get_node(loaded, "CBCT")), arr)


def test_corrupt_inputs_name_the_file(tmp_path):
    bad = tmp_path / "bad.mrml"
    bad.write_text("not xml")
    with pytest.raises(FluoInputError, match="bad.mrml"):
        mrml_io.load_scene(bad)
    with pytest.raises(FluoInputError, match="not found"):
        mrml_io.load_scene(tmp_path / "missing.mrml")
    scene, _, _, _ = _scene()
    path = mrml_io.save_scene(scene, tmp_path / "s" / "scene.mrml")
    (tmp_path / "s" / "CBCT.nrrd").write_bytes(b"NRRD0004\ngarbage")
    with pytest.raises(FluoInputError, match="CBCT.nrrd"):
        mrml_io.load_scene(path)
    (tmp_path / "s" / "CBCT.nrrd").unlink()
    with pytest.raises(FluoInputError, match="missing|CBCT"):
        mrml_io.load_scene(path)


def test_bad_arrays_rejected():
    scene = mrml_io.new_scene()
    with pytest.raises(FluoInputError, match="3D"):
        mrml_io.add_volume(scene, "V", np.zeros((2, 2)), (1, 1, 1), (0, 0, 0))
    with pytest.raises(FluoInputError, match="spacing"):
        mrml_io.add_volume(scene, "V", np.zeros((2, 2, 2), np.int16), (1, 0, 1), (0, 0, 0))
    with pytest.raises(FluoInputError, match="4x4"):
        mrml_io.set_transform(scene, "T", np.full((4, 4), np.nan))
    with pytest.raises(FluoInputError, match="node not found"):
        mrml_io.get_transform(scene, "Nope")
