"""Non-contact sources and detectors from a tracked laser and a tracked camera.

Reference: docs/physics.md section 8.2.

- A virtual source is where the calibrated, tracked laser beam enters the
  tissue surface (ray-surface intersection).
- Virtual detectors are surface points at the source positions plus points
  interpolated between neighbouring sources; for each active source the ones
  within ``exclude_mm`` of it are left out (specular/leakage and the
  diffusion-invalid zone near the source).
- Data: mean counts in a ~1 mm^2 surface ROI around each detector ->
  radiance L = (S - offset)/G -> exitance J = pi L (Lambertian) ->
  boundary fluence Phi = C_R J with C_R = 2A -> y = Phi / P_laser [1/mm^2].
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError


def ray_triangle_intersect(origins, directions, vertices, triangles, eps=1e-12):
    """First hit of each ray on a triangle surface (Moller-Trumbore, all pairs).

    Meant for a handful of rays (laser beams), not pixel grids.

    Parameters
    ----------
    origins, directions : (R, 3) mm and (R, 3) (normalised here)
    vertices : (P, 3) mm; triangles : (T, 3) int

    Returns
    -------
    points : (R, 3) mm, NaN where the ray misses
    distance_mm : (R,), inf where it misses
    face : (R,) int, -1 where it misses
    """
    o = np.atleast_2d(np.asarray(origins, float))
    d = np.atleast_2d(np.asarray(directions, float))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    v0 = vertices[triangles[:, 0]]
    e1 = vertices[triangles[:, 1]] - v0
    e2 = vertices[triangles[:, 2]] - v0
    pts = np.full(o.shape, np.nan)
    dist = np.full(len(o), np.inf)
    face = np.full(len(o), -1, dtype=np.int64)
    for r in range(len(o)):
        p = np.cross(d[r], e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > eps
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o[r] - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d[r]) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
        if np.any(hit):
            k = np.flatnonzero(hit)[np.argmin(t[hit])]
            dist[r] = t[k]
            face[r] = k
            pts[r] = o[r] + t[k] * d[r]
    return pts, dist, face


def virtual_detectors(source_points_mm, lines=None, factor=2):
    """Detector points at the sources plus ``factor - 1`` points between neighbours.

    Parameters
    ----------
    source_points_mm : (S, 3) surface points of the sources, in scan order
    lines : list of index arrays, optional
        Groups of sources that form scan lines (interpolation happens only
        between neighbours on one line); default: one line in the given order.
    factor : int >= 1, the thesis used 2-4

    Returns
    -------
    (D, 3) detector points [mm] (not yet projected onto the surface; the
    caller snaps them to the mesh surface).
    """
    src = np.asarray(source_points_mm, float)
    if factor < 1 or int(factor) != factor:
        raise FluoInputError("interpolation factor must be an integer >= 1", field="factor",
                             value=factor)
    if lines is None:
        lines = [np.arange(len(src))]
    out = []
    for line in lines:
        pts = src[np.asarray(line)]
        for a, b in zip(pts[:-1], pts[1:]):
            for k in range(int(factor)):
                out.append(a + (b - a) * k / factor)
        out.append(pts[-1])
    return np.asarray(out)


def detector_mask(source_points_mm, detector_points_mm, exclude_mm=3.0):
    """(S, D) bool: True where detector d is used for source s (farther than exclude_mm)."""
    s = np.asarray(source_points_mm, float)
    d = np.asarray(detector_points_mm, float)
    dist = np.linalg.norm(s[:, None, :] - d[None, :, :], axis=2)
    return dist > exclude_mm


def roi_mean_counts(image, hit_points_mm, valid, detector_points_mm, roi_area_mm2=1.0,
                    min_pixels=4, with_se=False):
    """Mean counts over the pixels whose surface hit lies in a disc ROI around each detector.

    Parameters
    ----------
    image : (H, W) counts [ADU] of one frame
    hit_points_mm : (H, W, 3) surface point seen by each pixel
    valid : (H, W) bool, pixels with a valid (visible, unsaturated) hit
    detector_points_mm : (D, 3)
    roi_area_mm2 : ROI area on the surface (thesis: about 1 mm^2)
    with_se : also return each mean's standard error [ADU], from the pixels'
        scatter about a plane fitted over the ROI (the light's own slope
        across 1 mm is not noise); NaN where the ROI has no pixel to spare

    Returns
    -------
    mean : (D,) counts, NaN where fewer than ``min_pixels`` pixels fall in the ROI
    n_pixels : (D,) int
    se : (D,) [ADU], only with ``with_se``
    """
    from scipy.spatial import cKDTree

    radius = np.sqrt(roi_area_mm2 / np.pi)
    idx = np.flatnonzero(valid.ravel())
    if len(idx) == 0:
        raise FluoInputError("no valid pixel sees the surface", field="valid")
    pts = hit_points_mm.reshape(-1, 3)[idx]
    tree = cKDTree(pts)
    vals = image.ravel()[idx].astype(float)
    groups = tree.query_ball_point(np.asarray(detector_points_mm, float), radius)
    mean = np.full(len(groups), np.nan)
    se = np.full(len(groups), np.nan)
    count = np.zeros(len(groups), dtype=np.int64)
    for k, g in enumerate(groups):
        count[k] = len(g)
        if len(g) >= min_pixels:
            mean[k] = vals[g].mean()
            if with_se:
                se[k] = _plane_fit_se(pts[g], vals[g])
    return (mean, count, se) if with_se else (mean, count)


def _plane_fit_se(points_mm, values):
    """Standard error of the mean of ``values`` [same units] taken at
    ``points_mm`` (n, 3) on a surface patch: the residual scatter about the
    best plane over the patch's own two principal directions, over sqrt(n);
    NaN with fewer than 4 points (no degree of freedom left)."""
    n = len(values)
    if n < 4:
        return np.nan
    p = points_mm - points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(p, full_matrices=False)
    a = np.c_[np.ones(n), p @ vt[:2].T]
    coef, *_ = np.linalg.lstsq(a, values, rcond=None)
    rss = float(np.sum((values - a @ coef) ** 2))
    return np.sqrt(rss / (n - 3) / n)


def counts_to_boundary_fluence(counts_adu, offset_adu, gain_adu_per_radiance, robin_A,
                               laser_power_w):
    """Detector counts -> normalised boundary fluence y = Phi / P_laser [1/mm^2].

    L = (S - offset) / G   [W/mm^2/sr]
    J = pi L               [W/mm^2]   (Lambertian exitance)
    Phi = 2 A J            [W/mm^2]   (Robin boundary, C_R = 2A)
    y = Phi / P_laser      [1/mm^2]
    """
    if not np.isfinite(laser_power_w) or laser_power_w <= 0:
        raise FluoInputError("laser power must be positive", field="laser_power_w",
                             value=laser_power_w)
    if not np.isfinite(gain_adu_per_radiance) or gain_adu_per_radiance <= 0:
        raise FluoInputError("camera gain must be positive", field="gain_adu_per_radiance",
                             value=gain_adu_per_radiance)
    radiance = (np.asarray(counts_adu, float) - offset_adu) / gain_adu_per_radiance
    exitance = np.pi * radiance
    return 2.0 * robin_A * exitance / laser_power_w


def boundary_fluence_to_counts(fluence_per_w, offset_adu, gain_adu_per_radiance, robin_A,
                               laser_power_w):
    """Inverse of :func:`counts_to_boundary_fluence` (noise-free expected counts)."""
    exitance = np.asarray(fluence_per_w, float) * laser_power_w / (2.0 * robin_A)
    return exitance / np.pi * gain_adu_per_radiance + offset_adu
