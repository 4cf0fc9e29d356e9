"""The region of interest of a reconstruction, chosen from the decay length and
graded against a larger domain (#18 item 7).

A cut face of the region of interest is a tissue-air boundary for the model:
light that would have come back from the tissue beyond it is lost.  Against
the full cylinder-tube phantom the demo's 30 x 50 mm region changed the
emission data by 7.9 % median / 29 % max, its quick 18 x 42 mm one by 36 % /
75 %, and a 60 x 80 mm one by 0.6 %.  Here the region is the box of the
optodes and the target, grown by a margin of ``MARGIN_DECAY_LENGTHS`` decay
lengths (1/mueff of the least absorbing tissue, at either wavelength) and
clipped to the tissue; its truncation error is estimated by comparing the
emission data of a uniformly fluorescent tissue on the region and on the whole
label map (both meshed at ``ESTIMATE_MM``, on the same anchored grid, so the
difference is the cut and not the discretisation), and the margin grows
(x1.5) until the largest relative change over the measured pairs is within
the tolerance or the region is the whole tissue.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

#: first margin, in decay lengths 1/mueff
MARGIN_DECAY_LENGTHS = 1.5
#: element size of the truncation estimate [mm]
ESTIMATE_MM = 2.0
#: most cells of the reference mesh (the whole label map beyond this is
#: replaced by the largest region grown from the optodes that fits)
REFERENCE_CELLS = 400_000


def _box(points, extra=None):
    p = np.asarray(points, float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    if extra is not None:
        lo, hi = np.minimum(lo, extra[0]), np.maximum(hi, extra[1])
    return lo, hi


def _roi(lo, hi, t_lo, t_hi):
    lo = np.maximum(lo, t_lo)
    hi = np.minimum(hi, t_hi)
    return np.array([lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]])


def _data(lm, optics, roi, sources, detectors, mask, anchor, h, cut_as_air=False):
    """Emission data of a uniformly fluorescent tissue (yield 1 /mm) on a mesh of
    roi (the label map's cut faces as tissue going on, or as air)."""
    from FluoTomoLib.fem.forward import FluorescenceModel
    from FluoTomoLib.tomography.model import membership, reconstruction_mesh

    surf = lm.surface()
    mesh = reconstruction_mesh(lm.labels_kji, lm.spacing_mm, h, roi, target=None, anchor=anchor,
                               surface=surf, name="roi-estimate")
    labs, F = membership(mesh, lm.labels_kji, lm.spacing_mm)
    px, pm = optics.nodal(labs, F)
    import warnings

    with warnings.catch_warnings():     # a coarse estimate: resolution warnings are expected
        warnings.simplefilter("ignore")
        fm = FluorescenceModel(mesh, px, pm, sources, detectors,
                               source_normals=surf.closest(sources)[1],
                               cut_facets=None if cut_as_air else lm.cut_facets(mesh))
        return fm.emission_data(np.ones(mesh.n_nodes))[mask], mesh


def choose_roi(lm, optics, sources, detectors, mask, target=None, tol_pct=1.0, anchor=None,
               estimate_mm=ESTIMATE_MM, progress=None, cancel=None):
    """Region of interest (local frame) for a reconstruction, with its estimated
    truncation error.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics
    sources, detectors : (S, 3), (D, 3) surface points in the local frame
    mask : (S, D) the pairs measured
    target : label that must lie inside (its box is added)
    tol_pct : largest relative change of the data allowed [%]

    Returns
    -------
    (roi (6,), info dict: ``margin_mm``, ``decay_length_mm``,
    ``truncation_max_pct``, ``truncation_median_pct``, ``reference``,
    ``seconds``, ``whole_tissue``).
    """
    t0 = time.perf_counter()
    t_lo, t_hi = lm.tissue_bounds_local()
    extra = lm.region_bounds_local(target) if target is not None else None
    lo, hi = _box(np.vstack([sources, detectors]), extra)
    decay = 1.0 / max(optics.min_mueff(lm.labels), 1e-6)
    margin = min(max(MARGIN_DECAY_LENGTHS * decay, 5.0), float(np.max(t_hi - t_lo)))
    if anchor is None:
        anchor = 0.5 * (lo + hi)
    full = _roi(t_lo, t_hi, t_lo, t_hi)
    info = {"decay_length_mm": decay, "tolerance_pct": tol_pct, "estimate_mm": estimate_mm}

    def is_full(roi):
        return bool(np.allclose(roi, full, atol=1e-6))

    # the reference: the whole tissue, or the largest region around the optodes
    # a coarse mesh affords
    def cells(roi):
        return float(np.prod((roi[1::2] - roi[0::2]) / estimate_mm))

    ref_roi = full
    if cells(full) > REFERENCE_CELLS:
        m_ref = 4.0 * margin
        while m_ref > margin and cells(_roi(lo - m_ref, hi + m_ref, t_lo, t_hi)) > REFERENCE_CELLS:
            m_ref /= 1.25
        ref_roi = _roi(lo - m_ref, hi + m_ref, t_lo, t_hi)
    info["reference"] = "whole tissue" if is_full(ref_roi) else \
        f"region {np.round(ref_roi, 1).tolist()} mm (the whole tissue is too large to mesh)"
    ref = None
    while True:
        check_cancel(cancel)
        roi = _roi(lo - margin, hi + margin, t_lo, t_hi)
        if is_full(roi) or np.allclose(roi, ref_roi, atol=1e-6):
            info.update(margin_mm=margin, truncation_max_pct=0.0 if is_full(roi) else None,
                        truncation_median_pct=0.0 if is_full(roi) else None,
                        whole_tissue=is_full(roi))
            if not is_full(roi):
                info["note"] = ("the region is the reference region: its own truncation is "
                                "not estimated")
            break
        if ref is None:
            # two coarse forward models, a second or more each on a large map
            report(progress, 0.02, "region of interest: the reference's data")
            ref, _ = _data(lm, optics, ref_roi, sources, detectors, mask, anchor, estimate_mm)
            check_cancel(cancel)
        report(progress, 0.02, f"region of interest: margin {margin:.0f} mm")
        got, _ = _data(lm, optics, roi, sources, detectors, mask, anchor, estimate_mm)
        rel = np.abs(got - ref) / np.maximum(np.abs(ref), 1e-300)
        info.update(margin_mm=margin, truncation_max_pct=100.0 * float(np.max(rel)),
                    truncation_median_pct=100.0 * float(np.median(rel)), whole_tissue=False)
        if info["truncation_max_pct"] <= tol_pct:
            break
        margin *= 1.5
    info["roi_local_mm"] = roi.tolist()
    info["seconds"] = time.perf_counter() - t0
    return roi, info


#: a cut of the label map this many decay lengths from every optode is not
#: estimated (its influence is below the estimate's own resolution)
CUT_CHECK_DECAY_LENGTHS = 6.0
#: the cut's influence above which the output warns [%]
CUT_WARN_PCT = 10.0


def label_map_cut(lm, optics, sources, detectors, mask, estimate_mm=ESTIMATE_MM, cancel=None):
    """How much the tissue beyond the label map's cut faces matters to these data.

    A label map cropped through tissue (a CBCT's field of view, a crop around the
    target) ends in cut faces, which the model treats as the same tissue going on
    (``DiffusionOperator``'s continuation condition, docs/physics.md section 2.5).
    What lies beyond is unknown; the data of a uniformly fluorescent tissue with
    the cut as air (nothing comes back) and as tissue going on bracket its
    influence: ``influence_max_pct`` is their largest relative difference over
    the measured pairs. On cropped ellipsoids graded against the uncropped map
    (docs/tomography-own-scene.md, "Cut faces") the continuation's own error was
    0.25-0.5 of that influence and the air condition's 0.3-0.65 of it.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics
    sources, detectors : (S, 3), (D, 3) surface points in the local frame
    mask : (S, D) the pairs measured

    Returns
    -------
    dict: ``sides`` (the cut sides, "I-", "K+", ...), ``nearest_optode_mm`` (the
    closest optode's distance to a cut face plane), ``decay_length_mm``,
    ``influence_max_pct`` / ``influence_median_pct`` (None when not estimated:
    no cut, or every optode farther than CUT_CHECK_DECAY_LENGTHS decay lengths),
    ``warnings`` (a list: one when the influence exceeds CUT_WARN_PCT).
    """
    sides = [f"{'IJK'[a]}{'-+'[s]}" for a, s in lm.cut_sides()]
    info = {"sides": sides, "nearest_optode_mm": None, "decay_length_mm": None,
            "influence_max_pct": None, "influence_median_pct": None, "warnings": []}
    if not sides:
        return info
    pts = np.vstack([sources, detectors])
    nearest = float(np.min(lm.distance_to_cut(pts)))
    decay = 1.0 / max(optics.min_mueff(lm.labels), 1e-6)
    info.update(nearest_optode_mm=nearest, decay_length_mm=decay)
    if nearest > CUT_CHECK_DECAY_LENGTHS * decay:
        return info
    t_lo, t_hi = lm.tissue_bounds_local()
    full = _roi(t_lo, t_hi, t_lo, t_hi)
    anchor = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    check_cancel(cancel)
    cont, _ = _data(lm, optics, full, sources, detectors, mask, anchor, estimate_mm)
    check_cancel(cancel)
    air, _ = _data(lm, optics, full, sources, detectors, mask, anchor, estimate_mm,
                   cut_as_air=True)
    rel = np.abs(air - cont) / np.maximum(np.abs(cont), 1e-300)
    info.update(influence_max_pct=100.0 * float(np.max(rel)),
                influence_median_pct=100.0 * float(np.median(rel)))
    if info["influence_max_pct"] > CUT_WARN_PCT:
        info["warnings"].append(
            f"the label map is cut through tissue {nearest:.1f} mm from the nearest optode "
            f"(side {', '.join(sides)}): the data depend on the unknown tissue beyond by up to "
            f"{info['influence_max_pct']:.0f} % (modelled as the same tissue going on, whose "
            "own error measured 0.2-0.5 of that); a larger crop, or optodes farther from "
            "the cut, lowers it")
    return info


def roi_from_ras(lm, roi_ras):
    """A region of interest typed in RAS (x0, x1, y0, y1, z0, z1) as a box in
    the label map's frame; only for label maps whose axes run along RAS."""
    from FluoTomoLib.meshing.voxel import signed_permutation

    r = np.asarray(roi_ras, float)
    if r.shape != (6,) or not np.all(np.isfinite(r)) or np.any(r[1::2] <= r[0::2]):
        raise FluoInputError("roi must be x0,x1,y0,y1,z0,z1 (RAS mm) with x0<x1 etc.",
                             field="roi", value=r.tolist())
    if not signed_permutation(lm.direction):
        raise FluoInputError("an RAS box cannot crop an oblique label map: leave the region "
                             "of interest to be chosen", field="roi")
    corners = np.array([[r[a], r[2 + b], r[4 + c]] for a in (0, 1) for b in (0, 1)
                        for c in (0, 1)])
    loc = lm.to_local(corners)
    lo, hi = loc.min(axis=0), loc.max(axis=0)
    return np.array([lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]])
