"""``fluo scene info SCENE.mrml``: what a scene holds (nodes, attributes, data);
``fluo scene import --cbct DIR|FILE --out DIR``: a scene made from a CBCT (a DICOM
series folder or a volume file)."""

from __future__ import annotations

from fluoguide import mrml_io
from fluoapp.cli import add_json_flag, cli_group
from fluoapp.commands import as_flags, module_logic


def _info(args):
    import vtk

    scene = mrml_io.load_scene(args.scene)
    out = []
    # one pass over the nodes (a name lookup per node was quadratic in the scene size)
    for node, item in zip(mrml_io.data_nodes(scene), mrml_io.node_summary(scene)):
        if node.IsA("vtkMRMLVolumeNode") and node.GetImageData() is not None:
            geo = mrml_io.volume_geometry(node)
            item["dimensions_ijk"] = list(node.GetImageData().GetDimensions())
            item["spacing_mm"] = geo["spacing"].tolist()
            item["origin_mm"] = geo["origin"].tolist()
        elif node.IsA("vtkMRMLModelNode") and node.GetPolyData() is not None:
            item["points"] = node.GetPolyData().GetNumberOfPoints()
            item["cells"] = node.GetPolyData().GetNumberOfCells()
        elif node.IsA("vtkMRMLLinearTransformNode"):
            vm = vtk.vtkMatrix4x4()
            node.GetMatrixTransformToParent(vm)
            item["matrix_to_parent"] = [[vm.GetElement(i, j) for j in range(4)] for i in range(4)]
            parent = node.GetParentTransformNode()
            item["parent"] = parent.GetName() if parent is not None else None
        # Attributes can hold whole JSON documents: list their keys only.
        item["attributes"] = sorted(item["attributes"])
        out.append(item)
    return {"scene": str(args.scene), "nodes": out}


def _import(args):
    with as_flags({"series": "--series"}):
        return module_logic("FluoTomo").importCbctToScene(args.cbct, args.out, series=args.series)


def add_cbct_options(p):
    """``--cbct`` and ``--series``: every command that takes a CBCT takes them alike."""
    p.add_argument("--cbct", required=True,
                   help="the CBCT: a folder of DICOM files (one slice per file), a volume file "
                   "(NRRD, NIfTI) or a scene (.mrml, its CBCT node)")
    p.add_argument("--series", default=None, metavar="UID",
                   help="the SeriesInstanceUID to read when the DICOM folder holds several "
                   "(default: the folder's only series; several are listed in the refusal)")


def register(sub):
    g = cli_group(sub, "scene", "inspect MRML scenes")
    p = g.add_parser("info", help="list the nodes of a scene with their data and attributes")
    p.add_argument("scene", help="scene file (.mrml)")
    add_json_flag(p)
    p.set_defaults(func=_info)
    p = g.add_parser("import", help="make a scene (scene.mrml, CBCT.nrrd) from a CBCT: a DICOM "
                     "series folder or a volume file",
                     description="Read a CBCT (a DICOM series: slices sorted along the slice "
                     "normal, values rescaled to HU, origin, spacing and direction kept; or a "
                     "NRRD/NIfTI file) and write OUT/scene.mrml with the volume node CBCT, "
                     "which the other commands and the app take. A series that cannot be "
                     "read without guessing (mixed series, missing or duplicated slices, "
                     "non-uniform spacing, gantry tilt, non-image objects) is refused "
                     "(docs/scene.md, DICOM input).")
    add_cbct_options(p)
    p.add_argument("--out", required=True, help="scene folder (created; its scene replaced)")
    add_json_flag(p)
    p.set_defaults(func=_import)
