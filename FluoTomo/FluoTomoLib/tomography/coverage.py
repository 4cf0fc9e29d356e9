"""What a scan can see of each labelled region, before any reconstruction.

A region's yield is measured only as far as the light of the scan's pairs
passes through it. :func:`scan_coverage` screens this cheaply, with no mesh
and no solve: each pair's sensitivity to fluorophore at a point is the product
of the excitation fluence from the source and the emission fluence from the
detector (the adjoint), each a half-space diffusion Green's function with an
extrapolated-boundary image (docs/physics.md section 8.2, "Scan coverage"), in the
optical properties of the largest tissue label. The screen gives, per region:

``share``
    the largest fraction, over the scan's pairs, of a measurement's signal that
    comes from this region when every tissue voxel holds the same yield per mm
    (a geometric number: how much of what the pairs see is this region);
``pairs_seeing``
    how many pairs draw at least the stated noise (``noise_pct``) from it at
    equal yield;
``contrast_to_be_seen``
    the yield contrast over the rest of the tissue at which the region's part
    of the best pair's signal reaches the noise: a region needs at least this
    much more dye than its surroundings for the data to tell its yield (None:
    no pair sees it at all);
``nearest_optode_mm``
    from the region's nearest voxel to the nearest source or detector.

A region whose ``contrast_to_be_seen`` exceeds ``UNSEEN_CONTRAST`` (the top of
the contrasts fluorescence-guided surgery meets, about 1000:1) is reported as
not seen: its reconstructed value would come from the prior and the
regularisation, not from the data.
"""

from __future__ import annotations

import numpy as np

#: a region needing more contrast than this over its surroundings is "not seen"
UNSEEN_CONTRAST = 1000.0
#: points per region in the screen: regions with more voxels are sampled on a
#: regular stride (the integrand is smooth at this spacing past the optodes'
#: burial depth)
POINTS_PER_REGION = 40000


def _green_half_space(optode_local, inward, points, mua, musp, n):
    """Half-space fluence [1/mm^2 per unit power] at ``points`` (P, 3) from a
    unit source buried z0 = 1/mut' below ``optode_local`` along ``inward``, with
    its image above the extrapolated boundary (docs/physics.md section 3.2); one row per
    optode (O, P)."""
    from FluoTomoLib.analytic import robin_parameters

    z0, zb, D, mu_eff = robin_parameters(mua, musp, n)
    out = np.empty((len(optode_local), len(points)))
    for o, (p, nv) in enumerate(zip(optode_local, inward)):
        r1 = np.linalg.norm(points - (p + z0 * nv), axis=1)
        r2 = np.linalg.norm(points - (p - (z0 + 2.0 * zb) * nv), axis=1)
        r1 = np.maximum(r1, 0.5 * z0)          # the buried source's own cell
        out[o] = np.exp(-mu_eff * r1) / r1 - np.exp(-mu_eff * r2) / r2
    return np.clip(out, 0.0, None) / (4.0 * np.pi * D)


def _region_points(lm, label, limit=POINTS_PER_REGION):
    """Voxel centres (local mm) of one label on a stride that keeps at most
    ``limit`` of them, and the volume each stands for [mm^3]."""
    mask = lm.labels_kji == int(label)
    count = int(mask.sum())
    stride = max(1, int(np.ceil((count / limit) ** (1.0 / 3.0))))
    sub = mask[::stride, ::stride, ::stride]
    k, j, i = np.nonzero(sub)
    pts = np.stack([i, j, k], axis=1) * stride * lm.spacing_mm
    return pts, float(np.prod(lm.spacing_mm)) * count / max(len(pts), 1)


def region_sensitivity(lm, optics, src_local, inward_src, det_local, inward_det,
                       points_per_region=POINTS_PER_REGION, cancel=None):
    """Each region's part of every pair's signal at unit yield: the screen's
    A_r(s, d) (module docstring; docs/physics.md section 8.2, "Scan coverage").

    Parameters
    ----------
    lm : LabelMap
    optics : Optics (the largest label's properties are used throughout)
    src_local, det_local : (S, 3), (D, 3) optodes in the label map's local frame [mm]
    inward_src, inward_det : (S, 3), (D, 3) unit inward surface normals there
    points_per_region : int, the most quadrature points per region
    cancel : fluoguide.progress cancel token (checked between regions)

    Returns
    -------
    (parts, nearest_mm, body): ``parts`` {label: (S, D) signal per unit yield
    [1/mm^2 per (1/mm)]}, ``nearest_mm`` {label: distance from the region to the
    nearest optode [mm]}, ``body`` the largest label
    """
    from scipy.spatial import cKDTree

    from fluoguide.progress import check_cancel

    vols = lm.region_volumes()
    body = max(vols, key=vols.get)
    (mx, sx), (mm, sm) = optics.excitation[body], optics.emission[body]
    parts, nearest = {}, {}
    optodes = cKDTree(np.vstack([src_local, det_local]))
    for lab in vols:
        check_cancel(cancel)
        pts, w = _region_points(lm, lab, points_per_region)
        gx = _green_half_space(src_local, inward_src, pts, mx, sx, optics.n)
        gm = _green_half_space(det_local, inward_det, pts, mm, sm, optics.n)
        parts[lab] = w * (gx @ gm.T)                       # (S, D) signal at unit yield
        nearest[lab] = float(optodes.query(pts)[0].min())
    return parts, nearest, body


def scan_coverage(lm, optics, sources_ras, detectors_ras, mask=None, noise_pct=1.0):
    """Screen what the scan sees of each labelled region (module docstring).

    Parameters
    ----------
    lm : LabelMap
    optics : Optics
    sources_ras, detectors_ras : (S, 3), (D, 3) RAS mm
    mask : (S, D) bool, the pairs measured (None: all)
    noise_pct : the data's relative noise [%] (what a region must exceed)

    Returns
    -------
    dict: ``regions`` {label str: {share, pairs_seeing, contrast_to_be_seen,
    nearest_optode_mm, seen}}, ``body_label``, ``noise_pct``, ``model``,
    ``warnings`` (one per region not seen, naming it)
    """
    src = lm.to_local(sources_ras)
    det = lm.to_local(detectors_ras)
    S, D = len(src), len(det)
    mask = np.ones((S, D), bool) if mask is None else np.asarray(mask, bool)
    surf = lm.surface()
    _, n_src, _ = surf.closest(src)
    _, n_det, _ = surf.closest(det)
    vols = lm.region_volumes()
    parts, nearest, body = region_sensitivity(lm, optics, src, -n_src, det, -n_det)
    total = sum(parts.values())
    used = mask & (total > 0)
    noise = max(float(noise_pct), 1e-3) / 100.0
    out = {}
    warnings = []
    for lab in sorted(vols):
        share = np.where(used, parts[lab] / np.where(total > 0, total, 1.0), 0.0)
        best = float(share.max()) if used.any() else 0.0
        # contrast c at which c*share / (c*share + 1 - share) reaches the noise
        need = (np.inf if best <= 0 else
                1.0 if best >= 1.0 else noise * (1.0 - best) / (best * (1.0 - noise)))
        seen = bool(lab == body or need <= UNSEEN_CONTRAST)
        out[str(lab)] = {"share": best, "pairs_seeing": int((share >= noise).sum()),
                         "contrast_to_be_seen": float(need) if np.isfinite(need) else None,
                         "nearest_optode_mm": nearest[lab], "seen": seen}
        if not seen:
            warnings.append(
                f"the scan does not see region {lab}: its best pair draws {best:.2g} of its "
                f"signal from it at equal yield (nearest optode {nearest[lab]:.1f} mm away), "
                f"so it would need {need:.3g}x the surrounding yield to stand above "
                f"{100 * noise:g} % noise: its value comes from the prior, not the data; "
                "scan over it (the default scan covers every inclusion; --scan-targets)")
    return {"regions": out, "body_label": int(body), "noise_pct": 100.0 * noise,
            "model": "half-space diffusion in the largest label's optics",
            "warnings": warnings}
