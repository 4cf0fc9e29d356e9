"""Tracked camera frames in the MRML scene: the one format that recording,
replay, the live loop and ``fluo nav correct`` share (see docs/scene.md).

A recording in the scene is

- ``CameraFrame-Sequence`` (vtkMRMLSequenceNode of 2D scalar volumes, index =
  frame time [s], saved as ``.seq.nrrd``): counts [ADU], pixel (i, j) =
  (column, row), spacing 1 px;
- ``FluoNavRecordingLog`` (vtkMRMLTableNode, one row per frame, string
  columns): ``frame``, ``timestamp_s``, ``exposure_s``, ``pose_valid``,
  ``pose_status`` and one column per tool (``CameraToolToTracker``, ...) with
  the tool pose interpolated to the frame time as 16 comma-separated numbers
  (row-major 4x4), empty when missing.

Numbers are written with Python's shortest round-trip repr, so a recording
read back gives the recorded poses bit for bit (VTK's numeric table columns
keep only 6 digits).  A frame whose pose is not valid has ``pose_valid`` 0;
readers get ``None`` for its pose and must never map such a frame.
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError

__all__ = ["FRAME_SEQUENCE", "LOG_TABLE", "BASE_COLUMNS", "new_recording",
           "append_tracked_frame", "number_of_frames", "read_tracked_frame", "recording_tools"]

FRAME_SEQUENCE = "CameraFrame-Sequence"
LOG_TABLE = "FluoNavRecordingLog"
BASE_COLUMNS = ("frame", "timestamp_s", "exposure_s", "pose_valid", "pose_status")


def _slicer():
    import slicer

    return slicer


def _log(scene, required=True):
    node = mrml_io.get_node(scene, LOG_TABLE, class_name="vtkMRMLTableNode", required=False)
    if node is None and required:
        raise FluoInputError("scene has no recording (no table node)", field=LOG_TABLE)
    return node


def _frames(scene, required=True):
    node = mrml_io.get_node(scene, FRAME_SEQUENCE, class_name="vtkMRMLSequenceNode", required=False)
    if node is None and required:
        raise FluoInputError("scene has no recording (no frame sequence)", field=FRAME_SEQUENCE)
    return node


def new_recording(scene, tools=("CameraToolToTracker",)):
    """Create (or empty) the frame sequence and the log table for ``tools``."""
    import vtk

    slicer = _slicer()
    seq = _frames(scene, required=False)
    if seq is None:
        seq = slicer.vtkMRMLSequenceNode()
        seq.SetName(FRAME_SEQUENCE)
        scene.AddNode(seq)
    seq.RemoveAllDataNodes()
    seq.SetIndexName("time")
    seq.SetIndexUnit("s")
    seq.SetIndexType(seq.NumericIndex)
    seq.SetNumericIndexValueTolerance(1e-9)
    log = _log(scene, required=False)
    if log is None:
        log = slicer.vtkMRMLTableNode()
        log.SetName(LOG_TABLE)
        scene.AddNode(log)
    table = log.GetTable()
    table.Initialize()
    for name in list(BASE_COLUMNS) + list(tools):
        col = vtk.vtkStringArray()
        col.SetName(name)
        table.AddColumn(col)
    log.Modified()
    return seq


def recording_tools(scene):
    """Tool names that have a pose column in the recording."""
    table = _log(scene).GetTable()
    names = [table.GetColumnName(i) for i in range(table.GetNumberOfColumns())]
    return [n for n in names if n not in BASE_COLUMNS]


def _fmt(x):
    return repr(float(x))


def append_tracked_frame(scene, image, timestamp_s, poses, exposure_s=None, pose_valid=True,
                         pose_status="OK"):
    """Add one frame (2D array [ADU]) and its tool poses (dict tool -> 4x4 or None).

    Returns the frame number.  Timestamps must increase.
    """
    import vtk
    from vtk.util import numpy_support as ns

    slicer = _slicer()
    img = np.asarray(image)
    if img.ndim != 2 or img.size == 0:
        raise FluoInputError("camera frame must be a non-empty 2D array", field="image",
                             value=getattr(img, "shape", None))
    ts = float(timestamp_s)
    if not np.isfinite(ts):
        raise FluoInputError("timestamp must be finite", field="timestamp_s", value=timestamp_s)
    seq = _frames(scene)
    log = _log(scene)
    table = log.GetTable()
    n = table.GetNumberOfRows()
    if n:
        last = float(table.GetValueByName(n - 1, "timestamp_s").ToString())
        if ts <= last:
            raise FluoInputError("frame timestamps must increase", field="timestamp_s",
                                 value=timestamp_s)
    tools = recording_tools(scene)
    unknown = set(poses or {}) - set(tools)
    if unknown:
        raise FluoInputError("tool not in this recording", field="poses", value=sorted(unknown))
    row = {"frame": str(n), "timestamp_s": _fmt(ts),
           "exposure_s": "" if exposure_s is None else _fmt(exposure_s),
           "pose_valid": "1" if pose_valid else "0", "pose_status": str(pose_status)}
    for tool in tools:
        m = (poses or {}).get(tool)
        if m is None:
            row[tool] = ""
            continue
        m = np.asarray(m, float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise FluoInputError("pose must be a finite 4x4 matrix", field=tool)
        row[tool] = ",".join(_fmt(v) for v in m.ravel())
    vol = slicer.vtkMRMLScalarVolumeNode()
    vol.SetName(f"CameraFrame_{n:06d}")
    data = vtk.vtkImageData()
    data.SetDimensions(img.shape[1], img.shape[0], 1)
    data.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(img).ravel(), deep=True))
    vol.SetAndObserveImageData(data)
    seq.SetDataNodeAtValue(vol, f"{ts:.9f}")
    r = table.InsertNextBlankRow()
    for name, text in row.items():
        table.SetValueByName(r, name, vtk.vtkVariant(text))
    log.Modified()
    return n


def number_of_frames(scene):
    return _log(scene).GetTable().GetNumberOfRows()


def read_tracked_frame(scene, n):
    """Frame ``n``: ``(image (H, W), info dict, {tool: 4x4 array or None})``.

    A tool's pose is None when it was missing or the frame's pose is not valid.
    """
    from vtk.util import numpy_support as ns

    table = _log(scene).GetTable()
    count = table.GetNumberOfRows()
    if not 0 <= int(n) < count:
        raise FluoInputError(f"no such frame (recording has {count})", field="frame", value=n)
    n = int(n)
    text = {table.GetColumnName(c): table.GetValue(n, c).ToString()
            for c in range(table.GetNumberOfColumns())}
    seq = _frames(scene)
    if seq.GetNumberOfDataNodes() != count:
        raise FluoInputError("frame sequence and log differ in length", field=FRAME_SEQUENCE,
                             value=(seq.GetNumberOfDataNodes(), count))
    vol = seq.GetNthDataNode(n)
    data = vol.GetImageData()
    nx, ny, _ = data.GetDimensions()
    img = ns.vtk_to_numpy(data.GetPointData().GetScalars()).reshape(ny, nx).copy()
    info = {"frame": int(text["frame"]), "timestamp_s": float(text["timestamp_s"]),
            "exposure_s": float(text["exposure_s"]) if text["exposure_s"] else None,
            "pose_valid": text["pose_valid"] == "1", "pose_status": text["pose_status"]}
    poses = {}
    for tool in [k for k in text if k not in BASE_COLUMNS]:
        if not text[tool] or not info["pose_valid"]:
            poses[tool] = None
            continue
        vals = np.array([float(v) for v in text[tool].split(",")])
        if vals.size != 16:
            raise FluoInputError("pose must have 16 numbers", field=tool, value=text[tool][:80])
        poses[tool] = vals.reshape(4, 4)
    return img, info, poses
