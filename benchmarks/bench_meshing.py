"""Meshing speed and quality: fast structured vs quality (fTetWild), same label maps.

For each label map and element size: wall time, nodes, tets, the worst
per-region volume error against the label map, min dihedral angle, slivers
and inverted elements, and the peak memory of the process so far.

    python -m benchmarks meshing [-- --cases cylinder,cylinder-roi,big --sizes 3,2 --threads 2]

Cases: ``cylinder`` (the cylinder-tube phantom, 121 x 121 x 33 at 0.8 mm),
``cylinder-roi`` (its central 40 x 40 mm around the tube), ``big``
(256 x 256 x 192 at 0.8 mm: a 128 x 128 x 96 mm box with a 25 mm sphere).
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def _big_labelmap():
    lab = np.zeros((192, 256, 256), np.uint8)
    lab[36:156, 48:208, 48:208] = 1
    k, j, i = np.ogrid[:192, :256, :256]
    v = 0.8
    r2 = ((i - 127.5) * v) ** 2 + ((j - 127.5) * v) ** 2 + ((k - 95.5) * v) ** 2
    lab[r2 <= 25.0 ** 2] = 2
    return lab, np.array([v, v, v]), np.zeros(3)


def _cases(names):
    from fluoguide.phantoms import make_phantom

    out = []
    ph = None
    for name in names:
        if name in ("cylinder", "cylinder-roi"):
            ph = ph or make_phantom("cylinder-tube")
            roi = None if name == "cylinder" else (-20, 20, -20, 20, -21, 1)
            out.append((name, ph.labels, ph.spacing_mm, ph.origin_mm, roi))
        elif name == "big":
            lab, sp, org = _big_labelmap()
            out.append((name, lab, sp, org, None))
        else:
            raise SystemExit(f"unknown case {name}")
    return out


def _row(name, method, size, mesh, ref, seconds):
    from FluoTomoLib.meshing.report import quality_report

    q = quality_report(mesh, ref)
    errs = {r: e.get("volume_error_pct", float("nan")) for r, e in q["regions"].items()}
    return {"case": name, "method": method, "size_mm": size, "seconds": seconds,
            "nodes": q["nodes"], "tets": q["tets"], "vol_err_pct": errs,
            "min_dihedral_deg": q["min_dihedral_deg"], "slivers": q["slivers"],
            "inverted": q["inverted"],
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def main(argv=None):
    from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality
    from FluoTomoLib.meshing.voxel import labelmap_region_volumes, mesh_labelmap_structured

    ap = argparse.ArgumentParser(prog="benchmarks meshing")
    ap.add_argument("--cases", default="cylinder-roi,cylinder,big")
    ap.add_argument("--sizes", default="2")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--skip-quality", action="store_true")
    args = ap.parse_args(argv or [])
    sizes = [float(s) for s in args.sizes.split(",")]
    rows = []
    for name, lab, sp, org, roi in _cases(args.cases.split(",")):
        for size in sizes:
            t0 = time.perf_counter()
            fast = mesh_labelmap_structured(lab, sp, org, size, roi=roi)
            t_fast = time.perf_counter() - t0
            ref_roi = roi or [v for lo, hi in zip(*fast.bounds()) for v in (lo, hi)]
            ref = labelmap_region_volumes(lab, sp, ref_roi, org)
            rows.append(_row(name, "fast", size, fast, ref, t_fast))
            print(rows[-1], flush=True)
            del fast
            if args.skip_quality:
                continue
            t0 = time.perf_counter()
            try:
                q = mesh_labelmap_quality(lab, sp, org, size, roi=roi, threads=args.threads)
            except Exception as exc:  # report and go on: one case must not hide the others
                print({"case": name, "method": "quality", "size_mm": size, "error": str(exc)})
                continue
            rows.append(_row(name, "quality", size, q, q.meta["labelmap_volumes_mm3"],
                             time.perf_counter() - t0))
            rows[-1]["timing"] = {k: round(v, 1) for k, v in q.meta["timing"].items()}
            print(rows[-1], flush=True)
            del q
    print()
    print("| label map | method | size mm | time s | nodes | tets | volume error % per region "
          "| min dihedral deg | slivers | inverted |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        err = ", ".join(f"{k}: {v:+.2f}" for k, v in sorted(r["vol_err_pct"].items()))
        print(f"| {r['case']} | {r['method']} | {r['size_mm']:g} | {r['seconds']:.1f} | "
              f"{r['nodes']:,} | {r['tets']:,} | {err} | {r['min_dihedral_deg']:.1f} | "
              f"{r['slivers']} | {r['inverted']} |")
    return 0
