"""Closed-form diffusion theory (docs/physics.md sections 1 and 3) and `fluo analytic`."""

import json
import warnings

import numpy as np
import pytest
from scipy.integrate import quad

from fluoapp.cli import main
from fluoguide.errors import FluoInputError
from FluoTomoLib.analytic import (
    excitation_fluence_1d,
    log_reflectance,
    robin_surface_fluence,
    spatially_resolved_reflectance,
    surface_fluence,
    total_diffuse_fluorescence,
    total_diffuse_reflectance,
)
from FluoTomoLib.optics import (
    DiffusionValidityWarning,
    boundary_method,
    check_properties,
    diffusion_coefficient,
    mueff,
    penetration_depth_mm,
    reff,
    robin_A,
    transport_mfp_mm,
)

# docs/physics.md section 3.4 (thesis Table 2-5): ICG, mua_x, musp_x, mua_f,x, mua_m, musp_m
ICG_ROWS = [
    (0.0, 0.0026, 0.89, 0.0, 0.0029, 0.81),
    (0.4, 0.016, 0.89, 0.013, 0.0068, 0.81),
    (0.8, 0.029, 0.89, 0.026, 0.011, 0.81),
    (1.2, 0.042, 0.89, 0.039, 0.015, 0.81),
    (1.6, 0.055, 0.89, 0.052, 0.018, 0.81),
    (2.0, 0.068, 0.89, 0.065, 0.022, 0.81),
]
ETA = 0.04


def test_boundary_coefficients():
    # matched index: almost no internal reflection, A ~ 1
    assert reff(1.0) == pytest.approx(0.0016, abs=1e-4)
    assert robin_A(1.0, "empirical") == pytest.approx(1.0032, abs=1e-4)
    assert robin_A(1.0, "fresnel") == 1.0
    # A grows monotonically with the index mismatch
    n = np.linspace(1.0, 1.6, 13)
    for method in ("empirical", "fresnel"):
        assert np.all(np.diff(robin_A(n, method)) > 0)
    assert robin_A(1.33, "empirical") == pytest.approx(2.790, abs=1e-3)
    assert robin_A(1.33, "fresnel") == pytest.approx(2.515, abs=1e-3)
    with boundary_method("fresnel"):
        assert robin_A(1.33) == robin_A(1.33, "fresnel")
    with boundary_method("empirical"):
        assert robin_A(1.33) == robin_A(1.33, "empirical")


def test_derived_quantities_of_the_2d_study():
    # docs/physics.md section 8.5: the thesis quotes "penetration depth at excitation 3.1 mm"
    assert penetration_depth_mm(0.032, 1.0) == pytest.approx(3.18, abs=0.01)
    assert diffusion_coefficient(0.032, 1.0) == pytest.approx(1 / (3 * 1.032))
    assert mueff(0.032, 1.0) == pytest.approx(np.sqrt(3 * 0.032 * 1.032))
    assert transport_mfp_mm(0.032, 1.0) == pytest.approx(1 / 1.032)
    assert np.isinf(penetration_depth_mm(0.0, 1.0))


def test_rd_reproduces_thesis_column():
    # the thesis used the empirical Reff(n)
    with boundary_method("empirical"):
        rd = [total_diffuse_reflectance(r[1], r[2], 1.33) for r in ICG_ROWS]
        np.testing.assert_allclose(rd, [0.777, 0.559, 0.471, 0.415, 0.374, 0.342], atol=6e-4)
        assert total_diffuse_reflectance(0.005, 0.89, 1.52) == pytest.approx(0.65, abs=0.005)


@pytest.mark.parametrize("unscattered", [False, True])
def test_fluorescence_closed_form_equals_quadrature(unscattered):
    for _, mx, sx, mf, mm, sm in ICG_ROWS[1:]:
        n = 1.33
        A = robin_A(n)
        Dm, mem = diffusion_coefficient(mm, sm), mueff(mm, sm)

        def integrand(z):
            escape = np.exp(-mem * z) / (1 + 2 * A * Dm * mem)
            return excitation_fluence_1d(z, mx, sx, n, unscattered) * escape

        ref = ETA * mf * quad(integrand, 0, np.inf, limit=400)[0]
        F = total_diffuse_fluorescence((mx, sx), (mm, sm), ETA * mf, n, unscattered)
        assert F == pytest.approx(ref, rel=1e-8)


def test_fluorescence_values_of_the_diffusion_model():
    # docs/physics.md section 3.4: 1D FEM of the coupled equations gives these (not the
    # thesis column, section 9)
    rows = [ICG_ROWS[1], ICG_ROWS[2], ICG_ROWS[5]]
    with boundary_method("empirical"):      # the thesis's boundary constant
        diffuse = [total_diffuse_fluorescence((r[1], r[2]), (r[4], r[5]), ETA * r[3], 1.33)
                   for r in rows]
        beam = [total_diffuse_fluorescence((r[1], r[2]), (r[4], r[5]), ETA * r[3], 1.33, True)
                for r in rows]
    np.testing.assert_allclose(diffuse, [0.0062, 0.0076, 0.0087], atol=6e-5)
    np.testing.assert_allclose(beam, [0.0066, 0.0083, 0.0101], atol=6e-5)
    # no fluorophore, no fluorescence
    r = ICG_ROWS[0]
    assert total_diffuse_fluorescence((r[1], r[2]), (r[4], r[5]), 0.0, 1.33) == 0.0


def test_excitation_1d_satisfies_robin_boundary():
    mx, sx, n = 0.016, 0.89, 1.33
    D, A = diffusion_coefficient(mx, sx), robin_A(n)
    h = 1e-6
    phi0 = excitation_fluence_1d(0.0, mx, sx, n)
    dphi = (excitation_fluence_1d(h, mx, sx, n) - excitation_fluence_1d(-h, mx, sx, n)) / (2 * h)
    # outward normal is -z: Phi - 2 A D dPhi/dz = 0
    assert phi0 - 2 * A * D * dphi == pytest.approx(0.0, abs=1e-7)
    # the Rd formula is the exitance Phi(0)/(2A) of this solution
    assert phi0 / (2 * A) == pytest.approx(total_diffuse_reflectance(mx, sx, n), rel=1e-10)


def test_robin_surface_fluence_conserves_escaping_power():
    """The Hankel-transform solution integrated over the surface equals the 1D
    escape probability of a source at depth z0: e^{-mueff z0} / (1 + 2 A D mueff)."""
    mua, musp, n = 0.02, 1.0, 1.4
    A, D, me = robin_A(n), diffusion_coefficient(mua, musp), mueff(mua, musp)
    z0 = 1 / (mua + musp)
    rho = np.concatenate([[0.0], np.geomspace(1e-3, 120, 400)])
    J = robin_surface_fluence(rho, mua, musp, n, n_k=40001) / (2 * A)
    total = np.trapezoid(2 * np.pi * rho * J, rho)
    assert total == pytest.approx(np.exp(-me * z0) / (1 + 2 * A * D * me), rel=5e-3)


def test_dipole_forms_are_consistent():
    mua, musp, n = 0.01, 1.0, 1.33
    rho = np.array([3.0, 10.0, 25.0])
    R = spatially_resolved_reflectance(rho, mua, musp, n)
    assert np.all(R > 0) and np.all(np.diff(R) < 0)
    np.testing.assert_allclose(np.log(R), log_reflectance(rho, mua, musp, n), rtol=1e-12)
    # far from the source the dipole's Fick flux and its fluence/(2A) converge
    ratio = surface_fluence(rho, mua, musp, n) / (2 * robin_A(n)) / R
    assert abs(ratio[-1] - 1) < 0.05


def test_far_detectors_underflow_without_nan():
    rho = np.array([100.0, 500.0, 5000.0])
    R = spatially_resolved_reflectance(rho, 1.0, 100.0, 1.6)
    assert np.all(np.isfinite(R)) and np.all(R >= 0)
    logR = log_reflectance(rho, 1.0, 100.0, 1.6)
    assert np.all(np.isfinite(logR)) and np.all(np.diff(logR) < 0)


@pytest.mark.parametrize("mua, musp, n", [(1e-6, 0.1, 1.0), (1e-6, 100.0, 1.6), (1.0, 100.0, 1.0),
                                          (1.0, 0.1, 1.6)])
def test_extreme_properties_are_finite(mua, musp, n):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DiffusionValidityWarning)
        rd = total_diffuse_reflectance(mua, musp, n)
        R = spatially_resolved_reflectance([3.0, 100.0], mua, musp, n)
        F = total_diffuse_fluorescence((mua, musp), (mua, musp), 1e-3, n)
    assert 0 < rd < 1
    assert np.all(np.isfinite(R)) and np.all(R >= 0)
    assert np.isfinite(F) and F > 0


def test_validity_warning_and_bad_input():
    with pytest.warns(DiffusionValidityWarning, match="musp/mua"):
        check_properties(0.2, 1.0, 1.33)
    with pytest.raises(FluoInputError, match=r"mua_per_mm\[2\]"):
        check_properties(np.array([0.01, 0.01, np.nan]), 1.0, 1.33)
    with pytest.raises(FluoInputError, match="musp_per_mm"):
        total_diffuse_reflectance(0.01, 0.0, 1.33)
    with pytest.raises(FluoInputError, match="refractive index"):
        total_diffuse_reflectance(0.01, 1.0, 0.9)
    with pytest.raises(FluoInputError, match="rho_mm"):
        spatially_resolved_reflectance([-1.0], 0.01, 1.0, 1.33)
    with pytest.raises(FluoInputError, match="mua_m"):
        total_diffuse_fluorescence((0.01, 1.0), (0.0, 1.0), 1e-3, 1.33)


def test_cli_analytic_json(capsys):
    rc = main(["analytic", "--mua", "0.016", "--musp", "0.89", "--n", "1.33", "--rho", "3,10,25",
               "--yield", str(ETA * 0.013), "--mua-m", "0.0068", "--musp-m", "0.81", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("Rd", "mueff", "D", "A", "R_rho", "F"):
        assert key in out
    # the default boundary constant is the Fresnel one (A 2.515 at n 1.33; docs/validation.md);
    # with the thesis's empirical A these are 0.559 and 0.0062 (test_rd_reproduces_thesis_column)
    assert out["A"] == pytest.approx(2.515, abs=1e-3)
    assert out["Rd"] == pytest.approx(0.5762, abs=6e-4)
    assert out["F"] == pytest.approx(0.00608, abs=6e-5)
    np.testing.assert_allclose(out["R_rho"],
                               spatially_resolved_reflectance([3, 10, 25], 0.016, 0.89, 1.33))
    assert main(["analytic", "--mua", "nan", "--musp", "1", "--json"]) == 2
    assert "mua_per_mm" in capsys.readouterr().err
    assert main(["analytic", "--mua", "0.01", "--musp", "1", "--rho", "3,x", "--json"]) == 2
    assert "--rho" in capsys.readouterr().err
