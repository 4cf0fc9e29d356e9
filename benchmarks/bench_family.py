"""The label-map tomography on the seeded scene family (issue #31; docs/validation.md,
"The scene family"): per method the median, 90th percentile and worst |yield error|,
the share of regions whose 95 % interval is narrower than +-20 % and their errors,
the coverage of the intervals (how often they hold the truth) and how many misses
carried a warning, the centroid's median error, and the time per scene.

Each scene (``FluoTomoLib.validation.family.make_scene(seed)``) is simulated on its
TRUE label map with the simulation's own whole-map mesh at the ``fine`` level and
its own noise, then reconstructed with HP and SP on the label map handed over
(with ``--segmentation-error-mm``: its inclusions dilated, eroded or shifted by
that much) at ``--accuracy``. Threads are pinned to one. Rows go to ``--json``
(one JSON object per region and method) as they finish, so a long run can be
read while it goes.

    python -m benchmarks family -- --seeds 1-24 --accuracy fast --json family.jsonl
    python -m benchmarks family -- --seeds 101-112 --segmentation-error-mm 1 --json seg.jsonl
    python -m benchmarks family -- --seeds 101-112 --segmentation-error-mm 1 \
        --segmentation-mm 1 --json seg1.jsonl      # the error stated to the reconstruction
    python -m benchmarks family -- --seeds 1-8 --scan plan,default --json plan.jsonl
    python -m benchmarks family -- --seeds 1-12 --grading none,bisection --json graded.jsonl
    python -m benchmarks family -- --seeds 1-12 --grading bisection \
        --accuracy fast,balanced,fine --json levels.jsonl     # the levels' trade

``--grading none,bisection`` simulates each scene once and reconstructs it on the
uniform grid and on the mesh graded by bisection (each row carries its ``grading``,
``mesh_nodes`` and seconds); the table is then one per mesh. ``--accuracy
fast,balanced,fine`` does the same for the accuracy levels (each row carries its
``accuracy``).

``--scan plan`` (issue #36) plans the laser positions on the label map handed over
(``tomography.plan.plan_scan``: every inclusion a target, as many positions as the
default scan lays, the scene's stated noise, the planner's default assumed yields)
and simulates that scan instead of the default grid; ``--scan plan,default`` runs
both on each scene. Each row then carries the scan, the plan's predicted HP 95 %
half-width (``predicted_half_width_pct``; for the default scan the same model's
prediction for the default grid), the prediction with the scene's true yields
(``predicted_true_half_width_pct``) and the reconstruction's own noise part
(``noise_half_width_pct``, 1.96 SD).
"""

from __future__ import annotations

import argparse
import json
import os
import time

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")


def _seeds(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def main(argv=None):
    from FluoTomoLib.validation import grade_scene, make_scene, summarise

    ap = argparse.ArgumentParser(prog="python -m benchmarks family")
    ap.add_argument("--seeds", default="1-6", help="scenes, e.g. 1-24 or 3,5,9")
    ap.add_argument("--segmentation-error-mm", type=float, default=0.0)
    ap.add_argument("--segmentation-mm", type=float, default=None,
                    help="the segmentation's accuracy stated to the reconstruction [mm] "
                    "(default: its own, half the largest voxel side)")
    ap.add_argument("--accuracy", default="fast",
                    help="fast, balanced, fine or a list of them (each scene simulated "
                    "once and reconstructed at each level)")
    ap.add_argument("--methods", default="HP,SP")
    ap.add_argument("--json", default=None, help="append the rows here (JSON lines)")
    ap.add_argument("--scan", default="default", help="default, plan, or plan,default")
    ap.add_argument("--grading", default="none",
                    help="reconstruction meshes, e.g. none,bisection: each scene simulated "
                         "once and reconstructed on each (none: the uniform grid)")
    ap.add_argument("--plan-time-s", type=float, default=30.0,
                    help="the planner's time budget per scene [s]")
    args = ap.parse_args(argv)
    scans = [v.strip() for v in args.scan.split(",") if v.strip()]
    if not scans or any(v not in ("default", "plan") for v in scans):
        ap.error("--scan: default, plan or plan,default")

    levels = [v.strip() for v in args.accuracy.split(",") if v.strip()]
    if not levels or any(v not in ("fast", "balanced", "fine") for v in levels):
        ap.error("--accuracy: fast, balanced, fine or a list of them")
    gradings = [v.strip() for v in args.grading.split(",") if v.strip()]
    if not gradings or any(v not in ("none", "bisection", "grid") for v in gradings):
        ap.error("--grading: none, grid, bisection or a list of them")
    if (gradings != ["none"] or len(levels) > 1) and scans != ["default"]:
        ap.error("--grading or several --accuracy levels with --scan plan: not supported "
                 "(the planned scans are reconstructed on the uniform grid at one level)")
    combos = [(g, a) for g in gradings for a in levels]
    rows = []
    t_all = time.perf_counter()
    for seed in _seeds(args.seeds):
        scene = make_scene(seed, segmentation_error_mm=args.segmentation_error_mm)
        print(f"scene {seed}: {scene.description} (segmentation {scene.segmentation})",
              flush=True)
        if scans == ["default"]:
            from FluoTomoLib.validation.family import simulate

            acq = simulate(scene)[0] if len(combos) > 1 else None
            mine = []
            for g, level in combos:
                got = grade_scene(scene, methods=args.methods.split(","),
                                  accuracy=level, acquisition=acq,
                                  segmentation_mm=args.segmentation_mm,
                                  grading=False if g == "none" else g)
                for r in got:
                    r["accuracy"] = level
                mine += got
        else:
            mine = []
            for scan in scans:
                mine += _graded_scan(scene, scan, args)
        for r in mine:
            ci = r["ci_half_width_pct"]
            print(f"  {r['grading']}, {r.get('accuracy', levels[0])} ({r['mesh_nodes']} nodes, "
                  f"{r['seconds_reconstruction']:.0f} s) "
                  f"{r['method']} label {r['label']}: error {r['error_pct']:+.1f} %, 95 % "
                  f"interval +-{ci if ci is None else round(ci, 1)} %, holds the truth: "
                  f"{r['covered']}, warned: {r['warned']}", flush=True)
        rows.extend(mine)
        if args.json:
            with open(args.json, "a", encoding="utf-8") as fh:
                for r in mine:
                    fh.write(json.dumps(r) + "\n")
    if scans != ["default"]:
        table = {scan: _summary(summarise([r for r in rows if r["scan"] == scan]),
                                [r for r in rows if r["scan"] == scan]) for scan in scans}
        print(f"{len({r['seed'] for r in rows})} scenes, accuracy {args.accuracy}, "
              f"{time.perf_counter() - t_all:.0f} s")
        print(json.dumps(table, indent=1))
        return 0
    if len(combos) > 1:
        import numpy as np

        table = {}
        for g, level in combos:
            mine = [r for r in rows if r["grading"] == g and r["accuracy"] == level]
            key = g if len(levels) == 1 else level if len(gradings) == 1 else f"{g}, {level}"
            table[key] = summarise(mine)
            table[key]["median_nodes"] = float(np.median([r["mesh_nodes"] for r in mine]))
            table[key]["median_seconds"] = float(np.median([r["seconds_reconstruction"]
                                                            for r in mine]))
        print(json.dumps(table, indent=1))
        return 0
    table = summarise(rows)
    print(f"{len({r['seed'] for r in rows})} scenes, accuracy {args.accuracy}, segmentation "
          f"error {args.segmentation_error_mm:g} mm, {time.perf_counter() - t_all:.0f} s")
    print(json.dumps(table, indent=1))
    return 0


def _graded_scan(scene, scan, args):
    """One scene simulated with the default grid or a planned scan (the same number
    of laser positions), reconstructed and graded; each row with the plan's
    predicted HP half-width for that scan."""
    import numpy as np

    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.plan import plan_scan, predict_scan
    from FluoTomoLib.tomography.simulate import default_scan, scan_pairs
    from FluoTomoLib.validation import grade_scene
    from FluoTomoLib.validation.family import simulate

    lm = scene.labelmap(recon=True)
    optics = optics_from_dict(scene.optics)
    targets = [int(i["label"]) for i in scene.inclusions]
    t0 = time.perf_counter()
    plan = plan_scan(lm, optics, targets, noise_pct=scene.noise_pct,
                     time_budget_s=args.plan_time_s)
    t_plan = time.perf_counter() - t0
    truth = {int(k): float(v) for k, v in scene.yield_by_label.items()}
    if scan == "plan":
        src, det = plan["sources_ras"], plan["detectors_ras"]
        predicted = plan["predicted"]["HP"]
        true_pred = predict_scan(lm, optics, src, det, targets, None, truth, scene.noise_pct)
        acq, _ = simulate(scene, sources_ras=src, detectors_ras=det)
    else:
        s, d, cfg = default_scan(lm, targets)
        predicted = plan["default_scan_predicted"]["HP"]
        true_pred = predict_scan(lm, optics, s, d, targets, scan_pairs(cfg, len(s), len(d)),
                                 truth, scene.noise_pct)
        acq, _ = simulate(scene)
    rows = grade_scene(scene, methods=args.methods.split(","), accuracy=args.accuracy,
                       acquisition=acq, segmentation_mm=args.segmentation_mm)
    for r in rows:
        lab = str(r["label"])
        r["scan"] = scan
        r["positions"] = len(acq.sources_ras_mm)
        r["pairs"] = int(np.sum(acq.mask))
        r["predicted_half_width_pct"] = predicted[lab]["half_width_pct"]
        r["predicted_true_half_width_pct"] = true_pred[lab]["half_width_pct"]
        r["noise_half_width_pct"] = None if r["sd_pct"] is None else 1.959964 * r["sd_pct"]
        r["seconds_plan"] = t_plan
    return rows


def _pct(values, q):
    import numpy as np

    v = [abs(x) for x in values if x is not None]
    return None if not v else float(np.percentile(v, q))


def _summary(table, rows):
    """The family's table per method, with the predicted half-widths against the
    reconstruction's own noise part (median ratio) for this scan."""
    for method, t in table.items():
        mine = [r for r in rows if r["method"] == method]
        ratio = [r["predicted_true_half_width_pct"] / r["noise_half_width_pct"] for r in mine
                 if r["noise_half_width_pct"] and r["predicted_true_half_width_pct"]]
        t.update({"pairs_median": _pct([r["pairs"] for r in mine], 50),
                  "median_predicted_half_width_pct":
                  _pct([r["predicted_half_width_pct"] for r in mine], 50),
                  "median_predicted_true_half_width_pct":
                  _pct([r["predicted_true_half_width_pct"] for r in mine], 50),
                  "median_noise_half_width_pct": _pct([r["noise_half_width_pct"]
                                                       for r in mine], 50),
                  "predicted_over_noise_median": _pct(ratio, 50),
                  "predicted_over_noise_p10_p90": [_pct(ratio, 10), _pct(ratio, 90)]})
    return table
