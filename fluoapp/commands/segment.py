"""``fluo segment --cbct DIR|FILE --thresholds SPEC --out LABELS.nrrd``: a CBCT's
label map by HU thresholds (largest component, holes filled), headless."""

from __future__ import annotations

from fluoapp.cli import add_json_flag
from fluoapp.commands import as_flags, module_logic
from fluoapp.commands.scene import add_cbct_options


def _handler(args):
    from fluoguide.progress import TqdmProgress

    logic = module_logic("FluoTomo")
    with as_flags({"series": "--series", "thresholds": "--thresholds"}), \
            TqdmProgress("segment") as progress:
        return logic.segmentCbctToFile(args.cbct, args.thresholds, args.out, series=args.series,
                                       progress=progress)


def register(sub):
    p = sub.add_parser(
        "segment", help="label map of a CBCT by HU thresholds (the app's threshold tool, "
        "headless)",
        description="Label a CBCT by HU ranges, as the app's threshold tool does, and clean "
        "each label: the voxels within its range (both ends included), its largest "
        "connected component (face neighbours), its holes filled; labels are painted in "
        "the order given, a later one over an earlier one (an inclusion inside the tissue "
        "stays itself). The label map is written on the CBCT's grid (docs/scene.md, "
        "DICOM input).")
    add_cbct_options(p)
    p.add_argument("--thresholds", required=True, metavar="LABEL:MIN:MAX[,...]|FILE.json",
                   help="each label's HU range, e.g. 1:-500:3000,2:60:3000 (labels 1..255, "
                   "painted in this order), or a JSON file {\"1\": [-500, 3000], ...}")
    p.add_argument("--out", required=True, help="the label map to write (.nrrd)")
    add_json_flag(p)
    p.set_defaults(func=_handler)
