"""Radiometric calibrations (issue #6): camera response, broad-beam cone and
laser line on synthetic data with known truth, at the binned test size
(348 x 260) and the full PCO Pixelfly size (1392 x 1040).

Prints, per size, medians over seeds of the errors against truth and the fit
times [s] (data generation not timed).  Targets: camera parameters within 3 %;
cone axis < 0.5 deg, half-angle < 0.2 deg, alpha/gamma/Dsys within 3 %, ratio
mean 1.00 +- 0.01; laser direction < 0.3 deg, held-out 3D error < 0.5 mm.
"""

import argparse
import time

import numpy as np

from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.camera_response import characterize
from FluoCalibLib.radiometry.illumination_fit import calibrate_illumination
from FluoCalibLib.radiometry.laser_line import calibrate_laser
from FluoCalibLib.radiometry.synthetic import (
    endoscope_camera,
    synthetic_illumination,
    synthetic_laser,
    synthetic_lens_spectral_frames,
    synthetic_stack,
)


def _pct(a, b):
    return 100.0 * abs(a - b) / abs(b)


def _deg(a, b):
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b),
                                              -1, 1))))


def _stack(binning, seed):
    shape = (1040 // binning, 1392 // binning)
    frames, truth = synthetic_stack(shape=shape, seed=seed)
    extra, tx = synthetic_lens_spectral_frames(shape=shape, seed=seed + 50,
                                               radiance_w_per_mm2_sr=truth["radiance_w_per_mm2_sr"])
    t0 = time.perf_counter()
    r = characterize(frames + extra)
    dt = time.perf_counter() - t0
    cam = truth["camera"]
    row = {k: _pct(r[k], cam[k]) for k in ("gain_adu_per_e", "dark_current_e_per_s", "bias_e",
                                            "read_noise_e")}
    row["NL %"] = r["nonlinearity_pct"]
    row["DR"] = r["dynamic_range"]
    row["lens alpha err"] = abs(r["lens_exponent"]["alpha"] - tx["lens_exponent"])
    spec = tx["spectral_e_per_radiance_s"]
    got = r["spectral_responsivity"]
    row["spectral max err %"] = max(_pct(v, spec[w]) for w, v in zip(got["wavelength_nm"],
                                                                     got["e_per_radiance_s"]))
    row["t s"] = dt
    return row


def _illumination(binning, seed):
    cam = endoscope_camera(binning)
    imgs, truth = synthetic_illumination(camera=cam, seed=seed)
    t0 = time.perf_counter()
    r = calibrate_illumination(imgs, cam, truth["phantom_to_camera"], truth["rd"],
                               truth["offset_adu"], saturation_adu=truth["saturation_adu"])
    dt = time.perf_counter() - t0
    c = truth["cone"]
    return {"axis deg": _deg(r["axis"], c["axis"]),
            "half-angle deg": abs(r["half_angle_deg"] - c["half_angle_deg"]),
            "alpha %": _pct(r["alpha"], c["alpha"]),
            "gamma %": _pct(r["gamma_per_mm"], c["gamma_per_mm"]),
            "Dsys %": _pct(r["system_gain_adu"], c["system_gain_adu"]),
            "ratio mean": r["ratio_mean"], "ratio SD": r["ratio_sd"],
            "crescent": float(r["model"] == "crescent"), "t s": dt}


def _laser(binning, seed):
    cam = CameraModel(4279.0 / binning, 4279.0 / binning, 739.3 / binning, 510.2 / binning,
                      (0, 0, 0, 0, 0), 1392 // binning, 1040 // binning)
    imgs, truth = synthetic_laser(camera=cam, seed=seed, spot_sigma_px=8.0 / binning)
    t0 = time.perf_counter()
    r = calibrate_laser(imgs, cam, truth["camera_to_tracker"], truth["laser_to_tracker"],
                        truth["phantom_to_tracker"], truth["pointer_origin_tool_mm"])
    dt = time.perf_counter() - t0
    return {"direction deg": _deg(r["direction"], truth["direction"]),
            "line rms mm": r["line_fit_rms_mm"], "3D mm": r["error_3d_mm"],
            "2D px": r["error_2d_px"], "t s": dt}


def _print(name, size, rows):
    keys = list(rows[0])
    med = {k: float(np.median([r[k] for r in rows])) for k in keys}
    print(f"{name:<13} {size:<10} " + "  ".join(f"{k}={med[k]:.4g}" for k in keys), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="bench_radiometry")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--binning", default="4,1", help="4 = 348x260, 1 = 1392x1040")
    args = ap.parse_args(argv)
    print("medians over seeds; camera errors in %, times exclude data generation")
    for b in [int(v) for v in args.binning.split(",")]:
        size = f"{1392 // b}x{1040 // b}"
        seeds = range(args.seeds) if b > 1 else range(max(1, args.seeds // 3))
        _print("camera", size, [_stack(b, 10 + s) for s in seeds])
        _print("illumination", size, [_illumination(b, 20 + s) for s in seeds])
        _print("laser", size, [_laser(b, 30 + s) for s in seeds])
    return 0
