"""OpenCV FileStorage YAML of camera intrinsics and hand-eye results.

Keys follow OpenCV's calibration sample (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``) so files load
in other OpenCV tools; ``camera_model`` ("pinhole"/"fisheye"),
``camera_to_tool`` and ``board_to_tracker`` (4x4, mm) are added when present.
Values are written with full double precision, so a round trip is exact.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fluoguide.errors import FluoInputError

from FluoCalibLib.geometry.camera_model import CameraModel

__all__ = ["write_calibration_yaml", "read_calibration_yaml"]


def write_calibration_yaml(path, camera=None, camera_to_tool=None, board_to_tracker=None,
                           rms_px=None):
    """Write an OpenCV YAML file (atomically: temporary name, then rename)."""
    from fluoguide import atomic

    path = Path(path)
    with atomic.atomic_path(path, field="yaml") as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise FluoInputError("cannot write file", file=path)
        try:
            if camera is not None:
                fs.write("camera_model", camera.model)
                fs.write("image_width", int(camera.width))
                fs.write("image_height", int(camera.height))
                fs.write("camera_matrix", camera.K)
                fs.write("distortion_coefficients", camera.dist_array.reshape(1, -1))
            if rms_px is not None:
                fs.write("avg_reprojection_error", float(rms_px))
            if camera_to_tool is not None:
                fs.write("camera_to_tool", np.asarray(camera_to_tool, dtype=float))
            if board_to_tracker is not None:
                fs.write("board_to_tracker", np.asarray(board_to_tracker, dtype=float))
        finally:
            fs.release()
    return path


def _check_duplicate_keys(path):
    """Refuse a YAML file with a key twice (FileStorage silently reads the first)."""
    import yaml

    from fluoguide.strict_yaml import check_duplicate_keys

    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return                  # not text: FileStorage refuses it with its own message
    try:
        check_duplicate_keys(text, file=path)
    except (yaml.YAMLError, RecursionError):
        pass                    # YAML that only OpenCV parses: it cannot hold this check


def read_calibration_yaml(path):
    """Read a file written by :func:`write_calibration_yaml` or OpenCV's calibration sample.

    Returns
    -------
    dict
        ``camera`` (CameraModel or None), ``camera_to_tool``,
        ``board_to_tracker`` (4x4 or None), ``rms_px`` (float or None).
    """
    path = Path(path)
    if not path.is_file():
        raise FluoInputError("file not found", file=path)
    if path.suffix.lower() in (".yaml", ".yml"):
        _check_duplicate_keys(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # the binding wraps the parser's cv2.error in a SystemError (its cause)
        from fluoguide.library_errors import opencv_problem

        cause = exc.__cause__ if isinstance(exc.__cause__, cv2.error) else exc
        raise FluoInputError(f"not an OpenCV FileStorage file ({opencv_problem(cause)})",
                             file=path) from None
    if not fs.isOpened():
        raise FluoInputError("not an OpenCV FileStorage file", file=path)
    try:
        def mat(key):
            node = fs.getNode(key)
            return None if node.empty() else node.mat()

        out = {"camera": None, "camera_to_tool": mat("camera_to_tool"),
               "board_to_tracker": mat("board_to_tracker"), "rms_px": None}
        K = mat("camera_matrix")
        if K is not None:
            D = mat("distortion_coefficients")
            D = np.zeros(5) if D is None else D.ravel()
            w = fs.getNode("image_width")
            h = fs.getNode("image_height")
            if w.empty() or h.empty():
                raise FluoInputError("image_width/image_height missing", file=path)
            model_node = fs.getNode("camera_model")
            model = "pinhole" if model_node.empty() else model_node.string()
            if model == "pinhole" and D.size > 5:
                if np.any(D[5:] != 0):
                    raise FluoInputError("rational/thin-prism distortion terms are not "
                                         "supported", file=path, field="distortion_coefficients")
                D = D[:5]
            out["camera"] = CameraModel.from_K(K, D, int(w.real()), int(h.real()), model)
        rms = fs.getNode("avg_reprojection_error")
        if not rms.empty():
            out["rms_px"] = float(rms.real())
        return out
    finally:
        fs.release()
