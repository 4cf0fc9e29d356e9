"""Geometric calibration results in the MRML scene (see docs/scene.md).

Nodes written:

- ``CameraToTracker`` (vtkMRMLLinearTransformNode): hand-eye, camera frame ->
  tracked camera-tool frame [mm] (``CameraToTool`` in FluoCalibLib.handeye);
  nested under ``CameraToolToTracker`` when that node exists.
- ``TrackerToReference`` (vtkMRMLLinearTransformNode): paired-point
  registration tracker -> CBCT/RAS [mm].
- ``FluoCalibration`` (vtkMRMLScriptedModuleNode) attributes
  ``FluoCalib.CameraIntrinsics`` (CameraModel.to_dict plus rms_px, board) and
  ``FluoCalib.HandEye`` (method, errors) and ``FluoCalib.Registration``
  (FRE/TRE).
"""

from __future__ import annotations

from fluoguide import mrml_io

from FluoCalibLib.geometry.camera_model import CameraModel

__all__ = ["CALIBRATION_NODE", "INTRINSICS_KEY", "HANDEYE_KEY", "REGISTRATION_KEY",
           "calibration_node", "store_intrinsics", "load_intrinsics", "store_handeye",
           "load_handeye", "store_registration"]

CALIBRATION_NODE = "FluoCalibration"
INTRINSICS_KEY = "FluoCalib.CameraIntrinsics"
HANDEYE_KEY = "FluoCalib.HandEye"
REGISTRATION_KEY = "FluoCalib.Registration"
HANDEYE_TRANSFORM = "CameraToTracker"
TOOL_TRANSFORM = "CameraToolToTracker"
REGISTRATION_TRANSFORM = "TrackerToReference"


def calibration_node(scene):
    """The ``FluoCalibration`` scripted-module node, created when missing."""
    node = mrml_io.get_node(scene, CALIBRATION_NODE, required=False)
    if node is None:
        import slicer  # provided by slicer-core outside Slicer

        node = slicer.vtkMRMLScriptedModuleNode()
        node.SetName(CALIBRATION_NODE)
        scene.AddNode(node)
    return node


def store_intrinsics(scene, camera, extra=None):
    """Write the intrinsics (plus e.g. rms_px, board) as ``FluoCalib.CameraIntrinsics``."""
    doc = camera.to_dict()
    doc.update(extra or {})
    mrml_io.set_json_attribute(calibration_node(scene), INTRINSICS_KEY, doc)


def load_intrinsics(scene):
    """CameraModel stored by :func:`store_intrinsics`."""
    node = mrml_io.get_node(scene, CALIBRATION_NODE)
    doc = mrml_io.get_json_attribute(node, INTRINSICS_KEY)
    if doc is None:
        from fluoguide.errors import FluoInputError

        raise FluoInputError("no camera intrinsics in scene", field=INTRINSICS_KEY)
    return CameraModel.from_dict(doc)


def store_handeye(scene, camera_to_tool, info=None):
    """Write ``CameraToTracker`` (camera -> camera tool) and ``FluoCalib.HandEye``."""
    parent = TOOL_TRANSFORM if mrml_io.get_node(scene, TOOL_TRANSFORM, required=False) else None
    mrml_io.set_transform(scene, HANDEYE_TRANSFORM, camera_to_tool, parent=parent)
    if info is not None:
        mrml_io.set_json_attribute(calibration_node(scene), HANDEYE_KEY, info)


def load_handeye(scene):
    """The 4x4 CameraToTool matrix stored as ``CameraToTracker``."""
    return mrml_io.get_transform(scene, HANDEYE_TRANSFORM)


def store_registration(scene, tracker_to_reference, info=None):
    """Write ``TrackerToReference`` and ``FluoCalib.Registration`` (FRE/TRE)."""
    mrml_io.set_transform(scene, REGISTRATION_TRANSFORM, tracker_to_reference)
    if info is not None:
        mrml_io.set_json_attribute(calibration_node(scene), REGISTRATION_KEY, info)
