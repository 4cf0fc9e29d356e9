"""Speed and accuracy of per-pixel surface mapping (``fluo bench mapping``,
``python -m benchmarks mapping``): full-resolution and binned frames, full and
decimated surfaces, on the oral-cavity phantom with homogeneous fluorescence.

Accuracy of each option is against the full-resolution cast on the full
62k-triangle surface: the hit point of every full-resolution pixel is
compared with what the option gives for that pixel (the binned pixel holding
it, or the decimated surface), and the corrected transport is compared with
the truth.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["run_mapping_benchmark"]


def _median_time(fn, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def run_mapping_benchmark(repeats=5, binning=10, decimated_triangles=15000, progress=None):
    from .flux_map import transport_image, view_model
    from .nav_synth import coupled_light, open_field_camera, oral_cavity_surface, render_view, view_poses
    from .pixel_cast import cast_camera

    caster, _ = oral_cavity_surface(62000)
    coarse, _ = oral_cavity_surface(decimated_triangles)
    cone = coupled_light()
    pose = view_poses(2)[1]                    # an oblique view
    cam = open_field_camera()
    full_s, hits = _median_time(lambda: cast_camera(caster, cam, pose), repeats)
    bin_s, hits_b = _median_time(lambda: cast_camera(caster, cam, pose, binning=binning), repeats * 4)
    dec_s, hits_d = _median_time(lambda: cast_camera(coarse, cam, pose), repeats)

    def full_map():
        h = cast_camera(caster, cam, pose)
        vm = view_model(h, cone, pose)
        return h, vm

    map_s, _ = _median_time(full_map, repeats)
    # accuracy of binning: each full-res pixel against its binned block's hit
    H, W = hits.shape
    hb, wb = hits_b.shape
    rows = np.minimum(np.arange(H) // binning, hb - 1)
    cols = np.minimum(np.arange(W) // binning, wb - 1)
    pb = hits_b.point_mm[rows][:, cols]
    vb = hits_b.visible[rows][:, cols]
    both = hits.visible & vb
    err_bin = np.linalg.norm(hits.point_mm - pb, axis=-1)[both]
    both_d = hits.visible & hits_d.visible
    err_dec = np.linalg.norm(hits.point_mm - hits_d.point_mm, axis=-1)[both_d]
    # transport accuracy (noisy frames) at full res and binned
    acc = {}
    for name, c in (("full", cam), (f"binned_{binning}x", cam.binned(binning))):
        counts, h, vm = render_view(caster, c, pose, cone, 0.3, seed=1)
        from FluoCalibLib.radiometric_model import RadiometricCamera

        T, ok = transport_image(counts - RadiometricCamera(gain_adu_per_e=1.0).offset_adu, vm, cone)
        within = ok & (np.abs(T / 0.3 - 1) < 0.05)
        acc[name] = {"visible_within_5pct": float(within.sum() / max(h.visible.sum(), 1)),
                     "median_abs_err_pct": float(100 * np.median(np.abs(T[ok] / 0.3 - 1)))}
    return {
        "fps_full": 1.0 / full_s, "fps_binned": 1.0 / bin_s, "fps_full_with_model": 1.0 / map_s,
        "fps_decimated": 1.0 / dec_s, "binning": binning,
        "triangles": int(caster.n_faces), "triangles_decimated": int(coarse.n_faces),
        "pixels": int(H * W), "pixels_binned": int(hb * wb),
        "binned_hit_error_mm": {"median": float(np.median(err_bin)), "p95": float(np.percentile(err_bin, 95))},
        "decimated_hit_error_mm": {"median": float(np.median(err_dec)), "p95": float(np.percentile(err_dec, 95))},
        "visible_agreement_decimated": float((hits.visible == hits_d.visible).mean()),
        "transport_accuracy": acc, "repeats": repeats,
        "method": "Embree BVH (embreex), built once per mesh; rays from the cached pixel-ray grid",
    }
