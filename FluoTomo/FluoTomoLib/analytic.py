"""Closed-form diffusion solutions for a homogeneous semi-infinite medium.

physics.md section 3.  The fluorescence formula is the 1D solution of the
coupled excitation/emission diffusion equations with the Robin boundary,
the same model the FEM solves, so the two agree for a thick slab
(Testing: test_analytic.py compares them).  It does not reproduce the
thesis's F column; see docs/fem.md for why.
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.optics import (
    MAX_COEFFICIENT_PER_MM,
    check_properties,
    diffusion_coefficient,
    mueff,
    reduced_albedo,
    robin_A,
)


def total_diffuse_reflectance(mua_per_mm, musp_per_mm, n):
    """Rd for planar unit irradiance (Kim & Wilson 2010 form of physics.md)."""
    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    a = reduced_albedo(mua, musp)
    A = robin_A(n)
    return a / (1.0 + 2.0 * A * (1.0 - a) + (1.0 + 2.0 * A / 3.0) * np.sqrt(3.0 * (1.0 - a)))


def spatially_resolved_reflectance(rho_mm, mua_per_mm, musp_per_mm, n):
    """R(rho) [1/mm^2] for a unit-power pencil beam (dipole, extrapolated boundary).

    Far detectors underflow to 0 (never NaN); use :func:`log_reflectance` for
    data that must stay finite in log space.
    """
    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    rho = np.asarray(rho_mm, dtype=float)
    if np.any(~np.isfinite(rho)) or np.any(rho < 0):
        raise FluoInputError("distances must be finite and >= 0", field="rho_mm")
    with np.errstate(under="ignore"):
        return np.exp(log_reflectance(rho, mua, musp, n))


def log_reflectance(rho_mm, mua_per_mm, musp_per_mm, n):
    """ln R(rho), computed in log space so 100 mm detectors stay finite."""
    mua = float(mua_per_mm)
    musp = float(musp_per_mm)
    rho = np.asarray(rho_mm, dtype=float)
    mut = mua + musp
    z0 = 1.0 / mut
    D = diffusion_coefficient(mua, musp)
    zb = 2.0 * robin_A(n) * D
    me = float(mueff(mua, musp))
    r1 = np.sqrt(z0**2 + rho**2)
    r2 = np.sqrt((z0 + 2 * zb) ** 2 + rho**2)
    # ln[a1 e^{-me r1} + a2 e^{-me r2}] with the larger exponent factored out
    l1 = np.log(z0 * (me + 1 / r1) / r1**2) - me * r1
    l2 = np.log((z0 + 2 * zb) * (me + 1 / r2) / r2**2) - me * r2
    hi = np.maximum(l1, l2)
    return hi + np.log(np.exp(l1 - hi) + np.exp(l2 - hi)) - np.log(4 * np.pi)


def surface_fluence(rho_mm, mua_per_mm, musp_per_mm, n):
    """Fluence Phi(rho, z=0) [1/mm^2] of the same dipole, for a unit-power source.

    Phi = 1/(4 pi D) [e^{-mueff r1}/r1 - e^{-mueff r2}/r2]; with the Robin
    boundary the exitance is J = Phi/(2A), which equals R(rho) up to the
    difference between Fick's-law flux and the boundary condition (< 1 % for
    rho > 3 mm at these properties; docs/fem.md).
    """
    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    rho = np.asarray(rho_mm, dtype=float)
    mut = float(mua + musp)
    z0 = 1.0 / mut
    D = float(diffusion_coefficient(mua, musp))
    zb = 2.0 * float(robin_A(n)) * D
    me = float(mueff(mua, musp))
    r1 = np.sqrt(z0**2 + rho**2)
    r2 = np.sqrt((z0 + 2 * zb) ** 2 + rho**2)
    with np.errstate(under="ignore"):
        return (np.exp(-me * r1) / r1 - np.exp(-me * r2) / r2) / (4 * np.pi * D)


def robin_surface_fluence(rho_mm, mua_per_mm, musp_per_mm, n, k_max_per_mm=None, n_k=200001):
    """Exact surface fluence [1/mm^2] of a unit point source buried 1/mut' in a
    half-space with the Robin (partial-current) boundary the FEM solves.

    Hankel transform of the 1D Green's function:
    Phi(rho, 0) = 1/(2 pi) int_0^inf k J0(k rho) 2A e^{-alpha z0} / (1 + 2 A D alpha) dk,
    alpha = sqrt(mueff^2 + k^2).  The extrapolated-boundary dipole (R(rho),
    :func:`surface_fluence`) approximates this; they differ by up to ~10 %
    at rho of 5-10 mm for musp ~ 1/mm, n = 1.33 (docs/fem.md), which is why
    the FEM is verified against this form.
    """
    from scipy.special import j0

    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    mua, musp = float(mua), float(musp)
    D = float(diffusion_coefficient(mua, musp))
    me = float(mueff(mua, musp))
    A = float(robin_A(n))
    z0 = 1.0 / (mua + musp)
    kmax = k_max_per_mm or 40.0 / z0  # e^{-k z0} < 1e-17 beyond
    k = np.linspace(0.0, kmax, n_k)
    alpha = np.sqrt(me**2 + k**2)
    kernel = k * 2 * A * np.exp(-alpha * z0) / (1 + 2 * A * D * alpha)
    rho = np.atleast_1d(np.asarray(rho_mm, float))
    out = np.array([np.trapezoid(kernel * j0(k * r), k) for r in rho]) / (2 * np.pi)
    return out.reshape(np.shape(rho_mm))


def excitation_fluence_1d(z_mm, mua_per_mm, musp_per_mm, n, include_unscattered=False):
    """Diffuse excitation fluence Phi_x(z) for unit planar collimated irradiance.

    Phi(z) = C e^{-mut' z} + B e^{-mueff z} (physics.md section 3), plus the
    unscattered beam e^{-mut' z} when ``include_unscattered``.
    """
    mua, musp = float(mua_per_mm), float(musp_per_mm)
    D = float(diffusion_coefficient(mua, musp))
    mut = mua + musp
    me = float(mueff(mua, musp))
    A = float(robin_A(n))
    C = musp / (mua - D * mut**2)
    B = -C * (1 + 2 * A * D * mut) / (1 + 2 * A * D * me)
    z = np.asarray(z_mm, float)
    phi = C * np.exp(-mut * z) + B * np.exp(-me * z)
    if include_unscattered:
        phi = phi + np.exp(-mut * z)
    return phi


def total_diffuse_fluorescence(props_x, props_m, yield_per_mm, n, include_unscattered=False):
    """Total diffuse fluorescence F for planar unit irradiance (exitance ratio).

    F = yield * integral_0^inf Phi_x(z) E_m(z) dz with
    E_m(z) = e^{-mueff_m z} / (1 + 2 A D_m mueff_m) (escape probability),
    integrated in closed form.

    Parameters
    ----------
    props_x, props_m : (mua_per_mm, musp_per_mm) at excitation and emission;
        mua_x includes the fluorophore's absorption
    yield_per_mm : eta * mua_f,x
    include_unscattered : add the unscattered beam e^{-mut'_x z} to Phi_x
    """
    from fluoguide.errors import check_number

    mua_x, musp_x = (float(v) for v in props_x)
    mua_m, musp_m = (float(v) for v in props_m)
    # eta * mua_f: a part of the excitation absorption, so bounded like it
    check_number("yield_per_mm", yield_per_mm, 0.0, MAX_COEFFICIENT_PER_MM)
    check_properties(mua_x, musp_x, n, where="excitation", warn=False)
    check_properties(mua_m, musp_m, n, where="emission", warn=False)
    if mua_m <= 0:
        raise FluoInputError("emission absorption must be > 0 for a finite escape integral",
                             field="mua_m_per_mm", value=mua_m)
    A = float(robin_A(n))
    Dx = float(diffusion_coefficient(mua_x, musp_x))
    Dm = float(diffusion_coefficient(mua_m, musp_m))
    mutx = mua_x + musp_x
    mex = float(mueff(mua_x, musp_x))
    mem = float(mueff(mua_m, musp_m))
    C = musp_x / (mua_x - Dx * mutx**2)
    B = -C * (1 + 2 * A * Dx * mutx) / (1 + 2 * A * Dx * mex)
    integral = C / (mutx + mem) + B / (mex + mem)
    if include_unscattered:
        integral += 1.0 / (mutx + mem)
    return float(yield_per_mm) * integral / (1 + 2 * A * Dm * mem)
