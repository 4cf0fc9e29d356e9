"""Per-pixel surface mapping: speed and accuracy (``python -m benchmarks mapping``).

    python -m benchmarks mapping [-- --repeats 5 --binning 10]
"""

from __future__ import annotations

import argparse
import json


def main(argv=None):
    from FluoNavLib.mapping.benchmark import run_mapping_benchmark

    ap = argparse.ArgumentParser(prog="python -m benchmarks mapping")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--binning", type=int, default=10)
    args = ap.parse_args(argv)
    r = run_mapping_benchmark(args.repeats, args.binning)
    print(f"oral cavity, {r['triangles']} triangles, {r['pixels']} pixels (1392 x 1040), medians of "
          f"repeated casts:")
    print(f"  full resolution: {r['fps_full']:.1f} frames/s (raster cast, target 30); Embree BVH "
          f"{r['fps_full_embree']:.1f}; raster cast + illumination model {r['fps_full_with_model']:.1f}")
    print(f"  {r['binning']}x binned ({r['pixels_binned']} pixels): {r['fps_binned']:.0f} frames/s "
          f"(target 300); Embree {r['fps_binned_embree']:.0f}; hit error vs full res median "
          f"{r['binned_hit_error_mm']['median']:.2f} mm, p95 {r['binned_hit_error_mm']['p95']:.2f} mm")
    print(f"  decimated to {r['triangles_decimated']} triangles: {r['fps_decimated']:.1f} frames/s; "
          f"hit error median {r['decimated_hit_error_mm']['median']:.3f} mm, p95 "
          f"{r['decimated_hit_error_mm']['p95']:.3f} mm")
    for m, a in r["reference_accuracy"].items():
        print(f"  {m} vs exact float64 brute force ({a['pixels']} random pixels): face agreement "
              f"{a['face_agreement']:.4f}, mask agreement {a['mask_agreement']:.4f}, hit error max "
              f"{a['hit_error_max_mm']:.1e} mm")
    for k, a in r["distorted_lens"].items():
        print(f"  distorted lens (k1 = -0.25), {k}: {a['fps']:.1f} frames/s; vs Embree mask agreement "
              f"{a['mask_agreement_vs_embree']:.5f}, face agreement {a['face_agreement_vs_embree']:.5f}")
    print("  corrected transport: " + json.dumps(r["transport_accuracy"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
