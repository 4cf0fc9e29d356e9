"""Paired-point rigid registration (Horn 1988) and pivot calibration.

Used for tracker-to-CBCT registration with fiducials touched by a tracked
pointer, for the board-to-tracker registration of hand-eye calibration (4 grid
corners touched with the pointer), and inside the paired-point hand-eye method.

Error measures (Fitzpatrick's definitions):

- FRE: RMS over fiducials of |T(p_i) - q_i| after the fit [mm].
- TRE: |T(t) - t_true| at target points not used in the fit [mm].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError

from FluoCalibLib.geometry import transforms as tf

__all__ = ["MAX_COORDINATE_MM", "check_points", "RegistrationResult", "register_points", "target_registration_error",
           "pivot_calibration"]


@dataclass
class RegistrationResult:
    """``transform`` maps moving (source) points onto fixed (target) points."""

    transform: np.ndarray
    fre_mm: float
    residuals_mm: np.ndarray

    def to_dict(self):
        return {"transform": self.transform.tolist(), "fre_mm": self.fre_mm,
                "residuals_mm": self.residuals_mm.tolist()}


#: the largest coordinate [mm] a tracked or image point may have: 100 m, far
#: beyond any tracker's working volume (an optical tracker's is ~3 m) or scanner
#: frame; the SVD squares coordinates, and 1e300 mm overflowed to a null FRE
MAX_COORDINATE_MM = 1e5


def check_points(points_mm, field, file=None):
    """(N, 3) points [mm] as an array: finite, each coordinate within
    +-MAX_COORDINATE_MM; else FluoInputError naming the file, ``field row R``
    (1-based) and the value.

    Parameters
    ----------
    points_mm : array_like
        Points [mm], one per row.
    field : str
        The option or argument named in the message.
    file : str or Path, optional
        The file the points came from.
    """
    try:
        arr = np.asarray(points_mm, dtype=float)
    except (TypeError, ValueError):
        raise FluoInputError("points must be numbers", file=file, field=field) from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FluoInputError("points must be N rows of x, y, z [mm]", file=file, field=field,
                             value=arr.shape)
    bad = ~np.isfinite(arr) | (np.abs(arr) > MAX_COORDINATE_MM)
    if np.any(bad):
        row = int(np.argwhere(bad)[0][0])
        value = float(arr[row][bad[row]][0])
        what = ("must be finite" if not np.isfinite(value) else
                f"coordinates must be within +-{MAX_COORDINATE_MM:g} mm (100 m, beyond any "
                "tracker's or scanner's volume)")
        raise FluoInputError(what, file=file, field=f"{field} row {row + 1}", value=value)
    return arr


def _points(name, p):
    return check_points(p, name)


def register_points(moving_mm, fixed_mm, weights=None):
    """Least-squares rigid transform with ``fixed ~ T(moving)`` (Horn / Arun SVD form).

    The SVD solution is algebraically the same optimum as Horn's quaternion
    method; the determinant correction keeps it a rotation (no reflection).

    Parameters
    ----------
    moving_mm, fixed_mm : (N, 3) array_like
        Corresponding points [mm], N >= 3 and not collinear.
    weights : (N,) array_like, optional

    Returns
    -------
    RegistrationResult
        ``transform`` = MovingToFixed, FRE and per-point residuals [mm].
    """
    P = _points("moving_mm", moving_mm)
    Q = _points("fixed_mm", fixed_mm)
    if P.shape != Q.shape:
        raise FluoInputError("moving and fixed point lists differ in length", field="fixed_mm",
                             value=(len(P), len(Q)))
    if len(P) < 3:
        raise FluoInputError("need at least 3 point pairs", field="moving_mm", value=len(P))
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float).ravel()
    if w.shape != (len(P),) or np.any(w < 0) or w.sum() <= 0:
        raise FluoInputError("weights must be N non-negative numbers", field="weights")
    w = w / w.sum()
    pc = w @ P
    qc = w @ Q
    Pc = P - pc
    Qc = Q - qc
    # collinear (or coincident) points leave the rotation about their line free
    s = np.linalg.svd(Pc * np.sqrt(w)[:, None], compute_uv=False)
    if s[1] < 1e-6 * max(s[0], 1e-12):
        raise FluoInputError("points are collinear: the rotation is not determined",
                             field="moving_mm")
    H = (Pc * w[:, None]).T @ Qc
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    t = qc - R @ pc
    T = tf.make_rigid(R, t)
    res = np.linalg.norm(tf.apply_rigid(T, P) - Q, axis=1)
    return RegistrationResult(T, float(np.sqrt(np.mean(res ** 2))), res)


def target_registration_error(transform, targets_moving_mm, targets_fixed_mm):
    """TRE [mm] per target: ``|T(target in moving frame) - target in fixed frame|``."""
    a = _points("targets_moving_mm", targets_moving_mm)
    b = _points("targets_fixed_mm", targets_fixed_mm)
    if a.shape != b.shape:
        raise FluoInputError("target lists differ in length", field="targets_fixed_mm")
    return np.linalg.norm(tf.apply_rigid(transform, a) - b, axis=1)


def pivot_calibration(tool_to_tracker, min_angle_deg=15.0):
    """Pivot calibration of a tracked pointer (algebraic two-step-free LSQ).

    Each pose satisfies ``R_i p_tip + t_i = p_pivot``; stacking
    ``[R_i, -I] [p_tip; p_pivot] = -t_i`` gives a linear least-squares problem.

    Parameters
    ----------
    tool_to_tracker : sequence of (4, 4)
        Pointer poses while its tip rests in a fixed divot [mm].
    min_angle_deg : float
        The poses must span at least this rotation, else the tip offset is
        not determined.

    Returns
    -------
    dict
        ``tip_in_tool_mm`` (3,), ``pivot_in_tracker_mm`` (3,), ``rms_mm``
        (RMS distance of the per-pose tip positions from the pivot), ``residuals_mm``.
    """
    Ts = tf.as_rigid_list(tool_to_tracker, "poses")
    if len(Ts) < 3:
        raise FluoInputError("pivot calibration needs at least 3 poses", field="poses",
                             value=len(Ts))
    spread = max(tf.rotation_angle(Ts[0][:3, :3].T @ T[:3, :3]) for T in Ts)
    if np.degrees(spread) < min_angle_deg:
        raise FluoInputError(f"pointer rotated only {np.degrees(spread):.1f} deg about the "
                             f"pivot; need >= {min_angle_deg:g} deg", field="poses")
    A = np.vstack([np.hstack([T[:3, :3], -np.eye(3)]) for T in Ts])
    b = -np.concatenate([T[:3, 3] for T in Ts])
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    tip, pivot = x[:3], x[3:]
    tips = np.array([T[:3, :3] @ tip + T[:3, 3] for T in Ts])
    res = np.linalg.norm(tips - pivot, axis=1)
    return {"tip_in_tool_mm": tip, "pivot_in_tracker_mm": pivot,
            "rms_mm": float(np.sqrt(np.mean(res ** 2))), "residuals_mm": res}
