"""Reconstruct the fluorescence yield of your own label map and save a scene.

    python docs/examples/reconstruct_own_labelmap.py LABELS.nrrd optics.json ACQ/ OUT/
    python docs/examples/reconstruct_own_labelmap.py --make-example OUT/   (writes inputs too)

``python``: the virtual environment's, after ``make venv`` (``.venv/bin/python``, or
``python`` with ``.venv`` activated), from any folder: ``FluoTomo`` is imported as
installed, as 3D Slicer imports it.

Inputs (docs/tomography-own-scene.md): a label map (.nrrd, .nii.gz or a 3D
Slicer .seg.nrrd; any direction, spacing and origin), ``optics.json`` (optical
properties per label) and an acquisition folder (sources, detectors, data).
Output: ``OUT/scene.mrml`` with the label map, the reconstruction mesh
(``FluoTomoMesh``) and one yield volume per method (``FluoTomoYieldHP``, ...)
on the label map's grid, each with its summary as the attribute
``FluoTomo.Reconstruction``; open it in 3D Slicer or ``fluo app --scene``.

Everything goes through ``FluoTomoLogic``, the API the desktop widget, the
web app and ``fluo tomo`` use: node objects in, output nodes out.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def make_example(folder, accuracy="fast"):
    """An ellipsoidal body (label 3) with a 6 mm inclusion (label 7) 4 mm under
    its curved top, on a 0.8 x 0.9 x 1.0 mm grid with the direction
    diag(-1, -1, 1), its optics.json and a simulated acquisition (the
    simulation meshes the whole label map, finer than a reconstruction)."""
    from fluoguide import mrml_io
    from fluoguide.labelmap_io import write_volume_nrrd
    from fluoguide.phantoms import ellipsoid_inclusion_labelmap
    from FluoTomo import FluoTomoLogic

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sc = ellipsoid_inclusion_labelmap(semi_axes_mm=(16.0, 13.0, 9.0), spacing_mm=(0.8, 0.9, 1.0),
                                      inclusion_gap_mm=3.0, inclusion_offset_mm=(1.0, -1.0))
    write_volume_nrrd(folder / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"],
                      sc["origin_mm"], sc["direction"])
    optics = {"n": 1.37, "fluorophore": "ICG", "names": {"3": "tissue", "7": "tumour"},
              "excitation": {"3": {"mua_per_mm": 0.01, "musp_per_mm": 1.0},
                             "7": {"mua_per_mm": 0.012, "musp_per_mm": 1.1}},
              "emission": {"3": {"mua_per_mm": 0.008, "musp_per_mm": 0.9},
                           "7": {"mua_per_mm": 0.01, "musp_per_mm": 1.0}}}
    (folder / "optics.json").write_text(json.dumps(optics, indent=2))
    logic = FluoTomoLogic(mrml_io.new_scene())
    labels = logic.loadLabelMap(folder / "labels.nrrd")
    logic.simulateAcquisition(labels, folder / "optics.json", {7: 0.0026}, noise=1.0, seed=0,
                              accuracy=accuracy, outputFolder=folder / "acquisition")
    return (folder / "labels.nrrd", folder / "optics.json", folder / "acquisition",
            sc["inclusion_centre_ras_mm"])


def reconstruct(labels_path, optics_path, acquisition, out_dir, methods=("HP", "SP"),
                accuracy="balanced"):
    """Label map + acquisition in, ``out_dir/scene.mrml`` out; returns the summaries."""
    from fluoguide import mrml_io
    from FluoTomo import FluoTomoLogic

    scene = mrml_io.new_scene()
    logic = FluoTomoLogic(scene)
    labels = logic.loadLabelMap(labels_path)
    # the mesh the reconstructions use (region of interest from the optodes)
    mesh = logic.buildMesh(labels, acquisition=acquisition, optics=optics_path,
                           accuracy=accuracy)
    summaries = {}
    for method in methods:
        summary, node = logic.reconstruct(labels, optics_path, acquisition, method=method,
                                          meshNode=mesh, accuracy=accuracy)
        summaries[method] = summary
        print(f"{method}: {node.GetName()}: target label {summary['target']} yield "
              f"{summary['regions'][str(summary['target'])]['yield_per_mm']:.4g} /mm, peak at "
              f"RAS {[round(v, 1) for v in summary['peak_ras_mm']]} (label "
              f"{summary['peak_label']}), {summary['seconds']:.1f} s; warnings: "
              f"{summary['warnings'] or 'none'}")
    path = mrml_io.save_scene(scene, Path(out_dir) / "scene.mrml")
    print(f"saved {path}")
    return summaries


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="*", help="LABELS optics.json ACQUISITION OUT")
    ap.add_argument("--make-example", metavar="OUT", help="write example inputs into OUT and "
                    "reconstruct them")
    ap.add_argument("--accuracy", default="balanced", choices=["fast", "balanced", "fine"])
    ap.add_argument("--methods", default="HP,SP")
    args = ap.parse_args(argv)
    methods = tuple(args.methods.split(","))
    if args.make_example:
        out = Path(args.make_example)
        labels, optics, acq, centre = make_example(out / "inputs", accuracy=args.accuracy)
        print(f"example inputs in {out / 'inputs'}; inclusion centre RAS "
              f"{[round(v, 2) for v in centre]}")
        reconstruct(labels, optics, acq, out, methods, args.accuracy)
        return 0
    if len(args.inputs) != 4:
        ap.error("give LABELS optics.json ACQUISITION OUT, or --make-example OUT")
    reconstruct(*args.inputs, methods=methods, accuracy=args.accuracy)
    return 0


if __name__ == "__main__":
    from fluoguide.errors import FluoInputError

    try:
        sys.exit(main())
    except FluoInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
