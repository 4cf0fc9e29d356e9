"""Intrinsic camera calibration from board images (Zhang's method via OpenCV).

Pipeline: read each image -> detect board corners (sub-pixel) -> check the view
geometry is not degenerate -> split off held-out validation views -> fit
(``cv2.calibrateCamera`` or ``cv2.fisheye.calibrate``) -> reject views whose
reprojection error is an outlier, with the reason, and refit -> score the
held-out views with the fitted intrinsics (pose by PnP only, no intrinsic
re-fit), so the validation error is not flattered by the fit.

Every reported error is computed directly by projecting the board corners
through :class:`CameraModel` (not copied from OpenCV), and the overall
``rms_px`` is sqrt(mean over all corners of the squared pixel distance) --
the same definition as the value ``cv2.calibrateCamera`` returns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

from FluoCalibLib.geometry.boards import parse_board
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.geometry import transforms as tf

__all__ = ["ViewResult", "IntrinsicsResult", "detect_views", "calibrate_camera",
           "calibrate_from_detections", "view_poses", "reprojection_errors",
           "MIN_VIEWS", "PARALLEL_VIEWS_DEG"]

MIN_VIEWS = 3
#: Views whose board normals all lie within this angle [deg] of each other
#: are degenerate for Zhang's method (focal length and principal point trade off).
PARALLEL_VIEWS_DEG = 5.0
#: A view is an outlier if its RMS exceeds max(this [px], OUTLIER_FACTOR x median).
OUTLIER_MIN_PX = 1.0
OUTLIER_FACTOR = 3.0


@dataclass
class ViewResult:
    """One image's fate in the calibration."""

    name: str
    status: str  # "used", "rejected" or "holdout"
    reason: str = ""
    n_corners: int = 0
    rms_px: float = float("nan")
    board_to_camera: np.ndarray = field(default=None, repr=False)
    ids: np.ndarray = field(default=None, repr=False)
    image_points: np.ndarray = field(default=None, repr=False)

    def to_dict(self):
        d = {"name": self.name, "status": self.status, "n_corners": self.n_corners,
             "rms_px": self.rms_px}
        if self.reason:
            d["reason"] = self.reason
        if self.board_to_camera is not None:
            d["board_to_camera"] = self.board_to_camera.tolist()
        return d


@dataclass
class IntrinsicsResult:
    """Calibrated camera plus per-view diagnostics."""

    camera: CameraModel
    rms_px: float
    views: list
    board_spec: str
    holdout_rms_px: float = float("nan")
    std_intrinsics: dict = field(default_factory=dict)
    view_spread_deg: float = float("nan")

    @property
    def used(self):
        return [v for v in self.views if v.status == "used"]

    @property
    def rejected(self):
        return [v for v in self.views if v.status == "rejected"]

    @property
    def holdout(self):
        return [v for v in self.views if v.status == "holdout"]

    def to_dict(self):
        """The JSON document of ``fluo calib camera``."""
        c = self.camera
        return {
            "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "dist": list(c.dist),
            "model": c.model, "width": c.width, "height": c.height,
            "rms_px": self.rms_px,
            "views_used": [v.name for v in self.used],
            "views_rejected": [{"name": v.name, "reason": v.reason} for v in self.rejected],
            "views_holdout": [v.name for v in self.holdout],
            "holdout_rms_px": self.holdout_rms_px,
            "per_view_rms_px": {v.name: v.rms_px for v in self.views if v.status != "rejected"},
            "std_intrinsics": self.std_intrinsics,
            "view_spread_deg": self.view_spread_deg,
            "board": self.board_spec,
        }


# ------------------------------------------------------------------ detection

# Smallest image side a board can be found in [px]
MIN_IMAGE_PX = 32

def _read_gray(item):
    if isinstance(item, np.ndarray):
        img = item
        name = "array"
    else:
        from fluoguide.errors import FluoInputError
        from fluoguide.images import read_image

        name = str(item)
        if not Path(name).is_file():
            return None, name, "file not found"
        try:
            img = read_image(name)
        except FluoInputError as exc:  # a view is rejected with its reason, the others go on
            return None, name, exc.problem
    if min(img.shape[:2]) < MIN_IMAGE_PX:
        # OpenCV's corner finder asserts (and throws) on images this small
        return None, name, f"image too small ({img.shape[1]} x {img.shape[0]} px)"
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        # 16-bit sensors: scale to 8 bit for the detector (corners are scale invariant)
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return img, name, ""


def detect_views(images, board, names=None, progress=None, cancel=None):
    """Detect the board in each image.

    Parameters
    ----------
    images : sequence of path or ndarray
    board : Board or str
    names : sequence of str, optional

    Returns
    -------
    views : list of ViewResult
        ``status`` "used" with ids/image_points when found, else "rejected" with reason.
    image_size : (width, height) or None
        Size of the first readable image.
    """
    board = parse_board(board)
    images = list(images)
    views = []
    size = None
    for i, item in enumerate(images):
        check_cancel(cancel)
        report(progress, i / max(len(images), 1), f"detecting board {i + 1}/{len(images)}")
        gray, name, why = _read_gray(item)
        if names is not None:
            name = str(names[i])
        elif isinstance(item, np.ndarray):
            name = f"view_{i:03d}"
        if gray is None:
            views.append(ViewResult(name, "rejected", why))
            continue
        h, w = gray.shape
        if size is None:
            size = (w, h)
        elif size != (w, h):
            views.append(ViewResult(name, "rejected",
                                    f"image size {w}x{h} differs from {size[0]}x{size[1]}"))
            continue
        det = board.detect(gray)
        if det is None:
            views.append(ViewResult(name, "rejected", "board not found"))
            continue
        views.append(ViewResult(name, "used", n_corners=len(det.ids), ids=det.ids,
                                image_points=det.image_points))
    report(progress, 1.0, "detection done")
    return views, size


# ------------------------------------------------------------------ geometry

def reprojection_errors(camera, board, view):
    """Per-corner reprojection distance [px] of a view with a known pose."""
    obj = board.object_points[view.ids]
    uv = camera.project(tf.apply_rigid(view.board_to_camera, obj))
    return np.linalg.norm(uv - view.image_points, axis=1)


def _pose_pnp(camera, obj, img):
    """Board-to-camera pose by PnP on undistorted points (works for both models)."""
    rays = camera.pixel_rays(img)
    if not np.all(np.isfinite(rays)):
        raise FluoInputError("corner outside the invertible part of the lens model")
    norm = rays[:, :2] / rays[:, 2:3]
    ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), norm.astype(np.float64), np.eye(3),
                                  None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise FluoInputError("PnP failed")
    # refine on the distorted image (minimises true pixel error)
    if camera.model == "pinhole":
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist_array, rvec, tvec)
    return tf.make_rigid(tf.rotvec_to_matrix(rvec.ravel()), tvec.ravel())


def view_poses(camera, board, views):
    """Set ``board_to_camera`` of each detected view by PnP with ``camera``."""
    for v in views:
        if v.ids is not None:
            v.board_to_camera = _pose_pnp(camera, board.object_points[v.ids], v.image_points)
    return views


def _normal_spread_deg(camera, board, views):
    """Largest angle [deg] between the board normals of any two views."""
    normals = []
    for v in views:
        try:
            T = _pose_pnp(camera, board.object_points[v.ids], v.image_points)
        except (FluoInputError, cv2.error):
            continue  # a view PnP cannot place says nothing about the spread
        normals.append(T[:3, 2])
    if len(normals) < 2:
        return 0.0
    n = np.array(normals)
    cosang = np.clip(n @ n.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosang.min())))


# ------------------------------------------------------------------ fitting

def _fit(views, board, size, model, fix_k3):
    obj = [board.object_points[v.ids].astype(np.float64).reshape(-1, 1, 3) for v in views]
    img = [v.image_points.astype(np.float64).reshape(-1, 1, 2) for v in views]
    w, h = size
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    std = {}
    try:
        if model == "fisheye":
            flags = (cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
                     | cv2.fisheye.CALIB_CHECK_COND)
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, (w, h), None, None,
                                                          flags=flags, criteria=crit)
            cam = CameraModel.from_K(K, D.ravel(), w, h, "fisheye")
        else:
            flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
            # calibrateCamera wants float32 points (fisheye wants float64)
            out = cv2.calibrateCameraExtended([o.astype(np.float32) for o in obj],
                                              [p.astype(np.float32) for p in img], (w, h),
                                              None, None, flags=flags, criteria=crit)
            _, K, D, rvecs, tvecs, sd_int = out[:6]
            cam = CameraModel.from_K(K, D.ravel()[:5], w, h, "pinhole")
            sd = sd_int.ravel()
            std = {k: float(sd[i]) for i, k in enumerate(["fx", "fy", "cx", "cy", "k1", "k2",
                                                          "p1", "p2", "k3"])}
    except cv2.error as exc:
        from fluoguide.library_errors import opencv_problem

        # OpenCV's text names its build's source file, line and function: in words
        raise FluoInputError(f"calibration failed (ill-conditioned views?): "
                             f"{opencv_problem(exc)}", field="images") from None
    for v, r, t in zip(views, rvecs, tvecs):
        v.board_to_camera = tf.make_rigid(tf.rotvec_to_matrix(np.ravel(r)), np.ravel(t))
    return cam, std


def _score(cam, board, views):
    sq = []
    for v in views:
        e = reprojection_errors(cam, board, v)
        v.rms_px = float(np.sqrt(np.mean(e ** 2)))
        sq.append(e ** 2)
    return float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else float("nan")


def calibrate_from_detections(views, board, image_size, model="pinhole", holdout=0,
                              fix_k3=False, reject_outliers=True, check_geometry=True):
    """Fit intrinsics to detected views (see :func:`calibrate_camera`)."""
    board = parse_board(board)
    if model not in ("pinhole", "fisheye"):
        raise FluoInputError("model must be pinhole or fisheye", field="model", value=model)
    usable = [v for v in views if v.status == "used"]
    for v in usable:
        if v.n_corners < 6:
            v.status, v.reason = "rejected", f"only {v.n_corners} corners (need 6)"
    usable = [v for v in views if v.status == "used"]
    holdout = int(holdout)
    if holdout < 0:
        raise FluoInputError("holdout must be >= 0", field="holdout", value=holdout)
    if len(usable) - holdout < MIN_VIEWS:
        reasons = "; ".join(f"{v.name}: {v.reason}" for v in views if v.status == "rejected")
        raise FluoInputError(
            f"need at least {MIN_VIEWS} usable views for the fit, have {len(usable)} usable"
            + (f" minus {holdout} held out" if holdout else "")
            + (f" (rejected: {reasons})" if reasons else ""), field="images", value=len(views))
    # Degeneracy check with a rough camera (f ~ image width, no distortion): a
    # wrong f distorts the tilt estimates but parallel boards stay parallel.
    w, h = image_size
    guess = CameraModel(float(max(w, h)), float(max(w, h)), (w - 1) / 2, (h - 1) / 2,
                        (0.0,) * (4 if model == "fisheye" else 5), w, h, model)
    spread = _normal_spread_deg(guess, board, usable)
    if check_geometry and spread < PARALLEL_VIEWS_DEG:
        raise FluoInputError(
            f"views are nearly parallel (board normals within {spread:.1f} deg; need > "
            f"{PARALLEL_VIEWS_DEG:g} deg): tilt the board in different directions, "
            "focal length and principal point cannot be separated otherwise",
            field="images", value=round(spread, 2))
    if holdout:
        idx = np.unique(np.round(np.linspace(0, len(usable) - 1, holdout + 2)[1:-1]).astype(int))
        for i in idx:
            usable[i].status = "holdout"
    fit_views = [v for v in usable if v.status == "used"]
    cam, std = _fit(fit_views, board, image_size, model, fix_k3)
    _score(cam, board, fit_views)
    if reject_outliers and len(fit_views) > MIN_VIEWS:
        med = float(np.median([v.rms_px for v in fit_views]))
        limit = max(OUTLIER_MIN_PX, OUTLIER_FACTOR * med)
        bad = [v for v in fit_views if v.rms_px > limit]
        if bad and len(fit_views) - len(bad) >= MIN_VIEWS:
            for v in bad:
                v.status = "rejected"
                v.reason = (f"reprojection RMS {v.rms_px:.2f} px > {limit:.2f} px "
                            f"(max of {OUTLIER_MIN_PX} px and {OUTLIER_FACTOR:g} x median)")
                v.board_to_camera = None
            fit_views = [v for v in fit_views if v.status == "used"]
            cam, std = _fit(fit_views, board, image_size, model, fix_k3)
    rms = _score(cam, board, fit_views)
    hold = [v for v in usable if v.status == "holdout"]
    hold_rms = float("nan")
    if hold:
        view_poses(cam, board, hold)
        hold_rms = _score(cam, board, hold)
    return IntrinsicsResult(cam, rms, list(views), board.spec, hold_rms, std, spread)


def calibrate_camera(images, board, model="pinhole", holdout=0, names=None, fix_k3=False,
                     reject_outliers=True, progress=None, cancel=None):
    """Calibrate a camera from board images.

    Parameters
    ----------
    images : sequence of path or ndarray
        Board photographs (any size in px, all the same).
    board : Board or str
        Board or spec string (``chessboard:9x6:25``).
    model : {"pinhole", "fisheye"}
    holdout : int
        Number of usable views kept out of the fit and scored separately
        (evenly spaced through the sequence).
    fix_k3 : bool
        Hold k3 at 0 (recommended for narrow lenses and few views).
    reject_outliers : bool
        Reject views with RMS > max(1 px, 3 x median) and refit.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    FluoInputError
        Fewer than 3 usable views (with each rejection's reason), nearly
        parallel views, or a failed fit.
    """
    images = list(images)
    if not images:
        raise FluoInputError("no images given", field="images")
    views, size = detect_views(images, board, names=names,
                               progress=None if progress is None else
                               (lambda f, m: report(progress, 0.8 * f, m)), cancel=cancel)
    if size is None:
        raise FluoInputError("none of the images could be read: "
                             + "; ".join(f"{v.name}: {v.reason}" for v in views), field="images")
    check_cancel(cancel)
    report(progress, 0.85, "fitting")
    res = calibrate_from_detections(views, board, size, model, holdout, fix_k3, reject_outliers)
    report(progress, 1.0, "done")
    return res
