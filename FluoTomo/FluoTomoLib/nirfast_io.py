"""NIRFAST mesh files: ``.node``, ``.elem``, ``.region``, ``.param``.

So meshes and optical properties can be cross-checked in NIRFAST:

- ``.node``: one row per node, ``bndvtx x y [z]`` (bndvtx 1 on the boundary);
- ``.elem``: one row per element, 1-based node indices (3 or 4 columns);
- ``.region``: one integer label per node (NIRFAST is node based; we write the
  node region of the mesh, the highest label of the elements around the node);
- ``.param``: a header line with the mesh type, then one row per node:
  ``stnd``: mua, kappa, ri; ``fluor``: muax, kappax, ri, muam, kappam, muaf,
  eta, tau (kappa = D = 1/(3(mua + musp)) [mm], mua in 1/mm, tau in s).

Element regions do not exist in NIRFAST; on reading, an element takes the
highest node region among its nodes (the inverse of how we write them), so
a mesh whose element regions follow that rule round-trips exactly.
The ``.source`` / ``.meas`` / ``.link`` files are not handled yet.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

from .mesh import Mesh

PARAM_COLUMNS = {
    "stnd": ("mua", "kappa", "ri"),
    "fluor": ("muax", "kappax", "ri", "muam", "kappam", "muaf", "eta", "tau"),
}


def _stem(path):
    p = Path(path)
    return p.with_suffix("") if p.suffix in (".node", ".elem", ".region", ".param") else p


def write_nirfast(mesh, path, param_type=None, params=None):
    """Write ``path.node/.elem/.region`` (and ``.param`` if ``params`` is given).

    Parameters
    ----------
    params : dict of nodal arrays (or scalars) named as in PARAM_COLUMNS[param_type]
    """
    stem = _stem(path)
    stem.parent.mkdir(parents=True, exist_ok=True)
    bnd = np.zeros(mesh.n_nodes, dtype=int)
    bnd[mesh.boundary_nodes] = 1
    files = {}
    files[".node"] = "\n".join(" ".join([str(b)] + [repr(float(c)) for c in row])
                               for b, row in zip(bnd, mesh.nodes_mm)) + "\n"
    files[".elem"] = "\n".join(" ".join(str(int(i) + 1) for i in row)
                               for row in mesh.elements) + "\n"
    files[".region"] = "\n".join(str(int(r)) for r in mesh.node_region) + "\n"
    if params is not None:
        if param_type not in PARAM_COLUMNS:
            raise FluoInputError(f"param type must be one of {', '.join(PARAM_COLUMNS)}",
                                 field="param_type", value=param_type)
        cols = []
        for name in PARAM_COLUMNS[param_type]:
            if name not in params:
                raise FluoInputError("missing optical parameter", field=f"params.{name}")
            cols.append(np.broadcast_to(np.asarray(params[name], float), (mesh.n_nodes,)))
        table = np.stack(cols, axis=1)
        files[".param"] = param_type + "\n" + "\n".join(
            " ".join(repr(float(v)) for v in row) for row in table) + "\n"
    written = []
    for ext, text in files.items():
        tmp = stem.with_name(stem.name + ext + ".tmp")
        tmp.write_text(text)
        written.append((tmp, stem.with_name(stem.name + ext)))
    for tmp, final in written:
        tmp.replace(final)
    return stem


def _load_table(path, what, dtype=float):
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    except FileNotFoundError:
        raise FluoInputError("file not found", file=path) from None
    if not rows:
        raise FluoInputError(f"empty {what} file", file=path)
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        bad = next(i for i, r in enumerate(rows) if len(r) != len(rows[0]))
        raise FluoInputError(f"line {bad + 1} has {len(rows[bad])} columns, expected "
                             f"{len(rows[0])}", file=path)
    try:
        return np.array(rows, dtype=dtype)
    except ValueError:
        raise FluoInputError(f"non-numeric {what} entry", file=path) from None


def read_nirfast(path):
    """Mesh (with ``meta["bndvtx"]``, ``meta["node_region"]`` and, if present,
    ``meta["param_type"]`` / ``meta["params"]``) from a NIRFAST file stem."""
    stem = _stem(path)
    node = _load_table(stem.with_name(stem.name + ".node"), "node")
    if node.shape[1] not in (3, 4):
        raise FluoInputError("node rows must be 'bndvtx x y [z]'", file=f"{stem}.node",
                             value=node.shape[1])
    elem = _load_table(stem.with_name(stem.name + ".elem"), "element", dtype=float)
    if np.any(elem != np.round(elem)):
        raise FluoInputError("element indices must be integers", file=f"{stem}.elem")
    elem = elem.astype(np.int64) - 1
    if elem.min() < 0 or elem.max() >= len(node):
        raise FluoInputError("element refers to a node that does not exist",
                             file=f"{stem}.elem", value=int(elem.max()) + 1)
    region_path = stem.with_name(stem.name + ".region")
    node_region = (_load_table(region_path, "region").astype(np.int64).ravel()
                   if region_path.exists() else np.ones(len(node), dtype=np.int64))
    if len(node_region) != len(node):
        raise FluoInputError(f"{len(node_region)} regions for {len(node)} nodes",
                             file=region_path)
    element_region = node_region[elem].max(axis=1)
    mesh = Mesh(node[:, 1:], elem, element_region, name=stem.name)
    mesh.meta["bndvtx"] = node[:, 0].astype(int)
    mesh.meta["node_region"] = node_region
    param_path = stem.with_name(stem.name + ".param")
    if param_path.exists():
        lines = [ln for ln in param_path.read_text().splitlines() if ln.strip()]
        kind = lines[0].strip()
        if kind not in PARAM_COLUMNS:
            raise FluoInputError("unsupported param type (stnd, fluor)", file=param_path,
                                 value=kind)
        try:
            table = np.array([ln.split() for ln in lines[1:]], dtype=float)
        except ValueError:
            raise FluoInputError("non-numeric or ragged parameter rows", file=param_path) from None
        if table.shape != (len(node), len(PARAM_COLUMNS[kind])):
            raise FluoInputError(f"expected {len(node)} rows of {len(PARAM_COLUMNS[kind])} values",
                                 file=param_path, value=table.shape)
        mesh.meta["param_type"] = kind
        mesh.meta["params"] = dict(zip(PARAM_COLUMNS[kind], table.T))
    return mesh
