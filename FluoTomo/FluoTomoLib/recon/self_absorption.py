"""Fluorophore self-absorption in yield reconstruction.

The Jacobian of the reference is taken with the background's optical
properties: a target's fluorescence is modelled as if its dye did not absorb.
But yield = eta * mua_f, so a target of known dye absorbs in proportion to the
yield being reconstructed (ICG at 2 ug/mL multiplies the liquid's mua at
780 nm by 26).  The excitation is then attenuated inside the target and the
reconstruction, blind to it, underestimates the yield: a 2.4 mm ICG tube came
out 18-29 % low with a hard prior, and within 3 % once the simulated tube was
made non-absorbing (measured, docs/tomography.md).

Here the absorption is fed back: reconstruct, add the absorption the
reconstructed yield implies (fluoguide.optics_table.icg_absorption_per_yield
for ICG), rebuild the forward model, reconstruct again.  For a hard prior
only the data of each region's basis are needed (forward solves, no Jacobian
assembly), so it iterates to convergence cheaply; a soft prior needs a new
nodal Jacobian per pass (one pass by default), so it starts from a converged
HP's absorption where the caller has one (``start``).  NP is left alone: without a
prior its yield is smeared towards the surface and would put the absorption
in the wrong place.

Limits (tested with a two-region model, test_graded_mesh_partial_volume.py):
the feedback is a fixed-point iteration, x -> what the data say given the
absorption of x.  Where one pass changes the error by less than 1x (the ICG
tubes here: ~0.25x) it finds the truth.  Where the target is so absorbing that
the truth is an unstable fixed point, the iteration climbs from the blind
value to a lower, stable one (still closer than the blind value); and where
the data cannot be explained by the absorbing model at all (the oral cavity
on a 2 mm mesh) the passes run away, and the blind solution is kept and the
stop reason says so.
"""

from __future__ import annotations

import numpy as np

from FluoTomoLib.recon.partial_volume import region_unknowns
from FluoTomoLib.recon.solver import reconstruct

#: the methods that feed the reconstructed dye's absorption back, by default on
#: every path (``fluo tomo reconstruct``, the logic, the demo's tube and oral
#: cases): HP and SP. The demo's cases fed back HP only until 2026-11-29, chosen
#: against a tube truth that held 13 % too much dye; on the honest truth SP
#: without its feedback read the 4.7 mm tube 24 % low, with it within 1 %
#: (docs/tomography.md, "SP feeds back its absorption in the demo too")
SELF_ABSORPTION = ("HP", "SP")


def absorbing_mua(mua_bg, yield_nodes, yield_bg, mua_per_yield):
    """Nodal absorption [1/mm]: background plus what the dye in excess of the
    background's yield absorbs."""
    extra = np.clip(np.asarray(yield_nodes, float) - float(yield_bg), 0.0, None)
    return float(mua_bg) + mua_per_yield * extra


def _aitken(v0, v1, v2, max_ratio=0.9):
    """Aitken's delta-squared extrapolation of a linearly converging fixed-point
    iteration, per component: v2 + d2 r / (1 - r), r = d2 / d1.  Only where the
    sequence contracts monotonically (0 < r < max_ratio, so the jump is at most
    9x the last step); other components keep v2 (an oscillating or stalled
    component extrapolated blindly ran the agar's yield away by 100x on a
    coarse mesh)."""
    d1, d2 = v1 - v0, v2 - v1
    out = v2.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(d1 != 0, d2 / d1, np.nan)
    ok = np.isfinite(r) & (r > 0) & (r < max_ratio)
    out[ok] = v2[ok] + d2[ok] * r[ok] / (1.0 - r[ok])
    return np.clip(out, 0.0, None)


def absorbing_model(make_model, yield_nodes, mua_bg, yield_bg, mua_per_yield, progress=None,
                    cancel=None):
    """The model with the dye's absorption at both wavelengths
    (:func:`absorbing_mua`; ``make_model(mua_x_nodes, mua_m_nodes)``), saying what
    it solves and factorises at the start of ``progress``'s share (the solver's
    iterations follow; a pass's model on a large mesh took seconds without a
    word) and checking ``cancel`` while it factorises."""
    from fluoguide.progress import scaled

    model = make_model(absorbing_mua(mua_bg[0], yield_nodes, yield_bg, mua_per_yield[0]),
                       absorbing_mua(mua_bg[1], yield_nodes, yield_bg, mua_per_yield[1]))
    model.progress = scaled(progress, 0.0, 0.0)
    model.cancel = cancel
    return model


#: how HP's stop reason opens where its feedback reached its fixed point
CONVERGED = "self-absorption converged"


def converged(res):
    """Whether ``res`` (HP's ReconResult) fed the dye's absorption back to its fixed
    point (its ``stop_reason``)."""
    return str(res.stop_reason).startswith(CONVERGED)


#: SP's feedback passes after its first solve (each a nodal Jacobian)
SP_PASSES = 1

#: q / (1 - q) for the feedback's slowest measured contraction q = 0.62 per pass
FEEDBACK_PENDING = 0.62 / (1 - 0.62)


def reconstruct_self_absorbing(method, J, y, mask, prior, make_model, mua_bg, yield_bg,
                               mua_per_yield, lam=10.0, passes=None, rel_tol=0.02,
                               cancel=None, progress=None, region_weights=None, noise_rel=None,
                               region_matrix=None, optodes=None, start=None):
    """Reconstruct with the fluorophore's absorption fed back into the model.

    Parameters
    ----------
    method : "SP" or "HP"
    J : (M, N) Jacobian with the background properties (first pass)
    y : (M,) data; ``mask`` the (S, D) boolean selecting them from the model's data
    prior : RegionPrior (HP uses ``prior.K()``)
    make_model : callable (mua_x_nodes, mua_m_nodes) -> FluorescenceModel on
        the reconstruction mesh with the reported sources and detectors
    mua_bg : (mua_x, mua_m) of the background [1/mm]
    yield_bg : the background's yield [1/mm] (its dye is already in mua_bg)
    mua_per_yield : (d mua_x / d yield, d mua_m / d yield)
    passes : feedback passes after the first solve (default at most 6 for HP,
        1 for SP)
    rel_tol : HP stops when the region values (or their Aitken extrapolation,
        from the second pass on) change by less than this, relative to the
        largest
    progress : progress(fraction, message): each pass, and the solver's
        iterations inside it
    region_weights : SP's region means (``reconstruct``'s), passed on
    noise_rel : the data's relative noise (a fraction), passed on to every solve
    region_matrix : (M, R) HP's first-pass region sensitivities J @ prior.K(), when
        the caller has them without J (``TissueModel.region_matrix``; J may then
        be None)
    optodes : HP: (sources, detectors) index of each used measurement: every
        solve's result also carries the fit with the optodes' gains
        (``reconstruct``'s ``optodes``); None: no such fit
    start : SP: (nodal yield [1/mm], {label: value [1/mm]}) of a converged HP on the
        same regions: the first solve takes its absorption (one pass from the blind
        model left SP's feedback a quarter to a half of the truth short on the
        scene family's absorbing inclusions: docs/reconstruction.md); None: blind

    Returns (ReconResult of the last pass with ``yield_per_mm`` nodal, list of
    the largest nodal yield after each pass).
    """
    method = method.upper()
    passes = (6 if method == "HP" else SP_PASSES) if passes is None else int(passes)
    if method != "HP":
        return _soft_prior_feedback(method, J, y, mask, prior, make_model, mua_bg, yield_bg,
                                    mua_per_yield, lam, passes, cancel, progress,
                                    region_weights, noise_rel, start)
    return _hard_prior_feedback(J, y, mask, prior, make_model, mua_bg, yield_bg,
                                mua_per_yield, lam, passes, rel_tol, cancel, progress,
                                noise_rel, region_matrix, optodes)


def _pass_progress(progress, method, passes, k, what):
    """Pass ``k`` of 1 + ``passes``: its share of the bar, its messages prefixed by
    the method and ``what`` it does."""
    from fluoguide.progress import scaled

    share = 1.0 / (passes + 1)
    return scaled(progress, k * share, (k + 1) * share, f"{method} {what}")


def _soft_prior_feedback(method, J, y, mask, prior, make_model, mua_bg, yield_bg,
                         mua_per_yield, lam, passes, cancel, progress, region_weights,
                         noise_rel, start=None):
    """:func:`reconstruct_self_absorbing` for SP (and any method but HP): each pass
    a new nodal Jacobian with the last result's absorption; the region rows say
    what the feedback still owes (``feedback_pending_per_mm``). ``start``: (nodal
    yield [1/mm], {label: value [1/mm]}) of a converged HP on the same regions, whose
    absorption the first solve takes instead of none (the blind model)."""
    from fluoguide.progress import check_cancel, report

    first = _pass_progress(progress, method, passes, 0, "first solve")
    if start is None:
        J0, before = J, None
    else:
        report(first, 0.0, "model with HP's dye absorption, its Jacobian")
        model = absorbing_model(make_model, start[0], mua_bg, yield_bg, mua_per_yield, first,
                                cancel)
        J0, before = model.jacobian_yield(mask), start[1]
        del model           # its fields, before the solve's workspace
    res = reconstruct(J0, y, method, lam=lam, prior=prior, progress=first,
                      region_weights=region_weights, noise_rel=noise_rel)
    # a pass's M x N Jacobian is not held while the next one is built (the caller
    # keeps the blind one, J, where it passed it)
    del J0
    history = [float(np.max(res.yield_per_mm))]
    for k in range(passes):
        check_cancel(cancel)
        step = _pass_progress(progress, method, passes, k + 1, f"self-absorption pass {k + 1}")
        report(step, 0.0, "model with the dye's absorption, its Jacobian")
        before = {int(lab): c["mean_yield_per_mm"] for lab, c in res.region_confidence.items()}
        model = absorbing_model(make_model, res.yield_per_mm, mua_bg, yield_bg,
                                mua_per_yield, step, cancel)
        J_k = model.jacobian_yield(mask)
        del model           # its fields, before the solve's workspace
        res = reconstruct(J_k, y, method, lam=lam,
                          prior=prior, progress=step, region_weights=region_weights,
                          noise_rel=noise_rel)
        del J_k
        history.append(float(np.max(res.yield_per_mm)))
    # what the feedback still owes: its last step moved each region by delta (from
    # the blind solve, or from HP's values whose absorption the first solve took);
    # a contraction q per pass leaves q / (1 - q) delta to come (q measured 0.25
    # for a thin tube, 0.62 for a bulk, optically thick target: the latter taken,
    # so the intervals reach it). With neither a start nor a pass nothing is owed
    # that the data can tell: the blind model's bias is the caller's to state
    if before is not None:
        for lab, c in res.region_confidence.items():
            delta = c["mean_yield_per_mm"] - before.get(int(lab), c["mean_yield_per_mm"])
            c["feedback_pending_per_mm"] = float(delta * FEEDBACK_PENDING)
    return res, history


def _hard_prior_feedback(J, y, mask, prior, make_model, mua_bg, yield_bg, mua_per_yield, lam,
                         passes, rel_tol, cancel, progress, noise_rel, region_matrix,
                         optodes=None):
    """:func:`reconstruct_self_absorbing` for HP: the unknowns are the region values
    v, the model's data for region r are those of the basis K[:, r], so each pass
    is forward solves only (:func:`_region_data`); Steffensen's iteration
    (:func:`_aitken`) to convergence, or the blind solution kept where the
    feedback amplifies instead of contracting."""
    from fluoguide.progress import check_cancel, report

    K = prior.K()
    unknowns = region_unknowns(prior.labels)
    A0 = J @ K if region_matrix is None else np.asarray(region_matrix, float)
    res = first = reconstruct(A0, y, "HP", lam=lam, prior=unknowns,
                              progress=_pass_progress(progress, "HP", passes, 0, "first solve"),
                              noise_rel=noise_rel, optodes=optodes)
    values = [res.yield_per_mm.copy()]     # every state the models were built from
    triple = [values[-1]]                  # the current fixed-point sequence
    # the stop reason, and carried alongside what callers decide on: whether it
    # reports a divergence, whether a warning already opens with it
    stop, diverged, warned = res.stop_reason, res.diverged, res.stop_warned
    for k in range(passes):
        check_cancel(cancel)
        step = _pass_progress(progress, "HP", passes, k + 1, f"self-absorption pass {k + 1}")
        report(step, 0.0, f"emission data of {K.shape[1]} regions with the dye's absorption")
        A = _region_data(make_model, K @ triple[-1], K, mask, mua_bg, yield_bg, mua_per_yield,
                         step, cancel)
        res = reconstruct(A, y, "HP", lam=lam, prior=unknowns, progress=step,
                          noise_rel=noise_rel, optodes=optodes)
        triple.append(res.yield_per_mm.copy())
        values.append(triple[-1])
        scale = max(float(np.max(np.abs(triple[-1]))), 1e-300)
        if len(triple) == 2:
            if np.max(np.abs(triple[-1] - triple[-2])) <= rel_tol * scale:
                stop = f"{CONVERGED} ({k + 1} passes)"
                diverged, warned = False, False
                break
            continue
        # Steffensen: the feedback contracts linearly (by ~4x per pass for a
        # thin tube, only ~1.6x for a bulk, optically thick target), so the
        # Aitken extrapolation of the last three states is both the stopping
        # test and the next state
        d1, d2 = triple[1] - triple[0], triple[2] - triple[1]
        if np.max(np.abs(d2)) >= np.max(np.abs(d1)):
            # the feedback amplifies instead of contracting (a target too thick
            # or too coarsely meshed for the linearised model): keep the blind
            # solution rather than a runaway one
            res = first
            values = values[:1]
            stop = (f"self-absorption feedback diverged after {k + 1} passes: "
                    "blind model kept")
            res.warnings = res.warnings + [
                f"{stop}: the yield ignores the dye's own absorption and is low for an "
                "absorbing target (docs/tomography.md)"]
            diverged, warned = True, True
            break
        v_a = _aitken(*triple)
        values.append(v_a)
        if np.max(np.abs(v_a - triple[-1])) <= rel_tol * scale:
            stop = f"{CONVERGED} (Aitken, {k + 1} passes)"
            diverged, warned = False, False
            break
        triple = [v_a]
    res.yield_per_mm = K @ values[-1]
    res.stop_reason, res.diverged, res.stop_warned = stop, diverged, warned
    return res, [float(np.max(K @ v)) for v in values]


def _region_data(make_model, x, K, mask, mua_bg, yield_bg, mua_per_yield, progress, cancel):
    """(M, R) the used data of each region's basis K[:, r] in the model with the
    absorption of the nodal yield ``x`` (:func:`absorbing_model`)."""
    model = absorbing_model(make_model, x, mua_bg, yield_bg, mua_per_yield, progress, cancel)
    return np.stack([model.emission_data(K[:, r])[mask] for r in range(K.shape[1])], axis=1)
