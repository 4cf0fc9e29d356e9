"""Studies as data: a grid of targets, methods, lambdas, noise, seeds and meshes,
expanded into the run engine's tasks (``fluoguide.runs``).

A study is a :class:`StudySpec`; it comes from a named study (A, B, C), a named
sweep (lambda, noise, mesh, roi), a study file (JSON/YAML) or ``--grid`` options,
in any mix (:func:`spec_from_mapping`). :func:`study_tasks` turns it into one
task per reconstruction, each needing three shared inputs that are computed once
per distinct model (:mod:`FluoTomoLib.studies.thesis`):

- ``data``: the Jacobian of the mesh the measurements are simulated on (the
  whole domain; by default the forward mesh itself, as in the thesis);
- ``forward``: the reconstruction model's forward Jacobian (on the region of
  interest, when one is cut);
- ``recon``: that Jacobian mapped to the reconstruction mesh.

A study of six lambdas on one target computes each Jacobian once, not six times.

Study file keys (each one value or a list; all optional)::

    study: B                 # start from study A, B or C (its targets, methods, lambdas)
    sweep: lambda            # or a named sweep (lambda, noise, mesh, roi) ...
    values: [0.1, 1, 10]     # ... with these values instead of its defaults
    dim: 2                   # 2 (section) or 3 (slab); one value
    targets: [[6, 2.5], {diameter_mm: 15, top_depth_mm: 2.5, inner_diameter_mm: 13}]
    diameters_mm: [5, 10]    # or targets as diameters x depths
    depths_mm: [2.5, 4.5]
    methods: [NP, SP, HP]
    lambdas: [0.1, 10]
    noise_pct: [0.5, 1, 2]   # Gaussian relative noise, max amplitude in % (sigma = value / 3)
    seeds: [0, 1, 2]
    forward_mm: 0.5          # forward (Jacobian) mesh size
    recon_mm: [1.0, 1.5]     # reconstruction mesh size (pairs with recon < forward are skipped)
    data_mm: 0.25            # mesh the data are simulated on
    roi_depth_mm: [15, 30]   # depth of the modelled region (data always from the whole domain)
    scheme: nirfast          # or reference
    hp_basis: forward        # or reconstruction
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

from fluoguide.errors import FluoInputError
from fluoguide.runs.grid import as_list, convert, parse_values

from FluoTomoLib.studies.thesis import (
    STUDIES,
    SWEEPS,
    WIDTH_MM,
    SLAB_Y_MM,
    default_sizes_mm,
    forward_jacobian,
    full_depth_mm,
    mapped_jacobian,
    recon_options,
    reconstruction_task,
)

METHODS = ("NP", "SP", "HP")
MAX_NODES = 250_000          # a 240 x N Jacobian of 480 MB; more is not a study mesh
MAX_TASKS = 100_000
KEYS = ("study", "sweep", "values", "dim", "targets", "diameters_mm", "depths_mm", "methods",
        "lambdas", "noise_pct", "seeds", "forward_mm", "recon_mm", "data_mm", "roi_depth_mm",
        "scheme", "hp_basis")
# the parameter each named sweep varies, and its name in a study file
SWEEP_AXIS = {"lambda": "lambdas", "noise": "noise_pct", "mesh": "recon_mm", "roi": "roi_depth_mm"}
DEFAULT_TARGET = (6.0, 3.5)


@dataclass
class StudySpec:
    """A study's grid (see the module docstring); None: the default of that axis."""

    dim: int = 2
    targets: list = field(default_factory=list)    # dicts: case, diameter_mm, top_depth_mm, ...
    methods: list | None = None
    lambdas: list | None = None
    noise_pct: list = field(default_factory=lambda: [1.0])
    seeds: list = field(default_factory=lambda: [0])
    forward_mm: list | None = None
    recon_mm: list | None = None
    data_mm: list | None = None
    roi_depth_mm: list | None = None
    scheme: list = field(default_factory=lambda: ["nirfast"])
    hp_basis: list = field(default_factory=lambda: ["forward"])
    label: str = "custom"
    sweep: str | None = None
    warnings: list = field(default_factory=list)
    file: str | None = None


def _target(case, diameter_mm, top_depth_mm, inner_diameter_mm=0.0, prior_diameter_mm=None,
            lambdas=None):
    return dict(case=case, diameter_mm=float(diameter_mm), top_depth_mm=float(top_depth_mm),
                inner_diameter_mm=float(inner_diameter_mm or 0.0),
                prior_diameter_mm=None if prior_diameter_mm is None else float(prior_diameter_mm),
                lambdas=lambdas)


def _custom(d, depth, dim):
    shape = "disc" if dim == 2 else "sphere"
    return _target(f"custom: {d:g} mm {shape}, top {depth:g} mm", d, depth)


def study_spec(name, target=None, dim=2, file=None, **axes):
    """Study A, B or C (or one custom ``target`` = (diameter, top depth))."""
    spec = StudySpec(dim=_dim(dim, file), file=None if file is None else str(file), **axes)
    if target is not None:
        spec.targets = [_custom(float(target[0]), float(target[1]), spec.dim)]
        spec.label = "custom"
    elif name in STUDIES:
        spec.targets = [_target(c, **kw) for c, kw in STUDIES[name]]
        spec.label = name
    else:
        raise FluoInputError("study must be A, B or C (or a study file .json/.yaml)",
                             file=file, field="study", value=name)
    if spec.dim == 3:
        for t in spec.targets:
            t["case"] = t["case"].replace("disc", "sphere").replace("annulus", "spherical shell")
    return spec


def sweep_spec(kind, target=DEFAULT_TARGET, dim=2, values=None, file=None, **axes):
    """One target, one axis varied: lambda, noise [%], mesh (reconstruction size,
    and the forward size too: pairs with recon >= forward) or roi (depth of the
    modelled region [mm]; the data come from the whole domain)."""
    if kind not in SWEEPS:
        raise FluoInputError(f"sweep must be one of {', '.join(SWEEPS)}", file=file,
                             field="sweep", value=kind)
    spec = study_spec(None, target=target or DEFAULT_TARGET, dim=dim, file=file, **axes)
    spec.label, spec.sweep = f"sweep {kind}", kind
    axis = SWEEP_AXIS[kind]
    # the sweep's values: given, else the axis as the caller set it, else the defaults
    vals = list(values) if values is not None else axes.get(axis)
    if vals is None:
        vals = list(SWEEPS[kind])
        if kind == "mesh" and spec.dim == 3:
            vals = [1.5 * v for v in vals]
        if kind == "roi" and spec.dim == 3:
            vals = [v for v in vals if v <= full_depth_mm(3)]
    setattr(spec, axis, vals)
    if kind == "lambda" and spec.methods is None:
        spec.methods = list(METHODS)
    if kind == "mesh" and spec.forward_mm is None:
        f = default_sizes_mm(spec.dim)[0]
        spec.forward_mm = [f, 1.5 * f, 2 * f]
    return spec


def spec_from_mapping(doc, file=None):
    """A StudySpec from a study file's mapping (or the CLI's options as one)."""
    unknown = [k for k in doc if k not in KEYS]
    if unknown:
        raise FluoInputError(f"unknown setting; known: {', '.join(KEYS)}", file=file,
                             field=unknown[0])

    def one(key, kind, default):
        v = doc.get(key, default)
        if isinstance(v, (list, tuple)):
            if len(v) != 1:
                raise FluoInputError("takes one value", file=file, field=key, value=v)
            v = v[0]
        return v if v is None else convert(v, key, kind, file)

    def many(key, kind):
        if doc.get(key) is None:
            return None
        return parse_values(as_list(doc[key]), key, kind, file)

    dim = _dim(one("dim", int, 2), file)
    axes = {}
    for key, kind in (("methods", str), ("lambdas", float), ("noise_pct", float), ("seeds", int),
                      ("forward_mm", float), ("recon_mm", float), ("data_mm", float),
                      ("roi_depth_mm", float), ("scheme", str), ("hp_basis", str)):
        vals = many(key, kind)
        if vals is not None:
            axes[key] = vals
    sweep = one("sweep", str, None)
    targets = _targets_from(doc, dim, file)
    if sweep is not None:
        if sweep not in SWEEPS:
            raise FluoInputError(f"sweep must be one of {', '.join(SWEEPS)}", file=file,
                                 field="sweep", value=sweep)
        if targets is not None and len(targets) != 1:
            raise FluoInputError("a sweep has one target", file=file, field="targets",
                                 value=len(targets))
        kind = float
        values = many("values", kind)
        if values is not None and SWEEP_AXIS[sweep] in axes:
            raise FluoInputError(f"give the {sweep} values once (values or "
                                 f"{SWEEP_AXIS[sweep]})", file=file, field="values")
        t = (targets[0]["diameter_mm"], targets[0]["top_depth_mm"]) if targets else None
        spec = sweep_spec(sweep, target=t, dim=dim, values=values, file=file, **axes)
    else:
        if doc.get("values") is not None:
            raise FluoInputError("values belong to a sweep (set sweep: lambda, noise, mesh or "
                                 "roi)", file=file, field="values")
        name = one("study", str, None)
        if targets is not None:
            spec = StudySpec(dim=dim, targets=targets, file=file, **axes)
            spec.label = name or "custom"
            if name is not None:
                raise FluoInputError("give a study name or targets, not both", file=file,
                                     field="study", value=name)
        elif name is not None:
            spec = study_spec(name, dim=dim, file=file, **axes)
        else:
            raise FluoInputError("a study file names a study (A, B, C), a sweep or targets",
                                 file=file)
    spec.file = None if file is None else str(file)
    return spec


def _targets_from(doc, dim, file):
    targets = []
    if doc.get("targets") is not None:
        if doc.get("diameters_mm") is not None or doc.get("depths_mm") is not None:
            raise FluoInputError("give targets or diameters_mm x depths_mm, not both", file=file,
                                 field="targets")
        for i, t in enumerate(as_list(doc["targets"])):
            where = f"targets[{i}]"
            if isinstance(t, str):
                t = t.split(",")
            if isinstance(t, (list, tuple)):
                if len(t) != 2:
                    raise FluoInputError("a target is [diameter_mm, top_depth_mm]", file=file,
                                         field=where, value=t)
                d, depth = (convert(v, where, float, file) for v in t)
                targets.append(_custom(d, depth, dim))
            elif isinstance(t, dict):
                allowed = ("diameter_mm", "top_depth_mm", "inner_diameter_mm", "prior_diameter_mm",
                           "case")
                bad = [k for k in t if k not in allowed]
                if bad or "diameter_mm" not in t or "top_depth_mm" not in t:
                    raise FluoInputError("a target has diameter_mm and top_depth_mm (and "
                                         "optionally inner_diameter_mm, prior_diameter_mm, case)",
                                         file=file, field=where, value=bad or sorted(t))
                kw = {k: convert(t[k], f"{where}.{k}", float, file) for k in allowed[:4]
                      if t.get(k) is not None}
                case = t.get("case") or _custom(kw["diameter_mm"], kw["top_depth_mm"], dim)["case"]
                if not isinstance(case, str):
                    raise FluoInputError("a case name is text", file=file, field=f"{where}.case",
                                         value=case)
                targets.append(_target(case, **kw))
            else:
                raise FluoInputError("a target is [diameter_mm, top_depth_mm] or a mapping",
                                     file=file, field=where, value=t)
    elif doc.get("diameters_mm") is not None or doc.get("depths_mm") is not None:
        ds = parse_values(as_list(doc.get("diameters_mm", 6.0)), "diameters_mm", float, file)
        zs = parse_values(as_list(doc.get("depths_mm", 3.5)), "depths_mm", float, file)
        targets = [_custom(d, z, dim) for d in ds for z in zs]
    else:
        return None
    if not targets:
        raise FluoInputError("the target list is empty", file=file, field="targets")
    return targets


def _dim(dim, file=None):
    if dim not in (2, 3) or isinstance(dim, bool):
        raise FluoInputError("dimension must be 2 or 3", file=file, field="dim", value=dim)
    return int(dim)


def _nodes(dim, h, depth):
    n = (WIDTH_MM / h + 1) * (depth / h + 1)
    return n * (SLAB_Y_MM / h + 1) if dim == 3 else n


def check_params(p, file=None):
    """Refuse a task whose parameters cannot run (one line: field and value)."""
    def bad(problem, key, value):
        raise FluoInputError(problem, file=file, field=key, value=value)

    if p["method"] not in METHODS:
        bad("method must be NP, SP or HP", "methods", p["method"])
    recon_options(p["scheme"], p["hp_basis"])
    lam = p["lambda"]
    if not (math.isfinite(lam) and 0 < lam <= 1e12):
        bad("lambda must be > 0 and <= 1e12", "lambdas", lam)
    if not (0 <= p["noise_pct"] <= 1000):
        bad("noise must be 0 to 1000 % (max amplitude)", "noise_pct", p["noise_pct"])
    if not (0 <= p["seed"] < 2 ** 32):
        bad("seed must be 0 to 2^32 - 1", "seeds", p["seed"])
    dim, full = p["dim"], full_depth_mm(p["dim"])
    roi = p["roi_depth_mm"]
    if not (0 < roi <= full):
        bad(f"the region of interest's depth must be > 0 and <= {full:g} mm", "roi_depth_mm", roi)
    for key in ("forward_mm", "recon_mm", "data_mm"):
        h = p[key]
        if not (0.05 <= h <= 10.0):
            bad("mesh size must be 0.05 to 10 mm", key, h)
        depth = full if key == "data_mm" else roi
        if h > depth / 2:
            bad(f"mesh size must be at most half the modelled depth ({depth:g} mm)", key, h)
        if _nodes(dim, h, depth) > MAX_NODES:
            bad(f"mesh size gives ~{_nodes(dim, h, depth):,.0f} nodes in {dim}D; at most "
                f"{MAX_NODES:,}", key, h)
    d, top, inner = p["diameter_mm"], p["top_depth_mm"], p["inner_diameter_mm"]
    prior = p["prior_diameter_mm"]
    limit = min(full, roi) - 2
    if not (0 < d < limit) or top < 0 or top + d > limit:
        bad(f"target must fit inside the modelled {limit + 2:g} mm depth with 2 mm to spare",
            "target", (d, top))
    if not (0 <= inner < d):
        bad("inner diameter must be 0 (a disc) or less than the diameter", "inner_diameter_mm",
            inner)
    if prior is not None and not (0 < prior and top + prior <= limit):
        bad("prior diameter must be > 0 and fit inside the domain", "prior_diameter_mm", prior)


def study_tasks(spec):
    """The run engine's tasks of a study, in table order: target, meshes, region of
    interest, scheme, noise, seed, method, lambda (the last varies fastest)."""
    from fluoguide.runs.tasks import Shared, Task

    dim = spec.dim
    f0, r0 = default_sizes_mm(dim)
    fwd = spec.forward_mm or [f0]
    rec = spec.recon_mm or [r0]
    pairs = [(f, r) for f in fwd for r in rec if r >= f]
    skipped = [(f, r) for f in fwd for r in rec if r < f]
    if not pairs:
        raise FluoInputError("every reconstruction mesh is finer than every forward mesh",
                             file=spec.file, field="recon_mm", value=rec)
    if skipped:
        spec.warnings.append("skipped mesh pairs with a reconstruction mesh finer than the "
                             "forward mesh (forward_mm, recon_mm): "
                             + ", ".join(f"({f:g}, {r:g})" for f, r in skipped))
    data = spec.data_mm
    if data is None and len(set(fwd)) > 1:
        # comparing forward meshes needs data from none of them
        data = [round(min(fwd) * (0.5 if dim == 2 else 0.75), 6)]
        spec.warnings.append(f"data simulated on a {data[0]:g} mm mesh, finer than every forward "
                             f"mesh (set data_mm to choose)")
    rois = spec.roi_depth_mm or [full_depth_mm(dim)]
    methods = spec.methods or list(METHODS)
    for m in methods:
        if m not in METHODS:
            raise FluoInputError("method must be NP, SP or HP", file=spec.file, field="methods",
                                 value=m)
    n_lam = max(len(spec.lambdas or (t.get("lambdas") or {}).get(m, [10.0]))
                for t in spec.targets for m in methods) if spec.targets else 0
    total = (len(spec.targets) * len(pairs) * len(data or [0]) * len(rois) * len(spec.scheme)
             * len(spec.hp_basis) * len(spec.noise_pct) * len(spec.seeds) * len(methods) * n_lam)
    if total > MAX_TASKS:
        raise FluoInputError(f"the study has {total:,} tasks; at most {MAX_TASKS:,} in one run",
                             file=spec.file, field="grid", value=total)
    if not spec.targets:
        raise FluoInputError("the study has no target", file=spec.file, field="targets")

    shared = {}

    def jac(h, depth):
        name = f"jacobian {dim}D {h:g} mm, depth {depth:g} mm"
        if name not in shared:
            shared[name] = Shared(name, forward_jacobian, (dim, h, depth))
        return shared[name]

    def mapped(f, r, depth):
        name = f"mapped {dim}D {f:g} -> {r:g} mm, depth {depth:g} mm"
        if name not in shared:
            shared[name] = Shared(name, mapped_jacobian, (jac(f, depth), dim, f, r, depth))
        return shared[name]

    full = full_depth_mm(dim)
    sweep_key = {"lambda": "lambda", "noise": "noise_pct", "mesh": "recon_mm",
                 "roi": "roi_depth_mm"}.get(spec.sweep)
    tasks = []
    for t, (f, r), dm, roi, scheme, hp, noise, seed, m in itertools.product(
            spec.targets, pairs, data or [None], rois, spec.scheme, spec.hp_basis,
            spec.noise_pct, spec.seeds, methods):
        f, r, roi = float(f), float(r), float(roi)
        dm = f if dm is None else float(dm)
        for lam in spec.lambdas or (t.get("lambdas") or {}).get(m, [10.0]):
            p = {"case": t["case"], "dim": dim, "diameter_mm": t["diameter_mm"],
                 "top_depth_mm": t["top_depth_mm"], "inner_diameter_mm": t["inner_diameter_mm"],
                 "prior_diameter_mm": t["prior_diameter_mm"], "method": m, "lambda": float(lam),
                 "noise_pct": float(noise), "seed": int(seed), "forward_mm": f, "recon_mm": r,
                 "data_mm": dm, "roi_depth_mm": roi, "scheme": scheme, "hp_basis": hp}
            if sweep_key:
                p["sweep"], p["value"] = spec.sweep, p[sweep_key]
            check_params(p, spec.file)
            tasks.append(Task(reconstruction_task, p, {"data": jac(dm, full),
                                                       "forward": jac(f, roi),
                                                       "recon": mapped(f, r, roi)}))
    return tasks
