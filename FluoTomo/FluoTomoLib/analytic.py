"""Closed-form diffusion solutions for a homogeneous semi-infinite medium.

docs/physics.md section 3.  The fluorescence formula is the 1D solution of the
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
    """Rd for planar unit irradiance (Kim & Wilson 2010 form, docs/physics.md section 3.1)."""
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
    rho = check_distances(rho_mm)
    with np.errstate(under="ignore"):
        return np.exp(log_reflectance(rho, mua, musp, n))


def log_reflectance(rho_mm, mua_per_mm, musp_per_mm, n):
    """ln R(rho), computed in log space so 100 mm detectors stay finite."""
    mua = float(mua_per_mm)
    musp = float(musp_per_mm)
    rho = check_distances(rho_mm)
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
    rho = check_distances(rho_mm)
    mut = float(mua + musp)
    z0 = 1.0 / mut
    D = float(diffusion_coefficient(mua, musp))
    zb = 2.0 * float(robin_A(n)) * D
    me = float(mueff(mua, musp))
    r1 = np.sqrt(z0**2 + rho**2)
    r2 = np.sqrt((z0 + 2 * zb) ** 2 + rho**2)
    with np.errstate(under="ignore"):
        return (np.exp(-me * r1) / r1 - np.exp(-me * r2) / r2) / (4 * np.pi * D)


def robin_parameters(mua_per_mm, musp_per_mm, n):
    """The lengths of the Robin half-space problem (docs/physics.md section 3.2), validated.

    Parameters
    ----------
    mua_per_mm, musp_per_mm : float
        Absorption and reduced scattering [1/mm] (``check_properties``: a bad one
        raises FluoInputError).
    n : float
        Refractive index of the tissue.

    Returns
    -------
    (z0, zb, D, mueff) : tuple of float
        The depth of the buried source 1/mut' [mm], the extrapolation distance
        2 A D [mm], the diffusion coefficient D = 1/(3 mut') [mm] and the effective
        attenuation sqrt(3 mua mut') [1/mm].
    """
    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    mua, musp = float(mua), float(musp)
    mut = mua + musp
    D = 1.0 / (3.0 * mut)
    return 1.0 / mut, 2.0 * float(robin_A(n)) * D, D, float(np.sqrt(3.0 * mua * mut))


#: the largest source-detector distance [mm] the half-space formulas take: 10 m,
#: more than any tissue or phantom a pair of optodes can span (a body is < 2 m)
#: and far inside the doubles (rho**2 overflows only past ~1e154 mm, which
#: printed nulls after numpy's overflow warnings)
MAX_DISTANCE_MM = 1e4


def check_distances(rho_mm, field="rho_mm"):
    """Source-detector distances [mm] as an array: finite, within 0..MAX_DISTANCE_MM.

    Parameters
    ----------
    rho_mm : array_like
        Distances [mm].
    field : str
        The option or argument named in the message.
    """
    rho = np.asarray(rho_mm, dtype=float)
    bad = ~np.isfinite(rho) | (rho < 0) | (rho > MAX_DISTANCE_MM)
    if rho.size == 0 or np.any(bad):
        raise FluoInputError(f"distances must be finite, within 0..{MAX_DISTANCE_MM:g} mm "
                             "(10 m: larger than any tissue)", field=field,
                             value=float(rho[bad].ravel()[0]) if np.any(bad) else "none")
    return rho


# Gauss-Legendre nodes per panel and the panel limits of the line-of-images
# quadrature: the geometric ratio of the image depth and the step of the
# exponent per panel.  Against the independent branch-cut integral over mua
# 1e-6..2, musp 0.05..200, n 1..1.6, rho 0.5..60 mm these give 2e-13 relative
# (test_analytic.py); the exponent is integrated to e^-50.
_GL_NODES = 16
_GEOMETRIC_RATIO = 1.5
_EXPONENT_STEP = 1.5
_EXPONENT_END = 50.0


def log_robin_surface_fluence(rho_mm, mua_per_mm, musp_per_mm, n):
    """ln of :func:`robin_surface_fluence` [ln(1/mm^2)]: finite at any distance
    (the fluence itself underflows beyond ~700 decay lengths)."""
    z0, zb, D, me = robin_parameters(mua_per_mm, musp_per_mm, n)
    rho = check_distances(rho_mm)
    u, inv = np.unique(rho.ravel(), return_inverse=True)   # each distance once
    out = np.empty(len(u))
    for i in range(0, len(u), 512):                          # bounded memory
        out[i:i + 512] = _log_robin_unique(u[i:i + 512], z0, zb, D, me)
    return out[inv].reshape(rho.shape)


def _log_robin_unique(rho, z0, zb, D, me):
    """The line-of-images integral for distinct distances (see robin_surface_fluence).

    With Z = z0 + s the depth of an image point and r = sqrt(rho^2 + Z^2):
    Phi = 1/(2 pi D) int_z0^inf e^{-(Z - z0)/zb} Z (1 + me r) e^{-me r} / r^3 dZ,
    every term positive, so no cancellation at any distance.  The exponent
    E(Z) = (Z - z0)/zb + me (r - r0) is factored out of the log (r - r0 in a
    form without cancellation); panels are geometric in Z (the algebraic
    factors) and never span more than _EXPONENT_STEP of E (the exponential).
    """
    from numpy.polynomial.legendre import leggauss

    r0 = np.sqrt(rho ** 2 + z0 ** 2)

    def exponent(Z, rr, R0):
        return (Z - z0) / zb + me * ((Z - z0) * (Z + z0) / (np.sqrt(rr ** 2 + Z ** 2) + R0))

    # depths where E reaches each multiple of the step, by bisection (E is
    # increasing and E(z0 + t zb) >= t)
    t = _EXPONENT_STEP * np.arange(1, int(np.ceil(_EXPONENT_END / _EXPONENT_STEP)) + 1)
    lo = np.full((len(rho), len(t)), z0)
    hi = z0 + np.outer(np.ones(len(rho)), t) * zb
    rr, R0 = rho[:, None], r0[:, None]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        above = exponent(mid, rr, R0) > t
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    z_exp = 0.5 * (lo + hi)
    z_end = z_exp[:, -1]
    k = int(np.ceil(np.log(np.max(z_end) / z0) / np.log(_GEOMETRIC_RATIO))) + 1
    z_geo = np.minimum(z0 * _GEOMETRIC_RATIO ** np.arange(1, k + 1)[None, :], z_end[:, None])
    edges = np.sort(np.concatenate([np.full((len(rho), 1), z0), z_geo, z_exp], axis=1), axis=1)
    a, b = edges[:, :-1, None], edges[:, 1:, None]
    x, w = leggauss(_GL_NODES)
    Z = 0.5 * (a + b) + 0.5 * (b - a) * x
    r = np.sqrt(rho[:, None, None] ** 2 + Z ** 2)
    f = np.exp(-exponent(Z, rho[:, None, None], r0[:, None, None])) * Z * (1.0 + me * r) / r ** 3
    integral = np.sum(0.5 * (b - a) * w * f, axis=(1, 2))
    return -np.log(2.0 * np.pi * D) - me * r0 + np.log(integral)


def robin_surface_fluence(rho_mm, mua_per_mm, musp_per_mm, n):
    """Exact surface fluence [1/mm^2] of a unit point source buried 1/mut' in a
    half-space with the Robin (partial-current) boundary Phi - zb dPhi/dz = 0,
    zb = 2 A D, that the FEM solves.

    In the Hankel domain the surface value is 2A e^{-alpha z0}/(1 + zb alpha),
    alpha = sqrt(mueff^2 + k^2); writing 1/(1 + zb alpha) as an integral over
    e^{-s/zb - alpha s} and integrating by parts turns it into a line of
    images below the source, each an infinite-medium Green's function:

        Phi(rho, 0) = -2 int_0^inf e^{-s/zb} dG/dZ(rho, z0 + s) ds,
        G(rho, Z) = e^{-mueff r} / (4 pi D r),  r = sqrt(rho^2 + Z^2),

    a positive integrand, evaluated by Gauss-Legendre panels in log space
    (:func:`log_robin_surface_fluence`).  Accurate to ~1e-13 relative over
    mua 1e-6..2, musp 0.05..200, n 1..1.6, rho 0..60 mm (checked against an
    independent branch-cut integral of the Hankel form in test_analytic.py);
    values below ~1e-308 underflow to 0.  Each distinct distance is computed
    once.  The extrapolated-boundary dipole (R(rho), :func:`surface_fluence`)
    approximates this; they differ by up to ~10 % at rho of 5-10 mm for
    musp ~ 1/mm, n = 1.33 (docs/fem.md), which is why the FEM is verified
    against this form.
    """
    with np.errstate(under="ignore"):
        return np.exp(log_robin_surface_fluence(rho_mm, mua_per_mm, musp_per_mm, n))


def _phi_1d_terms(mua, musp, n):
    """Coefficients of the 1D diffuse fluence without the removable singularity.

    Phi(z) = K [ (e^{-me z} - e^{-mut z}) / (mut - me) + c e^{-me z} ],
    K = 3 musp mut / (mut + me), c = 2 A D / (1 + 2 A D me): the classic
    C e^{-mut z} + B e^{-me z} regrouped (C and B are each infinite at
    musp = 2 mua, where mut = me); both terms are positive.
    """
    mut = mua + musp
    D = 1.0 / (3.0 * mut)
    me = float(np.sqrt(3.0 * mua * mut))
    A = float(robin_A(n))
    K = 3.0 * musp * mut / (mut + me)
    c = 2.0 * A * D / (1.0 + 2.0 * A * D * me)
    return mut, me, K, c


def excitation_fluence_1d(z_mm, mua_per_mm, musp_per_mm, n, include_unscattered=False):
    """Diffuse excitation fluence Phi_x(z) for unit planar collimated irradiance.

    Phi(z) = C e^{-mut' z} + B e^{-mueff z} (docs/physics.md section 3.3), computed in a
    form that stays finite and positive at musp = 2 mua (where C and B are each
    infinite): see :func:`_phi_1d_terms`.  Plus the unscattered beam
    e^{-mut' z} when ``include_unscattered``.  Depths ``z_mm`` >= 0.
    """
    mua, musp = check_properties(mua_per_mm, musp_per_mm, n, warn=False)
    mua, musp = float(mua), float(musp)
    z = np.asarray(z_mm, float)
    if np.any(~np.isfinite(z)) or np.any(z < 0):
        raise FluoInputError("depths must be finite and >= 0", field="z_mm")
    mut, me, K, c = _phi_1d_terms(mua, musp, n)
    lo, gap = min(mut, me), abs(mut - me)
    # (e^{-me z} - e^{-mut z}) / (mut - me) = e^{-lo z} (1 - e^{-gap z}) / gap -> z
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(gap * z > 0, -np.expm1(-gap * z) / np.where(gap > 0, gap, 1.0), z)
    phi = K * (np.exp(-lo * z) * ratio + c * np.exp(-me * z))
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
    Dm = float(diffusion_coefficient(mua_m, musp_m))
    mem = float(mueff(mua_m, musp_m))
    mutx, mex, K, c = _phi_1d_terms(mua_x, musp_x, n)
    # integral of K[(e^{-me z} - e^{-mut z})/(mut - me) + c e^{-me z}] e^{-mem z}
    integral = K * (1.0 / ((mex + mem) * (mutx + mem)) + c / (mex + mem))
    if include_unscattered:
        integral += 1.0 / (mutx + mem)
    return float(yield_per_mm) * integral / (1 + 2 * A * Dm * mem)


def diffusion_summary(mua, musp, n, rho=None, yield_per_mm=None, mua_m=None, musp_m=None,
                      unscattered=False):
    """Everything closed-form diffusion theory says of one homogeneous
    semi-infinite medium (``fluo analytic``, ``FluoTomoLogic.analytic``).

    Parameters
    ----------
    mua, musp : float
        Excitation absorption and reduced scattering [1/mm]; checked as
        ``properties``.
    n : float
        Refractive index of the tissue (outside: air).
    rho : sequence of float, optional
        Source-detector distances [mm] (checked as ``rho``): also R(rho)
        [1/mm^2], the exact Robin surface fluence and its logarithm.
    yield_per_mm : float, optional
        Fluorescence yield eta*mua_f [1/mm]: also F, with the emission's
        ``mua_m``, ``musp_m`` [1/mm] (default: the excitation's; checked as
        ``emission``).
    unscattered : bool
        Include the unscattered excitation beam in F.

    Returns
    -------
    dict
        The medium, Rd, mueff [1/mm], penetration_depth_mm, D [mm], A,
        diffusion_valid, the rho and F entries asked for, warnings.
    """
    from FluoTomoLib.optics import (NEAR_SOURCE_MFP, diffusion_validity, penetration_depth_mm,
                                    transport_mfp_mm)

    check_properties(mua, musp, n, where="properties", warn=False)
    rho = check_distances(rho, "rho") if rho is not None else None
    warnings = diffusion_validity(mua, musp, rho)
    out = {
        "mua_per_mm": mua, "musp_per_mm": musp, "n": n,
        "Rd": float(total_diffuse_reflectance(mua, musp, n)),
        "mueff": float(mueff(mua, musp)),
        "penetration_depth_mm": float(penetration_depth_mm(mua, musp)),
        "D": float(diffusion_coefficient(mua, musp)),
        "A": float(robin_A(n)),
        "diffusion_valid": musp >= 10 * mua,
    }
    if rho is not None:
        out["rho_mm"] = rho.tolist()
        out["R_rho"] = spatially_resolved_reflectance(rho, mua, musp, n).tolist()
        log_phi = log_robin_surface_fluence(rho, mua, musp, n)
        with np.errstate(under="ignore"):
            out["robin_surface_fluence"] = np.exp(log_phi).tolist()
        # values below the smallest double underflow to 0; their logs stay exact
        out["ln_robin_surface_fluence"] = log_phi.tolist()
        out["rho_diffusive"] = (rho >= NEAR_SOURCE_MFP * transport_mfp_mm(mua, musp)).tolist()
        tiny = np.log(np.finfo(float).tiny)
        if np.any(log_phi < tiny):
            warnings.append(f"{int(np.sum(log_phi < tiny))} fluence value(s) are below 1e-308 "
                            "and print as 0: use ln_robin_surface_fluence")
    if yield_per_mm is not None:
        mua_m = mua if mua_m is None else mua_m
        musp_m = musp if musp_m is None else musp_m
        check_properties(mua_m, musp_m, n, where="emission", warn=False)
        warnings += [f"emission: {w}" for w in diffusion_validity(mua_m, musp_m)]
        out["diffusion_valid"] = out["diffusion_valid"] and musp_m >= 10 * mua_m
        out["F"] = total_diffuse_fluorescence((mua, musp), (mua_m, musp_m), yield_per_mm, n,
                                              include_unscattered=unscattered)
        out["F_includes_unscattered_beam"] = bool(unscattered)
    out["warnings"] = warnings
    return out
