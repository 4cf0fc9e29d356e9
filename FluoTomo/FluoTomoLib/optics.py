"""Diffusion-theory optical quantities (docs/physics.md section 1).

All lengths in mm, coefficients in 1/mm.  Functions accept scalars or numpy
arrays (nodal values) and validate their input: NaN, negative absorption or
non-positive scattering raise FluoInputError naming the field; a reduced
albedo outside diffusion's range (musp/mua < 10) warns.
"""

from __future__ import annotations

import contextlib
import functools
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


# The boundary constant A of the Robin condition Phi + 2 A D dPhi/dn = 0 (and of the
# exitance J = Phi / (2A)).  "empirical": Reff(n) from the polynomial fit of reff();
# "fresnel": the partial-current boundary condition with the Fresnel reflection
# integrated exactly (fresnel_moments).  docs/validation.md compares both with Monte Carlo:
# the Fresnel constant fits the fluence inside the tissue (within ~2 % at n 1.37, against
# +5-6 % with the empirical one) and the emission of a buried inclusion, the empirical one
# fits R(rho) far from the beam (the Fresnel one is 1-4 % low beyond 10 mm).  Default:
# "fresnel", since the Jacobians and the emission data are made of the interior fluence.
BOUNDARY_METHODS = ("empirical", "fresnel")
DEFAULT_BOUNDARY = "fresnel"


@contextlib.contextmanager
def boundary_method(method):
    """Within the block, ``robin_A(n)`` (and so the FEM and the closed forms) uses
    ``method``: to reproduce work made with another boundary constant (the thesis's
    tables used "empirical").  Not thread-safe: it sets the module default."""
    global DEFAULT_BOUNDARY
    if method not in BOUNDARY_METHODS:
        raise FluoInputError(f"unknown boundary method; use one of {', '.join(BOUNDARY_METHODS)}",
                             field="boundary", value=method)
    old = DEFAULT_BOUNDARY
    DEFAULT_BOUNDARY = method
    try:
        yield
    finally:
        DEFAULT_BOUNDARY = old


# Below this many transport mean free paths from a pencil beam, diffusion theory
# over-predicts the reflectance by more than ~3-5 %: Monte Carlo (MCX, mua 0.01,
# musp 1, n 1.37; montecarlo/data/independent_reflectance_n137.csv) against the exact
# Robin solution:
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
    """Effective reflection coefficient of a tissue-air boundary, relative index n
    (empirical polynomial fit, docs/physics.md section 1)."""
    n = np.asarray(n, dtype=float)
    return -1.440 / n**2 + 0.710 / n + 0.668 + 0.0636 * n


def fresnel_reflectance(cos_i, n):
    """Unpolarised Fresnel reflectance for light inside a medium of index n hitting
    a boundary with air (index 1) at internal angle arccos(cos_i); 1 beyond the
    critical angle."""
    ci = np.clip(np.asarray(cos_i, float), 0.0, 1.0)
    n = float(n)
    si = np.sqrt(1.0 - ci**2)
    st = n * si
    out = np.ones_like(ci)
    ok = st < 1.0
    ct = np.sqrt(1.0 - st[ok] ** 2)
    c = ci[ok]
    rs = (n * c - ct) / (n * c + ct)
    rp = (n * ct - c) / (n * ct + c)
    out[ok] = 0.5 * (rs**2 + rp**2)
    return out


@functools.lru_cache(maxsize=4)
def _gauss_legendre(points):
    """Gauss-Legendre nodes and weights on [-1, 1], kept: every diffusion operator
    asks (its boundary constant), and the 400-point rule is an eigenvalue
    problem (0.2-0.4 s where BLAS threads compete for the cores)."""
    x, w = np.polynomial.legendre.leggauss(points)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w


def fresnel_moments(n, points=400):
    """(R_phi, R_J): the Fresnel reflectance's fluence and flux moments
    R_phi = 2 int_0^1 R(mu) mu dmu, R_J = 3 int_0^1 R(mu) mu^2 dmu (mu = cos of the
    internal angle), by Gauss-Legendre on both sides of the critical angle."""
    n = float(n)
    if n <= 1.0:
        return 0.0, 0.0
    mu_c = np.sqrt(1.0 - 1.0 / n**2)
    x, w = _gauss_legendre(int(points))
    # [0, mu_c]: total reflection (R = 1); [mu_c, 1]: Fresnel
    mu = mu_c + (1.0 - mu_c) * 0.5 * (x + 1.0)
    wm = w * 0.5 * (1.0 - mu_c)
    R = fresnel_reflectance(mu, n)
    r_phi = mu_c**2 + 2.0 * np.sum(wm * R * mu)
    r_j = mu_c**3 + 3.0 * np.sum(wm * R * mu**2)
    return float(r_phi), float(r_j)


def robin_A(n, method=None):
    """Boundary constant A of the Robin condition Phi + 2 A D dPhi/dn = 0.

    Parameters
    ----------
    n : refractive index of the tissue (outside: air)
    method : "empirical" - A = (1 + Reff)/(1 - Reff) with the polynomial Reff(n) of
        :func:`reff` (A(1.0) = 1.003, A(1.33) = 2.79, A(1.37) = 3.05, A(1.4) = 3.25);
        "fresnel" - A = (1 + R_J)/(1 - R_phi) with the Fresnel moments integrated
        exactly (:func:`fresnel_moments`; A(1.0) = 1, A(1.33) = 2.52, A(1.37) = 2.76,
        A(1.4) = 2.95).  None: ``DEFAULT_BOUNDARY``.
    """
    method = DEFAULT_BOUNDARY if method is None else method
    if method == "empirical":
        r = reff(n)
        return (1.0 + r) / (1.0 - r)
    if method == "fresnel":
        n_arr = np.asarray(n, dtype=float)
        vals = [(1.0 + rj) / (1.0 - rp) for rp, rj in (fresnel_moments(v) for v in n_arr.ravel())]
        out = np.array(vals).reshape(n_arr.shape)
        return out if out.ndim else float(out)
    raise FluoInputError(f"unknown boundary method; use one of {', '.join(BOUNDARY_METHODS)}",
                         field="boundary", value=method)


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
