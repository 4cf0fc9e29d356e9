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
Optodes (:func:`write_optodes` / :func:`read_optodes`), as NIRFAST's
``save_mesh`` writes them:

- ``.source``: an optional ``fixed`` line, a header ``num x y z fwhm``, one
  row per source (fwhm [mm] of the Gaussian source, 0 = point source);
- ``.meas``: an optional ``fixed`` line, a header ``num x y z``, one row per
  detector;
- ``.link``: a header ``source detector active``, one row per pair (1-based
  source and detector numbers, active 1 or 0).

Extra columns NIRFAST may add (``ele ip1..ip4``: the enclosing element and
its integration weights) are read back into ``source_int_func`` /
``meas_int_func`` (not written: they are mesh-specific and recomputed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.meshing.mesh import Mesh

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


# ------------------------------------------------------------------ optodes
def _write_atomic(files):
    written = []
    for final, text in files:
        tmp = final.with_name(final.name + ".tmp")
        tmp.write_text(text)
        written.append((tmp, final))
    for tmp, final in written:
        tmp.replace(final)


def write_optodes(path, sources_mm, detectors_mm, link=None, fwhm_mm=0.0, fixed=True):
    """Write NIRFAST ``path.source``, ``path.meas`` and ``path.link``.

    Parameters
    ----------
    sources_mm, detectors_mm : (S, d) and (D, d) positions [mm], d = 2 or 3
    link : (L, 2) or (L, 3) 0-based (source, detector[, active]) pairs; default:
        every source with every detector, all active
    fwhm_mm : scalar or (S,) source width (0 = point source)
    fixed : write the ``fixed`` line (NIRFAST then does not move optodes onto
        the surface)
    """
    stem = _stem(path)
    src = np.atleast_2d(np.asarray(sources_mm, float))
    det = np.atleast_2d(np.asarray(detectors_mm, float))
    for name, pts in (("sources_mm", src), ("detectors_mm", det)):
        if pts.ndim != 2 or pts.shape[1] not in (2, 3) or len(pts) == 0:
            raise FluoInputError("need an (N, 2) or (N, 3) array of positions", field=name,
                                 value=pts.shape)
        if not np.all(np.isfinite(pts)):
            raise FluoInputError("positions must be finite", field=name)
    if src.shape[1] != det.shape[1]:
        raise FluoInputError("sources and detectors need the same dimension", field="detectors_mm",
                             value=(src.shape[1], det.shape[1]))
    fwhm = np.broadcast_to(np.asarray(fwhm_mm, float), (len(src),))
    if not np.all(np.isfinite(fwhm)) or np.any(fwhm < 0):
        raise FluoInputError("fwhm must be >= 0 (mm)", field="fwhm_mm", value=fwhm_mm)
    if link is None:
        s, d = np.meshgrid(np.arange(len(src)), np.arange(len(det)), indexing="ij")
        link = np.stack([s.ravel(), d.ravel(), np.ones(s.size, int)], axis=1)
    link = np.atleast_2d(np.asarray(link))
    if link.ndim != 2 or link.shape[1] not in (2, 3) or not np.all(link == np.round(link)):
        raise FluoInputError("link must be (L, 2|3) integer (source, detector[, active]) rows",
                             field="link", value=link.shape)
    link = link.astype(np.int64)
    if link.shape[1] == 2:
        link = np.c_[link, np.ones(len(link), np.int64)]
    if (link[:, 0].min() < 0 or link[:, 0].max() >= len(src) or link[:, 1].min() < 0
            or link[:, 1].max() >= len(det) or not np.isin(link[:, 2], (0, 1)).all()):
        raise FluoInputError("link refers to a source/detector that does not exist, or active "
                             "is not 0/1", field="link")
    axes = "x y z" if src.shape[1] == 3 else "x y"
    head = "fixed\n" if fixed else ""
    stem.parent.mkdir(parents=True, exist_ok=True)
    num_s = np.arange(1, len(src) + 1)
    num_d = np.arange(1, len(det) + 1)
    rows = lambda num, table: "\n".join(  # noqa: E731
        " ".join([str(int(n))] + [repr(float(v)) for v in row]) for n, row in zip(num, table)) + "\n"
    _write_atomic([
        (stem.with_name(stem.name + ".source"), f"{head}num {axes} fwhm\n" + rows(num_s, np.c_[src, fwhm])),
        (stem.with_name(stem.name + ".meas"), f"{head}num {axes}\n" + rows(num_d, det)),
        (stem.with_name(stem.name + ".link"), "source detector active\n" + "\n".join(
            f"{s + 1} {d + 1} {a}" for s, d, a in link) + "\n"),
    ])
    return stem


def _read_header_table(path, what, required):
    """(fixed, columns, table) of a NIRFAST optode file with a column header."""
    try:
        lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    except FileNotFoundError:
        raise FluoInputError("file not found", file=path) from None
    except UnicodeDecodeError:
        raise FluoInputError(f"not a text {what} file", file=path) from None
    fixed = bool(lines) and lines[0] == ["fixed"]
    if fixed:
        lines = lines[1:]
    if not lines or not all(c in lines[0] for c in required):
        raise FluoInputError(f"expected a header line with columns {' '.join(required)}",
                             file=path, value=" ".join(lines[0]) if lines else "")
    cols = lines[0]
    rows = lines[1:]
    if not rows:
        raise FluoInputError(f"no {what} rows", file=path)
    bad = [i for i, r in enumerate(rows) if len(r) != len(cols)]
    if bad:
        raise FluoInputError(f"line {bad[0] + 2 + fixed} has {len(rows[bad[0]])} values, "
                             f"expected {len(cols)} ({' '.join(cols)})", file=path)
    try:
        table = np.array(rows, dtype=float)
    except ValueError:
        raise FluoInputError(f"non-numeric {what} entry", file=path) from None
    if not np.all(np.isfinite(table)):
        raise FluoInputError(f"non-finite {what} entry", file=path)
    return fixed, cols, table


def read_optodes(path):
    """Sources, detectors and link of a NIRFAST stem.

    Returns
    -------
    dict with ``sources_mm`` (S, d), ``source_fwhm_mm`` (S,), ``source_fixed``,
    ``detectors_mm`` (D, d), ``meas_fixed``, ``link`` (L, 3) 0-based
    (source, detector, active) rows, and ``source_int_func`` /
    ``meas_int_func`` when the files carry them.  Rows are put in ``num``
    order; ``.link`` is optional (default: all pairs active).
    """
    stem = _stem(Path(path).with_suffix("") if Path(path).suffix in (".source", ".meas", ".link")
                 else path)
    out = {}
    for ext, key, what in ((".source", "source", "source"), (".meas", "meas", "detector")):
        f = stem.with_name(stem.name + ext)
        fixed, cols, table = _read_header_table(f, what, ("num", "x", "y"))
        ax = [cols.index(c) for c in ("x", "y", "z") if c in cols]
        num = table[:, cols.index("num")]
        if np.any(num != np.round(num)) or len(np.unique(num)) != len(num):
            raise FluoInputError("'num' must be distinct integers", file=f)
        order = np.argsort(num, kind="stable")
        table = table[order]
        out[f"{key}_fixed"] = fixed
        out["sources_mm" if key == "source" else "detectors_mm"] = table[:, ax]
        if key == "source":
            out["source_fwhm_mm"] = (table[:, cols.index("fwhm")] if "fwhm" in cols
                                     else np.zeros(len(table)))
        if "ele" in cols:
            out[f"{key}_int_func"] = table[:, cols.index("ele"):]
    if out["sources_mm"].shape[1] != out["detectors_mm"].shape[1]:
        raise FluoInputError("sources and detectors differ in dimension", file=f"{stem}.meas")
    f = stem.with_name(stem.name + ".link")
    n_s, n_d = len(out["sources_mm"]), len(out["detectors_mm"])
    if f.exists():
        _, cols, table = _read_header_table(f, "link", ("source", "detector"))
        if np.any(table != np.round(table)):
            raise FluoInputError("link entries must be integers", file=f)
        link = table.astype(np.int64)
        s, d = link[:, cols.index("source")] - 1, link[:, cols.index("detector")] - 1
        active = link[:, cols.index("active")] if "active" in cols else np.ones(len(link), np.int64)
        if s.min() < 0 or s.max() >= n_s or d.min() < 0 or d.max() >= n_d:
            raise FluoInputError(f"link refers to a source/detector that does not exist "
                                 f"({n_s} sources, {n_d} detectors)", file=f)
        out["link"] = np.stack([s, d, active], axis=1)
    else:
        s, d = np.meshgrid(np.arange(n_s), np.arange(n_d), indexing="ij")
        out["link"] = np.stack([s.ravel(), d.ravel(), np.ones(s.size, np.int64)], axis=1)
    return out
