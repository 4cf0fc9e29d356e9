"""Speed and accuracy of per-pixel surface mapping (``fluo bench mapping``,
``python -m benchmarks mapping``): full-resolution and binned frames, full and
decimated surfaces, on the oral-cavity phantom with homogeneous fluorescence.

The cast itself is checked against the exact float64 brute force on random
pixels (``reference_accuracy``).  Accuracy of each option is against the
full-resolution cast on the full 62k-triangle surface: the hit point of every full-resolution pixel is
compared with what the option gives for that pixel (the binned pixel holding
it, or the decimated surface), and the corrected transport is compared with
the truth.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import seeded_rng

__all__ = ["run_mapping_benchmark"]


def _median_time(fn, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def _reference_accuracy(caster, cam, pose, methods, n_pixels=400, seed=0):
    """Each cast method against the exact float64 brute force on random pixels."""
    from FluoNavLib.mapping.pixel_cast import cast_camera, reference_cast

    rng = seeded_rng(seed)
    h, w = cam.height, cam.width
    idx = rng.choice(h * w, n_pixels, replace=False)
    rays = (cam.pixel_grid_rays() @ pose[:3, :3].T).reshape(-1, 3)[idx]
    rf, rd = reference_cast(caster.points_mm, caster.triangles, pose[:3, 3], rays)
    out = {}
    for m in methods:
        hits = cast_camera(caster, cam, pose, method=m)
        f = hits.face.reshape(-1)[idx]
        v = hits.visible.reshape(-1)[idx]
        d = hits.distance_mm.reshape(-1)[idx]
        ref_vis = rf >= 0
        both = v & ref_vis
        out[m] = {"pixels": int(n_pixels), "face_agreement": float((f[both] == rf[both]).mean()),
                  "mask_agreement": float((v == ref_vis).mean()),
                  "hit_error_max_mm": float(np.abs(d[both] - rd[both]).max()) if both.any() else 0.0}
    return out


def run_mapping_benchmark(repeats=5, binning=10, decimated_triangles=15000, progress=None):
    from fluoguide.errors import check_number

    # a median needs one repeat; 100 repeats of the slowest step take minutes already
    check_number("repeats", repeats, 1, 100, integer=True)
    check_number("binning", binning, 1, 64, integer=True)
    check_number("decimated_triangles", decimated_triangles, 100, 10_000_000, integer=True)
    from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

    from FluoNavLib.mapping.flux_map import transport_image, view_model
    from FluoNavLib.mapping.synthetic import (
        coupled_light,
        open_field_camera,
        oral_cavity_surface,
        render_view,
        view_poses,
    )
    from FluoNavLib.mapping.kernels import prepare_kernels
    from FluoNavLib.mapping.pixel_cast import cast_camera

    prepare_kernels(progress, 0.0)             # first run: compiled, reported as it goes
    caster, _ = oral_cavity_surface(62000)
    coarse, _ = oral_cavity_surface(decimated_triangles)
    cone = coupled_light()
    pose = view_poses(2)[1]                    # an oblique view
    cam = open_field_camera()
    cast_camera(caster, cam, pose)             # compile and build the grids once
    cast_camera(caster, cam, pose, binning=binning)
    cast_camera(coarse, cam, pose)
    full_s, hits = _median_time(lambda: cast_camera(caster, cam, pose), repeats * 4)
    bin_s, hits_b = _median_time(lambda: cast_camera(caster, cam, pose, binning=binning), repeats * 20)
    dec_s, hits_d = _median_time(lambda: cast_camera(coarse, cam, pose), repeats * 4)
    emb_s, _ = _median_time(lambda: cast_camera(caster, cam, pose, method="embree"), repeats)
    emb_b_s, _ = _median_time(lambda: cast_camera(caster, cam, pose, binning=binning, method="embree"),
                              repeats * 4)

    def full_map():
        h = cast_camera(caster, cam, pose)
        vm = view_model(h, cone, pose)
        return h, vm

    map_s, _ = _median_time(full_map, repeats)
    # a strongly distorted lens (barrel, k1 = -0.25): pixel-space rasterisation
    from FluoCalibLib.geometry.camera_model import CameraModel

    dcam = CameraModel(1860.0, 1860.0, 690.2, 522.8, (-0.25, 0.12, 0.0008, -0.0005, 0.0), 1392, 1040)
    distorted = {}
    for b in (1, binning):
        cast_camera(caster, dcam, pose, binning=b)
        sec, dh = _median_time(lambda: cast_camera(caster, dcam, pose, binning=b), repeats * (4 if b == 1 else 20))
        eh = cast_camera(caster, dcam, pose, binning=b, method="embree")
        both = dh.visible & eh.visible
        distorted[f"binning_{b}"] = {"fps": 1.0 / sec, "mask_agreement_vs_embree": float((dh.visible == eh.visible).mean()),
                                     "face_agreement_vs_embree": float((dh.face[both] == eh.face[both]).mean())}
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
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    acc = {}
    for name, c in (("full", cam), (f"binned_{binning}x", cam.binned(binning))):
        counts, h, vm = render_view(caster, c, pose, cone, 0.3, rc, seed=1)
        T, ok = transport_image(counts - rc.offset_adu, vm, cone)
        within = ok & (np.abs(T / 0.3 - 1) < 0.05)
        acc[name] = {"visible_within_5pct": float(within.sum() / max(h.visible.sum(), 1)),
                     "median_abs_err_pct": float(100 * np.median(np.abs(T[ok] / 0.3 - 1)))}
    return {
        "fps_full": 1.0 / full_s, "fps_binned": 1.0 / bin_s, "fps_full_with_model": 1.0 / map_s,
        "fps_decimated": 1.0 / dec_s, "fps_full_embree": 1.0 / emb_s,
        "fps_binned_embree": 1.0 / emb_b_s, "binning": binning,
        "triangles": int(caster.n_faces), "triangles_decimated": int(coarse.n_faces),
        "pixels": int(H * W), "pixels_binned": int(hb * wb),
        "reference_accuracy": _reference_accuracy(caster, cam, pose, ("raster", "embree")),
        "binned_hit_error_mm": {"median": float(np.median(err_bin)), "p95": float(np.percentile(err_bin, 95))},
        "decimated_hit_error_mm": {"median": float(np.median(err_dec)), "p95": float(np.percentile(err_dec, 95))},
        "visible_agreement_decimated": float((hits.visible == hits_d.visible).mean()),
        "visible_agreement_binned": float((hits.visible == vb).mean()),
        "transport_accuracy": acc, "distorted_lens": distorted, "repeats": repeats,
        "method": "z-buffer rasterisation in normalised coordinates + exact per-pixel intersection "
                  "(numba, default); Embree BVH (embreex) for comparison",
    }
