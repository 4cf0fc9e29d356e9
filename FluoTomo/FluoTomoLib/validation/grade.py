"""One scene of the family reconstructed and graded, and the family's table.

A scene's grade, per method and inclusion: the reconstructed yield against the
truth (signed error, %), the stated 95 % interval (``ci95_per_mm``) and whether
it holds the truth, its half-width relative to the truth, the half-maximum
centroid's distance from the target's centre, and whether the result carries a
warning. The family's table (:func:`summarise`) gives per method the median,
90th percentile and worst |error|, and the coverage of the intervals: how
often they hold the truth, and, where they do not, how often a warning said
the result might be off.
"""

from __future__ import annotations

import time

import numpy as np


def grade_scene(scene, methods=("HP", "SP"), accuracy="balanced", engine="fem",
                acquisition=None, progress=None, cancel=None, segmentation_mm=None,
                grading=False):
    """Simulate ``scene`` (unless ``acquisition`` is given), reconstruct it with
    each method at ``accuracy`` on the label map the scene hands over (with the
    segmentation's stated accuracy ``segmentation_mm``, None: the reconstruction's
    default) and the mesh ``grading`` (reconstruct_labelmap's), and grade the
    results. Returns a list of row dicts (one per method and inclusion)."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    t0 = time.perf_counter()
    if acquisition is None:
        acquisition, _ = simulate(scene, engine=engine)
    t_sim = time.perf_counter() - t0
    lm = scene.labelmap(recon=True)
    optics = optics_from_dict(scene.optics)
    t0 = time.perf_counter()
    out = reconstruct_labelmap_methods(lm, optics, acquisition, methods=list(methods),
                               accuracy=accuracy, target=scene.target(), progress=progress,
                               cancel=cancel, segmentation_mm=segmentation_mm,
                               grading=grading)
    t_rec = time.perf_counter() - t0
    rows = []
    for method in methods:
        s = out[method]["summary"]
        cen = s.get("target_centroid_ras_mm")
        for inc in scene.inclusions:
            lab = inc["label"]
            truth = scene.yield_by_label[lab]
            r = s["regions"].get(str(lab), {})
            val = r.get("yield_per_mm")
            ci = r.get("ci95_per_mm")
            corr = (r.get("interval_parts") or {}).get("resolution_corrected_per_mm")
            row = {"seed": scene.seed, "method": method, "label": lab,
                   "target": lab == scene.target(), "segmentation": scene.segmentation,
                   "noise_pct": scene.noise_pct, "depth_mm": inc["depth_mm"],
                   "diameter_mm": 2 * max(inc["radii_mm"]), "truth_per_mm": truth,
                   "yield_per_mm": val,
                   "error_pct": None if val is None else 100.0 * (val - truth) / truth,
                   "resolution_corrected_error_pct": None if corr is None else
                   100.0 * (corr - truth) / truth,
                   # SP: its image's mean over the label, beside the value it quotes
                   "image_mean_per_mm": r.get("image_mean_per_mm"),
                   "sd_pct": None if not r.get("sd_per_mm") or not np.isfinite(
                       r["sd_per_mm"]) else 100.0 * r["sd_per_mm"] / truth,
                   "ci95_per_mm": ci,
                   "ci_half_width_pct": None if ci is None or None in ci else
                   100.0 * (ci[1] - ci[0]) / 2 / truth,
                   "covered": None if ci is None or None in ci else bool(ci[0] <= truth <= ci[1]),
                   "warned": bool(s["warnings"]),
                   "warnings": list(s["warnings"]),
                   "centroid_error_mm": None if cen is None or lab != scene.target() else
                   float(np.linalg.norm(np.asarray(cen) - np.asarray(inc["centre_ras_mm"]))),
                   "misfit": s["solver"]["diagnostics"].get("relative_misfit"),
                   "segmentation_test": s.get("segmentation"),
                   "segmentation_values_per_mm": r.get("segmentation_values_per_mm"),
                   "rigid_move_values_per_mm": r.get("rigid_move_values_per_mm"),
                   "as_segmented_per_mm": r.get("as_segmented_per_mm"),
                   "description": scene.description,
                   "seconds_simulation": t_sim, "seconds_reconstruction": t_rec,
                   "grading": grading or "none",
                   "mesh_nodes": int(out[method]["mesh"].n_nodes)}
            rows.append(row)
    return rows


def _pct(values, q):
    v = np.abs(np.asarray([x for x in values if x is not None], float))
    return None if len(v) == 0 else float(np.percentile(v, q))


def summarise(rows, narrow_pct=20.0):
    """Per method: scenes, median / 90th percentile / worst absolute yield error [%]
    (all rows and the rows whose interval is narrower than +-``narrow_pct``),
    the share with a narrow interval, the coverage of the intervals and the
    share of misses that carried a warning, the centroid's median error."""
    table = {}
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method]
        err = [r["error_pct"] for r in mine]
        narrow = [r for r in mine if r["ci_half_width_pct"] is not None
                  and r["ci_half_width_pct"] < narrow_pct]
        graded = [r for r in mine if r["covered"] is not None]
        missed = [r for r in graded if not r["covered"]]
        cen = [r["centroid_error_mm"] for r in mine if r["centroid_error_mm"] is not None]
        table[method] = {
            "rows": len(mine),
            "median_abs_error_pct": _pct(err, 50), "p90_abs_error_pct": _pct(err, 90),
            "worst_abs_error_pct": _pct(err, 100),
            "narrow_share": len(narrow) / len(mine) if mine else None,
            "narrow_median_abs_error_pct": _pct([r["error_pct"] for r in narrow], 50),
            "narrow_p90_abs_error_pct": _pct([r["error_pct"] for r in narrow], 90),
            "coverage": sum(r["covered"] for r in graded) / len(graded) if graded else None,
            "misses": len(missed),
            "misses_warned": sum(r["warned"] for r in missed),
            "median_ci_half_width_pct": _pct([r["ci_half_width_pct"] for r in mine], 50),
            "median_centroid_error_mm": float(np.median(cen)) if cen else None,
        }
    return table
