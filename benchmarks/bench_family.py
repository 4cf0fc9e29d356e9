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
    ap.add_argument("--accuracy", default="fast", choices=["fast", "balanced", "fine"])
    ap.add_argument("--methods", default="HP,SP")
    ap.add_argument("--json", default=None, help="append the rows here (JSON lines)")
    args = ap.parse_args(argv)

    rows = []
    t_all = time.perf_counter()
    for seed in _seeds(args.seeds):
        scene = make_scene(seed, segmentation_error_mm=args.segmentation_error_mm)
        print(f"scene {seed}: {scene.description} (segmentation {scene.segmentation})",
              flush=True)
        mine = grade_scene(scene, methods=args.methods.split(","), accuracy=args.accuracy,
                           segmentation_mm=args.segmentation_mm)
        for r in mine:
            ci = r["ci_half_width_pct"]
            print(f"  {r['method']} label {r['label']}: error {r['error_pct']:+.1f} %, 95 % "
                  f"interval +-{ci if ci is None else round(ci, 1)} %, holds the truth: "
                  f"{r['covered']}, warned: {r['warned']}", flush=True)
        rows.extend(mine)
        if args.json:
            with open(args.json, "a", encoding="utf-8") as fh:
                for r in mine:
                    fh.write(json.dumps(r) + "\n")
    table = summarise(rows)
    print(f"{len({r['seed'] for r in rows})} scenes, accuracy {args.accuracy}, segmentation "
          f"error {args.segmentation_error_mm:g} mm, {time.perf_counter() - t_all:.0f} s")
    print(json.dumps(table, indent=1))
    return 0
