"""Rigid 4x4 transforms, rotations and quaternions.

Conventions
-----------
- A transform named ``AToB`` (SlicerIGT naming) maps point coordinates given in
  frame A to frame B: ``p_B = T_AToB @ p_A`` (homogeneous column vectors).
- Translations are in mm; angles in radians.
- Quaternions are ``(w, x, y, z)`` with ``w >= 0`` on output (the sign is
  otherwise arbitrary: q and -q are the same rotation).
- Camera frames follow OpenCV: x right, y down, z forward (along the optical axis).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = [
    "make_rigid",
    "invert_rigid",
    "apply_rigid",
    "rotation_matrix",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
    "matrix_to_quaternion",
    "quaternion_to_matrix",
    "slerp",
    "look_at",
    "is_rigid",
    "as_rigid",
    "as_rigid_list",
    "orthonormalize",
    "rotation_angle",
]


def _as_matrix(T, shape, name):
    arr = np.asarray(T, dtype=float)
    if arr.shape != shape:
        raise FluoInputError(f"must have shape {shape}", field=name, value=arr.shape)
    if not np.all(np.isfinite(arr)):
        raise FluoInputError("must be finite", field=name)
    return arr


def make_rigid(R, t_mm):
    """Build a 4x4 homogeneous transform from a rotation and a translation.

    Parameters
    ----------
    R : (3, 3) array_like
        Rotation matrix.
    t_mm : (3,) array_like
        Translation [mm].

    Returns
    -------
    (4, 4) ndarray
    """
    R = _as_matrix(R, (3, 3), "R")
    t = np.asarray(t_mm, dtype=float).reshape(-1)
    if t.shape != (3,):
        raise FluoInputError("must have 3 elements", field="t_mm", value=t.shape)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_rigid(T):
    """Inverse of a rigid 4x4 transform, using R^T (exact for rigid motions).

    Parameters
    ----------
    T : (4, 4) array_like

    Returns
    -------
    (4, 4) ndarray
    """
    T = _as_matrix(T, (4, 4), "T")
    R = T[:3, :3]
    t = T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def apply_rigid(T, points_mm):
    """Apply a 4x4 transform to points.

    Parameters
    ----------
    T : (4, 4) array_like
    points_mm : (N, 3) or (3,) array_like
        Points [mm].

    Returns
    -------
    ndarray, same shape as ``points_mm``
    """
    T = _as_matrix(T, (4, 4), "T")
    p = np.asarray(points_mm, dtype=float)
    single = p.ndim == 1
    p2 = np.atleast_2d(p)
    if p2.shape[-1] != 3:
        raise FluoInputError("points must have 3 columns", field="points_mm", value=p.shape)
    out = p2 @ T[:3, :3].T + T[:3, 3]
    return out[0] if single else out


def rotation_matrix(axis, angle_rad):
    """Rotation about ``axis`` by ``angle_rad`` (right hand rule; Rodrigues).

    Parameters
    ----------
    axis : (3,) array_like or {"x", "y", "z"}
    angle_rad : float

    Returns
    -------
    (3, 3) ndarray
    """
    if isinstance(axis, str):
        lookup = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
        if axis.lower() not in lookup:
            raise FluoInputError("axis must be x, y or z", field="axis", value=axis)
        axis = lookup[axis.lower()]
    a = np.asarray(axis, dtype=float).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n < 1e-12:
        raise FluoInputError("rotation axis must be a non-zero finite vector", field="axis",
                             value=tuple(a))
    return rotvec_to_matrix(a / n * float(angle_rad))


def rotvec_to_matrix(rotvec):
    """Rotation matrix from a rotation vector (axis * angle [rad]), as cv2.Rodrigues.

    Parameters
    ----------
    rotvec : (3,) array_like

    Returns
    -------
    (3, 3) ndarray
    """
    r = np.asarray(rotvec, dtype=float).reshape(3)
    theta = np.linalg.norm(r)
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-8:
        # Second-order Taylor series: avoids 0/0 and is exact to rounding here.
        return np.eye(3) + K + 0.5 * K @ K
    Kn = K / theta
    return np.eye(3) + np.sin(theta) * Kn + (1.0 - np.cos(theta)) * (Kn @ Kn)


def orthonormalize(R):
    """Closest rotation matrix (Frobenius norm) to ``R``, via SVD, det = +1."""
    R = np.asarray(R, dtype=float).reshape(3, 3)
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def matrix_to_quaternion(R):
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix.

    Uses Shepperd's method (largest diagonal pivot) so it is accurate for every
    angle including 180 degrees.
    """
    R = orthonormalize(_as_matrix(R, (3, 3), "R"))
    tr = np.trace(R)
    cands = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(cands))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_matrix(q):
    """Rotation matrix of a quaternion (w, x, y, z); the quaternion is normalised first."""
    q = np.asarray(q, dtype=float).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise FluoInputError("quaternion must be 4 finite numbers (w, x, y, z)", field="q",
                             value=q.shape)
    n = np.linalg.norm(q)
    if n < 1e-12:
        raise FluoInputError("quaternion must be non-zero", field="q")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_rotvec(R):
    """Rotation vector (axis * angle [rad], angle in [0, pi]) of a rotation matrix.

    Goes through the quaternion so that angles near pi stay accurate (the
    classic arccos formula loses the axis there).
    """
    q = matrix_to_quaternion(R)
    w = q[0]
    v = q[1:]
    s = np.linalg.norm(v)
    if s < 1e-12:
        return 2.0 * v  # small-angle limit: angle ~ 2|v|, axis v/|v|
    angle = 2.0 * np.arctan2(s, w)
    return v / s * angle


def rotation_angle(R):
    """Rotation angle [rad] in [0, pi] of a rotation matrix."""
    return float(np.linalg.norm(matrix_to_rotvec(R)))


def slerp(q0, q1, t):
    """Spherical linear interpolation between unit quaternions (w, x, y, z).

    Takes the short way round (flips q1 if q0.q1 < 0).

    Parameters
    ----------
    q0, q1 : (4,) array_like
    t : float or array_like
        Interpolation parameter(s); 0 gives q0, 1 gives q1.

    Returns
    -------
    (4,) or (M, 4) ndarray
    """
    a = np.asarray(q0, dtype=float).reshape(4)
    b = np.asarray(q1, dtype=float).reshape(4)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    d = float(np.dot(a, b))
    if d < 0:
        b, d = -b, -d
    tt = np.atleast_1d(np.asarray(t, dtype=float))
    if d > 1.0 - 1e-10:
        out = a[None] + tt[:, None] * (b - a)[None]
    else:
        theta = np.arccos(min(d, 1.0))
        s = np.sin(theta)
        out = (np.sin((1 - tt) * theta)[:, None] * a + np.sin(tt * theta)[:, None] * b) / s
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[out[:, 0] < 0] *= -1
    return out[0] if np.ndim(t) == 0 else out


def look_at(eye_mm, target_mm, up=(0.0, 0.0, 1.0)):
    """Camera-to-world transform of a camera at ``eye_mm`` looking at ``target_mm``.

    The camera frame is OpenCV's: z forward (towards the target), x right,
    y down, so that the world ``up`` direction appears towards the top of the
    image (negative y).

    Parameters
    ----------
    eye_mm, target_mm : (3,) array_like
        Camera centre and look-at point in world coordinates [mm].
    up : (3,) array_like
        World direction that should point up in the image.

    Returns
    -------
    (4, 4) ndarray
        ``CameraToWorld``: maps camera coordinates to world coordinates.
    """
    eye = np.asarray(eye_mm, dtype=float).reshape(3)
    target = np.asarray(target_mm, dtype=float).reshape(3)
    upv = np.asarray(up, dtype=float).reshape(3)
    z = target - eye
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        raise FluoInputError("eye and target must differ", field="target_mm", value=tuple(target))
    z /= nz
    x = np.cross(z, upv)  # right = forward x up (with y down this is right-handed)
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(np.linalg.norm(upv), 1e-300):
        raise FluoInputError("up must not be parallel to the viewing direction", field="up",
                             value=tuple(upv))
    x /= nx
    y = np.cross(z, x)  # down
    R = np.column_stack([x, y, z])
    return make_rigid(R, eye)


def is_rigid(T, tol=1e-6):
    """True if ``T`` is a 4x4 proper rigid transform within ``tol``.

    Checks R^T R = I, det R = +1 and a bottom row of (0, 0, 0, 1).
    """
    arr = np.asarray(T, dtype=float)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        return False
    R = arr[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > tol:
        return False
    if abs(np.linalg.det(R) - 1.0) > tol:
        return False
    return bool(np.max(np.abs(arr[3] - [0.0, 0.0, 0.0, 1.0])) <= tol)


def as_rigid(T, name, file=None, tol=1e-4):
    """``T`` as a (4, 4) float rigid transform, or FluoInputError naming ``name``.

    For values read from files (JSON of any shape): anything that is not a 4x4
    array of finite numbers forming a proper rigid transform within ``tol`` is
    refused, never half used.
    """
    try:
        arr = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise FluoInputError("expected a 4x4 matrix of numbers", file=file, field=name) from None
    if arr.shape != (4, 4):
        raise FluoInputError("expected a 4x4 matrix", file=file, field=name, value=arr.shape)
    if not np.all(np.isfinite(arr)):
        raise FluoInputError("matrix has NaN or inf entries", file=file, field=name)
    if not is_rigid(arr, tol):
        raise FluoInputError("is not a rigid 4x4 transform", file=file, field=name)
    return arr


def as_rigid_list(poses, name, file=None, tol=1e-4):
    """A list of rigid 4x4 transforms (see :func:`as_rigid`); ``name[i]`` in messages."""
    if isinstance(poses, (str, bytes, dict)) or not hasattr(poses, "__len__"):
        raise FluoInputError("expected a list of 4x4 matrices", file=file, field=name,
                             value=type(poses).__name__)
    return [as_rigid(T, f"{name}[{i}]", file, tol) for i, T in enumerate(poses)]
