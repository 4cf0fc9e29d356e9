"""Surface-flux mapping validated on data it did not make itself.

The frames are rendered the way the operating room makes them: on the *true*
tissue surface (the phantom's analytic geometry, intersected in closed form:
no mesh, no voxels) from the *true* camera pose.  The software corrects them
the way it must: with a surface extracted from the CBCT (0.8 mm voxels,
smoothed, decimated to 62,000 triangles; from its intensities or from its
label map) and the camera pose it is told, which carries optical tracking
error (per frame) and the hand-eye calibration's error (fixed for the
session).  The light is coupled to the camera, so its pose carries the same
errors.

Each source of mismatch is measured alone and all together, next to the
self-consistent case (render and correct on the same mesh with exact poses:
what the project reported before), with and without the model-error guard
(``flux_map.model_error``), so a reader sees how much of the headline
accuracy is real.

Measured per case (of the truly visible pixels; "accepted" = the corrected mask):

- ``within_5pct``: fraction of the truly visible pixels whose corrected
  transport is within 5 % of the truth (target >= 0.9);
- ``median_abs_error_pct`` / ``p95_abs_error_pct`` of the corrected transport;
- ``miss_rate_raw_pct`` / ``miss_rate_corrected_pct``: the 40 % contour of
  homogeneous tissue (every pixel is fluorescent, so a pixel outside the
  contour is a miss; target < 5 %);
- ``mapping_error_mm`` (median, p95): how far from the point a pixel really
  sees the software paints its value (what a surgeon reads off the surface).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError

from FluoNavLib.mapping.synthetic import PoseError

__all__ = ["MISMATCH_CASES", "mapping_under_mismatch", "mismatch_figure"]

#: case -> (the software's surface, pose errors switched on); surface "truth" is
#: the analytic surface itself, "mesh-truth" renders on the software's own mesh
MISMATCH_CASES = {
    "self-consistent": ("mesh-truth", ()),
    "surface (CBCT intensities)": ("cbct", ()),
    "surface (label map)": ("labels", ()),
    "tracking": ("truth", ("tracking",)),
    "hand-eye": ("truth", ("hand-eye",)),
    "all (CBCT intensities)": ("cbct", ("tracking", "hand-eye")),
    "all (label map)": ("labels", ("tracking", "hand-eye")),
}


def _stats(T_hat, ok, truth_visible, hit_true, hit_model, transport):
    from FluoNavLib.mapping.contours import miss_rate

    n_vis = max(int(truth_visible.sum()), 1)
    accepted = ok & truth_visible
    err = np.abs(T_hat[accepted] / transport - 1.0)
    both = truth_visible & hit_model.visible
    d = np.linalg.norm(hit_true.point_mm[both] - hit_model.point_mm[both], axis=-1)
    rate = float(miss_rate(T_hat, ok)[0]) if ok.any() else 100.0
    return {
        # a pixel the software does not correct is not "within 5 %"
        "within_5pct": float((err < 0.05).sum() / n_vis),
        "accepted_fraction": float(accepted.sum() / n_vis),
        "within_5pct_of_accepted": float((err < 0.05).mean()) if err.size else 0.0,
        "median_abs_error_pct": float(100 * np.median(err)) if err.size else float("nan"),
        "p95_abs_error_pct": float(100 * np.percentile(err, 95)) if err.size else float("nan"),
        "miss_rate_corrected_pct": rate,
        "mapping_error_mm": {"median": float(np.median(d)) if d.size else float("nan"),
                             "p95": float(np.percentile(d, 95)) if d.size else float("nan")},
    }


def _pooled(rows):
    out = {key: float(np.mean([r[key] for r in rows]))
           for key in ("within_5pct", "accepted_fraction", "within_5pct_of_accepted",
                       "median_abs_error_pct", "p95_abs_error_pct")}
    out["within_5pct_worst_view"] = float(min(r["within_5pct"] for r in rows))
    out["miss_rate_corrected_pct"] = float(max(r["miss_rate_corrected_pct"] for r in rows))
    out["mapping_error_mm"] = {
        "median": float(np.median([r["mapping_error_mm"]["median"] for r in rows])),
        "p95": float(max(r["mapping_error_mm"]["p95"] for r in rows))}
    return out


@dataclass(frozen=True)
class _Bench:
    """What every view shares: the analytic phantom the frames are made on, the
    software's meshes ({surface source: caster}), the camera, its coupled light,
    its radiometry, the true transport and the model-error guard's tolerance."""

    geometry: dict
    casters: dict
    cam: object
    cone: object
    rc: object
    transport: float
    tol: float


def _checked_tolerance(cases, n_views, binning, transport, cbct_voxel_mm, max_model_error):
    """Refuse unusable settings in one line before any work; return the model-error
    guard's tolerance (``flux_map.DEFAULT_MAX_MODEL_ERROR`` when None)."""
    from FluoNavLib.mapping.flux_map import DEFAULT_MAX_MODEL_ERROR

    unknown = [c for c in cases if c not in MISMATCH_CASES]
    if unknown:
        raise FluoInputError(f"unknown case; choose from {', '.join(MISMATCH_CASES)}",
                             field="cases", value=unknown[0])
    if not (isinstance(n_views, (int, np.integer)) and 1 <= n_views <= 32):
        raise FluoInputError("must be an integer 1..32", field="n_views", value=n_views)
    if not (isinstance(binning, (int, np.integer)) and 1 <= binning <= 64):
        raise FluoInputError("must be an integer 1..64", field="binning", value=binning)
    if not (np.isfinite(transport) and transport > 0):
        raise FluoInputError("must be a finite number > 0", field="transport", value=transport)
    if not (np.isfinite(cbct_voxel_mm) and 0.2 <= cbct_voxel_mm <= 2.0):
        raise FluoInputError("must be within 0.2..2 mm", field="cbct_voxel_mm",
                             value=cbct_voxel_mm)
    tol = DEFAULT_MAX_MODEL_ERROR if max_model_error is None else float(max_model_error)
    if not (np.isfinite(tol) and tol > 0):
        raise FluoInputError("must be a finite number > 0", field="max_model_error", value=tol)
    return tol


def _software_surfaces(cases, cbct_triangles, seed, cbct_voxel_mm, cancel, progress=None):
    """The meshes extracted from the phantom's CBCT that the cases correct with
    ({"cbct" | "labels" | "mesh-truth": caster}; the analytic "truth" needs none);
    ``progress`` hears of each."""
    from fluoguide.progress import check_cancel, run_reporting

    from FluoNavLib.mapping.synthetic import oral_cavity_surface

    casters = {}
    for case in cases:
        src = MISMATCH_CASES[case][0]
        if src != "truth" and src not in casters:
            # the self-consistent case renders on and corrects with the label-map mesh;
            # a surface takes seconds and cannot report from inside: reported beside it
            casters[src] = run_reporting(
                lambda src=src: oral_cavity_surface(
                    cbct_triangles, seed=seed, voxel_mm=cbct_voxel_mm,
                    source="cbct" if src == "cbct" else "labels")[0],
                progress, 0.0, f"from the {src}", cancel)
            check_cancel(cancel)
    return casters


def _told_pose(pose, errors, hand_eye_error, tracking_error):
    """The camera pose the software is told: the true pose with the case's errors."""
    told = pose
    if "hand-eye" in errors:
        told = told @ hand_eye_error          # camera-to-tool error, in the camera frame
    if "tracking" in errors:
        told = tracking_error @ told          # tool pose error, in the tracker frame
    return told


def _corrected(bench, case, told, hits_true, counts, seed):
    """One view corrected the way ``case`` does it (its surface, the pose it is told):
    the stats without and with the model-error guard, and the two images
    ({"guarded": (T, mask), "unguarded": (T, mask)})."""
    from FluoNavLib.mapping.flux_map import model_error, transport_image, view_model
    from FluoNavLib.mapping.pixel_cast import cast_camera
    from FluoNavLib.mapping.synthetic import exact_oral_cavity_hits, render_hits

    src = MISMATCH_CASES[case][0]
    cone, rc, transport = bench.cone, bench.rc, bench.transport
    seen = hits_true
    S = counts - rc.offset_adu
    if src == "mesh-truth":                   # the frame made on the software's own mesh
        seen = hits = cast_camera(bench.casters[src], bench.cam, told)
        S = render_hits(hits, cone, told, transport, rc, seed=seed)[0] - rc.offset_adu
    elif src == "truth":
        hits = exact_oral_cavity_hits(bench.cam, told, bench.geometry)
    else:
        hits = cast_camera(bench.casters[src], bench.cam, told)
    vm = view_model(hits, cone, told)
    T_hat, ok = transport_image(S, vm, cone)
    plain = _stats(T_hat, ok, seen.visible, seen, hits, transport)
    # the exact surface has exact normals: only its occluding rims are doubted
    caster = None if src == "truth" else bench.casters[src]
    trusted = ok & (model_error(hits, vm, caster) <= bench.tol)
    T_g = np.where(trusted, T_hat, 0.0)
    kept = _stats(T_g, trusted, seen.visible, seen, hits, transport)
    return plain, kept, {"guarded": (T_g, trusted), "unguarded": (T_hat, ok)}


def _settings(n_views, binning, transport, tracking, hand_eye, cbct_voxel_mm, cbct_triangles,
              tol):
    """The settings a result carries, so a reader knows what it was measured under."""
    return {
        "max_model_error": tol,
        "views": n_views, "binning": binning, "transport_truth": transport,
        "tracking_sd": {"translation_mm": tracking.translation_mm,
                        "rotation_deg": tracking.rotation_deg},
        "hand_eye_error": {"translation_mm": hand_eye.translation_mm,
                           "rotation_deg": hand_eye.rotation_deg},
        "truth_surface": "analytic (block faces, cavity half-ellipsoid, tongue ellipsoid)",
        "cbct": {"voxel_mm": cbct_voxel_mm, "triangles": cbct_triangles},
    }


def mapping_under_mismatch(n_views=4, binning=4, transport=0.3,
                           tracking=PoseError(0.25, 0.1), hand_eye=PoseError(0.3, 0.15),
                           cbct_voxel_mm=0.8, cbct_triangles=62000, max_model_error=None,
                           cases=tuple(MISMATCH_CASES), seed=0, keep_images=False,
                           progress=None, cancel=None):
    """Transport correction and contour miss rates when the software's surface
    and poses are not the ones that made the frames.

    Parameters
    ----------
    n_views : tracked views looking into the oral-cavity phantom's cavity
    binning : camera binning (4: 348 x 260 pixels)
    transport : the true, homogeneous optical transport T of the tissue
    tracking : per-frame optical tracking error of the camera tool (default
        0.25 mm / 0.1 deg per axis: an NDI Polaris small tool)
    hand_eye : the camera-to-tool calibration's error, fixed for the session
        (default 0.3 mm / 0.15 deg: about twice the hand-eye error measured in
        docs/calibration-geometry.md, the paired-point method's plateau)
    cbct_voxel_mm : voxel of the phantom's CBCT the software's surfaces are
        extracted from (smoothed, then decimated to ``cbct_triangles``)
    max_model_error : the model-error guard (``flux_map.model_error``); None:
        ``flux_map.DEFAULT_MAX_MODEL_ERROR``.  Every case is measured with the
        guard (``cases``) and without it (``cases_unguarded``)
    cases : names from :data:`MISMATCH_CASES`
    seed : noise and pose-error seed (the same errors for every case that
        includes them)
    keep_images : also return the images of view 1 (for :func:`mismatch_figure`):
        ``images[case]`` = {"guarded": (T, mask), "unguarded": (T, mask)},
        ``images["raw"]`` = (counts above offset, visible)

    Returns
    -------
    dict with ``cases`` and ``cases_unguarded`` ({name: stats pooled over the
    views}), ``per_view`` ({name: [stats]}, guarded), ``miss_rate_raw_pct``
    (per view), the settings, and ``images`` if asked.
    """
    from fluoguide.phantoms import make_phantom
    from fluoguide.progress import check_cancel, report, scaled

    from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

    from FluoNavLib.mapping.contours import miss_rate
    from FluoNavLib.mapping.kernels import prepare_kernels
    from FluoNavLib.mapping.synthetic import (
        coupled_light,
        exact_oral_cavity_hits,
        open_field_camera,
        render_hits,
        view_poses,
    )

    tol = _checked_tolerance(cases, n_views, binning, transport, cbct_voxel_mm, max_model_error)
    prepare_kernels(progress, 0.0, cancel)      # first run: compiled, reported as it goes
    report(progress, 0.02, "the CBCT surfaces")
    geometry = make_phantom("oral-cavity", voxel_mm=cbct_voxel_mm, seed=seed).truth()["geometry"]
    casters = _software_surfaces(cases, cbct_triangles, seed, cbct_voxel_mm, cancel,
                                 scaled(progress, 0.02, 0.1, "the CBCT surfaces"))
    cone = coupled_light()
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    cam = open_field_camera(binning=binning)
    bench = _Bench(geometry, casters, cam, cone, rc, transport, tol)
    rng = np.random.default_rng(seed)
    hand_eye_error = hand_eye.fixed(rng)
    true_poses = view_poses(n_views)
    tracking_errors = [tracking.random(rng) for _ in true_poses]

    guarded = {c: [] for c in cases}
    unguarded = {c: [] for c in cases}
    raw_rates = []
    images = {}
    for k, pose in enumerate(true_poses):
        report(progress, 0.1 + 0.85 * k / n_views, f"view {k + 1} of {n_views}")
        hits_true = exact_oral_cavity_hits(cam, pose, geometry)
        counts, _ = render_hits(hits_true, cone, pose, transport, rc, seed=seed + k)
        raw_rates.append(float(miss_rate(counts - rc.offset_adu, hits_true.visible)[0]))
        for case in cases:
            check_cancel(cancel)
            told = _told_pose(pose, MISMATCH_CASES[case][1], hand_eye_error, tracking_errors[k])
            plain, kept, shown = _corrected(bench, case, told, hits_true, counts, seed + k)
            unguarded[case].append(plain)
            guarded[case].append(kept)
            if keep_images and k == min(1, n_views - 1):
                images[case] = shown
                images["raw"] = (counts - rc.offset_adu, hits_true.visible)

    report(progress, 1.0, "mapping under mismatch done")
    result = {
        "cases": {c: _pooled(guarded[c]) for c in cases},
        "cases_unguarded": {c: _pooled(unguarded[c]) for c in cases},
        "per_view": guarded,
        "miss_rate_raw_pct": raw_rates,
        **_settings(n_views, binning, transport, tracking, hand_eye, cbct_voxel_mm,
                    cbct_triangles, tol),
    }
    if keep_images:
        result["images"] = images
    return result


def mismatch_figure(path, result, case="all (CBCT intensities)"):
    """PNG of view 1: raw counts, and the transport corrected with the CBCT surface
    and tracked poses without and with the model-error guard, each with its 40 %
    contour and miss rate (``result`` from ``mapping_under_mismatch(keep_images=True)``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from FluoNavLib.mapping.contours import miss_rate

    images = result.get("images") or {}
    if case not in images:
        raise FluoInputError("result has no images of this case (keep_images=True)",
                             field="case", value=case)
    T0 = result["transport_truth"]
    raw, vis = images["raw"]
    panels = [("raw counts above offset [ADU]", raw, vis, None),
              (f"corrected T, no guard ({case})", *images[case]["unguarded"], (0, 2 * T0)),
              (f"corrected T, model-error guard <= {100 * result['max_model_error']:.0f} %",
               *images[case]["guarded"], (0, 2 * T0))]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    for ax, (title, img, mask, lim) in zip(axes, panels):
        shown = np.where(mask, img, np.nan)
        rate, inside, _ = miss_rate(img, mask) if mask.any() else (100.0, mask, mask)
        im = ax.imshow(shown, cmap="magma", vmin=None if lim is None else lim[0],
                       vmax=None if lim is None else lim[1])
        ax.contour(inside.astype(float), levels=[0.5], colors="cyan", linewidths=0.8)
        ax.set_title(f"{title}\n40 % contour: miss {rate:.1f} %", fontsize=9)
        ax.axis("off")
        cb = fig.colorbar(im, ax=ax, shrink=0.8)
        cb.set_label("ADU" if lim is None else f"optical transport T (truth {T0:g})", fontsize=8)
    fig.suptitle("Frames rendered on the analytic phantom surface from the true poses; corrected "
                 "with the CBCT surface and tracked poses (tracking "
                 f"{result['tracking_sd']['translation_mm']} mm / "
                 f"{result['tracking_sd']['rotation_deg']} deg, hand-eye "
                 f"{result['hand_eye_error']['translation_mm']} mm / "
                 f"{result['hand_eye_error']['rotation_deg']} deg)", fontsize=10)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return str(path)
