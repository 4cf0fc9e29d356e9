"""Peak yield and centroid from a 1D depth profile (docs/physics.md section 8.5).

The reference reads both from a line profile through the target: the peak is
the profile's maximum, the centroid the centre of the region within 50 % of
the peak (the contiguous run around the maximum).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.fem.locate import locator


def depth_profile(mesh, nodal_values, xy_mm, z_top_mm=0.0, z_bottom_mm=-20.0, step_mm=0.05):
    """Values along the vertical line at (x, y) from z_top to z_bottom (3D), or at
    x from y_top to y_bottom (2D, xy_mm = x).  Returns depth [mm, > 0] and values
    (NaN outside the mesh)."""
    z = np.arange(z_top_mm, z_bottom_mm - 1e-9, -abs(step_mm))
    if mesh.dim == 3:
        pts = np.stack([np.full_like(z, xy_mm[0]), np.full_like(z, xy_mm[1]), z], axis=1)
    else:
        pts = np.stack([np.full_like(z, float(np.atleast_1d(xy_mm)[0])), z], axis=1)
    P = locator(mesh).interpolation_matrix(pts, outside="nan")
    inside = np.asarray(P.sum(axis=1)).ravel() > 0.5
    vals = np.where(inside, P @ np.asarray(nodal_values, float), np.nan)
    return z_top_mm - z, vals


def peak_and_centroid(depth_mm, values):
    """(peak value, centroid depth [mm]) of a profile; centroid = centre of the
    contiguous run within 50 % of the peak around the maximum."""
    v = np.asarray(values, float)
    if not np.any(np.isfinite(v)):
        raise FluoInputError("profile has no values inside the mesh", field="profile")
    k = int(np.nanargmax(v))
    peak = float(v[k])
    if peak <= 0:
        return peak, float("nan")
    half = np.nan_to_num(v, nan=-np.inf) >= 0.5 * peak
    lo = k
    while lo > 0 and half[lo - 1]:
        lo -= 1
    hi = k
    while hi < len(v) - 1 and half[hi + 1]:
        hi += 1
    return peak, 0.5 * (float(depth_mm[lo]) + float(depth_mm[hi]))
