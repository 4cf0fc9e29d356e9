"""Meshes to and from VTK: .vtu files, unstructured grids and surface polydata.

Region labels travel as the cell array ``region``; nodal fields as point
arrays.  2D meshes are stored with z = 0 and flagged by the field-data
entry ``fluo_dim`` so they read back as 2D.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.meshing.mesh import Mesh


def to_vtk(mesh, point_data=None):
    """vtkUnstructuredGrid of a Mesh (tetra or triangle cells)."""
    import vtk
    from vtk.util import numpy_support as ns

    pts = mesh.nodes_mm if mesh.dim == 3 else np.c_[mesh.nodes_mm, np.zeros(mesh.n_nodes)]
    grid = vtk.vtkUnstructuredGrid()
    vp = vtk.vtkPoints()
    vp.SetData(ns.numpy_to_vtk(np.ascontiguousarray(pts), deep=True))
    grid.SetPoints(vp)
    k = mesh.dim + 1
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, k * mesh.n_elements + 1, k, dtype=np.int64)
    cells.SetData(ns.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  ns.numpy_to_vtkIdTypeArray(mesh.elements.ravel().astype(np.int64), deep=True))
    grid.SetCells(vtk.VTK_TETRA if mesh.dim == 3 else vtk.VTK_TRIANGLE, cells)
    reg = ns.numpy_to_vtk(mesh.element_region.astype(np.int32), deep=True)
    reg.SetName("region")
    grid.GetCellData().AddArray(reg)
    for name, values in (point_data or {}).items():
        arr = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=float), deep=True)
        arr.SetName(name)
        grid.GetPointData().AddArray(arr)
    dim = vtk.vtkIntArray()
    dim.SetName("fluo_dim")
    dim.InsertNextValue(mesh.dim)
    grid.GetFieldData().AddArray(dim)
    return grid


def from_vtk(grid, name="mesh", source=None):
    """Mesh from a vtkUnstructuredGrid of tetrahedra (or triangles)."""
    import vtk
    from vtk.util import numpy_support as ns

    if grid.GetNumberOfPoints() == 0 or grid.GetNumberOfCells() == 0:
        raise FluoInputError("mesh has no points or cells", file=source)
    types = grid.GetCellTypes()  # VTK >= 9.6: the per-cell type array
    types = (ns.vtk_to_numpy(types) if types is not None and hasattr(types, "GetNumberOfTuples")
             else np.array([grid.GetCellType(i) for i in range(grid.GetNumberOfCells())]))
    if np.all(types == vtk.VTK_TETRA):
        k = 4
    elif np.all(types == vtk.VTK_TRIANGLE):
        k = 3
    else:
        raise FluoInputError("mesh must hold only tetrahedra or only triangles", file=source,
                             field="cell types", value=sorted(set(types.tolist())))
    pts = ns.vtk_to_numpy(grid.GetPoints().GetData()).astype(float)
    conn = ns.vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(-1, k)
    fd = grid.GetFieldData().GetArray("fluo_dim")
    dim = int(fd.GetValue(0)) if fd is not None else (3 if k == 4 else 2)
    nodes = pts if dim == 3 else pts[:, :2]
    reg = grid.GetCellData().GetArray("region")
    region = ns.vtk_to_numpy(reg).astype(np.int64) if reg is not None else None
    mesh = Mesh(nodes, conn.astype(np.int64), region, name=name)
    fields = {grid.GetPointData().GetArrayName(i):
              ns.vtk_to_numpy(grid.GetPointData().GetArray(i)).copy()
              for i in range(grid.GetPointData().GetNumberOfArrays())}
    mesh.meta["point_data"] = fields
    return mesh


def write_vtu(mesh, path, point_data=None):
    """Write ``path`` (.vtu, binary, compressed) atomically: a kill leaves the old
    file or the new one (and at most a hidden ``.NAME.tmp-*`` file)."""
    import vtk

    from fluoguide import atomic

    path = Path(path)
    if path.suffix != ".vtu":
        raise FluoInputError("mesh file must end in .vtu", file=path)
    grid = to_vtk(mesh, point_data)
    with atomic.atomic_path(path) as tmp:
        w = vtk.vtkXMLUnstructuredGridWriter()
        w.SetFileName(str(tmp))
        w.SetInputData(grid)
        w.SetDataModeToBinary()
        if not w.Write() or not tmp.exists():
            raise FluoInputError("cannot write mesh file", file=path)
    return path


def read_vtu(path):
    import vtk

    path = Path(path)
    if not path.is_file():
        raise FluoInputError("mesh file not found", file=path)
    head = path.read_bytes()[:256]
    if b"<VTKFile" not in head or b"UnstructuredGrid" not in head:
        raise FluoInputError("not a VTK unstructured grid (.vtu) file", file=path)
    r = vtk.vtkXMLUnstructuredGridReader()
    r.SetFileName(str(path))
    r.Update()
    if r.GetErrorCode() or r.GetOutput() is None:
        raise FluoInputError("corrupt .vtu file", file=path)
    return from_vtk(r.GetOutput(), name=path.stem, source=path)


def read_mesh(path):
    """Read a mesh by extension: .vtu, or a NIRFAST stem/.node file."""
    p = Path(path)
    if p.suffix == ".vtu":
        return read_vtu(p)
    if p.suffix in (".node", ".elem", ""):
        from FluoTomoLib.meshing import nirfast_io

        return nirfast_io.read_nirfast(p.with_suffix(""))
    raise FluoInputError("unknown mesh format (use .vtu or NIRFAST .node/.elem)", file=p)


def boundary_polydata(mesh):
    """The outer surface as vtkPolyData (3D: triangles, outward normals as point
    and cell data) for ray casting and display."""
    from fluoguide.mrml_io import polydata_from_arrays
    from vtk.util import numpy_support as ns

    if mesh.dim != 3:
        raise FluoInputError("surface extraction needs a 3D mesh", field="mesh", value=mesh.dim)
    used = np.unique(mesh.boundary_facets)
    remap = np.full(mesh.n_nodes, -1)
    remap[used] = np.arange(len(used))
    pd = polydata_from_arrays(mesh.nodes_mm[used], remap[mesh.boundary_facets])
    cn = ns.numpy_to_vtk(np.ascontiguousarray(mesh.boundary_normals), deep=True)
    cn.SetName("Normals")
    pd.GetCellData().SetNormals(cn)
    pn = ns.numpy_to_vtk(np.ascontiguousarray(mesh.boundary_node_normals[used]), deep=True)
    pn.SetName("Normals")
    pd.GetPointData().SetNormals(pn)
    ids = ns.numpy_to_vtk(used.astype(np.int64), deep=True)
    ids.SetName("mesh_node")
    pd.GetPointData().AddArray(ids)
    return pd
