"""Reading the inputs of the geometric calibrations from files, checked: board
image globs, tracked-pose JSON, point lists, intrinsics (OpenCV YAML or
FluoGuide JSON), 4x4 matrices. Every reader raises FluoInputError naming the
file, the field and the value; the CLI, the web app and the Slicer widget all
read through here, so a bad file fails the same way everywhere.
"""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import read_json

__all__ = ["image_files", "read_points", "read_matrix", "read_intrinsics", "read_handeye_poses"]


def image_files(pattern, field="--images", minimum=1):
    """Sorted files matching a glob (or every file of a folder); at least ``minimum``."""
    pattern = str(pattern or "").strip()
    if pattern and Path(pattern).is_dir():
        files = sorted(str(p) for p in Path(pattern).iterdir() if p.is_file())
    else:
        files = sorted(glob.glob(pattern)) if pattern else []
    if not files:
        raise FluoInputError("no files match", field=field, value=pattern)
    if len(files) < minimum:
        raise FluoInputError(f"need at least {minimum} images, found {len(files)}", field=field,
                             value=pattern)
    return files


def _json(path, field):
    return read_json(path, expect=None, field=field)


def read_points(path, field):
    """(N, 3) points [mm] from JSON (list or {"points": list}) or CSV/TXT."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        doc = _json(p, field)
        doc = doc.get("points", doc) if isinstance(doc, dict) else doc
        try:
            arr = np.asarray(doc, dtype=float)
        except (TypeError, ValueError):
            raise FluoInputError("points must be numbers", file=p, field=field) from None
    else:
        if not p.is_file():
            raise FluoInputError("file not found", file=p, field=field)
        try:
            arr = np.loadtxt(p, delimiter="," if p.suffix.lower() == ".csv" else None, ndmin=2)
        except ValueError as exc:
            raise FluoInputError(f"cannot parse points ({exc})", file=p, field=field) from None
    from FluoCalibLib.geometry.registration import check_points

    return check_points(arr, field, file=p)     # finite, within 100 m; the row named


def _matrix(value, file, field):
    try:
        m = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise FluoInputError("must be a 4x4 matrix of numbers", file=file, field=field) from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise FluoInputError("must be a finite 4x4 matrix", file=file, field=field,
                             value=m.shape)
    from FluoCalibLib.geometry.transforms import as_rigid

    return as_rigid(m, field, file)      # a pose: rotation and translation only


def read_matrix(path, field, key=None):
    """A 4x4 matrix from JSON: the top-level list, or ``doc[key]`` when that exists."""
    doc = _json(path, field)
    if isinstance(doc, dict) and key is not None:
        doc = doc.get(key, doc)
    return _matrix(doc, path, key or field)


def read_intrinsics(path, field="--intrinsics"):
    """CameraModel from OpenCV YAML/XML (``camera_matrix``...) or FluoGuide JSON
    (``{"camera": {...}}`` or the camera dict itself)."""
    from FluoCalibLib.geometry.camera_model import CameraModel

    p = Path(path)
    if p.suffix.lower() in (".yaml", ".yml", ".xml"):
        from FluoCalibLib.geometry.opencv_yaml import read_calibration_yaml

        cam = read_calibration_yaml(p)["camera"]
        if cam is None:
            raise FluoInputError("no camera_matrix in file", file=p, field=field)
        return cam
    doc = read_json(p, field=field)
    try:
        return CameraModel.from_dict(doc.get("camera", doc))
    except FluoInputError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise FluoInputError(f"not a camera model ({exc})", file=p, field=field) from None


def read_handeye_poses(path, field="--poses"):
    """The tracked poses of a hand-eye data set.

    A JSON object with ``tool_to_tracker`` (one 4x4 per image, in the images'
    sorted order) and optionally ``board_to_tracker`` (grid registration) and
    ``camera_to_tool`` (the truth of a synthetic set).

    Returns
    -------
    dict with ``tool_to_tracker`` (list of 4x4 arrays), ``board_to_tracker``
    and ``camera_to_tool`` (4x4 arrays or None).
    """
    doc = read_json(path, field=field)
    if "tool_to_tracker" not in doc or not isinstance(doc["tool_to_tracker"], list):
        raise FluoInputError('poses file needs a "tool_to_tracker" list of 4x4 matrices',
                             file=path, field="tool_to_tracker")
    poses = [_matrix(T, path, f"tool_to_tracker[{i}]") for i, T in enumerate(doc["tool_to_tracker"])]
    out = {"tool_to_tracker": poses, "board_to_tracker": None, "camera_to_tool": None}
    for key in ("board_to_tracker", "camera_to_tool"):
        if doc.get(key) is not None:
            out[key] = _matrix(doc[key], path, key)
    return out
