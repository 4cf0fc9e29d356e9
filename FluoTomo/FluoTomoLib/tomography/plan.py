"""Planning a scan: where the tracked laser should enter the tissue so that the
targets' yields come out with the narrowest intervals (issue #36).

:func:`plan_scan` lays candidate entry points on the skin the camera can see
near the targets, screens each candidate's sensitivity to every labelled
region with the scan-coverage model (half-space diffusion Green's functions,
no mesh and no solve: :func:`FluoTomoLib.tomography.coverage.region_sensitivity`),
and chooses the sources one at a time (greedy, then exchange passes while the
time budget lasts) to minimise the sum over the targets of the predicted
relative variance of the hard-prior (HP) estimate. The detectors are the
default scan's detector grid over each target (:func:`default_scan`). The
criterion and its approximations: docs/physics.md section 8.6.

The plan's pairs are every source-detector pair farther apart than
``exclude_mm``: what ``fluo tomo simulate --sources/--detectors`` measures of
the same points.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

#: two-sided 95 % normal quantile
Z95 = 1.959964
#: a target whose predicted 95 % interval (its noise part) is wider than +-this %
#: of its yield is reported as not covered: the family's bar for a narrow
#: interval (docs/validation.md, "The scene family"), which the model's error and
#: the resolution's bias only widen
COVERED_HALF_WIDTH_PCT = 20.0
#: the planner's assumed yields when none are given: every label but the body at
#: 1, the body (the largest label) at 1/PLAN_CONTRAST (only ratios matter)
PLAN_CONTRAST = 100.0
#: quadrature points per region in the planner's screen (coverage uses 40,000;
#: the design needs ratios between candidates, smooth at this density)
PLAN_POINTS_PER_REGION = 8000
#: most candidate entry points (the candidate pitch grows until they fit)
MAX_CANDIDATES = 1500
#: candidates per batch of the sensitivity screen (progress between batches)
BATCH = 64


def _check_number(v, name, lo, hi, integer=False, lo_open=False):
    ok = v is not None and not isinstance(v, bool)
    try:
        f = float(v)
    except (TypeError, ValueError):
        ok = False
        f = float("nan")
    ok = ok and np.isfinite(f) and (f > lo if lo_open else f >= lo) and f <= hi
    if integer:
        ok = ok and f == int(f)
    if not ok:
        kind = "an integer" if integer else "a number"
        raise FluoInputError(f"must be {kind} within {'(' if lo_open else '['}{lo:g}, {hi:g}]",
                             field=name, value=v)
    return int(f) if integer else f


def _direction(v, name):
    try:
        d = np.asarray(v, float).reshape(3)
    except (TypeError, ValueError):
        raise FluoInputError("must be three numbers x,y,z (RAS)", field=name,
                             value=v) from None
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise FluoInputError("must be a finite, non-zero direction (RAS)", field=name,
                             value=np.asarray(v).tolist())
    return d / np.linalg.norm(d)


def _candidates(lm, skin_points, visible, pitch_mm, reach_mm, camera_local=None):
    """Candidate entry points (local mm) and their outward normals: skin triangle
    centres within ``reach_mm`` of a target's skin point whose normal is within
    the visibility cone, thinned to one per ``pitch_mm`` cell."""
    surf = lm.surface()
    skin = surf.skin_only()
    centres = skin.points[skin.triangles].mean(axis=1)
    normals = skin.normals / np.linalg.norm(skin.normals, axis=1, keepdims=True)
    d_near = np.min(np.linalg.norm(centres[:, None] - skin_points[None], axis=2), axis=1)
    keep = visible(centres, normals) & (d_near <= reach_mm)
    c, n, dn = centres[keep], normals[keep], d_near[keep]
    if camera_local is not None and len(c):       # no other tissue between it and the camera
        to = c - camera_local
        dist = np.linalg.norm(to, axis=1)
        hit, face = surf.cast(np.tile(camera_local, (len(c), 1)), to / dist[:, None])
        seen = (face >= 0) & (np.linalg.norm(hit - c, axis=1) <= 0.5)
        c, n, dn = c[seen], n[seen], dn[seen]
    pitch = float(pitch_mm)
    while True:
        order = np.argsort(dn, kind="stable")       # nearest the targets first
        cells = np.floor(c[order] / pitch).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        idx = order[np.sort(first)]
        if len(idx) <= MAX_CANDIDATES:
            break
        pitch *= 1.25
    c, n = c[idx], n[idx]
    if len(c):
        ok = surf.closest_is_skin(c)               # not onto a cut face
        c, n = c[ok], n[ok]
    return c, n, pitch


def _design_matrices(parts, labels, mask, yields, noise_rel):
    """Per source: h_s = sum_d A_sd A_sd^T and q_s = sum_d sigma_sd^2 A_sd A_sd^T
    (R x R, in columns scaled by ``scale``), A_sd the regions' sensitivities
    of pair (s, d), sigma_sd = noise_rel * y_sd its noise SD."""
    A = np.stack([parts[lab] for lab in labels], axis=-1)          # (S, D, R)
    scale = np.maximum(np.abs(A).reshape(-1, len(labels)).max(axis=0), 1e-300)
    A = A / scale
    y = A @ (yields * scale)                                        # (S, D) signal
    sig2 = (noise_rel * y) ** 2
    Am = A * mask[..., None]
    h = np.einsum("sdr,sdq->srq", Am, Am)
    q = np.einsum("sdr,sd,sdq->srq", Am, sig2, Am)
    return h, q, scale


def _variances(H, Q):
    """diag(H^-1 Q H^-1) for a stack of (R, R) H and Q (the sandwich variance of
    the unweighted least-squares estimate), inf where H is singular."""
    R = H.shape[-1]
    tr = np.trace(H, axis1=-2, axis2=-1)[..., None, None]
    Hr = H + 1e-13 * tr * np.eye(R)
    try:
        Hi = np.linalg.inv(Hr)
    except np.linalg.LinAlgError:
        Hi = np.linalg.pinv(Hr)
    V = np.einsum("...ij,...jk,...lk->...il", Hi, Q, Hi)
    var = np.diagonal(V, axis1=-2, axis2=-1).copy()
    cond_bad = np.linalg.cond(Hr) > 1e14
    var[cond_bad] = np.inf
    return var


def _predict(var, labels, targets, yields, scale, noise_pct):
    """The HP prediction per target from the scaled variances."""
    out = {}
    for t in targets:
        r = labels.index(t)
        v = float(var[r])
        sd = np.sqrt(v) / scale[r] if np.isfinite(v) else float("inf")
        y = float(yields[r])
        hw_pct = 100.0 * Z95 * sd / y if np.isfinite(sd) else float("inf")
        finite = bool(np.isfinite(hw_pct))
        out[str(t)] = {
            "assumed_yield_per_mm": y,
            "sd_per_mm": float(sd) if finite else None,
            "half_width_pct": round(float(hw_pct), 4) if finite else None,
            "ci95_per_mm": [float(y - Z95 * sd), float(y + Z95 * sd)] if finite else None,
            "covered": bool(finite and hw_pct <= COVERED_HALF_WIDTH_PCT)}
    return out


def _objective(var, t_idx, yields_scaled):
    """Sum over targets of the relative variance (scaled units cancel)."""
    return np.sum(var[..., t_idx] / yields_scaled[t_idx] ** 2, axis=-1)


def _pair_mask(src, det, exclude_mm):
    return np.linalg.norm(src[:, None] - det[None], axis=2) > exclude_mm


def predict_scan(lm, optics, sources_ras, detectors_ras, targets, mask=None,
                 yield_by_label=None, noise_pct=1.0, exclude_mm=3.0,
                 points_per_region=PLAN_POINTS_PER_REGION):
    """The predicted HP 95 % interval of each target for a given scan.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics
    sources_ras, detectors_ras : (S, 3), (D, 3) RAS mm on the skin
    targets : list of int, the labels predicted
    mask : (S, D) bool, the pairs measured (None: every pair farther apart than
        ``exclude_mm``; a given mask is also limited to them)
    yield_by_label : {label: assumed yield [1/mm]} (None: see PLAN_CONTRAST)
    noise_pct : relative noise per measurement [%]
    exclude_mm : pairs closer than this are not measured [mm]
    points_per_region : quadrature points per region of the screen

    Returns
    -------
    {label str: {assumed_yield_per_mm, sd_per_mm, half_width_pct, ci95_per_mm, covered}}
    """
    from FluoTomoLib.tomography.coverage import region_sensitivity

    src = lm.to_local(sources_ras)
    det = lm.to_local(detectors_ras)
    surf = lm.surface()
    _, ns, _ = surf.closest(src)
    _, nd, _ = surf.closest(det)
    parts, _, body = region_sensitivity(lm, optics, src, -ns, det, -nd, points_per_region)
    labels = sorted(parts)
    yields = _assumed_yields(lm, labels, body, yield_by_label)
    m = _pair_mask(src, det, exclude_mm)
    if mask is not None:
        m = m & np.asarray(mask, bool)
    h, q, scale = _design_matrices(parts, labels, m, yields, noise_pct / 100.0)
    var = _variances(h.sum(axis=0), q.sum(axis=0))
    return _predict(var, labels, list(targets), yields, scale, noise_pct)


def _assumed_yields(lm, labels, body, yield_by_label):
    if yield_by_label is None:
        return np.array([1.0 / PLAN_CONTRAST if lab == body else 1.0 for lab in labels])
    y = np.array([float(yield_by_label.get(lab, 0.0)) for lab in labels])
    return y


def check_plan_inputs(lm, targets, positions, min_spacing_mm=2.0, noise_pct=1.0,
                      visible_from=None, max_angle_deg=60.0, camera_ras=None,
                      yield_by_label=None, time_budget_s=60.0, reach_mm=None,
                      exclude_mm=3.0, detectors_per_side=None):
    """The planner's input checked (cheap: before any work); refused in one line
    naming the field. Returns the targets as a list of int."""
    from FluoTomoLib.tomography.simulate import check_scan_targets, check_yields

    targets = check_scan_targets(lm, targets, field="targets")
    if targets is None:
        raise FluoInputError("name at least one target label", field="targets")
    _check_number(positions, "positions", 1, 256, integer=True)
    _check_number(min_spacing_mm, "min_spacing_mm", 0, 30)
    _check_number(noise_pct, "noise_pct", 0, 100, lo_open=True)
    _check_number(max_angle_deg, "max_angle_deg", 0, 90, lo_open=True)
    _check_number(time_budget_s, "time_budget_s", 0, 86400, lo_open=True)
    _check_number(exclude_mm, "exclude_mm", 0, 100)
    if reach_mm is not None:
        _check_number(reach_mm, "reach_mm", 1, 200)
    if detectors_per_side is not None:
        _check_number(detectors_per_side, "detectors_per_side", 1, 32, integer=True)
    if visible_from is not None and camera_ras is not None:
        raise FluoInputError("give a camera position or a direction, not both",
                             field="visible_from")
    if visible_from is not None:
        _direction(visible_from, "visible_from")
    if camera_ras is not None:
        _direction(camera_ras, "camera_ras")         # three finite numbers
    if yield_by_label is not None:
        check_yields(lm, yield_by_label)
        zero = [t for t in targets if not yield_by_label.get(t, 0) > 0]
        if zero:
            raise FluoInputError("a target needs an assumed yield > 0 (its interval is "
                                 "relative to it)", field="yield", value=zero[0])
    return targets


def plan_scan(lm, optics, targets, positions=None, min_spacing_mm=2.0, noise_pct=1.0,
              visible_from=None, max_angle_deg=60.0, camera_ras=None, yield_by_label=None,
              time_budget_s=60.0, reach_mm=None, exclude_mm=3.0, detectors_per_side=None,
              candidate_pitch_mm=1.0, progress=None, cancel=None):
    """Choose the laser's entry points for ``targets`` (module docstring).

    Parameters
    ----------
    lm : LabelMap
    optics : Optics (every label of the map)
    targets : int or list of int, the labels whose yields the scan is for (at
        most MAX_SCAN_PATCHES)
    positions : int, laser positions to choose (None: as many as the default
        scan lays, 16 per patch)
    min_spacing_mm : no two entry points closer than this [mm]
    noise_pct : relative noise per measurement [%] (the noise model)
    visible_from : RAS direction (towards the camera) or None: a candidate's
        outward normal must lie within ``max_angle_deg`` of it (default: the
        mean outward normal of the skin points nearest the targets)
    max_angle_deg : the visibility cone's half-angle [deg]
    camera_ras : RAS position of the camera instead of a direction: within the
        cone of the direction to it, and not hidden behind other tissue
    yield_by_label : {label: assumed yield [1/mm]} (None: targets and every other
        label but the body 1, the body 1/PLAN_CONTRAST)
    time_budget_s : the planner's time [s]: the exchange passes stop when it is
        spent (the greedy choice is always finished)
    reach_mm : candidates within this of a target's skin point [mm] (None: the
        detector grid's half-span plus 1.5 diffusion lengths 1/mu_eff, at least
        8 mm)
    exclude_mm : pairs closer than this are not measured [mm]
    detectors_per_side : the detector grid per target (default scan's 7)
    candidate_pitch_mm : spacing of the candidate grid on the skin [mm]
    progress, cancel : fluoguide.progress reporter and cancel token

    Returns
    -------
    dict: ``sources_ras`` (N, 3), ``detectors_ras`` (D, 3), ``mask`` (N, D) bool,
    ``approach_ras`` (N, 3) unit inward normals (the laser's direction),
    ``predicted`` {"HP": {label: ...}, "SP": None}, ``default_scan_predicted``
    (the default grid's HP prediction with as many positions), ``candidates``,
    ``objective``, ``assumptions``, ``warnings``, ``seconds``
    """
    from FluoTomoLib.tomography.simulate import default_scan

    t0 = time.perf_counter()
    targets = check_plan_inputs(lm, targets, 1 if positions is None else positions,
                                min_spacing_mm, noise_pct, visible_from, max_angle_deg,
                                camera_ras, yield_by_label, time_budget_s, reach_mm,
                                exclude_mm, detectors_per_side)
    optics.check_labels(lm.labels)
    report(progress, 0.0, "detector grid and candidate entry points")
    kw = {} if detectors_per_side is None else {"detectors_per_side": int(detectors_per_side)}
    d_src, det_ras, cfg = default_scan(lm, targets, **kw)
    if positions is None:
        positions = len(d_src)
    positions = int(positions)
    det = lm.to_local(det_ras)
    cands = _entry_candidates(lm, optics, cfg, positions, max_angle_deg, camera_ras,
                              visible_from, reach_mm, candidate_pitch_mm, cancel)
    cand, cand_n, reach = cands.points, cands.normals, cands.reach
    parts, last = _screen(lm, optics, cand, cand_n, det, cands.surface, progress, cancel)
    labels = sorted(parts)
    yields = _assumed_yields(lm, labels, cands.body, yield_by_label)
    mask_all = _pair_mask(cand, det, float(exclude_mm))
    h, q, scale = _design_matrices(parts, labels, mask_all, yields, noise_pct / 100.0)
    design = _Design(cand, h, q, [labels.index(t) for t in targets], yields * scale,
                     float(min_spacing_mm))
    chosen, H, Q, last = _choose_greedy(design, positions, reach, progress, cancel, last)
    chosen, H, Q, best, passes, warnings = _exchange_passes(
        design, chosen, H, Q, t0, time_budget_s, progress, cancel, last)
    chosen = np.array(chosen)
    src = cand[chosen]
    var = _variances(H, Q)
    predicted = _predict(var, labels, targets, yields, scale, noise_pct)
    report(progress, 0.95, "the default grid's prediction, for comparison")
    default_pred = _default_grid_prediction(lm, optics, d_src, det_ras, cfg, targets, positions,
                                            yield_by_label, noise_pct, exclude_mm)
    for t, p in predicted.items():
        if not p["covered"]:
            warnings.append(f"target {t} is not covered by the plan: its predicted 95 % "
                            f"interval is +-{p['half_width_pct']} % of its yield")
    mask = _pair_mask(src, det, float(exclude_mm))
    report(progress, 1.0, "planned")
    return {
        "sources_ras": lm.to_ras(src), "detectors_ras": det_ras, "mask": mask,
        "approach_ras": lm.vector_to_ras(-cand_n[chosen]),
        "targets": targets,
        "predicted": {"HP": predicted, "SP": None},
        "default_scan_predicted": None if default_pred is None else {"HP": default_pred},
        "objective": {"criterion": "sum over targets of the HP estimate's relative variance "
                      "(A-optimal on the region unknowns, sandwich variance of the "
                      "unweighted fit; docs/physics.md section 8.6)", "value": best,
                      "exchange_passes": passes},
        "candidates": {"count": int(len(cand)), "pitch_mm": cands.pitch, "reach_mm": reach,
                       "visibility": cands.view, "max_angle_deg": float(max_angle_deg)},
        "assumptions": _plan_assumptions(noise_pct, exclude_mm, design.spacing, positions,
                                         cfg, labels, yields),
        "warnings": warnings, "seconds": time.perf_counter() - t0,
        "default_scan_positions": int(len(d_src)),
        "detector_grid": {k: cfg[k] for k in ("detectors_per_side", "detector_pitch_mm")},
    }


@dataclass
class _Design:
    """The screen's design: what the greedy choice and the exchange passes share.

    ``cand`` (N, 3) candidate entry points [local mm]; ``h``, ``q`` (N, R, R)
    each candidate's information and sandwich matrices on the R region unknowns;
    ``t_idx`` the targets' indices among the regions; ``ys`` the assumed yields,
    scaled as ``h`` and ``q``; ``spacing`` the least distance between two entry
    points [mm].
    """

    cand: np.ndarray
    h: np.ndarray
    q: np.ndarray
    t_idx: list
    ys: np.ndarray
    spacing: float


@dataclass
class _Candidates:
    """The candidate entry points on the visible skin near the targets.

    ``points``, ``normals`` (N, 3) positions [local mm] and outward unit
    normals; ``pitch`` their grid's spacing [mm]; ``reach`` their largest
    distance from a target's skin point [mm]; ``view`` the visibility's
    description; ``body`` the largest label; ``surface`` the label map's
    surface.
    """

    points: np.ndarray
    normals: np.ndarray
    pitch: float
    reach: float
    view: str
    body: int
    surface: object


def _entry_candidates(lm, optics, cfg, positions, max_angle_deg, camera_ras, visible_from,
                      reach_mm, candidate_pitch_mm, cancel):
    """The candidate entry points (:class:`_Candidates`) for the default scan ``cfg``'s
    patches; FluoInputError when fewer than ``positions``."""
    surf = lm.surface()
    skin_pts = np.array([q["centre_ras_mm"] for q in cfg["patches"]])
    skin_pts = lm.to_local(skin_pts)
    _, skin_n, _ = surf.closest(skin_pts)
    visible, view, cam_local = _visibility(lm, skin_n, max_angle_deg, camera_ras,
                                           visible_from)
    body, reach = _body_and_reach(lm, optics, cfg, reach_mm)
    cand, cand_n, pitch = _candidates(lm, skin_pts, visible, candidate_pitch_mm, reach,
                                      cam_local)
    check_cancel(cancel)
    if len(cand) < positions:
        raise FluoInputError(f"only {len(cand)} candidate entry point(s) on the visible skin "
                             f"within {reach:.3g} mm of the targets (visibility: {view}, "
                             f"within {max_angle_deg:g} deg): ask for fewer positions or "
                             "widen the visibility", field="positions", value=positions)
    return _Candidates(cand, cand_n, pitch, reach, view, body, surf)


def _visibility(lm, skin_n, max_angle_deg, camera_ras, visible_from):
    """The visibility test of candidate entry points.

    Returns
    -------
    visible : callable (points (K, 3), outward normals (K, 3)) -> (K,) bool, local mm
    view : str, the visibility's description for messages and the plan
    cam_local : (3,) camera position [local mm], or None without ``camera_ras``
    """
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    cam_local = None
    if camera_ras is not None:
        cam_local = lm.to_local(np.asarray(camera_ras, float))[0]

        def visible(p, n):
            to = cam_local - p
            to /= np.linalg.norm(to, axis=1, keepdims=True)
            return np.sum(n * to, axis=1) >= cos_max
        view = "camera at " + ",".join(f"{v:g}" for v in np.asarray(camera_ras, float))
    else:
        if visible_from is not None:
            v = lm.vector_to_local(_direction(visible_from, "visible_from"))[0]
            view = "direction " + ",".join(f"{x:.3g}" for x in _direction(visible_from, ""))
        else:
            v = skin_n.mean(axis=0)
            v /= np.linalg.norm(v)
            view = "the mean outward normal over the targets"

        def visible(p, n):
            return n @ v >= cos_max
    return visible, view, cam_local


def _body_and_reach(lm, optics, cfg, reach_mm):
    """The body (the largest label) and the candidates' reach from a target's skin point.

    Returns
    -------
    body : int, the largest label
    reach : float [mm], ``reach_mm`` or the detector grid's half-span plus 1.5
        diffusion lengths 1/mu_eff of the body, at least 8 mm
    """
    from FluoTomoLib.analytic import robin_parameters

    body = max(lm.region_volumes(), key=lm.region_volumes().get)
    mx, sx = optics.excitation[body]
    mu_eff = robin_parameters(mx, sx, optics.n)[3]
    span = 0.5 * (cfg["detectors_per_side"] - 1) * cfg["detector_pitch_mm"]
    reach = float(reach_mm) if reach_mm is not None else max(8.0, span + 1.5 / mu_eff)
    return body, reach


def _screen(lm, optics, cand, cand_n, det, surf, progress, cancel):
    """Every candidate's sensitivity to every region, batch by batch.

    Returns
    -------
    parts : {label: (N, D) sensitivity of each candidate-detector pair}
    last : float, ``time.perf_counter()`` of the last progress report [s]
    """
    from FluoTomoLib.tomography.coverage import region_sensitivity

    _, det_n, _ = surf.closest(det)
    parts = None
    last = time.perf_counter()
    for b in range(0, len(cand), BATCH):
        check_cancel(cancel)
        p, _, _ = region_sensitivity(lm, optics, cand[b:b + BATCH], -cand_n[b:b + BATCH], det,
                                     -det_n, PLAN_POINTS_PER_REGION, cancel)
        parts = p if parts is None else {k: np.vstack([parts[k], p[k]]) for k in parts}
        if time.perf_counter() - last > 1.0 or b == 0:
            report(progress, 0.05 + 0.55 * min(1.0, (b + BATCH) / len(cand)),
                   f"sensitivity of {min(b + BATCH, len(cand))} of {len(cand)} candidates")
            last = time.perf_counter()
    return parts, last


def _allowed(design, chosen, excluding=None):
    """(N,) bool: the candidates not chosen and at least ``design.spacing`` [mm] from
    every chosen one (but ``excluding``, the position being exchanged)."""
    cand = design.cand
    ok = np.ones(len(cand), bool)
    for j in chosen:
        if j == excluding:
            continue
        ok &= np.linalg.norm(cand - cand[j], axis=1) >= design.spacing
    ok[[j for j in chosen]] = False
    return ok


def _choose_greedy(design, positions, reach, progress, cancel, last):
    """Choose ``positions`` entry points one at a time, each the best for the objective.

    ``reach`` [mm] is only for the message when the spacing leaves too few;
    ``last`` the time of the last progress report [s].

    Returns
    -------
    chosen : list of candidate indices
    H, Q : (R, R) the chosen candidates' summed information and sandwich matrices
    last : float, the time of the last progress report [s]
    """
    h, q, t_idx, ys, spacing = design.h, design.q, design.t_idx, design.ys, design.spacing
    R = h.shape[1]
    chosen = []
    H, Q = np.zeros((R, R)), np.zeros((R, R))
    for k in range(positions):
        check_cancel(cancel)
        free = _allowed(design, chosen)
        if not free.any():
            raise FluoInputError(f"only {k} entry points fit {spacing:g} mm apart on the "
                                 f"visible skin within {reach:.3g} mm of the targets: ask for "
                                 "fewer positions or a smaller spacing", field="positions",
                                 value=positions)
        obj = _objective(_variances(H + h, Q + q), t_idx, ys)
        obj[~free] = np.inf
        if not np.isfinite(obj).any():      # nothing determines the regions yet: most signal
            obj = -np.where(free, np.trace(h, axis1=1, axis2=2), -np.inf)
        j = int(np.argmin(obj))
        chosen.append(j)
        H, Q = H + h[j], Q + q[j]
        if time.perf_counter() - last > 1.0:
            report(progress, 0.6 + 0.2 * (k + 1) / positions,
                   f"chose {k + 1} of {positions} entry points")
            last = time.perf_counter()
    return chosen, H, Q, last


def _exchange_passes(design, chosen, H, Q, t0, time_budget_s, progress, cancel, last):
    """Exchange each chosen entry point for the best allowed one while that improves
    the objective, at most 5 passes and until ``time_budget_s`` [s] after ``t0``.

    Returns
    -------
    chosen, H, Q : the exchanged choice and its summed matrices
    best : float, the objective of the choice
    passes : int, the exchange passes begun
    warnings : list of str (the time budget ended the passes)
    """
    h, q, t_idx, ys = design.h, design.q, design.t_idx, design.ys
    positions = len(chosen)
    warnings = []
    best = float(_objective(_variances(H, Q), t_idx, ys))
    passes = 0
    improved = True
    while improved and time.perf_counter() - t0 < time_budget_s and passes < 5:
        improved = False
        passes += 1
        for n_pos in range(positions):
            check_cancel(cancel)
            if time.perf_counter() - t0 >= time_budget_s:
                warnings.append(f"the time budget ({time_budget_s:g} s) ended the exchange "
                                "passes: the plan may be improved with more time")
                break
            j = chosen[n_pos]
            ok = _allowed(design, chosen, excluding=j)
            Hb, Qb = H - h[j], Q - q[j]
            obj = _objective(_variances(Hb + h, Qb + q), t_idx, ys)
            obj[~ok] = np.inf
            c = int(np.argmin(obj))
            if obj[c] < best * (1 - 1e-6):
                chosen[n_pos], H, Q, best, improved = c, Hb + h[c], Qb + q[c], float(obj[c]), True
            if time.perf_counter() - last > 1.0:
                report(progress, 0.8 + 0.15 * min(1.0, passes / 5),
                       f"exchange pass {passes}: position {n_pos + 1} of {positions}")
                last = time.perf_counter()
    return chosen, H, Q, best, passes, warnings


def _default_grid_prediction(lm, optics, d_src, det_ras, cfg, targets, positions,
                             yield_by_label, noise_pct, exclude_mm):
    """The default grid's HP prediction (:func:`predict_scan`) when it lays as many
    positions as the plan, else None."""
    # the default grid with as many positions: its patches' sources, pairs within a patch
    if positions != len(d_src):
        return None
    from FluoTomoLib.tomography.simulate import scan_pairs

    return predict_scan(lm, optics, d_src, det_ras, targets,
                        scan_pairs(cfg, len(d_src), len(det_ras)),
                        yield_by_label, noise_pct, exclude_mm)


def _plan_assumptions(noise_pct, exclude_mm, spacing, positions, cfg, labels, yields):
    """The plan's ``assumptions``: the noise model [%], pair exclusion and spacing [mm],
    the detector grid, the assumed yields [1/mm] and the model's limits."""
    return {
        "noise_pct": float(noise_pct), "exclude_mm": float(exclude_mm),
        "min_spacing_mm": spacing, "positions": positions,
        "detectors": "the default scan's grid over each target "
                     f"({cfg['detectors_per_side']} x {cfg['detectors_per_side']}, "
                     f"{cfg['detector_pitch_mm']:g} mm pitch)",
        "pairs": f"every source-detector pair farther apart than {float(exclude_mm):g} mm",
        "yield_by_label": {str(lab): float(y) for lab, y in zip(labels, yields)},
        "model": "half-space diffusion in the largest label's optics (scan coverage's "
                 "screen), HP region unknowns; the interval is the noise part only",
        "SP": "not predicted: SP's interval depends on the mesh, its regularisation and "
              "the resolution's bias, which the screen does not model"}


def write_plan(folder, plan):
    """Write a plan: ``sources.csv``, ``detectors.csv`` (what ``fluo tomo simulate
    --sources/--detectors`` reads) and ``plan.json``, as one transaction."""
    from fluoguide import atomic
    from fluoguide.jsonable import dumps

    def pts_csv(p):
        return "x_mm,y_mm,z_mm\n" + "".join(f"{a:.9g},{b:.9g},{c:.9g}\n" for a, b, c in p)

    doc = plan_document(plan)
    with atomic.staged_folder(folder, last=("plan.json",)) as stage:
        atomic.write_text(stage / "sources.csv", pts_csv(plan["sources_ras"]))
        atomic.write_text(stage / "detectors.csv", pts_csv(plan["detectors_ras"]))
        atomic.write_text(stage / "plan.json", dumps(doc))
    return doc


def plan_document(plan):
    """plan.json's content: everything but the arrays, and per source its RAS
    position and approach direction."""
    doc = {k: v for k, v in plan.items()
           if k not in ("sources_ras", "detectors_ras", "mask", "approach_ras")
           and not k.startswith("_")}
    doc["format"] = "fluoguide-scan-plan"
    doc["version"] = 1
    doc["sources_csv"], doc["detectors_csv"] = "sources.csv", "detectors.csv"
    doc["sources"] = [{"ras_mm": np.round(p, 4).tolist(), "approach_ras": np.round(a, 5).tolist()}
                      for p, a in zip(plan["sources_ras"], plan["approach_ras"])]
    doc["pairs_measured"] = int(np.sum(plan["mask"]))
    return doc
