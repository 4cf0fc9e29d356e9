"""Running the thesis's studies: a study, a sweep, one case or any study spec
on the run engine (``fluoguide.runs``), with the result table and figures.

The layers of ``FluoTomoLib.studies``, each importing only those before it:
``thesis`` (domain, meshes, shared Jacobians, one reconstruction task, the
studies' targets), ``spec`` (a study as data, expanded into tasks), ``plots``
(figures), and this module, which runs a spec and gathers what it made.
"""

from __future__ import annotations

from fluoguide.runs.engine import run_tasks
from fluoguide.runs.store import RunStore

from FluoTomoLib.studies.spec import StudySpec, study_spec, study_tasks, sweep_spec
from FluoTomoLib.studies.thesis import (
    N_SOURCES,
    disc,
    domain_mesh,
    full_depth_mm,
    study_meshes,
    true_yield,
)


def run_case(case, diameter_mm, top_depth_mm, inner_diameter_mm=0.0, prior_diameter_mm=None,
             methods=("NP", "SP", "HP"), lambdas=None, seed=0, noise_pct=1.0, meshes=None,
             scheme="nirfast", hp_basis="forward", progress=None, cancel=None):
    """One target through NP/SP/HP in this process; returns (rows, figure data).

    ``scheme``: "nirfast" or "reference" (module docstring); ``hp_basis``:
    "forward" (HP's region Jacobian J_f K_f from node regions of the forward
    mesh) or "reconstruction" (J_f P K from those of the reconstruction mesh).
    ``meshes``: (forward, reconstruction) from :func:`study_meshes` (their sizes
    are used). Many cases at once: :func:`run_study` or the run engine.
    """
    fine, coarse = meshes or study_meshes()
    spec = StudySpec(dim=fine.dim, forward_mm=[fine.meta["size_mm"]],
                     recon_mm=[coarse.meta["size_mm"]], methods=list(methods),
                     seeds=[seed], noise_pct=[noise_pct], scheme=[scheme], hp_basis=[hp_basis],
                     targets=[dict(case=case, diameter_mm=diameter_mm, top_depth_mm=top_depth_mm,
                                   inner_diameter_mm=inner_diameter_mm,
                                   prior_diameter_mm=prior_diameter_mm, lambdas=lambdas)])
    out = run_tasks(study_tasks(spec), progress=progress, cancel=cancel, label=case)
    return out["rows"], case_fields(out["records"])

def case_fields(records, arrays=None):
    """Figure data of one case's records: the truth on the data mesh, then each
    method's reconstruction (``arrays(record)`` -> its saved arrays)."""
    first = records[0]["params"]
    dim = int(first["dim"])
    data_mesh = domain_mesh(dim, first["data_mm"], full_depth_mm(dim))
    inside, _ = disc(first["diameter_mm"], first["top_depth_mm"], first["inner_diameter_mm"])
    fields = {"truth": (data_mesh, true_yield(data_mesh, inside))}
    for rec in records:
        a = arrays(rec) if arrays is not None else (rec.get("_arrays") or {})
        if rec["status"] == "ok" and "yield_per_mm" in a:
            p = rec["params"]
            coarse = domain_mesh(dim, p["recon_mm"], p["roi_depth_mm"])
            fields[f"{p['method']} (lambda {p['lambda']:g})"] = (coarse, a["yield_per_mm"])
    return fields

def run_study(name, seed=0, target=None, out_dir=None, dim=2, scheme="nirfast",
              hp_basis="forward", progress=None, cancel=None, executor=None, resume=False,
              threads=1):
    """Run study A, B or C (or one custom ``target`` = (diameter, top depth)), in 2D
    (discs in a 50 x 30 mm section) or 3D (spheres in a 50 x 30 x 20 mm slab),
    with a reconstruction ``scheme`` and ``hp_basis`` as in :func:`run_case`.

    ``executor`` (``fluoguide.runs``): serial in this process by default, or a
    Dask cluster; ``out_dir``: the run folder (table.csv, one record per task,
    figures), resumable with ``resume``.
    """
    spec = study_spec(name, target=target, dim=dim, seeds=[seed], scheme=[scheme],
                      hp_basis=[hp_basis])
    return run_spec(spec, out_dir=out_dir, progress=progress, cancel=cancel, executor=executor,
                    resume=resume, threads=threads)

def run_sweep(kind, target=(6.0, 3.5), dim=2, seed=0, scheme="nirfast", hp_basis="forward",
              progress=None, cancel=None, values=None, out_dir=None, executor=None, resume=False,
              threads=1):
    """Error against time for one target as lambda, noise [% max amplitude], the
    mesh sizes [mm] or the region of interest's depth [mm] varies: the
    speed/accuracy trade a user makes (:func:`FluoTomoLib.studies.spec.sweep_spec`)."""
    spec = sweep_spec(kind, target=target, dim=dim, values=values, seeds=[seed],
                      scheme=[scheme], hp_basis=[hp_basis])
    return run_spec(spec, out_dir=out_dir, progress=progress, cancel=cancel, executor=executor,
                    resume=resume, threads=threads)

def run_spec(spec, out_dir=None, progress=None, cancel=None, executor=None, resume=False,
             threads=1):
    """Run a study spec on the run engine; the study's result dict.

    Returns ``rows`` (one per task, task order), ``failed``, the run's
    counts and executor, mesh sizes, ``warnings``, and with ``out_dir`` the
    figures: ``error_vs_time.png`` and, when only the target, method and
    lambda vary (studies A, B, C, a custom target), one PNG per target
    (truth | NP | SP | HP).
    """
    tasks = study_tasks(spec)
    store = RunStore(out_dir, resume=resume) if out_dir is not None else None
    out = run_tasks(tasks, store=store, executor=executor, threads=threads, progress=progress,
                    cancel=cancel, label=spec.label)
    records = out.pop("records")
    first = tasks[0].params
    fine = domain_mesh(spec.dim, first["forward_mm"], first["roi_depth_mm"])
    coarse = domain_mesh(spec.dim, first["recon_mm"], first["roi_depth_mm"])
    result = {"study": spec.label, "dim": spec.dim, **out,
              "forward_mesh": [fine.n_nodes, fine.n_elements],
              "reconstruction_mesh": [coarse.n_nodes, coarse.n_elements],
              "measurements": N_SOURCES * (N_SOURCES - 1),
              "noise": "Gaussian, sigma = noise_pct / 3 % relative (max ~noise_pct %)",
              "scheme": spec.scheme[0] if len(spec.scheme) == 1 else spec.scheme,
              "hp_basis": spec.hp_basis[0] if len(spec.hp_basis) == 1 else spec.hp_basis,
              "figures": []}
    if out["failures"]:
        spec.warnings.append(f"{out['failures']} of {out['tasks']} tasks failed: their rows have "
                             f"status 'failed' and the error")
    result["warnings"] = list(spec.warnings)
    if spec.sweep:
        result["sweep"] = spec.sweep
        result["target"] = [first["diameter_mm"], first["top_depth_mm"]]
    if out_dir is not None:
        from FluoTomoLib.studies.plots import plot_case, plot_error_vs_time

        result["error_vs_time"] = plot_error_vs_time(out["rows"], out_dir, title=spec.label)
        single = all(len({(r["params"][k]) for r in records}) == 1 for k in (
            "forward_mm", "recon_mm", "data_mm", "roi_depth_mm", "noise_pct", "seed", "scheme",
            "hp_basis"))
        if single and not spec.sweep:
            groups = {}
            for rec in records:
                groups.setdefault(rec["params"]["case"], []).append(rec)
            for i, (case, recs) in enumerate(groups.items()):
                result["figures"].append(plot_case(out_dir, i, case,
                                                   case_fields(recs, store.arrays)))
    return result
