"""Boundary data of sources and detectors on a mesh read from a file: the exact
half-space answer where the tissue under the optodes is one, else the FEM,
refused where the mesh is too coarse for its optics (``fluo forward`` and
``FluoTomoLogic.forwardMesh``)."""

from __future__ import annotations

import time
import warnings

import numpy as np

from fluoguide.errors import FluoInputError


def read_forward_mesh(path):
    """A mesh file (.vtu with a cell array ``region``, or a NIRFAST stem) with
    elements of either orientation turned positive -> (mesh, elements turned);
    degenerate elements are refused naming the file."""
    from FluoTomoLib.meshing.vtu_io import read_mesh

    mesh = read_mesh(path)
    try:
        mesh.check_elements()
    except FluoInputError as exc:
        raise FluoInputError(exc.problem + " (only degenerate elements are refused; either "
                             "orientation is fine)", file=path, field=exc.field,
                             value=exc.value) from None
    flipped = int(np.sum(mesh.signed_measures < 0))
    return (mesh.oriented() if flipped else mesh), flipped


def read_points(path, field):
    """Points (N, 2 or 3) [mm] from a CSV file of ``x,y[,z]`` rows (``,`` or
    ``;``; ``#`` comments and a header line allowed), refused naming the file,
    the field and the line."""
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise FluoInputError("file not found", file=p, field=field)
    rows = []
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FluoInputError("not UTF-8 text", file=p, field=field) from None
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [v for v in line.replace(";", ",").split(",") if v.strip()]
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            if not rows and i == 1:  # header line
                continue
            raise FluoInputError(f"line {i} is not numeric", file=p, field=field,
                                 value=line) from None
        if len(vals) not in (2, 3) or not np.all(np.isfinite(vals)):
            raise FluoInputError(f"line {i} needs 2 or 3 finite coordinates (x,y[,z] mm)", file=p,
                                 field=field, value=line)
        rows.append(vals)
    if not rows:
        raise FluoInputError("no points", file=p, field=field)
    if len({len(r) for r in rows}) != 1:
        raise FluoInputError("mixed 2D and 3D points", file=p, field=field)
    return np.array(rows)


def check_optodes(mesh, points, field, file=None):
    """Sources or detectors (N, 2 or 3) [mm] in the mesh's dimension."""
    if points.shape[1] != mesh.dim:
        raise FluoInputError(f"points are {points.shape[1]}D but the mesh is {mesh.dim}D",
                             file=file, field=field)
    return points


def half_space_data(mesh, mua, musp, n, src, det, required=False, file=None):
    """The exact Robin half-space answer for one material (``mua``, ``musp``
    [1/mm], ``n``) where the check says the tissue under the optodes is one
    (flat, far boundaries).

    Returns
    -------
    (check dict, result dict or None)
        None when the check refuses (``required``: raised instead, field
        ``model``). The result holds ``model``, ``detector_fluence`` [1/mm^2
        per W], ``accuracy``, ``warnings`` and ``log_valid_fraction``.
    """
    from FluoTomoLib.fem.forward import safe_log
    from FluoTomoLib.fem.halfspace import half_space_check, half_space_excitation_data
    from FluoTomoLib.optics import NEAR_SOURCE_MFP, diffusion_validity, transport_mfp_mm

    check = half_space_check(mesh, mua, musp, n, src, det)
    if required and not check["usable"]:
        raise FluoInputError(f"the analytic half-space model does not apply: "
                             f"{check['reason']}", file=file, field="model", value="analytic")
    if not check["usable"]:
        return check, None
    data = half_space_excitation_data(mesh, mua, musp, n, src, det)
    notes = diffusion_validity(mua, musp)
    rho = np.linalg.norm(src[:, None, :] - det[None, :, :], axis=2)
    near = rho < NEAR_SOURCE_MFP * transport_mfp_mm(mua, musp)
    if near.any():
        notes.append(f"{int(near.sum())} pair(s) are within {NEAR_SOURCE_MFP:g} transport "
                     "mean free paths: diffusion theory itself over-predicts there")
    return check, {
        "model": "analytic", "detector_fluence": data.tolist(),
        "accuracy": {"model_error_bound_rel": check["boundary_effect_bound"],
                     "what": "the exact Robin half-space solution; other boundaries of "
                             "the mesh change the data by at most this much"},
        "warnings": notes, "log_valid_fraction": float(safe_log(data)[1].mean())}


def _size_hint(acc):
    size = acc.get("element_size_needed_mm")
    if size is None or not np.isfinite(size):
        return ""
    return f"; elements of at most {size:.3g} mm near the optodes would do"


def fem_data(mesh, optics, src, det, yields=None, solver="auto", jacobian=False, force=False,
             file=None, force_name="force"):
    """Excitation (and with ``yields`` {region: yield [1/mm]} fluorescence)
    boundary data [1/mm^2 per W] of the diffusion FEM on ``mesh``.

    A mesh too coarse for its optics (the resolution guard: negative fluence,
    elements beyond the measured range) is refused, naming ``file`` and field
    ``elements`` and the element size that would do, unless ``force``
    (``force_name``: how the caller spells it, for the message).

    Returns
    -------
    dict
        ``model``, ``detector_fluence``, [``fluorescence``, ``yield_by_region``],
        [``jacobian_mua`` (S*D, nodes), ``jacobian_yield``: arrays, with
        ``jacobian``], ``log_valid_fraction``, ``accuracy``, ``negative_nodes``,
        ``warnings``, ``forced``, ``solver``, ``timings``.
    """
    from FluoTomoLib.fem.forward import FluorescenceModel, safe_log

    props_x, props_m, y_nodes = optics.nodal_from_mesh(mesh, yields)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fm = FluorescenceModel(mesh, props_x, props_m, src, det, solver=solver)
        acc = fm.accuracy()
    if acc["refuse"] and not force:
        raise FluoInputError("; ".join(acc["refuse"]) + _size_hint(acc) + f" ({force_name} to "
                             "output the data anyway, with these warnings)", file=file,
                             field="elements")
    data = fm.excitation_data()
    out = {"model": "fem", "detector_fluence": data.tolist()}
    if yields is not None:
        out["fluorescence"] = fm.emission_data(y_nodes).tolist()
        out["yield_by_region"] = {str(k): v for k, v in yields.items()}
    if jacobian:
        out["jacobian_mua"] = fm.jacobian_mua_x()
        if yields is not None:
            out["jacobian_yield"] = fm.jacobian_yield()
    out["log_valid_fraction"] = float(safe_log(data)[1].mean())
    out["accuracy"] = {k: acc[k] for k in ("target_rel_err", "estimated_rel_err",
                                            "element_size_needed_mm")}
    out["negative_nodes"] = acc["negative_nodes"]
    notes = acc["refuse"] + acc["warnings"]
    for w in caught:                      # the operators' own warnings, once each
        text = str(w.message)
        if text not in notes:
            notes.append(text)
    out["warnings"] = notes
    out["forced"] = bool(acc["refuse"]) and bool(force)
    out["solver"] = fm.solver_name
    out["timings"] = fm.timings
    return out


def mesh_boundary_data(mesh, optics, src, det, yields=None, model="auto", solver="auto",
                       jacobian=False, force=False, half_space=None, file=None,
                       force_name="force"):
    """Boundary data of ``mesh`` for sources ``src`` and detectors ``det``
    (N, dim) [mm]: the half-space answer (``half_space``: (mua, musp, n) of
    the one material) where ``model`` is "auto" or "analytic" and it applies
    and no Jacobian is asked for, else :func:`fem_data` (``model`` "fem").

    Returns the result dict (``analytic_check`` first where the half-space was
    checked; ``seconds``: the computation's wall time).
    """
    from FluoTomoLib.fem.operators import check_solver

    t0 = time.perf_counter()
    check_solver(solver, field="solver")      # even where the analytic path will not use it
    if model not in ("auto", "fem", "analytic"):
        raise FluoInputError("model must be auto, fem or analytic", field="model", value=model)
    out = {}
    if model in ("auto", "analytic") and half_space is not None and yields is None:
        check, done = half_space_data(mesh, *half_space, src, det,
                                      required=model == "analytic", file=file)
        out["analytic_check"] = check
        if done is not None and not jacobian:
            return {**out, **done, "seconds": time.perf_counter() - t0}
    out.update(fem_data(mesh, optics, src, det, yields, solver, jacobian, force, file,
                        force_name))
    out["seconds"] = time.perf_counter() - t0
    return out
