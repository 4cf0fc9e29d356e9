"""Geometric calibration: accuracy vs number of views and image noise, and run time.

Synthetic board images (640x480, distorted camera, 9x6 board) with known truth;
medians over seeds. Prints intrinsic errors [%], hand-eye translation error [mm]
per method and the fit times [s].
"""

import argparse
import time

import numpy as np

from FluoCalibLib.geometry import handeye as he
from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.boards import parse_board
from FluoCalibLib.geometry.intrinsics import calibrate_camera
from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset


def _one(n_views, noise, seed):
    cam = default_camera(640, 480)
    board = parse_board("chessboard:9x6:20")
    ds = make_dataset(None, cam, board, n_views=n_views, seed=seed, supersample=2,
                      noise_sigma=noise, tracker_noise_mm=0.1, tracker_noise_deg=0.03)
    t0 = time.perf_counter()
    res = calibrate_camera([v.image for v in ds["views"]], board)
    t_cal = time.perf_counter() - t0
    f_err = 100 * abs(res.camera.fx - cam.fx) / cam.fx
    c_err = 100 * max(abs(res.camera.cx - cam.cx) / cam.cx, abs(res.camera.cy - cam.cy) / cam.cy)
    idx = [int(v.name.split("_")[1]) for v in res.used]
    A = [ds["views"][i].tool_to_tracker for i in idx]
    B = [v.board_to_camera for v in res.used]
    rng = np.random.default_rng(seed)
    corners = [0, board.cols - 1, board.n_corners - board.cols, board.n_corners - 1]
    tips = tf.apply_rigid(np.array(ds["board_to_tracker"]), board.object_points[corners])
    G = he.board_to_tracker_from_pointer(board, corners, tips + rng.normal(0, 0.15, (4, 3)))
    t0 = time.perf_counter()
    cmp = he.compare_methods(res.camera, board, B, A, [(v.ids, v.image_points) for v in res.used],
                             G.transform, truth_camera_to_tool=ds["camera_to_tool"])
    t_he = time.perf_counter() - t0
    return f_err, c_err, res.rms_px, t_cal, t_he, cmp


def main(argv=None):
    ap = argparse.ArgumentParser(prog="bench_calibration")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--views", default="6,10,16")
    ap.add_argument("--noise", default="2,6")
    args = ap.parse_args(argv)
    print(f"{'views':>5} {'noise':>5} {'fx err %':>9} {'c err %':>8} {'rms px':>7} "
          f"{'t_cal s':>7} {'t_he s':>7}  hand-eye translation error mm (median)")
    for n in [int(v) for v in args.views.split(",")]:
        for noise in [float(v) for v in args.noise.split(",")]:
            rows = [_one(n, noise, 100 + s) for s in range(args.seeds)]
            med = lambda i: float(np.median([r[i] for r in rows]))  # noqa: E731
            he_err = {m: float(np.median([r[5][m]["translation_error_mm"] for r in rows]))
                      for m in he.METHODS}
            he_txt = " ".join(f"{m}={v:.3f}" for m, v in he_err.items())
            print(f"{n:>5} {noise:>5g} {med(0):>9.4f} {med(1):>8.4f} {med(2):>7.3f} "
                  f"{med(3):>7.3f} {med(4):>7.3f}  {he_txt}", flush=True)
    return 0
