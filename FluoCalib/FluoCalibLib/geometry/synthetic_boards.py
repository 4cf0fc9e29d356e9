"""Synthetic calibration data with known truth: board images and tracked tool poses.

A board is fixed in the tracker frame (``BoardToTracker``); a camera rigidly
mounted on a tracked tool (``CameraToTool``, the hand-eye truth) looks at it
from several poses. Each view yields a rendered image (lens distortion,
defocus blur, sensor noise) and the tracker's measurement of ``ToolToTracker``
(with optional tracking noise), so intrinsic and hand-eye calibration can be
scored against the truth.

Rendering traces one ray per sub-pixel sample (the camera model's exact
inverse distortion), intersects it with the board plane and samples a high
resolution board texture; sub-pixel samples are averaged (box filter = pixel
area integration), then Gaussian blur and Gaussian noise are applied.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fluoguide.errors import FluoInputError, check_number, seeded_rng
from fluoguide.progress import check_cancel, report, scaled

from FluoCalibLib.geometry.boards import parse_board
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.geometry import transforms as tf

__all__ = ["SyntheticView", "random_board_poses", "render_view", "make_dataset",
           "default_camera", "default_camera_to_tool"]

BLACK_LEVEL = 30.0
WHITE_LEVEL = 220.0
BACKGROUND_LEVEL = 120.0


def default_camera(width=800, height=600):
    """A moderately distorted camera (about 60 deg horizontal field of view)."""
    from fluoguide.images import MAX_IMAGE_PIXELS

    check_number("width", width, 16, 20000, integer=True)
    check_number("height", height, 16, 20000, integer=True)
    if width * height > MAX_IMAGE_PIXELS:
        raise FluoInputError(f"image larger than {MAX_IMAGE_PIXELS} pixels", field="width x height",
                             value=(width, height))
    f = 0.87 * width
    return CameraModel(f, f * 1.002, width / 2 - 0.5 + 7.3, height / 2 - 0.5 - 4.1,
                       (-0.28, 0.11, 6e-4, -4e-4, -0.02), width, height)


def default_camera_to_tool():
    """Hand-eye truth: camera 40 mm in front of and 25 mm off the tool origin, tilted."""
    R = tf.rotation_matrix([0.3, -1.0, 0.2], np.deg2rad(35.0))
    return tf.make_rigid(R, [25.0, -12.0, 40.0])


@dataclass
class SyntheticView:
    board_to_camera: np.ndarray
    tool_to_tracker_true: np.ndarray
    tool_to_tracker: np.ndarray
    image: np.ndarray = field(default=None, repr=False)


def random_board_poses(camera, board, n_views, rng, distance_mm=None, max_tilt_deg=40.0,
                       motion="general", margin_px=15, max_tries=2000):
    """Board-to-camera poses with the whole board inside the image.

    Parameters
    ----------
    camera : CameraModel
    board : Board
    n_views : int
    rng : numpy Generator
    distance_mm : float, optional
        Mean camera-board distance; default makes the board fill about half the image.
    max_tilt_deg : float
        Largest angle between optical axis and board normal.
    motion : {"general", "translation", "parallel"}
        ``translation``: every view has the same orientation (pure translation;
        degenerate for hand-eye and for intrinsics). ``parallel``: board
        facing the camera head-on in every view (degenerate for intrinsics).

    Returns
    -------
    list of (4, 4) ndarray
        ``BoardToCamera`` transforms.
    """
    obj = board.object_points
    x0, y0, x1, y1 = board.extent_mm
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    size = max(x1 - x0, y1 - y0)
    if distance_mm is None:
        distance_mm = 1.6 * size * camera.fx / camera.width
    fixed_R = None
    out = []
    tries = 0
    while len(out) < n_views:
        tries += 1
        if tries > max_tries:
            raise FluoInputError("could not place the board inside the image; lower the "
                                 "distance or the tilt", field="distance_mm", value=distance_mm)
        d = distance_mm * rng.uniform(0.85, 1.2)
        if motion == "parallel":
            tilt, az = 0.0, 0.0
        else:
            tilt = np.deg2rad(rng.uniform(10.0, max_tilt_deg))
            az = rng.uniform(0, 2 * np.pi)
        # the viewer is on the -z side of the board (board z points into the board)
        direction = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        eye = centre + d * direction
        target = centre + np.append(rng.uniform(-0.15, 0.15, 2) * size, 0.0)
        roll = rng.uniform(-0.5, 0.5) if motion == "general" else 0.0
        up = np.array([np.sin(roll), -np.cos(roll), 0.0])  # board -y appears up, rolled
        try:
            cam_to_board = tf.look_at(eye, target, up)
        except FluoInputError:
            continue
        board_to_cam = tf.invert_rigid(cam_to_board)
        if motion == "translation":
            if fixed_R is None:
                fixed_R = board_to_cam[:3, :3].copy()
            # keep orientation, move the camera: board centre along a jittered axis
            pc = np.array([rng.uniform(-0.12, 0.12) * size, rng.uniform(-0.12, 0.12) * size, d])
            board_to_cam = tf.make_rigid(fixed_R, pc - fixed_R @ centre)
        uv, front = camera.project(tf.apply_rigid(board_to_cam, obj), return_mask=True)
        ok = front.all() and np.all(np.isfinite(uv))
        ok = ok and uv[:, 0].min() > margin_px and uv[:, 0].max() < camera.width - 1 - margin_px
        ok = ok and uv[:, 1].min() > margin_px and uv[:, 1].max() < camera.height - 1 - margin_px
        if ok:
            out.append(board_to_cam)
    return out


class _RayCache:
    """Sub-pixel sample rays of one camera (shared across views)."""

    def __init__(self, camera, supersample, progress=None, cancel=None, chunks=8):
        s = int(supersample)
        offs = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(camera.width)[:, None] + offs[None]).ravel()
        v = (np.arange(camera.height)[:, None] + offs[None]).ravel()
        uu, vv = np.meshgrid(u, v)
        self.shape = uu.shape
        self.s = s
        uv = np.column_stack([uu.ravel(), vv.ravel()])
        # in chunks (each ray is its own): undistorting millions of samples takes
        # seconds, and the caller hears from it (and may stop it) in between
        parts = []
        for k, block in enumerate(np.array_split(uv, chunks)):
            check_cancel(cancel)
            report(progress, k / chunks, f"sample rays, part {k + 1} of {chunks}")
            parts.append(camera.pixel_rays(block))
        self.rays = np.concatenate(parts)


def render_view(camera, board, board_to_camera, rng=None, blur_sigma_px=0.6, noise_sigma=2.0,
                supersample=3, texture_px_per_mm=None, _rays=None, _texture=None):
    """Render a grayscale image of ``board`` at pose ``board_to_camera``.

    Parameters
    ----------
    camera : CameraModel
    board : Board
    board_to_camera : (4, 4) array_like
    rng : numpy Generator, optional (noise)
    blur_sigma_px : float
        Gaussian defocus blur [px] (0: none).
    noise_sigma : float
        Gaussian sensor noise [grey levels of 255].
    supersample : int
        Samples per pixel along each axis (anti-aliasing).

    Returns
    -------
    (H, W) uint8 ndarray
    """
    rng = np.random.default_rng() if rng is None else rng
    rays = _rays or _RayCache(camera, supersample)
    if _texture is None:
        if texture_px_per_mm is None:
            texture_px_per_mm = 12.0
        _texture = (*board.texture(texture_px_per_mm), texture_px_per_mm)
    tex, origin, ppm = _texture
    T = np.asarray(board_to_camera, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    n = R[:, 2]
    denom = rays.rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / denom
        P = rays.rays * s[:, None]
        B = (P - t) @ R  # board coordinates = R^T (P - t)
    valid = np.isfinite(s) & (s > 0)
    mapx = ((B[:, 0] - origin[0]) * ppm - 0.5)
    mapy = ((B[:, 1] - origin[1]) * ppm - 0.5)
    mapx[~valid] = -10
    mapy[~valid] = -10
    texf = (BLACK_LEVEL + (WHITE_LEVEL - BLACK_LEVEL) * (tex.astype(np.float32) / 255.0))
    img = cv2.remap(texf, mapx.reshape(rays.shape).astype(np.float32),
                    mapy.reshape(rays.shape).astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND_LEVEL)
    k = rays.s
    img = img.reshape(camera.height, k, camera.width, k).mean(axis=(1, 3))
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _perturb(T, rng, trans_sigma_mm, rot_sigma_deg):
    if trans_sigma_mm <= 0 and rot_sigma_deg <= 0:
        return T.copy()
    dR = tf.rotvec_to_matrix(rng.normal(0, np.deg2rad(rot_sigma_deg), 3))
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ dR
    out[:3, 3] = T[:3, 3] + rng.normal(0, trans_sigma_mm, 3)
    return out


def make_dataset(out_dir=None, camera=None, board="chessboard:9x6:20", n_views=12, seed=0,
                 camera_to_tool=None, board_to_tracker=None, blur_sigma_px=0.6,
                 noise_sigma=2.0, tracker_noise_mm=0.1, tracker_noise_deg=0.05,
                 motion="general", supersample=3, max_tilt_deg=40.0, distance_mm=None,
                 progress=None, cancel=None):
    """Render a calibration data set and (optionally) write it to ``out_dir``.

    Files written: ``view_000.png`` ... and ``truth.json`` with keys
    ``camera`` (CameraModel dict), ``board`` (spec), ``camera_to_tool``,
    ``board_to_tracker`` (4x4 lists), ``images`` (file names), ``board_to_camera``
    (true, per view), ``tool_to_tracker`` (measured, with tracking noise, per
    view -- the poses file of ``fluo calib handeye``), ``tool_to_tracker_true``
    and the noise settings.

    Returns
    -------
    dict
        The truth document, plus ``views`` (list of SyntheticView with images).
    """
    board = parse_board(board)
    camera = camera or default_camera()
    if out_dir is not None:
        from fluoguide import atomic

        atomic.check_writable(out_dir, "out_dir", folder=True)   # before rendering
    check_number("n_views", n_views, 1, 1000, integer=True)
    check_number("blur_sigma_px", blur_sigma_px, 0.0, 50.0)
    check_number("noise_sigma", noise_sigma, 0.0, 255.0, what="must be 0..255 grey levels")
    check_number("tracker_noise_mm", tracker_noise_mm, 0.0, 100.0)
    check_number("tracker_noise_deg", tracker_noise_deg, 0.0, 90.0)
    rng = seeded_rng(seed)
    X = default_camera_to_tool() if camera_to_tool is None else np.asarray(camera_to_tool, float)
    if board_to_tracker is None:
        board_to_tracker = tf.make_rigid(tf.rotation_matrix([1.0, 0.2, 0.1], 2.8),
                                         [-150.0, 40.0, -1200.0])
    board_to_tracker = np.asarray(board_to_tracker, float)
    poses = random_board_poses(camera, board, n_views, rng, distance_mm=distance_mm,
                               max_tilt_deg=max_tilt_deg, motion=motion)
    rays = _RayCache(camera, supersample, scaled(progress, 0.0, 0.2), cancel)
    ppm = 12.0
    texture = (*board.texture(ppm), ppm)
    views = []
    for i, b2c in enumerate(poses):
        check_cancel(cancel)
        report(progress, 0.2 + 0.8 * i / n_views, f"rendering view {i + 1}/{n_views}")
        cam_to_tracker = board_to_tracker @ tf.invert_rigid(b2c)
        tool_true = cam_to_tracker @ tf.invert_rigid(X)
        tool_meas = _perturb(tool_true, rng, tracker_noise_mm, tracker_noise_deg)
        img = render_view(camera, board, b2c, rng, blur_sigma_px, noise_sigma,
                          _rays=rays, _texture=texture)
        views.append(SyntheticView(b2c, tool_true, tool_meas, img))
    report(progress, 1.0, "rendered")
    names = [f"view_{i:03d}.png" for i in range(n_views)]
    truth = {
        "camera": camera.to_dict(), "board": board.spec, "camera_to_tool": X.tolist(),
        "board_to_tracker": board_to_tracker.tolist(), "images": names,
        "board_to_camera": [v.board_to_camera.tolist() for v in views],
        "tool_to_tracker": [v.tool_to_tracker.tolist() for v in views],
        "tool_to_tracker_true": [v.tool_to_tracker_true.tolist() for v in views],
        "noise": {"blur_sigma_px": blur_sigma_px, "noise_sigma": noise_sigma,
                  "tracker_noise_mm": tracker_noise_mm, "tracker_noise_deg": tracker_noise_deg,
                  "motion": motion, "seed": seed},
    }
    if out_dir is not None:
        from fluoguide import atomic

        # the data set as a whole: a kill leaves the old set or the new one
        with atomic.staged_folder(out_dir, last=("truth.json",)) as stage:
            for name, v in zip(names, views):
                if not cv2.imwrite(str(stage / name), v.image):
                    raise FluoInputError("cannot write image", file=Path(out_dir) / name)
            (stage / "truth.json").write_text(json.dumps(truth, indent=1, allow_nan=False))
    return {**truth, "views": views}
