"""MRML scene helpers: the one shared state between FluoCalib, FluoNav and FluoTomo.

Real MRML from slicer-core (``slicer.vtkMRMLScene``), so a scene written here
opens in 3D Slicer and one saved by Slicer loads here.  Every function takes the
scene explicitly: nothing relies on a global ``slicer.mrmlScene``.

Coordinate conventions follow Slicer: volumes and models are in RAS mm,
transforms are ``AToB`` (maps coordinates of frame A into frame B, stored as
the node's "transform to parent").  Node names are listed in docs/scene.md.

Saving is atomic per scene: storage files and the ``.mrml`` are written into a
staging folder next to the target and moved in as one journaled transaction
(``fluoguide.atomic``): a failed or killed save leaves the old scene or the new
one, never a mix. Loading refuses data paths that leave the scene's folder,
anything that is not a regular file, corrupt models and transforms, and
transform cycles.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from fluoguide import atomic
from fluoguide.errors import FluoInputError
from fluoguide.jsonable import to_jsonable


def _slicer():
    # Imported lazily: importing slicer-core loads VTK/MRML (~0.5 s).
    import slicer

    return slicer


def _vtk():
    import vtk

    return vtk


# ---------------------------------------------------------------- scene

def new_scene():
    """A new, empty ``vtkMRMLScene``."""
    return _slicer().vtkMRMLScene()


def nodes(scene, class_name="vtkMRMLNode"):
    """All nodes of a class (including subclasses) in scene order."""
    out = []
    col = scene.GetNodesByClass(class_name)
    for i in range(col.GetNumberOfItems()):
        out.append(col.GetItemAsObject(i))
    return out


def get_node(scene, name, class_name=None, required=True):
    """The first node called ``name`` (optionally of ``class_name``)."""
    for node in nodes(scene, class_name or "vtkMRMLNode"):
        if node.GetName() == name:
            return node
    if required:
        raise FluoInputError("node not found in scene", field=name,
                             file=scene.GetURL() or None)
    return None


def _get_or_add(scene, class_name, name):
    node = get_node(scene, name, class_name, required=False)
    if node is None:
        node = getattr(_slicer(), class_name)()
        node.SetName(name)
        scene.AddNode(node)
    return node


def remove_node(scene, name):
    node = get_node(scene, name, required=False)
    if node is not None:
        for i in range(node.GetNumberOfStorageNodes() if hasattr(node, "GetNumberOfStorageNodes") else 0):
            sn = node.GetNthStorageNode(i)
            if sn is not None:
                scene.RemoveNode(sn)
        scene.RemoveNode(node)


_SUMMARY_SKIP = ("vtkMRMLSubjectHierarchyNode", "vtkMRMLStorageNode", "vtkMRMLDisplayNode",
                 "vtkMRMLSelectionNode", "vtkMRMLInteractionNode", "vtkMRMLColorTableNode")


def data_nodes(scene):
    """The nodes a person would call the scene's data (no display, storage, hierarchy ... nodes)."""
    return [node for node in nodes(scene)
            if not any(node.IsA(c) for c in _SUMMARY_SKIP)
            and not (node.GetHideFromEditors() and not node.GetName())]


def node_summary(scene):
    """List of dicts (name, class, attributes) of the data nodes in a scene."""
    out = []
    for node in data_nodes(scene):
        attrs = {key: node.GetAttribute(key) for key in (node.GetAttributeNames() or ())}
        out.append({"name": node.GetName(), "class": node.GetClassName(), "attributes": attrs})
    return out


# ---------------------------------------------------------------- attributes

def set_json_attribute(node, key, obj):
    """Store a JSON-serialisable object as a node attribute (saved in the .mrml)."""
    node.SetAttribute(key, json.dumps(to_jsonable(obj), separators=(",", ":")))


def get_json_attribute(node, key, default=None):
    text = node.GetAttribute(key)
    if text is None:
        return default
    from fluoguide.jsonable import loads

    try:
        # a key twice (hand-edited .mrml) is refused, not resolved to the last
        return loads(text, field=f"{node.GetName()}.{key}")
    except json.JSONDecodeError as exc:
        raise FluoInputError(f"attribute is not valid JSON ({exc.msg})",
                             field=f"{node.GetName()}.{key}") from None
    except RecursionError:  # a hostile scene: JSON nested thousands deep
        raise FluoInputError("attribute is JSON nested too deeply to read",
                             field=f"{node.GetName()}.{key}") from None


# ---------------------------------------------------------------- transforms

def _matrix_to_vtk(matrix):
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise FluoInputError("transform must be a finite 4x4 matrix", field="matrix", value=m.shape)
    vm = _vtk().vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            vm.SetElement(i, j, float(m[i, j]))
    return vm


def _vtk_to_matrix(vm):
    return np.array([[vm.GetElement(i, j) for j in range(4)] for i in range(4)])


def set_transform(scene, name, matrix, parent=None):
    """Create or update linear transform node ``name`` (``AToB``: maps A into B).

    Parameters
    ----------
    matrix : (4, 4) array, homogeneous, mm
    parent : str, optional
        Name of a transform node to nest under (SlicerIGT chains such as
        ``CameraToolToTracker`` under ``TrackerToReference``).
    """
    node = _get_or_add(scene, "vtkMRMLLinearTransformNode", name)
    node.SetMatrixTransformToParent(_matrix_to_vtk(matrix))
    if parent is not None:
        node.SetAndObserveTransformNodeID(get_node(scene, parent).GetID())
    return node


def set_transform_matrix(node, matrix):
    """Set a linear transform node's matrix to parent (finite 4x4, mm); returns the node."""
    if node is None or not node.IsA("vtkMRMLLinearTransformNode"):
        raise FluoInputError("not a linear transform node", field=getattr(node, "GetName", str)()
                             if node is not None else "transform")
    node.SetMatrixTransformToParent(_matrix_to_vtk(matrix))
    return node


def transform_matrix(node):
    """The 4x4 matrix (to parent) of a linear transform node."""
    vm = _vtk().vtkMatrix4x4()
    node.GetMatrixTransformToParent(vm)
    return _vtk_to_matrix(vm)


def get_transform(scene, name):
    """The 4x4 matrix (to parent) of linear transform node ``name``."""
    node = get_node(scene, name, "vtkMRMLLinearTransformNode")
    vm = _vtk().vtkMatrix4x4()
    node.GetMatrixTransformToParent(vm)
    return _vtk_to_matrix(vm)


def get_transform_to_world(scene, name):
    """The 4x4 matrix of ``name`` composed with all its parents (to RAS world)."""
    node = get_node(scene, name, "vtkMRMLLinearTransformNode")
    vm = _vtk().vtkMatrix4x4()
    node.GetMatrixTransformToWorld(vm)
    return _vtk_to_matrix(vm)


# ---------------------------------------------------------------- volumes

_VTK_TYPES = {
    np.dtype(np.uint8): "VTK_UNSIGNED_CHAR",
    np.dtype(np.int8): "VTK_SIGNED_CHAR",
    np.dtype(np.int16): "VTK_SHORT",
    np.dtype(np.uint16): "VTK_UNSIGNED_SHORT",
    np.dtype(np.int32): "VTK_INT",
    np.dtype(np.uint32): "VTK_UNSIGNED_INT",
    np.dtype(np.float32): "VTK_FLOAT",
    np.dtype(np.float64): "VTK_DOUBLE",
}


def add_volume(scene, name, array_kji, spacing, origin, direction=None, labelmap=False):
    """Create or replace a scalar (or label-map) volume node from a numpy array.

    Parameters
    ----------
    array_kji : (K, J, I) array, indexed [slice, row, column] as in Slicer's
        ``arrayFromVolume``
    spacing : 3 floats, mm (I, J, K order)
    origin : 3 floats, RAS mm of voxel (0, 0, 0)
    direction : (3, 3) IJK-to-RAS direction cosines (columns = I, J, K axes);
        identity if None
    labelmap : bool, make a ``vtkMRMLLabelMapVolumeNode``
    """
    cls = "vtkMRMLLabelMapVolumeNode" if labelmap else "vtkMRMLScalarVolumeNode"
    arr = _volume_input(name, array_kji, spacing)
    node = get_node(scene, name, required=False)
    if node is not None and node.GetClassName() != cls:
        remove_node(scene, name)
        node = None
    if node is None:
        node = _get_or_add(scene, cls, name)
    return set_volume_array(node, arr, spacing, origin, direction)


def _volume_input(name, array_kji, spacing):
    arr = np.ascontiguousarray(array_kji)
    if arr.ndim != 3:
        raise FluoInputError("volume array must be 3D (K, J, I)", field=name, value=arr.shape)
    if arr.dtype not in _VTK_TYPES:
        raise FluoInputError("unsupported voxel type", field=name, value=str(arr.dtype))
    spacing = np.asarray(spacing, float)
    if spacing.shape != (3,) or np.any(~np.isfinite(spacing)) or np.any(spacing <= 0):
        raise FluoInputError("spacing must be 3 positive numbers (mm)", field=f"{name}.spacing",
                             value=spacing.tolist())
    return arr


def set_volume_array(node, array_kji, spacing, origin, direction=None):
    """Fill an existing (caller-chosen) volume node with a numpy array and its geometry.

    Same arguments as :func:`add_volume`; returns the node.
    """
    from vtk.util import numpy_support

    arr = _volume_input(node.GetName(), array_kji, spacing)
    spacing = np.asarray(spacing, float)
    vtk = _vtk()
    img = vtk.vtkImageData()
    img.SetDimensions(arr.shape[2], arr.shape[1], arr.shape[0])
    scalars = numpy_support.numpy_to_vtk(arr.ravel(), deep=True,
                                         array_type=getattr(vtk, _VTK_TYPES[arr.dtype]))
    img.GetPointData().SetScalars(scalars)
    node.SetAndObserveImageData(img)
    node.SetSpacing(*spacing.tolist())
    node.SetOrigin(*np.asarray(origin, float).tolist())
    d = np.eye(3) if direction is None else np.asarray(direction, float)
    vm = _vtk().vtkMatrix4x4()
    for i in range(3):
        for j in range(3):
            vm.SetElement(i, j, float(d[i, j]))
    node.SetIJKToRASDirectionMatrix(vm)
    # Label maps get their display node (and colour table) from the viewer:
    # slicer-core alone has no default label colour table to point it at.
    if not node.IsA("vtkMRMLLabelMapVolumeNode") and node.GetDisplayNodeID() is None:
        node.CreateDefaultDisplayNodes()
    return node


def volume_array(node):
    """The voxels of a volume node as a (K, J, I) numpy array (a copy)."""
    from vtk.util import numpy_support

    img = node.GetImageData()
    if img is None:
        raise FluoInputError("volume node has no image data", field=node.GetName())
    dims = img.GetDimensions()
    arr = numpy_support.vtk_to_numpy(img.GetPointData().GetScalars())
    return arr.reshape(dims[2], dims[1], dims[0]).copy()


def volume_geometry(node):
    """Dict with ``spacing`` (3,), ``origin`` (3,), ``direction`` (3, 3) and
    ``ijk_to_ras`` (4, 4) of a volume node (RAS mm)."""
    vm = _vtk().vtkMatrix4x4()
    node.GetIJKToRASMatrix(vm)
    ijk_to_ras = _vtk_to_matrix(vm)
    dm = _vtk().vtkMatrix4x4()
    node.GetIJKToRASDirectionMatrix(dm)
    return {
        "spacing": np.array(node.GetSpacing()),
        "origin": np.array(node.GetOrigin()),
        "direction": _vtk_to_matrix(dm)[:3, :3],
        "ijk_to_ras": ijk_to_ras,
    }


# ---------------------------------------------------------------- models

def polydata_from_arrays(points, triangles):
    """vtkPolyData from (P, 3) points [mm] and (T, 3) triangle indices."""
    from vtk.util import numpy_support

    vtk = _vtk()
    pts = np.ascontiguousarray(points, dtype=float)
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or tri.ndim != 2 or tri.shape[1] != 3:
        raise FluoInputError("model needs (P, 3) points and (T, 3) triangles",
                             field="model", value=(pts.shape, tri.shape))
    vpts = vtk.vtkPoints()
    vpts.SetData(numpy_support.numpy_to_vtk(pts, deep=True))
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, 3 * len(tri) + 1, 3, dtype=np.int64)
    cells.SetData(numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(tri.ravel(), deep=True))
    pd = vtk.vtkPolyData()
    pd.SetPoints(vpts)
    pd.SetPolys(cells)
    return pd


def add_model(scene, name, points_or_polydata, triangles=None, color=(0.9, 0.7, 0.6)):
    """Create or replace a model node from vtkPolyData or (points, triangles)."""
    vtk = _vtk()
    if isinstance(points_or_polydata, vtk.vtkPolyData):
        pd = points_or_polydata
    else:
        pd = polydata_from_arrays(points_or_polydata, triangles)
    node = _get_or_add(scene, "vtkMRMLModelNode", name)
    node.SetAndObservePolyData(pd)
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    node.GetDisplayNode().SetColor(*color)
    return node


def set_model_polydata(node, polydata, color=None):
    """Show ``polydata`` in an existing (caller-chosen) model node; returns the node."""
    node.SetAndObservePolyData(polydata)
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    if color is not None:
        node.GetDisplayNode().SetColor(*color)
    return node


def model_arrays(node):
    """(points (P, 3), triangles (T, 3)) of a triangle model node."""
    from vtk.util import numpy_support

    pd = node.GetPolyData()
    if pd is None or pd.GetNumberOfPoints() == 0:
        raise FluoInputError("model node has no geometry", field=node.GetName())
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData()).astype(float)
    polys = pd.GetPolys()
    conn = numpy_support.vtk_to_numpy(polys.GetConnectivityArray())
    off = numpy_support.vtk_to_numpy(polys.GetOffsetsArray())
    if len(off) > 1 and not np.all(np.diff(off) == 3):
        raise FluoInputError("model has non-triangle polygons", field=node.GetName())
    return pts, conn.reshape(-1, 3).astype(np.int64)


# ---------------------------------------------------------------- tables / text

def set_table(scene, name, columns):
    """Create or replace a table node from a dict of equal-length 1D arrays."""
    from vtk.util import numpy_support

    node = _get_or_add(scene, "vtkMRMLTableNode", name)
    table = node.GetTable()
    table.Initialize()
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise FluoInputError("table columns differ in length", field=name, value=sorted(lengths))
    for key, values in columns.items():
        arr = numpy_support.numpy_to_vtk(np.asarray(values, dtype=float), deep=True)
        arr.SetName(str(key))
        table.AddColumn(arr)
    node.Modified()
    return node


def get_table(node):
    from vtk.util import numpy_support

    table = node.GetTable()
    return {table.GetColumnName(i): numpy_support.vtk_to_numpy(table.GetColumn(i)).copy()
            for i in range(table.GetNumberOfColumns())}


# ---------------------------------------------------------------- save / load

def _storable_nodes(scene):
    return [n for n in nodes(scene, "vtkMRMLStorableNode")
            if not n.IsA("vtkMRMLStorageNode") and n.GetSaveWithScene()]


def _safe_file_stem(name):
    keep = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in name)
    return keep or "node"


def _default_extension(node):
    if node.IsA("vtkMRMLVolumeNode"):
        return ".nrrd"
    if node.IsA("vtkMRMLModelNode"):
        return ".vtk"
    if node.IsA("vtkMRMLTransformNode"):
        return ".h5"
    if node.IsA("vtkMRMLTableNode"):
        return ".tsv"
    if node.IsA("vtkMRMLMarkupsNode"):
        return ".mrk.json"
    if node.IsA("vtkMRMLSequenceNode"):
        return ".seq.mrb"
    return None


def save_scene(scene, path):
    """Write ``path`` (.mrml) plus one storage file per data node beside it.

    Data go to NRRD (volumes), VTK (models), HDF5 ITK transforms (.h5, as
    Slicer writes them) and TSV (tables).  Everything is written into a
    staging folder first and moved in as one transaction (``fluoguide.atomic``):
    a crash at any moment leaves the old scene or the new one.
    Returns the scene file path (resolved); messages name it as given.
    """
    given = Path(path)
    path = given.resolve()
    if path.suffix != ".mrml":
        raise FluoInputError("scene file must end in .mrml", file=given)
    out_dir = path.parent
    if out_dir.exists() and not out_dir.is_dir():
        raise FluoInputError("output folder is a file", file=given.parent)
    if path.is_dir():
        raise FluoInputError("scene path is a folder", file=given)
    try:
        tmp = atomic.staging_folder(out_dir)
    except OSError as exc:
        raise FluoInputError(f"cannot write here ({exc.strerror})", file=given.parent) from None
    try:
        used = set()
        targets = []
        for node in _storable_nodes(scene):
            ext = _default_extension(node)
            if ext is None:
                continue
            sn = node.GetStorageNode()
            if sn is None:
                sn = node.CreateDefaultStorageNode()
                if sn is None:
                    continue
                scene.AddNode(sn)
                node.SetAndObserveStorageNodeID(sn.GetID())
            if node.IsA("vtkMRMLSequenceNode"):
                # volume sequences are .seq.nrrd; ask the storage node
                ext = "." + (sn.GetDefaultWriteFileExtension() or "seq.mrb")
            stem = _safe_file_stem(node.GetName())
            fname = stem + ext
            k = 1
            while fname in used or fname == path.name:
                fname = f"{stem}_{k}{ext}"
                k += 1
            used.add(fname)
            if node.IsA("vtkMRMLVolumeNode"):
                sn.SetUseCompression(1)
            sn.SetFileName(str(tmp / fname))
            if not sn.WriteData(node):
                raise FluoInputError("failed to write storage file", file=given.parent / fname,
                                     field=node.GetName())
            # the writer's file list holds paths into the staging folder (saved
            # relative to the wrong folder): one file per node, no list
            sn.ResetFileNameList()
            targets.append((sn, fname))
        # Committed inside the staging folder, the scene refers to its data
        # files by bare relative names, so moving them together keeps it valid.
        scene.SetRootDirectory(str(tmp))
        scene.SetURL(str(tmp / path.name))
        if not scene.Commit():
            raise FluoInputError("failed to write scene file", file=given)
        # Some writers add companion files (a table's .schema.tsv): move all,
        # the .mrml last (readers open it first).
        data = sorted(f.name for f in tmp.iterdir() if f.name != path.name)
        atomic.commit_files(tmp, out_dir, data + [path.name])
        for sn, fname in targets:
            sn.SetFileName(str(out_dir / fname))
        scene.SetRootDirectory(str(out_dir))
        scene.SetURL(str(path))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def _check_storage_paths(path, given=None):
    """Refuse a scene whose storage nodes point outside its folder or at non-files.

    Checked on the XML before MRML opens anything: a hostile scene must not make
    the loader read /etc/passwd or block forever on a FIFO. Messages name the
    scene as ``given`` (the path the user typed) and its files beside it.
    """
    given = Path(path) if given is None else Path(given)
    root_dir = path.parent.resolve()
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        raise FluoInputError(f"corrupt MRML scene (XML: {exc})", file=given) from None
    except RecursionError:
        raise FluoInputError("corrupt MRML scene (XML nested too deeply)", file=given) from None
    for elem in tree.iter():
        for key, value in elem.attrib.items():
            if not (key == "fileName" or key.startswith("fileListMember")) or not value:
                continue
            rel = Path(value)
            if rel.is_absolute():
                raise FluoInputError("scene refers to a data file by an absolute path; "
                                     "only files inside the scene's folder are read",
                                     file=given, field=elem.get("id") or elem.tag, value=value)
            full = (root_dir / rel).resolve()
            try:
                full.relative_to(root_dir)
            except ValueError:
                raise FluoInputError("scene refers to a data file outside its folder",
                                     file=given, field=elem.get("id") or elem.tag,
                                     value=value) from None
            if not full.exists():
                if key != "fileName":
                    continue  # a stale member of a file list (Slicer keeps them): not read
                raise FluoInputError("data file of the scene is missing", file=given.parent / rel,
                                     field=elem.get("id") or elem.tag)
            if not stat.S_ISREG(full.stat().st_mode):
                raise FluoInputError("data file of the scene is not a regular file",
                                     file=given.parent / rel,
                                     field=elem.get("id") or elem.tag)
            if key == "fileName" and "Volume" in elem.tag:
                # MRML reads volumes through ITK, which trusts a lying header (a NaN
                # voxel size becomes 1, extra data is cut): checked first
                from fluoguide.volume_header import check_volume_file

                check_volume_file(given.parent / rel)    # confined above; named as given


def _check_transforms(scene, path):
    for node in nodes(scene, "vtkMRMLLinearTransformNode"):
        vm = _vtk().vtkMatrix4x4()
        node.GetMatrixTransformToParent(vm)
        m = _vtk_to_matrix(vm)
        # VTK reads NaN as 0: a singular matrix is a corrupt (or NaN) transform
        if not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise FluoInputError("corrupt transform (not finite or singular)", file=path,
                                 field=node.GetName())
        seen = {node.GetID()}
        parent_id = node.GetTransformNodeID()
        while parent_id:
            if parent_id in seen:
                raise FluoInputError("transform parents form a cycle", file=path,
                                     field=node.GetName())
            seen.add(parent_id)
            parent = scene.GetNodeByID(parent_id)
            parent_id = parent.GetTransformNodeID() if parent is not None else None


def scene_to_update(path, field="--scene"):
    """The scene at ``path`` to add results to and save back (a new one if the
    file does not exist yet).

    Called before any work, so a scene that cannot be read or written refuses
    the run while nothing has been written.
    """
    path = Path(path)
    if path.suffix != ".mrml":
        raise FluoInputError("scene file must end in .mrml", file=path, field=field)
    atomic.check_writable(path, field)
    return load_scene(path) if path.exists() else new_scene()


def load_scene(path):
    """Read a .mrml scene and the storage files it refers to.

    Raises FluoInputError naming the file when the scene or one of its data
    files is missing or unreadable.
    """
    given = Path(path)              # messages name the files as the user gave them
    path = given.resolve()
    if path.parent.is_dir():
        atomic.recover(path.parent)  # finish a save that a crash interrupted
    if not path.is_file():
        raise FluoInputError("scene file not found", file=given)
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if b"<MRML" not in head:
        raise FluoInputError("not an MRML scene (no <MRML> element)", file=given)
    _check_storage_paths(path, given)
    scene = new_scene()
    scene.SetURL(str(path))
    scene.SetRootDirectory(str(path.parent))
    imported = scene.Import()
    if scene.GetNumberOfNodes() == 0:
        raise FluoInputError("corrupt MRML scene (no nodes)", file=given)
    # Import fails as a whole when one data file does: find and name that file.
    for node in _storable_nodes(scene):
        sn = node.GetStorageNode()
        if sn is None:
            continue
        fname = sn.GetFileName()
        if not fname:
            continue
        full = Path(fname) if os.path.isabs(fname) else path.parent / fname
        try:        # MRML holds it absolute: shown beside the scene as given
            shown = given.parent / full.relative_to(path.parent)
        except ValueError:
            shown = full
        if not full.is_file():
            raise FluoInputError("data file of the scene is missing", file=shown,
                                 field=node.GetName())
        if node.IsA("vtkMRMLVolumeNode") and node.GetImageData() is None:
            raise FluoInputError("corrupt volume file", file=shown, field=node.GetName())
        if node.IsA("vtkMRMLVolumeNode") and not node.IsA("vtkMRMLSequenceNode"):
            from fluoguide.volume_header import check_geometry

            geo = volume_geometry(node)
            check_geometry(geo["spacing"], geo["origin"], geo["direction"], file=shown,
                           field=node.GetName())
        # a model holds a surface (polydata) or a volume mesh (unstructured grid)
        if node.IsA("vtkMRMLModelNode") and (node.GetMesh() is None
                                            or node.GetMesh().GetNumberOfPoints() == 0
                                            or node.GetMesh().GetNumberOfCells() == 0):
            raise FluoInputError("corrupt model file", file=shown, field=node.GetName())
    if not imported:
        raise FluoInputError("corrupt MRML scene", file=given)
    _check_transforms(scene, given)
    return scene
