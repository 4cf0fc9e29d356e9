"""Hand-eye calibration: camera frame to tracked camera-tool frame.

Frames (SlicerIGT ``AToB`` = maps coordinates in A into B):

- ``BoardToCamera_i``: board pose seen by the camera in view i (PnP).
- ``ToolToTracker_i``: tracked tool pose of view i.
- ``BoardToTracker``: board (grid) registered to the tracker, e.g. by touching
  4 grid corners with a tracked pointer (:func:`board_to_tracker_from_pointer`).
- Unknown: ``CameraToTool`` (the thesis' X^-1; stored in the scene as
  ``CameraToCameraTool`` under the tool's ``CameraToolToTracker``).

Loop: ``ToolToTracker_i @ CameraToTool = BoardToTracker @ inv(BoardToCamera_i)``.

Methods compared on the same data:

- ``TSAI``, ``PARK``, ``HORAUD``, ``ANDREFF``, ``DANIILIDIS``: OpenCV's AX = XB
  solvers (``cv2.calibrateHandEye``); they use only relative motions.
- ``PAIRED_POINT``: the reference's method (docs/physics.md section 4.2, Horn 1988).
  Each view gives the camera pose in grid coordinates (PnP) and the tool pose
  in grid coordinates (tracking + grid registration); a set of points fixed in
  the camera frame is mapped into the tool frame by every view, and one Horn
  registration of camera-frame points to tool-frame points over all views
  gives CameraToTool.

Metrics (docs/physics.md section 4.3), with the camera pose predicted from tracking
and calibration, ``BoardToCamera_pred = inv(ToolToTracker_i @ CameraToTool) @ BoardToTracker``:

- 3D error [mm]: detected corners back-projected (ray through the undistorted
  pixel) onto the grid plane, distance to the true corner positions.
- 2D error [px]: true corners projected through ``BoardToCamera_pred`` and the
  intrinsics, distance to the detected corners.
"""

from __future__ import annotations

import cv2
import numpy as np

from fluoguide.errors import FluoInputError

from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.registration import register_points

__all__ = ["OPENCV_METHODS", "METHODS", "check_motion", "solve_handeye",
           "paired_point_handeye", "handeye_errors", "compare_methods",
           "board_to_tracker_from_pointer", "estimate_board_to_tracker", "MIN_ROTATION_DEG"]

OPENCV_METHODS = {
    "TSAI": cv2.CALIB_HAND_EYE_TSAI,
    "PARK": cv2.CALIB_HAND_EYE_PARK,
    "HORAUD": cv2.CALIB_HAND_EYE_HORAUD,
    "ANDREFF": cv2.CALIB_HAND_EYE_ANDREFF,
    "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
METHODS = tuple(OPENCV_METHODS) + ("PAIRED_POINT",)
#: Relative tool rotations below this [deg] carry no rotation information.
MIN_ROTATION_DEG = 2.0
#: Rotation axes must spread by at least this [deg] (two non-parallel axes needed).
MIN_AXIS_SPREAD_DEG = 5.0


def _as_poses(name, poses):
    return tf.as_rigid_list(poses, name)


def check_motion(tool_to_tracker):
    """Raise FluoInputError if the tool motion cannot determine hand-eye.

    Needs relative rotations of at least MIN_ROTATION_DEG about at least two
    axes that differ by MIN_AXIS_SPREAD_DEG (Tsai & Lenz's condition);
    otherwise rotation (pure translation) or the translation along the single
    rotation axis is unobservable.

    Returns
    -------
    dict
        ``max_rotation_deg`` and ``axis_spread_deg`` of the relative motions.
    """
    Ts = _as_poses("tool_to_tracker", tool_to_tracker)
    axes = []
    max_rot = 0.0
    for i in range(len(Ts)):
        for j in range(i + 1, len(Ts)):
            rv = tf.matrix_to_rotvec(Ts[i][:3, :3].T @ Ts[j][:3, :3])
            ang = np.degrees(np.linalg.norm(rv))
            max_rot = max(max_rot, ang)
            if ang >= MIN_ROTATION_DEG:
                axes.append(rv / np.linalg.norm(rv))
    if not axes:
        raise FluoInputError(
            f"tool motion is (nearly) pure translation (largest relative rotation "
            f"{max_rot:.2f} deg < {MIN_ROTATION_DEG:g} deg): hand-eye rotation is not "
            "determined; rotate the camera between views", field="tool_to_tracker",
            value=round(max_rot, 3))
    A = np.array(axes)
    # Axes are sign-ambiguous, so use the scatter matrix mean(a a^T): for two
    # axes at angle theta its second eigenvalue is sin^2(theta / 2).
    s = np.linalg.svd(A, compute_uv=False)
    second = s[1] if len(s) > 1 else 0.0
    spread = float(2.0 * np.degrees(np.arcsin(min(1.0, second / np.sqrt(len(A))))))
    if spread < MIN_AXIS_SPREAD_DEG:
        raise FluoInputError(
            "all tool rotations are about (nearly) one axis: translation along it is not "
            "determined; rotate about at least two different axes", field="tool_to_tracker",
            value=round(spread, 3))
    return {"max_rotation_deg": max_rot, "axis_spread_deg": spread}


def _check_counts(board_to_camera, tool_to_tracker):
    if len(board_to_camera) != len(tool_to_tracker):
        raise FluoInputError(
            f"{len(board_to_camera)} board views but {len(tool_to_tracker)} tool poses: each "
            "image needs exactly one synchronised tool pose", field="tool_to_tracker",
            value=(len(board_to_camera), len(tool_to_tracker)))
    if len(board_to_camera) < 3:
        raise FluoInputError("hand-eye calibration needs at least 3 views",
                             field="board_to_camera", value=len(board_to_camera))


def solve_handeye(board_to_camera, tool_to_tracker, method="TSAI", board_to_tracker=None):
    """CameraToTool from synchronised board and tool poses.

    Parameters
    ----------
    board_to_camera, tool_to_tracker : sequences of (4, 4) [mm]
    method : one of METHODS
    board_to_tracker : (4, 4), optional
        Grid registration; needed by PAIRED_POINT (estimated from the
        OpenCV TSAI solution when not given).

    Returns
    -------
    (4, 4) ndarray
        CameraToTool.
    """
    B = _as_poses("board_to_camera", board_to_camera)
    A = _as_poses("tool_to_tracker", tool_to_tracker)
    _check_counts(B, A)
    check_motion(A)
    m = str(method).upper()
    if m == "PAIRED_POINT":
        return paired_point_handeye(B, A, board_to_tracker)
    if m not in OPENCV_METHODS:
        raise FluoInputError(f"unknown hand-eye method; choose from {', '.join(METHODS)}",
                             field="method", value=method)
    R, t = cv2.calibrateHandEye([T[:3, :3] for T in A], [T[:3, 3] for T in A],
                                [T[:3, :3] for T in B], [T[:3, 3] for T in B],
                                method=OPENCV_METHODS[m])
    X = tf.make_rigid(tf.orthonormalize(R), np.ravel(t))
    if not np.all(np.isfinite(X)):
        raise FluoInputError(f"{m} returned no solution (degenerate motion?)", field="method")
    return X


def estimate_board_to_tracker(board_to_camera, tool_to_tracker, camera_to_tool):
    """Mean BoardToTracker implied by a hand-eye solution (rotation averaged by SVD).

    Used when no pointer registration of the grid is available.
    """
    B, A, X = board_to_camera, tool_to_tracker, camera_to_tool
    Ms = [Ai @ X @ Bi for Ai, Bi in zip(A, B)]
    R = tf.orthonormalize(sum(M[:3, :3] for M in Ms))
    t = np.mean([M[:3, 3] for M in Ms], axis=0)
    return tf.make_rigid(R, t)


def paired_point_handeye(board_to_camera, tool_to_tracker, board_to_tracker=None,
                         probe_mm=100.0):
    """Paired-point (Horn) hand-eye calibration of the reference.

    The camera origin and points ``probe_mm`` along each camera axis are the
    fiducials; in view i their tool-frame positions are
    ``inv(BoardToTracker^-1 ToolToTracker_i) inv(BoardToCamera_i) p`` and one
    Horn registration over all views maps camera-frame points to tool frame.
    """
    B = _as_poses("board_to_camera", board_to_camera)
    A = _as_poses("tool_to_tracker", tool_to_tracker)
    _check_counts(B, A)
    if board_to_tracker is None:
        X0 = solve_handeye(B, A, "TSAI")
        board_to_tracker = estimate_board_to_tracker(B, A, X0)
    G = np.asarray(board_to_tracker, dtype=float)
    s = float(probe_mm)
    p_cam = np.array([[0, 0, 0], [s, 0, 0], [0, s, 0], [0, 0, s]], dtype=float)
    moving, fixed = [], []
    G_inv = tf.invert_rigid(G)
    for Ai, Bi in zip(A, B):
        tool_to_board = G_inv @ Ai
        cam_to_board = tf.invert_rigid(Bi)
        cam_to_tool = tf.invert_rigid(tool_to_board) @ cam_to_board
        moving.append(p_cam)
        fixed.append(tf.apply_rigid(cam_to_tool, p_cam))
    return register_points(np.vstack(moving), np.vstack(fixed)).transform


def handeye_errors(camera, board, detections, tool_to_tracker, camera_to_tool,
                   board_to_tracker):
    """3D [mm] and 2D [px] errors of the reference, per corner over all views.

    Parameters
    ----------
    camera : CameraModel
    board : Board
    detections : sequence of (ids, image_points)
        Detected corners per view (ids index ``board.object_points``).
    tool_to_tracker : sequence of (4, 4)
    camera_to_tool, board_to_tracker : (4, 4)

    Returns
    -------
    dict
        ``err3d_mm`` and ``err2d_px`` arrays (all corners, all views) and
        ``err3d_mean_mm``, ``err3d_sd_mm``, ``err2d_mean_px``, ``err2d_sd_px``.
    """
    if len(detections) != len(tool_to_tracker):
        raise FluoInputError("detections and tool poses differ in number",
                             field="tool_to_tracker", value=(len(detections), len(tool_to_tracker)))
    obj = board.object_points
    e3, e2 = [], []
    for (ids, uv), A in zip(detections, tool_to_tracker):
        ids = np.asarray(ids, dtype=int)
        uv = np.asarray(uv, dtype=float)
        cam_to_board = tf.invert_rigid(board_to_tracker) @ np.asarray(A, float) @ camera_to_tool
        # 3D: back-project detected corners onto the grid plane z = 0
        rays = camera.pixel_rays(uv) @ cam_to_board[:3, :3].T
        o = cam_to_board[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -o[2] / rays[:, 2]
        hit = o + lam[:, None] * rays
        e3.append(np.linalg.norm(hit[:, :2] - obj[ids, :2], axis=1))
        # 2D: true corners projected through tracking + calibration
        pred = camera.project(tf.apply_rigid(tf.invert_rigid(cam_to_board), obj[ids]))
        e2.append(np.linalg.norm(pred - uv, axis=1))
    e3 = np.concatenate(e3)
    e2 = np.concatenate(e2)
    return {"err3d_mm": e3, "err2d_px": e2,
            "err3d_mean_mm": float(np.nanmean(e3)), "err3d_sd_mm": float(np.nanstd(e3, ddof=1)),
            "err2d_mean_px": float(np.nanmean(e2)), "err2d_sd_px": float(np.nanstd(e2, ddof=1))}


def board_to_tracker_from_pointer(board, touched_corner_ids, pointer_tips_tracker_mm):
    """Grid registration from corners touched with a tracked pointer.

    Parameters
    ----------
    board : Board
    touched_corner_ids : sequence of int
        Indices into ``board.object_points`` (the thesis used the 4 outer corners).
    pointer_tips_tracker_mm : (N, 3)
        Tip positions in tracker coordinates [mm].

    Returns
    -------
    RegistrationResult
        ``transform`` = BoardToTracker, with FRE.
    """
    ids = np.asarray(touched_corner_ids, dtype=int)
    return register_points(board.object_points[ids], pointer_tips_tracker_mm)


def compare_methods(camera, board, board_to_camera, tool_to_tracker, detections,
                    board_to_tracker, methods=METHODS, truth_camera_to_tool=None, holdout=0):
    """Run every method on the same data; errors by the reference's metrics.

    Parameters
    ----------
    holdout : int
        Number of views (evenly spaced) left out of every fit; their errors
        are reported separately as ``holdout_err3d_mean_mm`` etc., so the
        accuracy is not judged on the views that were fitted.

    Returns
    -------
    dict
        method -> {``camera_to_tool``, ``err3d_mean_mm``, ``err3d_sd_mm``,
        ``err2d_mean_px``, ``err2d_sd_px`` (fitted views), ``holdout_*`` (the
        same on held-out views, when ``holdout``), and with a truth:
        ``translation_error_mm``, ``rotation_error_deg``}.
    """
    _check_counts(board_to_camera, tool_to_tracker)
    n = len(board_to_camera)
    holdout = int(holdout)
    if holdout < 0 or n - holdout < 3:
        raise FluoInputError(f"holdout leaves {n - holdout} views to fit; need 3",
                             field="holdout", value=holdout)
    hold = set()
    if holdout:
        picks = np.round(np.linspace(0, n - 1, holdout + 2)[1:-1]).astype(int)
        hold = set(np.unique(picks).tolist())
    fit = [i for i in range(n) if i not in hold]
    B_fit = [board_to_camera[i] for i in fit]
    A_fit = [tool_to_tracker[i] for i in fit]
    check_motion(A_fit)
    out = {}
    for m in methods:
        X = solve_handeye(B_fit, A_fit, m, board_to_tracker)
        row = {"camera_to_tool": X}
        err = handeye_errors(camera, board, [detections[i] for i in fit], A_fit, X,
                             board_to_tracker)
        row.update({k: v for k, v in err.items() if not isinstance(v, np.ndarray)})
        if hold:
            idx = sorted(hold)
            err = handeye_errors(camera, board, [detections[i] for i in idx],
                                 [tool_to_tracker[i] for i in idx], X, board_to_tracker)
            row.update({f"holdout_{k}": v for k, v in err.items() if not isinstance(v, np.ndarray)})
            row["holdout_views"] = idx
        if truth_camera_to_tool is not None:
            Xt = np.asarray(truth_camera_to_tool, dtype=float)
            row["translation_error_mm"] = float(np.linalg.norm(X[:3, 3] - Xt[:3, 3]))
            dR = X[:3, :3].T @ Xt[:3, :3]
            row["rotation_error_deg"] = float(np.degrees(tf.rotation_angle(dR)))
        out[m] = row
    return out
