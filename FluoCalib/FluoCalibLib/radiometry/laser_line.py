"""Laser beam-line calibration (docs/physics.md section 7).

Per image: spot centroid (intensity-weighted centroid of the pixels above 90 %
of the maximum after a 4x4 median), the pixel ray meets the tracked phantom
plane, and the point is expressed in the laser tool's frame.  A line through
those points (least orthogonal distance: eigen-decomposition of their scatter)
is the beam; its origin is the pointer-touched point on the collimator face
projected onto the line.  Accuracy on held-out images: distance between the
predicted beam hit (line and plane) and the measured spot point (3D, mm), and
between their image projections (2D, px).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from fluoguide.errors import FluoInputError

from FluoCalibLib.radiometry.synthetic import ray_plane_points

__all__ = ["spot_centroid", "fit_line", "calibrate_laser"]


def spot_centroid(image_adu, fraction=0.9, median_px=4):
    """(u, v) [px] of the laser spot; raises when there is no distinct spot."""
    img = np.asarray(image_adu, float)
    f = ndimage.median_filter(img, size=median_px)
    lo, hi = float(np.median(f)), float(f.max())
    if not hi > lo:
        raise FluoInputError("no laser spot (flat image)", field="image")
    mask = f >= lo + fraction * (hi - lo)
    lab, n = ndimage.label(mask)
    if n > 1:  # keep the blob holding the maximum
        mask = lab == lab[np.unravel_index(int(np.argmax(f)), f.shape)]
    if mask.sum() > 0.01 * mask.size:
        raise FluoInputError("spot covers more than 1 % of the image (saturated or not a laser "
                             "spot)", field="image", value=int(mask.sum()))
    w = f[mask] - lo
    ys, xs = np.nonzero(mask)
    return float(np.sum(xs * w) / w.sum()), float(np.sum(ys * w) / w.sum())


def fit_line(points_mm):
    """(centroid, unit direction, rms orthogonal residual [mm]) of 3D points."""
    P = np.asarray(points_mm, float)
    if len(P) < 3:
        raise FluoInputError("need >= 3 beam points for a line", field="points", value=len(P))
    c = P.mean(axis=0)
    w, V = np.linalg.eigh(np.cov((P - c).T))
    d = V[:, -1]
    spread = np.sqrt(max(w[-1], 0.0))
    if spread < 1.0:
        raise FluoInputError("beam points coincide (spread < 1 mm): vary the phantom distance",
                             field="points", value=float(spread))
    r = (P - c) - np.outer((P - c) @ d, d)
    return c, d, float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def _spot_point_tracker(camera, uv, camera_to_tracker, phantom_to_tracker):
    phantom_to_camera = np.linalg.inv(camera_to_tracker) @ phantom_to_tracker
    pts, valid = ray_plane_points(camera, phantom_to_camera, np.array([uv]))
    if not valid[0]:
        raise FluoInputError("the spot's ray misses the phantom plane", field="phantom pose")
    return (camera_to_tracker @ np.append(pts[0], 1.0))[:3]


def calibrate_laser(images, camera, camera_to_tracker, laser_to_tracker, phantom_to_tracker,
                    pointer_origin_tool_mm=None, holdout=4):
    """Fit the beam line in laser-tool coordinates and score it on held-out images.

    Parameters
    ----------
    images : list of (H, W) spot images [ADU]
    camera : CameraModel
    camera_to_tracker : 4x4 (one for all images) or list of 4x4 per image [mm]
    laser_to_tracker, phantom_to_tracker : lists of 4x4 per image [mm]
    pointer_origin_tool_mm : the collimator point touched with a tracked pointer
        (laser-tool coordinates); its projection onto the line is the origin
    holdout : images (evenly spaced) kept out of the fit for the accuracy
    """
    from fluoguide.errors import check_number

    n = len(images)
    check_number("holdout", holdout, 0, None, integer=True, what="must be 0 or more images")
    if not (len(laser_to_tracker) == len(phantom_to_tracker) == n):
        raise FluoInputError("one laser and one phantom pose per image", field="poses",
                             value=(n, len(laser_to_tracker), len(phantom_to_tracker)))
    C = np.asarray(camera_to_tracker, float)
    cams = [C] * n if C.shape == (4, 4) else list(C)
    if n - holdout < 3:
        raise FluoInputError(f"need >= 3 fit images plus {holdout} held out", field="images",
                             value=n)
    test = set(np.linspace(1, n - 2, holdout).round().astype(int).tolist()) if holdout else set()
    uv, pts_tool = [], []
    for k in range(n):
        c = spot_centroid(images[k])
        p_tr = _spot_point_tracker(camera, c, cams[k], np.asarray(phantom_to_tracker[k], float))
        p_tool = np.linalg.inv(np.asarray(laser_to_tracker[k], float)) @ np.append(p_tr, 1.0)
        uv.append(c)
        pts_tool.append(p_tool[:3])
    fit_idx = [k for k in range(n) if k not in test]
    c, d, rms = fit_line([pts_tool[k] for k in fit_idx])
    # orient the beam away from the tool (increasing distance of the points)
    if np.mean([(pts_tool[k] - c) @ d * np.linalg.norm(pts_tool[k]) for k in fit_idx]) < 0:
        d = -d
    if pointer_origin_tool_mm is not None:
        q = np.asarray(pointer_origin_tool_mm, float)
        origin = c + ((q - c) @ d) * d
    else:
        origin = c + min((pts_tool[k] - c) @ d for k in fit_idx) * d
    e3, e2 = [], []
    for k in sorted(test):
        L = np.asarray(laser_to_tracker[k], float)
        o = (L @ np.append(origin, 1.0))[:3]
        dd = L[:3, :3] @ d
        P = np.asarray(phantom_to_tracker[k], float)
        nrm, p0 = P[:3, 2], P[:3, 3]
        s = ((p0 - o) @ nrm) / (dd @ nrm)
        hit = o + s * dd
        meas = (L @ np.append(pts_tool[k], 1.0))[:3]
        e3.append(float(np.linalg.norm(hit - meas)))
        hit_cam = np.linalg.inv(cams[k]) @ np.append(hit, 1.0)
        e2.append(float(np.linalg.norm(camera.project(hit_cam[None, :3])[0] - np.asarray(uv[k]))))
    return {"origin_mm": origin.tolist(), "direction": d.tolist(), "line_fit_rms_mm": rms,
            "error_3d_mm": float(np.mean(e3)) if e3 else None,
            "error_3d_sd_mm": float(np.std(e3)) if e3 else None,
            "error_2d_px": float(np.mean(e2)) if e2 else None,
            "error_2d_sd_px": float(np.std(e2)) if e2 else None,
            "images_fit": len(fit_idx), "images_held_out": len(test),
            "spots_px": [list(map(float, u)) for u in uv]}
