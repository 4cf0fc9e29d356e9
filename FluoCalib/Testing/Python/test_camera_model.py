"""Tests of FluoCalibLib.camera_model against OpenCV's own projection code."""

import cv2
import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry.camera_model import CameraModel

# the thesis' 10 mm endoscope (docs/physics.md section 4.3), with some tangential terms added
ENDO = CameraModel(949.1, 951.0, 780.4, 465.9, (-0.4709, 0.3153, 1e-3, -5e-4, -0.134), 1392, 1040)
FISH = CameraModel(420.0, 421.0, 640.5, 480.2, (0.05, -0.02, 0.004, -0.001), 1280, 960, "fisheye")


def _points(n=200, seed=0, half_angle_tan=0.6):
    rng = np.random.default_rng(seed)
    z = rng.uniform(20, 200, n)
    xy = rng.uniform(-half_angle_tan, half_angle_tan, (n, 2)) * z[:, None]
    return np.column_stack([xy, z])


def test_project_matches_cv2_pinhole():
    p = _points()
    uv = ENDO.project(p)
    ref, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), ENDO.K,
                               ENDO.dist_array)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-8)


def test_project_matches_cv2_fisheye():
    p = _points(half_angle_tan=1.5)
    uv = FISH.project(p)
    ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), FISH.K,
                                       FISH.dist_array)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-7)


def test_points_behind_camera_masked():
    p = np.array([[0, 0, 100.0], [10, 0, -5.0], [0, 0, 0.0]])
    uv, mask = ENDO.project(p, return_mask=True)
    assert mask.tolist() == [True, False, False]
    assert np.all(np.isnan(uv[1:])) and np.all(np.isfinite(uv[0]))


@pytest.mark.parametrize("cam", [ENDO, FISH], ids=["pinhole", "fisheye"])
def test_pixel_rays_invert_projection(cam):
    p = _points(half_angle_tan=0.55, seed=3)
    uv = cam.project(p)
    rays = cam.pixel_rays(uv)
    truth = p / np.linalg.norm(p, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, truth, atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-14)


def test_pixel_rays_agree_with_cv2_undistort_iterative():
    uv = np.array([[300.0, 200.0], [780.0, 466.0], [1200.0, 800.0]])
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), ENDO.K, ENDO.dist_array, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    ref = np.column_stack([ref.reshape(-1, 2), np.ones(3)])
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(ENDO.pixel_rays(uv), ref, atol=1e-8)


def test_pixel_outside_invertible_distortion_is_nan():
    # With the thesis' endoscope coefficients the distorted radius r*(1+k1 r^2+...)
    # peaks at ~0.72; the image corner (radius ~0.82) has no ray. cv2 silently
    # returns a point that does not re-project there; we return NaN.
    ray = ENDO.pixel_rays([[100.0, 80.0]])
    assert np.all(np.isnan(ray))
    bogus = cv2.undistortPoints(np.array([[[100.0, 80.0]]]), ENDO.K, ENDO.dist_array).reshape(1, 2)
    back = ENDO.project(np.column_stack([bogus, [1.0]]))
    assert np.linalg.norm(back - [100.0, 80.0]) > 1.0


def test_grid_rays_cached_and_binned_consistent():
    cam = CameraModel(500.0, 500.0, 319.5, 239.5, (-0.2, 0.05, 0, 0, 0), 640, 480)
    g4 = cam.pixel_grid_rays(4)
    assert g4.shape == (120, 160, 3)
    assert cam.pixel_grid_rays(4) is g4  # cached
    # block (j, i) ray == ray of the block centre pixel
    j, i = 17, 101
    centre = np.array([[i * 4 + 1.5, j * 4 + 1.5]])
    np.testing.assert_allclose(g4[j, i], cam.pixel_rays(centre)[0], atol=1e-14)
    # the binned camera's own full-resolution grid is the same set of rays
    np.testing.assert_allclose(cam.binned(4).pixel_grid_rays(1), g4, atol=1e-12)
    np.testing.assert_allclose(cam.pixel_grid_rays(1)[240, 320],
                               cam.pixel_rays([[320, 240]])[0], atol=1e-14)
    with pytest.raises(FluoInputError):
        cam.pixel_grid_rays(0)


def test_dict_roundtrip_and_validation():
    for cam in (ENDO, FISH):
        back = CameraModel.from_dict(cam.to_dict())
        assert back == cam
    assert CameraModel(1, 1, 0, 0, (0.1, 0, 0, 0), 10, 10).dist == (0.1, 0, 0, 0, 0)
    with pytest.raises(FluoInputError):
        CameraModel(-1, 1, 0, 0)
    with pytest.raises(FluoInputError):
        CameraModel(1, 1, 0, 0, (0, 0, 0), 10, 10)
    with pytest.raises(FluoInputError):
        CameraModel(1, 1, 0, 0, (0,) * 5, 10, 10, "fisheye")
    with pytest.raises(FluoInputError):
        CameraModel.from_dict({"fx": 1})


def test_undistort_maps_straighten_a_rendered_board():
    from FluoCalibLib.geometry import transforms as tf
    from FluoCalibLib.geometry.boards import parse_board
    from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset
    from FluoCalibLib.geometry.undistort import undistort_image, undistort_maps

    cam = default_camera(640, 480)
    board = parse_board("chessboard:9x6:20")
    ds = make_dataset(None, cam, board, n_views=1, seed=9, supersample=2, noise_sigma=1.0)
    view = ds["views"][0]
    assert undistort_maps(cam) is undistort_maps(cam)  # cached per camera
    flat = undistort_image(view.image, cam)
    det = board.detect(flat)
    ideal = CameraModel(cam.fx, cam.fy, cam.cx, cam.cy, (0.0,) * 5, cam.width, cam.height)
    truth = ideal.project(tf.apply_rigid(view.board_to_camera, board.object_points))
    err = np.linalg.norm(det.image_points - truth, axis=1)
    assert np.median(err) < 0.15 and err.max() < 0.5
    # the distorted image's corners are far from the pinhole prediction (k1 = -0.28)
    raw = board.detect(view.image)
    assert np.linalg.norm(raw.image_points - truth, axis=1).max() > 5.0
    with pytest.raises(FluoInputError):
        undistort_image(np.zeros((10, 10), np.uint8), cam)
