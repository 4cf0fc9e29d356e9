"""``fluo mesh LABELMAP --out MESH.vtu``: label map to a tetrahedral mesh with regions."""

from __future__ import annotations

import time
from pathlib import Path

from fluoguide.cli import add_json_flag
from fluoguide.errors import FluoInputError


def _read_labelmap(path):
    """(labels_kji, spacing, origin, direction) from a NRRD/NIfTI file or an MRML
    scene's ``CBCTLabels`` node; RAS coordinates."""
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise FluoInputError("label map file not found", file=p)
    if p.suffix == ".mrml":
        from fluoguide import mrml_io

        node = mrml_io.get_node(mrml_io.load_scene(p), "CBCTLabels", "vtkMRMLLabelMapVolumeNode")
        geo = mrml_io.volume_geometry(node)
        return mrml_io.volume_array(node), geo["spacing"], geo["origin"], geo["direction"]
    import SimpleITK as sitk

    try:
        img = sitk.ReadImage(str(p))
    except RuntimeError as exc:
        raise FluoInputError(f"cannot read label map ({str(exc).splitlines()[0][:120]})",
                             file=p) from None
    arr = sitk.GetArrayFromImage(img)
    if arr.ndim != 3 or not np.issubdtype(arr.dtype, np.integer):
        raise FluoInputError("label map must be a 3D integer image", file=p,
                             value=(arr.shape, str(arr.dtype)))
    # ITK is LPS; MRML/FluoGuide are RAS: flip x and y of origin and directions
    lps_to_ras = np.diag([-1.0, -1.0, 1.0])
    direction = lps_to_ras @ np.array(img.GetDirection()).reshape(3, 3)
    origin = lps_to_ras @ np.array(img.GetOrigin())
    return arr, np.array(img.GetSpacing()), origin, direction


def _handler(args):
    import numpy as np

    from .mesh_quality import quality_report
    from .voxel_mesh import labelmap_region_volumes, mesh_labelmap_structured
    from .vtu_io import write_vtu

    if not args.fast:
        raise FluoInputError("only the fast structured mesher is available so far (the "
                             "pytetwild quality mesher is open work): add --fast",
                             field="--fast")
    t0 = time.perf_counter()
    labels, spacing, origin, direction = _read_labelmap(args.labelmap)
    roi = None
    if args.roi:
        try:
            roi = [float(v) for v in args.roi.split(",")]
        except ValueError:
            raise FluoInputError("expected x0,x1,y0,y1,z0,z1 in mm", field="--roi",
                                 value=args.roi) from None
        if len(roi) != 6:
            raise FluoInputError("expected six numbers x0,x1,y0,y1,z0,z1", field="--roi",
                                 value=args.roi)
    mesh = mesh_labelmap_structured(labels, spacing, origin, args.size, roi=roi,
                                    direction=direction)
    if roi is None:
        lo, hi = mesh.bounds()
        roi = [lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]]
    ref = labelmap_region_volumes(labels, spacing, roi, origin) if np.allclose(
        np.abs(direction), np.eye(3)) and np.all(np.diag(direction) > 0) else None
    report = quality_report(mesh, ref)
    write_vtu(mesh, args.out)
    report["file"] = str(Path(args.out).resolve())
    report["method"] = "structured (Kuhn, 6 tets per cell)"
    report["seconds"] = time.perf_counter() - t0
    return report


def register(sub):
    p = sub.add_parser("mesh", help="label map to a tetrahedral mesh with region labels",
                       description="Label map (NRRD/NIfTI, or an MRML scene's CBCTLabels) to a "
                       "tetrahedral .vtu mesh; prints counts, per-region volumes against the "
                       "label map, dihedral angles, inverted and sliver elements.")
    p.add_argument("labelmap", help="label map file (.nrrd, .nii.gz) or scene (.mrml)")
    p.add_argument("--out", required=True, help="output mesh (.vtu)")
    p.add_argument("--size", type=float, default=1.6, help="element size [mm] (default 1.6)")
    p.add_argument("--roi", default=None, help="crop first: x0,x1,y0,y1,z0,z1 (RAS mm); write --roi=-10,10,... "
                   "when the first value is negative")
    p.add_argument("--fast", action="store_true", help="structured voxel-to-tet mesher")
    add_json_flag(p)
    p.set_defaults(func=_handler)
