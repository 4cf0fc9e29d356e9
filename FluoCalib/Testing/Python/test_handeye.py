"""Hand-eye calibration on synthetic tracked views with known CameraToTool."""

import json

import cv2
import numpy as np
import pytest

from fluoguide import mrml_io
from fluoapp.cli import main as fluo_main
from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import scene as gs
from FluoCalibLib.geometry import handeye as he
from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.boards import parse_board
from FluoCalibLib.geometry.intrinsics import calibrate_camera
from FluoCalibLib.geometry.opencv_yaml import read_calibration_yaml
from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

CAM = default_camera(640, 480)
BOARD = parse_board("chessboard:9x6:20")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("handeye")
    # realistic noise: optical tracker ~0.1 mm / 0.03 deg, sensor noise 2 grey levels
    ds = make_dataset(out, CAM, BOARD, n_views=16, seed=11, supersample=2,
                      tracker_noise_mm=0.1, tracker_noise_deg=0.03)
    res = calibrate_camera([v.image for v in ds["views"]], BOARD)
    used = res.used
    idx = [int(v.name.split("_")[1]) for v in used]
    rng = np.random.default_rng(2)
    corners = [0, BOARD.cols - 1, BOARD.n_corners - BOARD.cols, BOARD.n_corners - 1]
    G_true = np.array(ds["board_to_tracker"])
    tips = tf.apply_rigid(G_true, BOARD.object_points[corners]) + rng.normal(0, 0.15, (4, 3))
    G = he.board_to_tracker_from_pointer(BOARD, corners, tips).transform
    return {"out": out, "ds": ds, "camera": res.camera, "views": used,
            "A": [ds["views"][i].tool_to_tracker for i in idx],
            "B": [v.board_to_camera for v in used], "G": G,
            "det": [(v.ids, v.image_points) for v in used],
            "X": np.array(ds["camera_to_tool"])}


def test_all_methods_recover_truth(data):
    cmp = he.compare_methods(data["camera"], BOARD, data["B"], data["A"], data["det"],
                             data["G"], truth_camera_to_tool=data["X"])
    assert set(cmp) == set(he.METHODS)
    for m, row in cmp.items():
        assert tf.is_rigid(row["camera_to_tool"], 1e-9)
        assert row["translation_error_mm"] < 1.0, m
        assert row["rotation_error_deg"] < 0.3, m
        assert row["err3d_mean_mm"] < 1.0 and row["err2d_mean_px"] < 2.0, m
    # paired-point inherits the pointer grid-registration error (0.15 mm per corner
    # here), which the AX = XB solvers never use: looser bound, see docs
    assert cmp["PAIRED_POINT"]["translation_error_mm"] < 0.6
    assert np.median([r["translation_error_mm"] for r in cmp.values()]) < 0.3


def test_errors_match_direct_computation(data):
    X = he.solve_handeye(data["B"], data["A"], "PAIRED_POINT", data["G"])
    err = he.handeye_errors(data["camera"], BOARD, data["det"], data["A"], X, data["G"])
    cam = data["camera"]
    e2, e3 = [], []
    for (ids, uv), A in zip(data["det"], data["A"]):
        board_to_cam = np.linalg.inv(np.linalg.inv(data["G"]) @ A @ X)
        rvec, _ = cv2.Rodrigues(board_to_cam[:3, :3])
        proj, _ = cv2.projectPoints(BOARD.object_points[ids], rvec, board_to_cam[:3, 3], cam.K,
                                    cam.dist_array)
        e2.append(np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1))
        # 3D: undistort with OpenCV, intersect the ray with the board plane via the
        # homography of the plane z = 0 (independent of handeye's ray code)
        xy = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), cam.K, cam.dist_array, None, None,
                                     (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))
        H = board_to_cam[:3, [0, 1, 3]]
        q = np.linalg.solve(H, np.column_stack([xy.reshape(-1, 2), np.ones(len(uv))]).T).T
        q = q[:, :2] / q[:, 2:3]
        e3.append(np.linalg.norm(q - BOARD.object_points[ids, :2], axis=1))
    np.testing.assert_allclose(err["err2d_px"], np.concatenate(e2), atol=1e-6)
    np.testing.assert_allclose(err["err3d_mm"], np.concatenate(e3), atol=1e-6)
    assert abs(err["err3d_mean_mm"] - np.concatenate(e3).mean()) < 1e-9


def test_exact_data_gives_exact_solution(data):
    """Noise-free poses: every method returns the truth to rounding error."""
    X = data["X"]
    G = np.array(data["ds"]["board_to_tracker"])
    A = [v.tool_to_tracker_true for v in data["ds"]["views"]]
    B = [v.board_to_camera for v in data["ds"]["views"]]
    for m in he.METHODS:
        Xm = he.solve_handeye(B, A, m, G if m == "PAIRED_POINT" else None)
        assert np.linalg.norm(Xm[:3, 3] - X[:3, 3]) < 1e-5, m
        assert tf.rotation_angle(Xm[:3, :3].T @ X[:3, :3]) < 1e-7, m
    # paired-point without a pointer registration estimates the grid itself
    Xp = he.paired_point_handeye(B, A)
    assert np.linalg.norm(Xp[:3, 3] - X[:3, 3]) < 1e-5


def test_degenerate_motion_and_mismatch(data):
    A, B = data["A"], data["B"]
    with pytest.raises(FluoInputError, match="board views but"):
        he.solve_handeye(B, A[:-1])
    # pure translation: same orientation in every view
    A_tr = [tf.make_rigid(A[0][:3, :3], A[0][:3, 3] + [10.0 * i, 3.0 * i, -5.0 * i])
            for i in range(len(A))]
    with pytest.raises(FluoInputError, match="pure translation"):
        he.solve_handeye(B, A_tr)
    # rotations all about one axis
    A_ax = [A[0] @ tf.make_rigid(tf.rotation_matrix("z", 0.2 * i), [5.0 * i, 0, 0])
            for i in range(len(A))]
    with pytest.raises(FluoInputError, match="one axis"):
        he.solve_handeye(B, A_ax)
    with pytest.raises(FluoInputError, match="unknown hand-eye method"):
        he.solve_handeye(B, A, "MAGIC")
    with pytest.raises(FluoInputError, match="rigid"):
        he.solve_handeye(B, [np.eye(4) * 2] * len(B))


def test_cli_handeye_and_scene(data, tmp_path, capsys):
    out = data["out"]
    scene = tmp_path / "s" / "scene.mrml"
    yaml_path = tmp_path / "he.yaml"
    rc = fluo_main(["calib", "handeye", "--images", str(out / "*.png"), "--board", BOARD.spec,
                    "--poses", str(out / "truth.json"), "--json", "--scene", str(scene),
                    "--yaml", str(yaml_path), "--holdout", "3"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["methods"]) == set(he.METHODS)
    pp = doc["methods"]["PAIRED_POINT"]
    assert pp["translation_error_mm"] < 0.5
    assert len(pp["holdout_views"]) == 3 and pp["holdout_err3d_mean_mm"] < 1.0
    X = np.array(doc["camera_to_tool"])
    np.testing.assert_array_equal(read_calibration_yaml(yaml_path)["camera_to_tool"], X)
    # ITK HDF5 storage keeps the matrix to ~1e-15 relative (it stores the inverse)
    np.testing.assert_allclose(gs.load_handeye(mrml_io.load_scene(scene)), X, rtol=0, atol=1e-12)
    # mismatched image / pose counts
    poses = json.loads((out / "truth.json").read_text())
    poses["tool_to_tracker"] = poses["tool_to_tracker"][:-2]
    (tmp_path / "p.json").write_text(json.dumps(poses))
    rc = fluo_main(["calib", "handeye", "--images", str(out / "*.png"), "--board", BOARD.spec,
                    "--poses", str(tmp_path / "p.json")])
    assert rc == 2 and "16 images but 14 tool poses" in capsys.readouterr().err
