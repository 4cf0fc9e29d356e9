"""Undistortion maps for live video (computed once per camera, cached).

``cv2.remap`` with precomputed maps costs about one memory pass per frame,
so live video can be rectified at frame rate; the maps depend only on the
intrinsics, hence the cache keyed by the camera's parameters.
"""

from __future__ import annotations

import cv2
import numpy as np

from fluoguide.errors import FluoInputError

from FluoCalibLib.geometry.camera_model import CameraModel

__all__ = ["undistort_maps", "undistort_image", "clear_cache"]

_CACHE = {}
_CACHE_MAX = 8  # each map pair of a 1392x1040 camera is ~11 MB


def _key(camera, new_camera, fixed_point):
    return (camera.fx, camera.fy, camera.cx, camera.cy, camera.dist, camera.width,
            camera.height, camera.model,
            None if new_camera is None else (new_camera.fx, new_camera.fy, new_camera.cx,
                                             new_camera.cy, new_camera.width, new_camera.height),
            fixed_point)


def undistort_maps(camera, new_camera=None, fixed_point=True):
    """Maps for ``cv2.remap`` from a distorted frame to an ideal pinhole frame.

    Parameters
    ----------
    camera : CameraModel
        The real (distorted) camera.
    new_camera : CameraModel, optional
        Intrinsics of the output image (distortion ignored); default: the
        same K and size without distortion.
    fixed_point : bool
        Return the compact fixed-point (CV_16SC2) maps, faster to apply.

    Returns
    -------
    (map1, map2)
        Arguments for ``cv2.remap``.
    """
    if not isinstance(camera, CameraModel):
        raise FluoInputError("camera must be a CameraModel", field="camera")
    key = _key(camera, new_camera, fixed_point)
    if key in _CACHE:
        return _CACHE[key]
    newc = new_camera or CameraModel(camera.fx, camera.fy, camera.cx, camera.cy,
                                     (0.0,) * 5, camera.width, camera.height)
    size = (newc.width, newc.height)
    m1type = cv2.CV_16SC2 if fixed_point else cv2.CV_32FC1
    if camera.model == "fisheye":
        maps = cv2.fisheye.initUndistortRectifyMap(camera.K, camera.dist_array, np.eye(3),
                                                   newc.K, size, m1type)
    else:
        maps = cv2.initUndistortRectifyMap(camera.K, camera.dist_array, np.eye(3), newc.K,
                                           size, m1type)
    if len(_CACHE) >= _CACHE_MAX:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = maps
    return maps


def undistort_image(image, camera, new_camera=None, interpolation=cv2.INTER_LINEAR):
    """Undistort one frame (grayscale or colour) with cached maps."""
    img = np.asarray(image)
    if img.shape[:2] != (camera.height, camera.width):
        raise FluoInputError("frame size differs from the camera's", field="image",
                             value=img.shape[:2])
    m1, m2 = undistort_maps(camera, new_camera)
    return cv2.remap(img, m1, m2, interpolation, borderMode=cv2.BORDER_CONSTANT)


def clear_cache():
    """Drop all cached maps."""
    _CACHE.clear()
