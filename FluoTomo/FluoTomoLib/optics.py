"""Diffusion-theory optical quantities (physics.md section 1).

All lengths in mm, coefficients in 1/mm.  Functions accept scalars or numpy
arrays (nodal values) and validate their input: NaN, negative absorption or
non-positive scattering raise FluoInputError naming the field; a reduced
albedo outside diffusion's range (musp/mua < 10) warns.
"""

from __future__ import annotations

import warnings

import numpy as np

from fluoguide.errors import FluoInputError


class DiffusionValidityWarning(UserWarning):
    """Diffusion theory is inaccurate here (musp/mua < 10 or too close to a source)."""


# Largest absorption or reduced scattering accepted [1/mm]: tissue is 1e-3..10 /mm
MAX_COEFFICIENT_PER_MM = 1e3


def check_properties(mua_per_mm, musp_per_mm, n=None, where="optical properties", warn=True):
    """Validate absorption, scattering and refractive index; return float arrays."""
    mua = np.asarray(mua_per_mm, dtype=float)
    musp = np.asarray(musp_per_mm, dtype=float)
    for name, v in (("mua_per_mm", mua), ("musp_per_mm", musp)):
        if not np.all(np.isfinite(v)):
            bad = np.flatnonzero(~np.isfinite(np.atleast_1d(v)))[0]
            raise FluoInputError("must be finite", field=f"{where}.{name}[{bad}]",
                                 value=float(np.atleast_1d(v)[bad]))
    if np.any(mua < 0):
        bad = np.flatnonzero(np.atleast_1d(mua) < 0)[0]
        raise FluoInputError("absorption must be >= 0", field=f"{where}.mua_per_mm[{bad}]",
                             value=float(np.atleast_1d(mua)[bad]))
    if np.any(musp <= 0):
        bad = np.flatnonzero(np.atleast_1d(musp) <= 0)[0]
        raise FluoInputError("reduced scattering must be > 0", field=f"{where}.musp_per_mm[{bad}]",
                             value=float(np.atleast_1d(musp)[bad]))
    # beyond any tissue by orders of magnitude (and where the closed forms overflow)
    for name, v in (("mua_per_mm", mua), ("musp_per_mm", musp)):
        if np.any(v > MAX_COEFFICIENT_PER_MM):
            bad = np.flatnonzero(np.atleast_1d(v) > MAX_COEFFICIENT_PER_MM)[0]
            raise FluoInputError(f"must be at most {MAX_COEFFICIENT_PER_MM:g} /mm",
                                 field=f"{where}.{name}[{bad}]", value=float(np.atleast_1d(v)[bad]))
    if n is not None:
        n_arr = np.asarray(n, dtype=float)
        if not np.all(np.isfinite(n_arr)) or np.any(n_arr < 1.0) or np.any(n_arr > 3.0):
            raise FluoInputError("refractive index must be within 1..3", field=f"{where}.n",
                                 value=float(np.atleast_1d(n_arr)[0]))
    if warn and np.any(musp < 10 * mua):
        ratio = float(np.min(musp / np.maximum(mua, 1e-300)))
        warnings.warn(f"{where}: musp/mua = {ratio:.3g} < 10, diffusion theory is inaccurate",
                      DiffusionValidityWarning, stacklevel=2)
    return mua, musp


def reff(n):
    """Effective reflection coefficient of a tissue-air boundary, relative index n."""
    n = np.asarray(n, dtype=float)
    return -1.440 / n**2 + 0.710 / n + 0.668 + 0.0636 * n


def robin_A(n):
    """A = (1 + Reff) / (1 - Reff).  A(1.0) = 1 (no index mismatch), A(1.33) ~ 2.5."""
    r = reff(n)
    return (1.0 + r) / (1.0 - r)


def diffusion_coefficient(mua_per_mm, musp_per_mm):
    """D = 1 / (3 (mua + musp)) [mm] (NIRFAST convention)."""
    return 1.0 / (3.0 * (np.asarray(mua_per_mm, float) + np.asarray(musp_per_mm, float)))


def mueff(mua_per_mm, musp_per_mm):
    """Effective attenuation sqrt(3 mua mut') [1/mm]."""
    mua = np.asarray(mua_per_mm, float)
    return np.sqrt(3.0 * mua * (mua + np.asarray(musp_per_mm, float)))


def penetration_depth_mm(mua_per_mm, musp_per_mm):
    """delta = 1 / mueff [mm] (inf for mua = 0)."""
    with np.errstate(divide="ignore"):
        return 1.0 / mueff(mua_per_mm, musp_per_mm)


def transport_mfp_mm(mua_per_mm, musp_per_mm):
    """MFP' = 1 / (mua + musp) [mm]: the depth a collimated beam's source is buried at."""
    return 1.0 / (np.asarray(mua_per_mm, float) + np.asarray(musp_per_mm, float))


def reduced_albedo(mua_per_mm, musp_per_mm):
    musp = np.asarray(musp_per_mm, float)
    return musp / (np.asarray(mua_per_mm, float) + musp)
