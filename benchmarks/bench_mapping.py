"""Per-pixel surface mapping: speed and accuracy (``python -m benchmarks mapping``).

    python -m benchmarks mapping [-- --repeats 5 --binning 10]
"""

from __future__ import annotations

import argparse
import json


def main(argv=None):
    from FluoNavLib.mapping_bench import run_mapping_benchmark

    ap = argparse.ArgumentParser(prog="python -m benchmarks mapping")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--binning", type=int, default=10)
    args = ap.parse_args(argv)
    r = run_mapping_benchmark(args.repeats, args.binning)
    print(f"oral cavity, {r['triangles']} triangles, {r['pixels']} pixels (1392 x 1040), medians of "
          f"{r['repeats']}:")
    print(f"  full resolution: {r['fps_full']:.1f} frames/s (cast), {r['fps_full_with_model']:.1f} "
          f"with the illumination model (target 30)")
    print(f"  {r['binning']}x binned ({r['pixels_binned']} pixels): {r['fps_binned']:.0f} frames/s "
          f"(target 300); hit error vs full res median {r['binned_hit_error_mm']['median']:.2f} mm, "
          f"p95 {r['binned_hit_error_mm']['p95']:.2f} mm")
    print(f"  decimated to {r['triangles_decimated']} triangles: {r['fps_decimated']:.1f} frames/s; "
          f"hit error median {r['decimated_hit_error_mm']['median']:.3f} mm, p95 "
          f"{r['decimated_hit_error_mm']['p95']:.3f} mm")
    print("  corrected transport: " + json.dumps(r["transport_accuracy"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
