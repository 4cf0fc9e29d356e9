"""Optode coupling: one unknown gain per source and per detector beside the yield.

Why: on the scene family (docs/validation.md, "Optode coupling") 94-99 % of the
residual of a hard-prior fit at the true yields is a product of one factor per
source and one per detector: the model reads each optode a few per cent high or
low, the same for all its pairs. The factors follow how the mesh meets each
optode (the near-source and near-detector fields of a point optode 1 mm under a
curved, voxel-derived surface), not the tissue: two fine simulation meshes of one
scene (0.5 and 0.4 mm at the optodes) differ by 1.6 % rms per source and 3 % per
detector, and a 1.0 mm reconstruction mesh from either by 3-6 %. Real scans add
their own (laser power per position, the camera's gain across the field, the
surface under each spot). Left in, those factors were 3-6 times the noise in the
residual, so every fit graded "poor", the model-error bound set the intervals, and
the segmentation test preferred a moved boundary on 6 of 24 correct segmentations
(a moved boundary partly mimics them).

What: the data are fitted as ``y[s, d] ~ exp(a_s + b_d) (A v)[s, d]`` with the
region values v >= 0 and the log gains a, b, each set of gains of zero mean (the
yield's scale stays with the model), by alternating a non-negative least-squares
fit of v with the gains' closed-form update on the log ratios (a two-way layout).
The segmentation test compares its boundaries on this fit's residual where the
data's noise is stated (tomography/model.py, SEGMENTATION_COUPLING); the values a
reconstruction reports are fitted without the gains: where each inclusion has its
own patch of optodes, a patch's mean gain and its inclusion's yield are one unknown
to the data (on the family, values fitted with the gains missed by up to +580 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: alternations of the region fit and the gains' update, and the change of the
#: largest log gain below which they stop
MAX_ALTERNATIONS = 40
GAIN_TOL = 1e-5
#: prior count of each gain's zero (a weak shrinkage: a source seen by one pair
#: keeps half its log ratio, one seen by 40 nearly all of it)
PRIOR_PAIRS = 1.0
#: the gains are not estimated with fewer than this many measurements per unknown
#: (region values and gains together): the yield would pay for them
MIN_PAIRS_PER_UNKNOWN = 3.0


@dataclass
class OptodeCoupling:
    """The gains of one fit: ``factors`` (M,) exp(a_s + b_d) per used measurement,
    ``source_log`` (S,) and ``detector_log`` (D,) the log gains (0 where an optode
    has no used pair), ``parameters`` the gains' number less the two zero-mean
    constraints (what they take from the residual's degrees of freedom), ``rss``
    and ``rss_plain`` the residual sums of squares with and without the gains
    (each with its own non-negative values; the data's units squared),
    ``values`` the region values with the gains and ``residual_over_noise`` the
    rms of that fit's residual in units of the stated noise (None without one)."""
    factors: np.ndarray
    source_log: np.ndarray
    detector_log: np.ndarray
    parameters: int
    rss: float
    rss_plain: float
    values: np.ndarray
    residual_over_noise: float | None = None


def _nnls(A, y):
    """Non-negative least squares of a few columns (HP's region values); None where
    it does not converge or the numbers are not finite."""
    from scipy.optimize import nnls

    scale = np.max(np.abs(A), axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    try:
        v, _ = nnls(A / scale, y)
    except (RuntimeError, ValueError):
        return None
    return v / scale


def optode_coupling(A, y, sources, detectors, sigma=None):
    """The optodes' gains of a fit of ``y`` by ``A @ v`` (module docstring).

    Parameters
    ----------
    A : (M, R) each measurement's sensitivity to each unknown (HP's region values)
    y : (M,) the data (linear, the fit's units)
    sources, detectors : (M,) each measurement's source and detector index
    sigma : the stated noise's standard deviation per measurement (scalar or (M,),
        the data's units), or None

    Returns
    -------
    OptodeCoupling, or None where the gains cannot be told apart from the values
    (fewer than MIN_PAIRS_PER_UNKNOWN measurements per unknown, or too few positive
    data and predictions) or explain nothing.
    """
    A = np.asarray(A, float)
    y = np.asarray(y, float).ravel()
    src = np.asarray(sources, np.int64).ravel()
    det = np.asarray(detectors, np.int64).ravel()
    M, R = A.shape
    S, D = int(src.max()) + 1, int(det.max()) + 1
    seen_s = np.bincount(src, minlength=S) > 0
    seen_d = np.bincount(det, minlength=D) > 0
    n_gains = max(int(seen_s.sum()) - 1, 0) + max(int(seen_d.sum()) - 1, 0)
    if n_gains == 0 or M < MIN_PAIRS_PER_UNKNOWN * (R + n_gains):
        return None
    v0 = _nnls(A, y)
    if v0 is None:
        return None
    rss_plain = float(np.sum((A @ v0 - y) ** 2))
    a, b, v = np.zeros(S), np.zeros(D), v0
    for _ in range(MAX_ALTERNATIONS):
        pred = A @ v
        ok = (y > 0) & (pred > 0)
        if ok.sum() < MIN_PAIRS_PER_UNKNOWN * (R + n_gains):
            return None
        L = np.log(y[ok] / pred[ok])
        si, di = src[ok], det[ok]
        n_s = np.bincount(si, minlength=S) + PRIOR_PAIRS
        n_d = np.bincount(di, minlength=D) + PRIOR_PAIRS
        b_new = b
        for _ in range(10):
            a_new = np.bincount(si, L - b_new[di], S) / n_s
            b_new = np.bincount(di, L - a_new[si], D) / n_d
        # zero mean over the optodes that have data (the others stay 0): the
        # scale stays with v
        a_new[seen_s] -= a_new[seen_s].mean()
        b_new[seen_d] -= b_new[seen_d].mean()
        change = max(np.max(np.abs(a_new - a)), np.max(np.abs(b_new - b)))
        a, b = a_new, b_new
        v = _nnls(A * np.exp(a[src] + b[det])[:, None], y)
        if v is None:
            return None
        if change < GAIN_TOL:
            break
    g = np.exp(a[src] + b[det])
    resid = g * (A @ v) - y
    rss = float(resid @ resid)
    if not rss < rss_plain:
        return None
    ratio = None
    if sigma is not None:
        chi2 = float(np.sum((resid / np.broadcast_to(sigma, y.shape)) ** 2))
        ratio = float(np.sqrt(chi2 / max(M - R - n_gains, 1)))
    return OptodeCoupling(g, a, b, n_gains, rss, rss_plain, v, ratio)
