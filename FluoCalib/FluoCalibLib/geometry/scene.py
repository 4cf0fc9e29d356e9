"""Geometric calibration results in the MRML scene (see docs/scene.md).

Nodes written:

- ``CameraToCameraTool`` (vtkMRMLLinearTransformNode): hand-eye, camera frame ->
  tracked camera-tool frame [mm] (``CameraToTool`` in FluoCalibLib.handeye);
  nested under ``CameraToolToTracker`` when that node exists. Scenes written
  before the SlicerIGT ``AToB`` name was adopted call it ``CameraToTracker``;
  :func:`load_handeye` reads either, :func:`store_handeye` writes the new
  name and removes the old node (it held the same transform).
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
           "HANDEYE_TRANSFORM", "LEGACY_HANDEYE_TRANSFORMS", "TOOL_TRANSFORM",
           "REGISTRATION_TRANSFORM", "calibration_node", "store_intrinsics", "load_intrinsics",
           "intrinsics_doc", "store_handeye", "handeye_node", "load_handeye",
           "store_registration"]

CALIBRATION_NODE = "FluoCalibration"
INTRINSICS_KEY = "FluoCalib.CameraIntrinsics"
HANDEYE_KEY = "FluoCalib.HandEye"
REGISTRATION_KEY = "FluoCalib.Registration"
HANDEYE_TRANSFORM = "CameraToCameraTool"
#: Older name of the hand-eye node (before SlicerIGT's AToB naming), still read.
LEGACY_HANDEYE_TRANSFORMS = ("CameraToTracker",)
TOOL_TRANSFORM = "CameraToolToTracker"
REGISTRATION_TRANSFORM = "TrackerToReference"


def calibration_node(scene, node=None):
    """The calibration node: ``node`` when given (a caller-chosen
    vtkMRMLScriptedModuleNode), else the scene's ``FluoCalibration``, created
    when missing. It is shown in node selectors (not hidden from editors)."""
    if node is not None:
        if not node.IsA("vtkMRMLScriptedModuleNode"):
            from fluoguide.errors import FluoInputError

            raise FluoInputError("calibration node must be a vtkMRMLScriptedModuleNode",
                                 field=node.GetName(), value=node.GetClassName())
        return node
    node = mrml_io.get_node(scene, CALIBRATION_NODE, required=False)
    if node is None:
        import slicer  # provided by slicer-core outside Slicer

        node = slicer.vtkMRMLScriptedModuleNode()
        node.SetName(CALIBRATION_NODE)
        node.SetHideFromEditors(False)
        node.SetAttribute("FluoGuide.Role", "Calibration")
        scene.AddNode(node)
    return node


def intrinsics_doc(camera, extra=None):
    """The ``FluoCalib.CameraIntrinsics`` document: the camera model plus e.g. rms_px, board."""
    doc = camera.to_dict()
    doc.update(extra or {})
    return doc


def store_intrinsics(scene, camera, extra=None, node=None):
    """Write the intrinsics (plus e.g. rms_px, board) as ``FluoCalib.CameraIntrinsics``."""
    mrml_io.set_json_attribute(calibration_node(scene, node), INTRINSICS_KEY,
                               intrinsics_doc(camera, extra))


def load_intrinsics(scene, node=None):
    """CameraModel stored by :func:`store_intrinsics` (on ``node`` or ``FluoCalibration``)."""
    node = node if node is not None else mrml_io.get_node(scene, CALIBRATION_NODE)
    doc = mrml_io.get_json_attribute(node, INTRINSICS_KEY)
    if doc is None:
        from fluoguide.errors import FluoInputError

        raise FluoInputError("no camera intrinsics in scene", field=INTRINSICS_KEY)
    return CameraModel.from_dict(doc)


def store_handeye(scene, camera_to_tool, info=None, node=None, transform_node=None):
    """Write the hand-eye transform (camera -> camera tool) and ``FluoCalib.HandEye``.

    ``transform_node``: a caller-chosen linear transform node, else
    ``CameraToCameraTool`` (nested under ``CameraToolToTracker`` when that
    exists); an old ``CameraToTracker`` node is removed (same transform, old name).
    Returns the transform node.
    """
    if transform_node is None:
        parent = TOOL_TRANSFORM if mrml_io.get_node(scene, TOOL_TRANSFORM, required=False) else None
        transform_node = mrml_io.set_transform(scene, HANDEYE_TRANSFORM, camera_to_tool,
                                               parent=parent)
        for old in LEGACY_HANDEYE_TRANSFORMS:
            mrml_io.remove_node(scene, old)
    else:
        mrml_io.set_transform_matrix(transform_node, camera_to_tool)
    if info is not None:
        mrml_io.set_json_attribute(calibration_node(scene, node), HANDEYE_KEY, info)
    return transform_node


def handeye_node(scene, required=True):
    """The hand-eye transform node: ``CameraToCameraTool``, or in a scene saved
    before that name ``CameraToTracker``."""
    for name in (HANDEYE_TRANSFORM,) + LEGACY_HANDEYE_TRANSFORMS:
        node = mrml_io.get_node(scene, name, "vtkMRMLLinearTransformNode", required=False)
        if node is not None:
            return node
    if required:
        from fluoguide.errors import FluoInputError

        raise FluoInputError("no hand-eye calibration in scene", field=HANDEYE_TRANSFORM,
                             file=scene.GetURL() or None)
    return None


def load_handeye(scene):
    """The 4x4 CameraToTool matrix (``CameraToCameraTool`` or the old ``CameraToTracker``)."""
    return mrml_io.get_transform(scene, handeye_node(scene).GetName())


def store_registration(scene, tracker_to_reference, info=None, node=None, transform_node=None):
    """Write ``TrackerToReference`` (or a caller-chosen transform node) and
    ``FluoCalib.Registration`` (FRE/TRE)."""
    if transform_node is None:
        transform_node = mrml_io.set_transform(scene, REGISTRATION_TRANSFORM, tracker_to_reference)
    else:
        mrml_io.set_transform_matrix(transform_node, tracker_to_reference)
    if info is not None:
        mrml_io.set_json_attribute(calibration_node(scene, node), REGISTRATION_KEY, info)
    return transform_node
