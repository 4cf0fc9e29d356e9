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


# Below this many transport mean free paths from a pencil beam, diffusion theory
# over-predicts the reflectance by more than ~3-5 %: Monte Carlo (MCX, mua 0.01,
# musp 1, n 1.37; /work/shared/reference/mc) against the exact Robin solution:
# +7.0 % at 1 MFP', +7.8 % at 2, +4.0 % at 3, +1.4 % at 4, within 2 % from 5
# (docs/fem.md).
NEAR_SOURCE_MFP = 4.0


def diffusion_validity(mua_per_mm, musp_per_mm, rho_mm=None):
    """Where diffusion theory may be wrong by more than a few percent.

    Returns a list of messages (empty when valid): a reduced albedo below
    diffusion's range (musp/mua < 10) and distances within
    :data:`NEAR_SOURCE_MFP` transport mean free paths of the source.
    """
    mua = np.atleast_1d(np.asarray(mua_per_mm, float))
    musp = np.atleast_1d(np.asarray(musp_per_mm, float))
    out = []
    if np.any(musp < 10 * mua):
        ratio = float(np.min(musp / np.maximum(mua, 1e-300)))
        out.append(f"musp/mua = {ratio:.3g} < 10: not a diffusive medium, diffusion theory "
                   "is inaccurate here")
    if rho_mm is not None:
        rho = np.atleast_1d(np.asarray(rho_mm, float))
        near_mm = NEAR_SOURCE_MFP * float(np.max(transport_mfp_mm(mua, musp)))
        close = rho < near_mm
        if np.any(close):
            out.append(f"{int(close.sum())} of {rho.size} distance(s) are within "
                       f"{NEAR_SOURCE_MFP:g} transport mean free paths ({near_mm:.3g} mm) of the "
                       "source, where diffusion theory over-predicts the reflectance by 4-8 % "
                       "(Monte Carlo, docs/fem.md)")
    return out


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
