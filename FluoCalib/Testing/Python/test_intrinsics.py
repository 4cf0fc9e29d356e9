"""Intrinsic calibration on rendered board images with known truth."""

import glob
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from fluoguide import mrml_io
from fluoapp.cli import main as fluo_main
from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import scene as gs
from FluoCalibLib.geometry.boards import parse_board
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.geometry.intrinsics import calibrate_camera, calibrate_from_detections, detect_views
from FluoCalibLib.geometry.opencv_yaml import read_calibration_yaml
from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

CAM = default_camera(640, 480)
REAL = Path(__file__).resolve().parents[2] / "Resources" / "TestData" / "opencv_left"
BOARD = "chessboard:9x6:20"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("boards")
    ds = make_dataset(out, CAM, BOARD, n_views=10, seed=3, supersample=2, noise_sigma=2.0,
                      blur_sigma_px=0.6)
    return out, ds


def _files(out, ds):
    return [str(out / n) for n in ds["images"]]


def test_intrinsics_within_0p2_percent_of_truth(data):
    out, ds = data
    res = calibrate_camera(_files(out, ds), BOARD, holdout=2)
    c = res.camera
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(c, k) - getattr(CAM, k)) < 0.002 * getattr(CAM, k), k
    assert abs(c.dist[0] - CAM.dist[0]) < 0.01
    assert 0 < res.rms_px < 0.2  # noise 2 grey levels, blur 0.6 px: well under 0.2 px
    assert len(res.used) == 8 and len(res.holdout) == 2 and not res.rejected
    assert np.isfinite(res.holdout_rms_px) and res.holdout_rms_px < 0.3
    assert not set(res.to_dict()["views_holdout"]) & set(res.to_dict()["views_used"])


def test_reported_errors_match_direct_opencv_computation(data):
    out, ds = data
    res = calibrate_camera(_files(out, ds), BOARD)
    board = parse_board(BOARD)
    sq = []
    for v in res.used:
        obj = board.object_points[v.ids]
        rvec, _ = cv2.Rodrigues(v.board_to_camera[:3, :3])
        uv, _ = cv2.projectPoints(obj, rvec, v.board_to_camera[:3, 3], res.camera.K,
                                  res.camera.dist_array)
        e2 = np.sum((uv.reshape(-1, 2) - v.image_points) ** 2, axis=1)
        assert abs(np.sqrt(e2.mean()) - v.rms_px) < 1e-9
        sq.append(e2)
    assert abs(np.sqrt(np.concatenate(sq).mean()) - res.rms_px) < 1e-9


def test_agrees_with_plain_opencv_calibration(data):
    """The textbook pipeline (OpenCV tutorial) on the same files gives the same camera."""
    out, ds = data
    files = _files(out, ds)
    objp = parse_board(BOARD).object_points.astype(np.float32)
    objs, imgs = [], []
    for f in files:
        g = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
        ok, corners = cv2.findChessboardCorners(g, (9, 6), None)
        assert ok
        corners = cv2.cornerSubPix(g, corners, (11, 11), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001))
        objs.append(objp)
        imgs.append(corners)
    rms, K, D, _, _ = cv2.calibrateCamera(objs, imgs, g.shape[::-1], None, None)
    res = calibrate_camera(files, BOARD)
    np.testing.assert_allclose(res.camera.K, K, rtol=1e-3)
    np.testing.assert_allclose(res.camera.dist_array[:2], D.ravel()[:2], atol=0.01)
    assert abs(res.rms_px - rms) < 0.05


def test_fisheye_model(tmp_path):
    cam = CameraModel(300.0, 300.5, 322.0, 236.0, (0.04, -0.01, 0.003, -0.001), 640, 480,
                      "fisheye")
    ds = make_dataset(None, cam, BOARD, n_views=8, seed=4, supersample=2)
    res = calibrate_camera([v.image for v in ds["views"]], BOARD, model="fisheye")
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(res.camera, k) - getattr(cam, k)) < 0.003 * getattr(cam, k), k
    assert res.camera.model == "fisheye" and len(res.camera.dist) == 4


def test_charuco_board():
    spec = "charuco:7x5:30:22:DICT_5X5_100"
    ds = make_dataset(None, CAM, spec, n_views=6, seed=5, supersample=2)
    res = calibrate_camera([v.image for v in ds["views"]], spec, fix_k3=True)
    assert abs(res.camera.fx - CAM.fx) < 0.005 * CAM.fx
    assert res.rms_px < 0.3


def test_outlier_view_rejected_with_reason(data):
    out, ds = data
    views, size = detect_views(_files(out, ds), BOARD)
    rng = np.random.default_rng(0)
    views[4].image_points = views[4].image_points + rng.normal(0, 4.0, views[4].image_points.shape)
    res = calibrate_from_detections(views, BOARD, size)
    assert [v.name for v in res.rejected] == [views[4].name]
    assert "reprojection RMS" in res.rejected[0].reason
    assert res.rms_px < 0.2


def test_bad_inputs_give_clear_messages(data, tmp_path):
    out, ds = data
    files = _files(out, ds)
    # corrupt file and blank image: rejected with a reason each, then too few views
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG not really")
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((480, 640), 128, np.uint8))
    bad = [str(tmp_path / "corrupt.png"), str(tmp_path / "blank.png")]
    with pytest.raises(FluoInputError) as ei:
        calibrate_camera(bad + files[:1], BOARD)
    msg = str(ei.value)
    assert "at least 3 usable views" in msg and "board not found" in msg
    assert "corrupt or not an image" in msg
    res = calibrate_camera(bad + files, BOARD)
    assert {v.reason for v in res.rejected} == {"board not found",
                                                "cannot read image (corrupt or not an image file)"}
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((240, 320), np.uint8))
    res = calibrate_camera(files + [str(small)], BOARD)
    assert "differs from 640x480" in res.rejected[0].reason
    with pytest.raises(FluoInputError, match="no images"):
        calibrate_camera([], BOARD)
    with pytest.raises(FluoInputError, match="board kind"):
        calibrate_camera(files, "circles:4x11:20")


def test_nearly_parallel_views_detected():
    ds = make_dataset(None, CAM, BOARD, n_views=5, seed=6, supersample=1, motion="parallel")
    with pytest.raises(FluoInputError, match="nearly parallel"):
        calibrate_camera([v.image for v in ds["views"]], BOARD)


def test_cli_camera_json_yaml_and_scene_roundtrip(data, tmp_path, capsys):
    out, _ = data
    yaml_path = tmp_path / "cam.yaml"
    scene_path = tmp_path / "scene" / "scene.mrml"
    rc = fluo_main(["calib", "camera", "--images", str(out / "*.png"), "--board", BOARD,
                    "--holdout", "1", "--json", "--yaml", str(yaml_path),
                    "--scene", str(scene_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    for key in ("fx", "fy", "cx", "cy", "dist", "rms_px", "views_used", "views_rejected"):
        assert key in doc
    assert len(doc["dist"]) == 5 and len(doc["views_used"]) == 9
    from_yaml = read_calibration_yaml(yaml_path)["camera"]
    from_scene = gs.load_intrinsics(mrml_io.load_scene(scene_path))
    for cam in (from_yaml, from_scene):
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (doc["fx"], doc["fy"], doc["cx"], doc["cy"])
        assert list(cam.dist) == doc["dist"]
    rc = fluo_main(["calib", "camera", "--images", str(tmp_path / "none*.png"), "--board", BOARD])
    assert rc == 2 and "no files match" in capsys.readouterr().err


def _plain_opencv(files, pattern, square_mm):
    """The OpenCV tutorial pipeline: findChessboardCorners, cornerSubPix 11x11, calibrateCamera."""
    objp = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    objp[:, :2] = np.mgrid[0:pattern[0], 0:pattern[1]].T.reshape(-1, 2) * square_mm
    objs, imgs = [], []
    for f in files:
        g = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, pattern, None)
        assert ok, f
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1),
                             (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001))
        objs.append(objp)
        imgs.append(c)
    return cv2.calibrateCamera(objs, imgs, g.shape[::-1], None, None)


def test_real_photographs_agree_with_plain_opencv():
    files = sorted(glob.glob(str(REAL / "left*.jpg")))
    assert len(files) == 13
    rms, K, D, _, _ = _plain_opencv(files, (9, 6), 25.0)
    same = calibrate_camera(files, "chessboard:9x6:25", reject_outliers=False)
    np.testing.assert_allclose(same.camera.K, K, rtol=1e-6)
    np.testing.assert_allclose(same.camera.dist_array, D.ravel(), rtol=1e-5, atol=1e-6)
    assert abs(same.rms_px - rms) < 1e-6
    # default: the one view above 1 px RMS is rejected with its reason; the refit
    # moves fx, fy, cx, cy by less than 4 of the fit's own standard deviations
    res = calibrate_camera(files, "chessboard:9x6:25")
    assert [Path(v.name).name for v in res.rejected] == ["left02.jpg"]
    assert "reprojection RMS" in res.rejected[0].reason
    plain = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    for k, v in plain.items():
        assert abs(getattr(res.camera, k) - v) < 4 * res.std_intrinsics[k], k
    assert res.rms_px < rms


def test_cli_synth_boards_writes_truth(tmp_path, capsys):
    out = tmp_path / "syn"
    rc = fluo_main(["calib", "synth-boards", "--out", str(out), "--views", "3", "--width", "320",
                    "--height", "240", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    truth = json.loads((out / "truth.json").read_text())
    assert truth["images"] == doc["images"] and len(truth["tool_to_tracker"]) == 3
    img = cv2.imread(str(out / "view_000.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (240, 320)
    board = parse_board(truth["board"])
    det = board.detect(img)
    cam = CameraModel.from_dict(truth["camera"])
    from FluoCalibLib.geometry import transforms as tf
    pred = cam.project(tf.apply_rigid(np.array(truth["board_to_camera"][0]), board.object_points))
    assert np.median(np.linalg.norm(det.image_points - pred, axis=1)) < 0.2
