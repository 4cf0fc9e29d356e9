"""The FEM's discretisation error, estimated from measured tables: the resolution guard.

For a buried point source in a half-space with the Robin boundary the error of
the P1 FEM depends on three dimensionless numbers (the problem is scale-free):
``mueff h`` (elements against the decay length), ``mut' h`` (against the
burial depth 1/mut') and ``rho / h`` (the source-detector distance in
elements), plus the refractive index and where the source and the detector
sit within their elements.  ``benchmarks/bench_fem_accuracy.py`` measured
``|ln(FEM / exact)|`` against the exact Robin solution on Kuhn-cube meshes for six
source positions within a cell, 16 directions and n = 1.0, 1.37 and 1.6; the
tables below are, per grid point, the worst case over all of those
(``WORST``) and the median (``MEDIAN``).  docs/fem.md prints them.

What the tables say, in words: detectors need to be many elements away from
their source (the field falls by e^-(mueff + 3/rho) per mm and linear
elements interpolate it with an error ~ h^2 (mueff + 3/rho)^2 / 4 in the worst
position), sources buried shallower than an element (mut' h > 1) add an
error that decays slowly with distance, and beyond mueff h ~ 0.3 the
phase error of the elements grows with every decay length travelled.
Negative nodal values appear from mueff h ~ 1 (a few, far away) and
everywhere at 1.4.

A general mesh is mapped onto the table through an element size per
source-detector pair (:func:`pair_sizes`): the largest of the sizes at the
buried source, at the detector and the RMS along the light's path between
them.  The estimate is validated on meshes the table was not made on
(graded slabs, Testing/Python/test_fem_resolution.py).  Triangle meshes (2D)
use the same table: against the exact half-plane solution their errors were
within it (spot checks in the same test), but it was not measured in 2D.
"""

from __future__ import annotations

import numpy as np

# where the error is too large to estimate: beyond the measured mueff h
UNRESOLVED = np.inf

# log-error growth per decay length travelled beyond the last measured
# rho / h, per (mueff h)^2: the fitted 0.12-0.18 of the table, rounded up
DISPERSION_SLOPE = 0.2

def element_sizes(mesh, elements=None):
    """Size h of each element [mm] (or of the given element ids): the edge of
    the Kuhn cube (or square) it is a part of for structured meshes, ~0.9 x
    the edge for regular tetrahedra; the larger of ``(d! |e|)^(1/d)`` and the
    longest edge / sqrt(d), so that flat elements count with their long side.
    All elements: computed once per mesh and cached."""
    from math import factorial

    def sizes(m, ids):
        el = m.elements if ids is None else m.elements[ids]
        p = m.nodes_mm[el]
        d = m.dim
        longest = np.max([np.linalg.norm(p[:, a] - p[:, b], axis=1)
                          for a in range(d + 1) for b in range(a + 1, d + 1)], axis=0)
        vol = m.measures if ids is None else m.measures[ids]
        return np.maximum((factorial(d) * vol) ** (1.0 / d), longest / np.sqrt(d))

    if elements is not None:
        return sizes(mesh, np.asarray(elements))
    return mesh.cached("_element_sizes", lambda m: sizes(m, None))


def _last_measured(table):
    """Index of the last finite-or-inf rho / h per row; -1 if none."""
    idx = np.where(~np.isnan(table), np.arange(table.shape[-1]), -1)
    return idx.max(axis=-1)


def _lookup(table, n, mueff_h, mutp_h, rho_h):
    """Conservative interpolation in the measured table (axes n, mut' h,
    mueff h, rho / h): linear in n between its two neighbours (the error
    falls as n grows), the larger neighbour in mut' h and rho / h, the next
    larger mueff h.  mueff h below the grid: its first value; mut' h below
    1: the mut' h = 1 row (deeper sources, relative to h, are measured to
    be better); above the grids' ends: the last row; mueff h beyond the
    grid: UNRESOLVED.  Beyond the last measured rho / h (20): that value plus
    DISPERSION_SLOPE (mueff h)^2 per decay length further."""
    from FluoTomoLib.fem import _resolution_table as T

    n, me, mt, rh = np.broadcast_arrays(*(np.asarray(v, float)
                                          for v in (n, mueff_h, mutp_h, rho_h)))
    last_all = _last_measured(table)
    i = np.searchsorted(T.MUEFF_H, me, side="left")           # next larger (or equal)
    inside = i < len(T.MUEFF_H)
    i = np.minimum(i, len(T.MUEFF_H) - 1)
    k_lo = np.clip(np.searchsorted(T.RHO_H, rh, side="right") - 1, 0, len(T.RHO_H) - 1)
    k_hi = np.clip(np.searchsorted(T.RHO_H, rh, side="left"), 0, len(T.RHO_H) - 1)
    a_hi = np.clip(np.searchsorted(T.N, n, side="left"), 1, len(T.N) - 1)
    a_lo = a_hi - 1
    frac = np.clip((n - T.N[a_lo]) / (T.N[a_hi] - T.N[a_lo]), 0.0, 1.0)

    def at(a):
        best = np.full(me.shape, -np.inf)
        for side in ("right", "left"):                        # both mut' h neighbours
            j = np.clip(np.searchsorted(T.MUTP_H, mt, side=side) - (side == "right"),
                        0, len(T.MUTP_H) - 1)
            last = last_all[a, j, i]
            lastc = np.maximum(last, 0)
            near = np.maximum(table[a, j, i, np.minimum(k_lo, lastc)],
                              table[a, j, i, np.minimum(k_hi, lastc)])
            # beyond the last measured distance: the near-field part is held
            # (it falls with distance, but for shallow sources, mut' h >= 10,
            # by only 6 % from 16 to 20 elements), the phase error grows with
            # every decay length
            far = (table[a, j, i, lastc]
                   + DISPERSION_SLOPE * np.maximum(me, 0.0) ** 3 * (rh - T.RHO_H[lastc]))
            val = np.where(rh > T.RHO_H[lastc], far, near)
            best = np.maximum(best, np.where((last >= 0) & ~np.isnan(val), val, UNRESOLVED))
        return best

    lo, hi = at(a_lo), at(a_hi)
    with np.errstate(invalid="ignore"):
        val = np.where(np.isinf(lo) | np.isinf(hi), np.maximum(lo, hi),
                       (1 - frac) * lo + frac * hi)
    return np.where(inside, val, UNRESOLVED)


def log_error_estimate(mueff_h, mutp_h, rho_h, n=1.37, worst=True):
    """Estimated ``|ln(FEM / exact)|`` for a buried source and a surface detector.

    Parameters
    ----------
    mueff_h, mutp_h, rho_h, n : array-like, broadcast together
        mueff * h, mut' * h, rho / h (dimensionless) and the refractive index.
    worst : the worst case over where the optodes sit within their elements
        and the direction between them (True) or the median (False).

    Returns
    -------
    ndarray of the estimate (np.inf where mueff h is beyond the measured
    range or a detector went negative there: the FEM is not resolved).
    """
    from FluoTomoLib.fem import _resolution_table as T

    return _lookup(T.WORST if worst else T.MEDIAN, n, mueff_h, mutp_h, rho_h)


def required_size(mueff, mutp, rho_mm, h_mm, n=1.37, target=0.05):
    """The largest element size <= ``h_mm`` (in steps of 10 %) whose worst-case
    estimate is within ``target`` (relative error); per pair, NaN where even
    1/100 of h would not do (detectors within an element or two of the
    source: nothing but a finer model of the source would)."""
    mueff, mutp, rho, h = np.broadcast_arrays(*(np.asarray(v, float)
                                                for v in (mueff, mutp, rho_mm, h_mm)))
    out = np.full(h.shape, np.nan)
    todo = np.ones(h.shape, bool)
    limit = np.log1p(target)
    for k in range(44):                         # 0.9^43 ~ 1/100
        hk = h * 0.9 ** k
        ok = todo & (log_error_estimate(mueff * hk, mutp * hk, rho / hk, n) <= limit)
        out[ok] = hk[ok]
        todo &= ~ok
        if not todo.any():
            break
    return out


def pair_sizes(mesh, sources_buried_mm, sources_surface_mm, detectors_mm, mueff_nodal,
               samples=12):
    """Element size [mm] that governs each source-detector pair's error: the
    largest of the sizes of the element holding the buried source, of the
    elements at the detector and the RMS of the sizes along the path of the
    light, sampled on the straight line between them at the surface depth of
    the source and at the depth the diffusing light reaches half way,
    min(rho / 4, sqrt(rho / mueff) / 2).

    Returns (S, D) sizes and (S, D) distances rho [mm].
    """
    from FluoTomoLib.fem.locate import locator

    loc = locator(mesh)
    src_b = np.atleast_2d(sources_buried_mm)
    src_s = np.atleast_2d(sources_surface_mm)
    det = np.atleast_2d(detectors_mm)
    S, D = len(src_b), len(det)
    rho = np.linalg.norm(src_s[:, None, :] - det[None, :, :], axis=2)
    e_src, _ = loc.locate(src_b)
    h_src = element_sizes(mesh, np.maximum(e_src, 0))
    # the detector: the element under its surface point (a hair inside)
    down = src_b - src_s                         # inward, per source
    nrm = np.linalg.norm(down, axis=1, keepdims=True)
    inward = np.where(nrm > 0, down / np.maximum(nrm, 1e-300), 0.0).mean(axis=0)
    inward /= max(np.linalg.norm(inward), 1e-300)
    e_det, _ = loc.locate(det + 1e-3 * float(np.min(h_src)) * inward)
    h_det = np.where(e_det >= 0, element_sizes(mesh, np.maximum(e_det, 0)), np.max(h_src))
    me = float(np.max(mueff_nodal))
    t = (np.arange(samples) + 0.5) / samples
    depth = np.minimum(rho / 4.0, 0.5 * np.sqrt(rho / max(me, 1e-12)))          # (S, D)
    line = src_b[:, None, None, :] + t[None, None, :, None] * (det[None, :, None, :]
                                                             - src_s[:, None, None, :])
    pts = np.stack([line, line + depth[:, :, None, None] * inward], axis=2)   # (S, D, 2, T, d)
    e_path, _ = loc.locate(pts.reshape(-1, mesh.dim))
    e_path = e_path.reshape(S * D, -1)
    inside = e_path >= 0
    h2 = np.where(inside, element_sizes(mesh, np.maximum(e_path, 0).ravel()).reshape(
        e_path.shape) ** 2, 0.0).sum(axis=1)
    h_path = np.sqrt(h2 / np.maximum(inside.sum(axis=1), 1)).reshape(S, D)
    h = np.maximum(np.maximum(h_src[:, None], h_det[None, :]), h_path)
    return h, rho
