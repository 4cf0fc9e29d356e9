"""The accuracy levels of the label-map pipeline (``--accuracy fast|balanced|fine``):
error and time of each, on the ellipsoid scene of issue #17.

Scene: an ellipsoidal body (56 x 44 x 28 mm, label 3) with a 6 mm spherical
inclusion (label 7, 2 ug/mL ICG: yield 2.6e-3 /mm, its absorption included)
4 mm below the curved top surface, on a 0.5 x 0.6 x 0.7 mm grid with the
direction diag(-1, -1, 1) and the origin at (120, -80, 340) mm.  The
acquisition is simulated once on a finer mesh of the whole label map
(``--simulate-mm``, default 0.5 mm near the optodes, 1.25 mm elsewhere) with
1 % noise; each level then reconstructs it with HP and SP.  Printed per level
and method: the inclusion's yield error, the distance of the half-maximum
centroid from the inclusion's centre, whether the peak voxel lies in the
inclusion, the reconstruction mesh and the wall time (median of ``--repeats``).
Threads are pinned to one (OMP/MKL/OpenBLAS/numba) unless the caller set them.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

TRUE_YIELD = 2.6e-3


def main(argv=None):
    import numpy as np

    from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics
    from FluoTomoLib.tomography import (LabelMap, optics_from_dict, reconstruct_labelmap,
                                        simulate_acquisition)

    ap = argparse.ArgumentParser(prog="python -m benchmarks own_scene")
    ap.add_argument("--levels", default="fast,balanced,fine,balanced:grading",
                    help="accuracy levels; LEVEL:grading adds optode-aware grading")
    ap.add_argument("--methods", default="HP,SP")
    ap.add_argument("--simulate-mm", type=float, default=0.5)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--background-yield", type=float, default=0.0)
    ap.add_argument("--json", default=None, help="also write the rows here")
    args = ap.parse_args(argv)

    sc = ellipsoid_inclusion_labelmap()
    lm = LabelMap(sc["labels_kji"], sc["spacing_mm"], sc["origin_mm"], sc["direction"])
    optics = optics_from_dict(ellipsoid_inclusion_optics())
    t0 = time.perf_counter()
    acq, info = simulate_acquisition(lm, optics, {3: args.background_yield, 7: TRUE_YIELD},
                                     noise_pct=1.0, seed=1, accuracy="fine",
                                     simulate_mm=args.simulate_mm)
    print(f"simulation: {info['mesh_nodes']} nodes, {acq.n_measurements} measurements, "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    centre = sc["inclusion_centre_ras_mm"]
    rows = []
    for spec in args.levels.split(","):
        level, _, opt = spec.partition(":")
        for method in args.methods.split(","):
            times, out = [], None
            for _ in range(args.repeats):
                t = time.perf_counter()
                out = reconstruct_labelmap(lm, optics, acq, method=method, accuracy=level,
                                           grading=opt == "grading")
                times.append(time.perf_counter() - t)
            s = out["summary"]
            inc = s["regions"]["7"]["yield_per_mm"]
            cen = np.array(s["target_centroid_ras_mm"])
            row = {"level": spec, "method": method,
                   "yield_error_pct": 100.0 * (inc - TRUE_YIELD) / TRUE_YIELD,
                   "centroid_error_mm": float(np.linalg.norm(cen - centre)),
                   "peak_in_inclusion": s["peak_label"] == 7,
                   "nodes": s["mesh"]["nodes"], "measurements": s["measurements"],
                   "seconds_median": statistics.median(times),
                   "timings": s["timings"], "warnings": s["warnings"]}
            rows.append(row)
            print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v)
                              for k, v in row.items() if k != "timings"}), flush=True)
    if args.json:
        from pathlib import Path

        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0
