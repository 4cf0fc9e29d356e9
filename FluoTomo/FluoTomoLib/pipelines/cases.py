"""The demo's tomography cases as run-engine tasks: plain values in, plain values out.

A case (one cylinder-tube depth, or the oral cavity) builds its phantom from
its parameters, simulates the tracked acquisition, reconstructs NP / SP / HP
(:mod:`~FluoTomoLib.pipelines.tube`, :mod:`~FluoTomoLib.pipelines.oral`) and
returns what the demo reports: numbers as the row of ``fluoguide.runs``, and as
arrays the depth profiles, the reconstructed yields on the reconstruction mesh
(its nodes and elements), a rendered frame and the y-z section images of the
figures.  The simulation mesh (the whole phantom, up to ~400k nodes) stays in
the task: what comes back is a few MB, and it can be pickled, so a case runs
the same in this process, on a local Dask worker or on a remote cluster, and a
killed demo resumes from the cases it finished.

:func:`case_tasks` lists the tasks; :func:`case_of_record` rebuilds, from a
task's record and arrays, the dict ``simulate_and_reconstruct`` returns
(``coarse`` a :class:`~FluoTomoLib.meshing.mesh.Mesh` again), less the
simulation mesh, plus ``sections``.
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import to_jsonable

METHODS = ("NP", "SP", "HP")

#: y-z section windows of the figures (y range, z range; mm) per phantom
SECTIONS = {"cylinder-tube": ((-8.0, 8.0), (0.0, -10.0)),
            "oral-cavity": ((-16.0, 26.0), (-8.0, -40.0))}

#: keyword options of the case functions a task may set (a smaller case for a
#: test; the demo uses the defaults; ``truth="simulate"`` remakes the stored truth)
TUBE_OPTIONS = {"fine_mm", "coarse_mm", "n_sources", "source_spacing_mm", "simulate_coarse_mm",
                "lam", "accuracy", "grading", "truth"}
ORAL_OPTIONS = {"fine_mm", "coarse_mm", "n_sources", "source_spacing_mm", "lam", "accuracy",
                "grading"}


def section_images(run, y_mm, z_mm, px_per_mm=8):
    """The y-z section at x = 0 of truth | NP | SP | HP, sampled on a pixel grid.

    Parameters
    ----------
    run : dict
        What ``simulate_and_reconstruct`` (or ``_oral``) returned: the truth as
        ``true_yield_at`` (a function of points: the phantom's analytic
        target, NaN outside the tissue), ``coarse`` and each method's
        ``yield`` on the reconstruction mesh.
    y_mm, z_mm : (float, float)
        The window (z from top to bottom, as the image rows go).
    px_per_mm : float

    Returns
    -------
    dict
        ``truth``, ``NP``, ``SP``, ``HP``: (nz, ny) yield images [1/mm], NaN
        outside the mesh (not tissue); ``y_mm``, ``z_mm``: the window.
    """
    from FluoTomoLib.fem.locate import locator

    ny = int(abs(y_mm[1] - y_mm[0]) * px_per_mm) + 1
    nz = int(abs(z_mm[1] - z_mm[0]) * px_per_mm) + 1
    yy, zz = np.meshgrid(np.linspace(*y_mm, ny), np.linspace(*z_mm, nz))
    pts = np.stack([np.zeros(yy.size), yy.ravel(), zz.ravel()], axis=1)
    out = {"y_mm": np.asarray(y_mm, float), "z_mm": np.asarray(z_mm, float)}
    out["truth"] = np.asarray(run["true_yield_at"](pts), float).reshape(yy.shape)
    panels = [(m, run["results"][m]["yield"]) for m in METHODS if m in run["results"]]
    if panels:
        # every method's yield lives on the one reconstruction mesh: the pixels
        # located once, as a grid (each element visits the pixels in its box),
        # on ascending axes and flipped back to the window's order
        ys, zs = np.sort([yy[0, 0], yy[0, -1]]), np.sort([zz[0, 0], zz[-1, 0]])
        step = np.array([1.0, (ys[1] - ys[0]) / max(ny - 1, 1), (zs[1] - zs[0]) / max(nz - 1, 1)])
        P = locator(run["coarse"]).grid_interpolation_matrix(
            np.array([0.0, ys[0], zs[0]]), step, (nz, ny, 1))
        order = np.arange(nz * ny).reshape(nz, ny)
        order = order[::-1 if zz[0, 0] > zz[-1, 0] else 1, ::-1 if yy[0, 0] > yy[0, -1] else 1]
        P = P[order.ravel()]
        inside = np.asarray(P.sum(axis=1)).ravel() > 0.5     # rows outside the mesh are empty
    for name, values in panels:
        out[name] = np.where(inside, P @ np.asarray(values, float), np.nan).reshape(yy.shape)
    return out


def _options(params, allowed, where):
    extra = {k: v for k, v in params.items() if k not in ("depth_mm", "seed")}
    bad = sorted(set(extra) - allowed)
    if bad:
        raise FluoInputError(f"unknown case option (options: {', '.join(sorted(allowed))})",
                             field=where, value=bad[0])
    return extra


def _record_of(run, phantom_name, extra_rows, keep_truth=False):
    """The task's result: headline columns, ``case`` (every number), ``arrays``
    (with the simulated true fields when ``keep_truth``)."""
    results = {m: {k: v for k, v in r.items() if k != "yield"} for m, r in run["results"].items()}
    coarse = run["coarse"]
    arrays = {
        "coarse_nodes_mm": coarse.nodes_mm, "coarse_elements": coarse.elements,
        "coarse_region": coarse.element_region,
        "sources_true_mm": run["sources_true_mm"], "sources_reported_mm": run["sources_reported_mm"],
        "detectors_mm": run["detectors_mm"], "frame_example": run["frame_example"],
    }
    for m, r in run["results"].items():
        arrays[f"yield_{m}"] = r["yield"]
    if "profiles" in run:
        arrays["profile_depth_mm"] = run["profile_depth_mm"]
        for k, v in run["profiles"].items():
            arrays[f"profile_{k}"] = v
    y_mm, z_mm = SECTIONS[phantom_name]
    for k, v in section_images(run, y_mm, z_mm).items():
        arrays[f"section_{k}"] = v
    truth = run.get("surface_truth")
    if keep_truth and truth is not None:
        # asked for (fluo demo --simulate-truth stores it): ~1 MB more per case
        arrays.update({"truth_vertices_mm": truth.vertices_mm, "truth_facets": truth.facets,
                       "truth_fields_per_w": truth.fields_per_w,
                       "truth_sources_mm": truth.sources_mm})
    skip = {"results", "coarse", "profiles", "profile_depth_mm",
            "sources_true_mm", "sources_reported_mm", "detectors_mm", "frame_example",
            "surface_truth", "true_yield_at"}
    case = {k: v for k, v in run.items() if k not in skip}
    case["results"] = results
    case["coarse_meta"] = {k: v for k, v in coarse.meta.items() if not str(k).startswith("_")}
    case["coarse_name"] = coarse.name
    row = dict(extra_rows)
    for m, r in results.items():
        for k in ("peak_error_pct", "centroid_error_pct", "tongue_yield_error_pct",
                  "agar_yield_error_pct"):
            if k in r:
                row[f"{m}_{k}"] = r[k]
    row["warnings"] = sum(len(r.get("warnings", [])) for r in results.values())
    row["case"] = to_jsonable(case)        # numpy scalars and small arrays made plain
    row["arrays"] = arrays
    return row


def tube_case(params, progress=None, cancel=None):
    """Run-engine task: one cylinder-tube depth end to end (tube.simulate_and_reconstruct).

    ``params``: ``depth_mm``, ``seed`` and the options of :data:`TUBE_OPTIONS`;
    ``progress``/``cancel`` come from the serial loop (``fluoguide.runs.engine``).
    """
    from fluoguide.phantoms import make_phantom
    from FluoTomoLib.pipelines.tube import simulate_and_reconstruct

    opts = _options(params, TUBE_OPTIONS, "tube case")
    ph = make_phantom("cylinder-tube", depth_mm=float(params["depth_mm"]),
                      seed=int(params["seed"]))
    run = simulate_and_reconstruct(ph, seed=int(params["seed"]), progress=progress,
                                   cancel=cancel, **opts)
    return _record_of(run, ph.name, {"depth_mm": run["depth_mm"]},
                      keep_truth=opts.get("truth") == "simulate")


tube_case.reports_progress = True


def oral_case(params, progress=None, cancel=None):
    """Run-engine task: the oral-cavity case (oral.simulate_and_reconstruct_oral).

    ``params``: ``seed`` and the options of :data:`ORAL_OPTIONS`; ``progress``/``cancel``
    as :func:`tube_case`'s.
    """
    from fluoguide.phantoms import make_phantom
    from FluoTomoLib.pipelines.oral import simulate_and_reconstruct_oral

    opts = _options(params, ORAL_OPTIONS, "oral case")
    ph = make_phantom("oral-cavity", seed=int(params["seed"]))
    run = simulate_and_reconstruct_oral(ph, seed=int(params["seed"]), progress=progress,
                                        cancel=cancel, **opts)
    return _record_of(run, ph.name, {})


oral_case.reports_progress = True


def case_tasks(tube_depths_mm=(), oral=False, seed=0, tube_options=None, oral_options=None):
    """The run-engine tasks of the demo's tomography cases, tube depths first.

    Parameters
    ----------
    tube_depths_mm : sequence of float
        One cylinder-tube case per depth [mm].
    oral : bool
        Add the oral-cavity case.
    seed : int
        Every case's noise seed (and its phantom's).
    tube_options, oral_options : dict, optional
        Options of :data:`TUBE_OPTIONS` / :data:`ORAL_OPTIONS`.
    """
    from fluoguide.runs import Task

    tube_options, oral_options = dict(tube_options or {}), dict(oral_options or {})
    _options(tube_options, TUBE_OPTIONS, "tube case")
    _options(oral_options, ORAL_OPTIONS, "oral case")
    tasks = [Task(tube_case, {"depth_mm": float(d), "seed": int(seed), **tube_options})
             for d in tube_depths_mm]
    if oral:
        tasks.append(Task(oral_case, {"seed": int(seed), **oral_options}))
    return tasks


def case_of_record(record, arrays):
    """The case as ``simulate_and_reconstruct`` returns it, from a run's record.

    Parameters
    ----------
    record : dict
        The task's record (``fluoguide.runs`` store or ``run_tasks``'s records).
    arrays : dict
        Its arrays (``RunStore.arrays(record)`` or the record's ``_arrays``).

    Returns
    -------
    dict
        ``results`` (each method's numbers and ``yield``), ``coarse`` (a Mesh),
        ``profiles`` and ``profile_depth_mm`` (tube), the optode positions,
        ``frame_example``, ``sections`` (:func:`section_images`' dict) and
        every other number of the case; no simulation mesh (``fine``);
        ``surface_truth`` (a tube case's :class:`.tube_truth.SurfaceTruth`)
        where the case simulated it.
    """
    from FluoTomoLib.meshing.mesh import Mesh

    if record.get("status") != "ok":
        raise FluoInputError(f"the case failed: {record.get('error')}", field="case",
                             value=record.get("params"))
    case = dict(record["result"]["case"])
    results = {m: dict(r) for m, r in case.pop("results").items()}
    for m in results:
        results[m]["yield"] = arrays[f"yield_{m}"]
    meta = case.pop("coarse_meta", {})
    case["coarse"] = Mesh(arrays["coarse_nodes_mm"], arrays["coarse_elements"],
                          arrays["coarse_region"], case.pop("coarse_name", "reconstruction"),
                          dict(meta))
    case["results"] = results
    for k in ("sources_true_mm", "sources_reported_mm", "detectors_mm", "frame_example"):
        case[k] = arrays[k]
    if "profile_depth_mm" in arrays:
        case["profile_depth_mm"] = arrays["profile_depth_mm"]
        case["profiles"] = {k[len("profile_"):]: v for k, v in arrays.items()
                            if k.startswith("profile_") and k != "profile_depth_mm"}
    case["sections"] = {k[len("section_"):]: v for k, v in arrays.items()
                        if k.startswith("section_")}
    if "truth_fields_per_w" in arrays:
        from FluoTomoLib.pipelines.tube_truth import SurfaceTruth

        case["surface_truth"] = SurfaceTruth(
            arrays["truth_vertices_mm"], arrays["truth_facets"], arrays["truth_fields_per_w"],
            arrays["truth_sources_mm"], dict(case.get("truth") or {}))
    return case
