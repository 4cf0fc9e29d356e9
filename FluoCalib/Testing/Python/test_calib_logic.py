"""FluoCalibLogic's calls with caller-chosen outputs and checked inputs."""

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError


def _logic():
    from FluoCalib import FluoCalibLogic

    return FluoCalibLogic(mrml_io.new_scene())


def _rigid(angle_deg, axis, t):
    from FluoCalibLib.geometry import transforms as tf

    return tf.make_rigid(tf.rotation_matrix(axis, np.deg2rad(angle_deg)), t)


def test_registration_into_a_chosen_transform_and_calibration_node():
    import slicer

    logic = _logic()
    truth = _rigid(25.0, [0.3, 1.0, 0.2], [12.0, -40.0, 7.5])
    moving = np.array([[0.0, 0, 0], [60, 0, 0], [0, 45, 0], [0, 0, 30], [20, 30, 10]])
    fixed = (truth[:3, :3] @ moving.T).T + truth[:3, 3]
    targets = np.array([[10.0, 10, 10], [-20, 5, 40]])
    node = logic.scene.AddNode(slicer.vtkMRMLLinearTransformNode())
    calib = logic.scene.AddNode(slicer.vtkMRMLScriptedModuleNode())
    out = logic.registerTrackerToReference(moving, fixed, targets,
                                           (truth[:3, :3] @ targets.T).T + truth[:3, 3],
                                           outputTransformNode=node, calibrationNode=calib)
    # exact data: the registration is the rigid transform written above
    np.testing.assert_allclose(mrml_io.transform_matrix(node), truth, atol=1e-9)
    assert out["fre_mm"] < 1e-9 and out["tre_mean_mm"] < 1e-9
    assert mrml_io.get_json_attribute(calib, "FluoCalib.Registration")["fre_mm"] < 1e-9
    assert mrml_io.get_node(logic.scene, "TrackerToReference", required=False) is None
    assert mrml_io.get_node(logic.scene, "FluoCalibration", required=False) is None
    with pytest.raises(FluoInputError, match="targets"):
        logic.registerTrackerToReference(moving, fixed, targets, None)


def test_the_calibration_node_must_be_a_scripted_module_node():
    import slicer

    logic = _logic()
    model = logic.scene.AddNode(slicer.vtkMRMLModelNode())
    with pytest.raises(FluoInputError, match="vtkMRMLScriptedModuleNode"):
        logic.calibrationNode(model)
    node = logic.calibrationNode()
    assert node.GetName() == "FluoCalibration" and not node.GetHideFromEditors()
    assert node.GetAttribute("FluoGuide.Role") == "Calibration"
    assert logic.calibrationNode() is node


@pytest.fixture(scope="module")
def boards():
    from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

    return make_dataset(None, default_camera(480, 360), "chessboard:9x6:20", n_views=7, seed=3)


def test_camera_and_hand_eye_into_chosen_nodes(boards, tmp_path):
    import json

    import slicer

    logic = _logic()
    calib = logic.scene.AddNode(slicer.vtkMRMLScriptedModuleNode())
    calib.SetName("MyCalibration")
    images = [v.image for v in boards["views"]]
    res = logic.calibrateCamera(images, boards["board"], calibrationNode=calib,
                                calibrationJson=tmp_path / "c.json")
    assert abs(res.camera.fx / boards["camera"]["fx"] - 1) < 0.02
    assert logic.cameraModel(calib).fx == res.camera.fx
    assert logic.cameraModel() is None              # nothing went to FluoCalibration
    node = logic.scene.AddNode(slicer.vtkMRMLLinearTransformNode())
    out = logic.calibrateHandEye(images, boards["board"], boards["tool_to_tracker"],
                                 camera=res.camera, methods="PAIRED_POINT",
                                 truthCameraToTool=boards["camera_to_tool"],
                                 outputTransformNode=node, calibrationNode=calib,
                                 calibrationJson=tmp_path / "c.json")
    assert out["transform_node_id"] == node.GetID()
    np.testing.assert_allclose(mrml_io.transform_matrix(node), out["camera_to_tool"])
    assert out["methods"]["PAIRED_POINT"]["translation_error_mm"] < 1.5
    assert mrml_io.get_node(logic.scene, "CameraToCameraTool", required=False) is None
    saved = json.loads((tmp_path / "c.json").read_text())
    np.testing.assert_allclose(saved["HandEye"]["camera_to_tool"], out["camera_to_tool"])
    assert saved["CameraIntrinsics"]["fx"] == pytest.approx(res.camera.fx)


def test_hand_eye_inputs_are_checked_before_any_work(boards):
    logic = _logic()
    images = [v.image for v in boards["views"]]
    with pytest.raises(FluoInputError, match="7 images but 6 tool poses"):
        logic.calibrateHandEye(images, boards["board"], boards["tool_to_tracker"][:6])
    with pytest.raises(FluoInputError, match="unknown hand-eye method"):
        logic.calibrateHandEye(images, boards["board"], boards["tool_to_tracker"],
                               methods="MAGIC")
    with pytest.raises(FluoInputError, match="stored method was not run"):
        logic.calibrateHandEye(images, boards["board"], boards["tool_to_tracker"],
                               methods=("TSAI", "PARK"), storeMethod="PAIRED_POINT")


def test_handeye_pose_file_reader_names_the_bad_entry(tmp_path):
    from FluoCalibLib.geometry.files import read_handeye_poses

    p = tmp_path / "poses.json"
    p.write_text('{"tool_to_tracker": [[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], '
                 '[[1, 0, 0]]]}')
    with pytest.raises(FluoInputError, match=r"tool_to_tracker\[1\]"):
        read_handeye_poses(p)
    p.write_text('{"poses": []}')
    with pytest.raises(FluoInputError, match="tool_to_tracker"):
        read_handeye_poses(p)
