"""``fluo scene info SCENE.mrml``: what a scene holds (nodes, attributes, data)."""

from __future__ import annotations

from fluoguide import mrml_io
from fluoapp.cli import add_json_flag, cli_group


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


def register(sub):
    g = cli_group(sub, "scene", "inspect MRML scenes")
    p = g.add_parser("info", help="list the nodes of a scene with their data and attributes")
    p.add_argument("scene", help="scene file (.mrml)")
    add_json_flag(p)
    p.set_defaults(func=_info)
