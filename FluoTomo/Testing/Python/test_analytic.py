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
    log_robin_surface_fluence,
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
    h = 1e-4
    phi0, phi1, phi2 = excitation_fluence_1d([0.0, h, 2 * h], mx, sx, n)
    dphi = (-3 * phi0 + 4 * phi1 - phi2) / (2 * h)          # one-sided, O(h^2)
    # outward normal is -z: Phi - 2 A D dPhi/dz = 0
    assert phi0 - 2 * A * D * dphi == pytest.approx(0.0, abs=1e-7)
    # the Rd formula is the exitance Phi(0)/(2A) of this solution
    assert phi0 / (2 * A) == pytest.approx(total_diffuse_reflectance(mx, sx, n), rel=1e-10)


def test_robin_surface_fluence_conserves_escaping_power():
    """The surface fluence integrated over the surface equals the 1D escape
    probability of a source at depth z0: e^{-mueff z0} / (1 + 2 A D mueff)."""
    mua, musp, n = 0.02, 1.0, 1.4
    A, D, me = robin_A(n), diffusion_coefficient(mua, musp), mueff(mua, musp)
    z0 = 1 / (mua + musp)
    rho = np.concatenate([[0.0], np.geomspace(1e-4, 400, 4000)])
    J = robin_surface_fluence(rho, mua, musp, n) / (2 * A)
    total = np.trapezoid(2 * np.pi * rho * J, rho)
    assert total == pytest.approx(np.exp(-me * z0) / (1 + 2 * A * D * me), rel=1e-5)


def _branch_cut_log_fluence(rho, mua, musp, n):
    """ln Phi(rho, 0) of the Robin half-space, written here independently of
    analytic.py, by a different route: the Hankel form
    Phi = 1/(2 pi) int_0^inf k J0(k rho) 2A e^{-alpha z0} / (1 + zb alpha) dk
    with J0 = (H0(1) + H0(2)) / 2 and the contour closed around the branch cut
    k = i y, y > mueff, where H0(1)(i y rho) = 2/(i pi) K0(y rho):

        Phi = 2A/pi^2 int_0^inf b K0(rho sqrt(b^2 + mueff^2))
                        (sin(b z0) + zb b cos(b z0)) / (1 + zb^2 b^2) db.

    Evaluated with QUADPACK's sine/cosine-weighted rule, e^{mueff rho}
    factored out (kve), so values far below the smallest double are exact
    in the log."""
    from scipy.special import kve

    mut = mua + musp
    D = 1 / (3 * mut)
    zb, z0, me = 2 * robin_A(n) * D, 1 / mut, np.sqrt(3 * mua * mut)
    b_max = np.sqrt((me + 60 / rho) ** 2 - me ** 2)           # K0 factor e^{-60} beyond

    def f(b):
        s = np.sqrt(b * b + me * me)
        return b * kve(0, rho * s) * np.exp(-rho * b * b / (s + me)) / (1 + zb * zb * b * b)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                        # QUADPACK round-off notes
        i_sin = quad(f, 0, b_max, weight="sin", wvar=z0, limit=2000, epsabs=0, epsrel=1e-13)[0]
        i_cos = quad(lambda b: zb * b * f(b), 0, b_max, weight="cos", wvar=z0, limit=2000,
                     epsabs=0, epsrel=1e-13)[0]
    return np.log(2 * robin_A(n) / np.pi ** 2) - me * rho + np.log(i_sin + i_cos)


@pytest.mark.parametrize("mua", [1e-6, 1e-3, 0.1, 2.0])
def test_robin_surface_fluence_matches_an_independent_exact_solution(mua):
    """Every distance 0.5..60 mm, musp 0.05..200, n 1..1.6: the line-of-images
    quadrature against the branch-cut integral.  Measured agreement 2e-13
    (relative, in the log); the issue asks for 1e-6 in the far field, the test
    holds 1e-9 everywhere, down to values of e^-2100."""
    rho = np.array([0.5, 1.0, 3.0, 10.0, 30.0, 60.0])
    for musp in (0.05, 1.0, 10.0, 200.0):
        for n in (1.0, 1.33, 1.6):
            ours = log_robin_surface_fluence(rho, mua, musp, n)
            ref = np.array([_branch_cut_log_fluence(r, mua, musp, n) for r in rho])
            np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9,
                                       err_msg=f"mua {mua} musp {musp} n {n}")


def test_branch_cut_form_is_the_hankel_transform():
    """The test's reference itself, against the plain Hankel quadrature where
    that is accurate (near the source, values >> 1e-8 of the peak)."""
    from scipy.special import j0

    mua, musp, n = 0.01, 1.0, 1.4
    mut = mua + musp
    D, A, me = 1 / (3 * mut), robin_A(n), np.sqrt(3 * mua * mut)
    k = np.linspace(0, 40 * mut, 400001)
    alpha = np.sqrt(me ** 2 + k ** 2)
    kernel = k * 2 * A * np.exp(-alpha / mut) / (1 + 2 * A * D * alpha)
    for rho in (0.5, 1.0, 2.0):
        hankel = np.trapezoid(kernel * j0(k * rho), k) / (2 * np.pi)
        assert np.log(hankel) == pytest.approx(_branch_cut_log_fluence(rho, mua, musp, n),
                                               abs=1e-7)


def test_robin_surface_fluence_deduplicates_and_keeps_shape():
    rho = np.array([[5.0, 10.0, 5.0], [10.0, 5.0, 60.0]])
    out = robin_surface_fluence(rho, 0.01, 1.0, 1.37)
    assert out.shape == rho.shape
    assert out[0, 0] == out[0, 2] == out[1, 1] and out[0, 1] == out[1, 0]
    assert np.all(np.diff(robin_surface_fluence([0.0, 0.5, 5, 60], 0.01, 1.0, 1.37)) < 0)
    assert robin_surface_fluence(7.0, 0.01, 1.0, 1.37).shape == ()
    # below the smallest double the value underflows to 0; its log stays exact
    assert robin_surface_fluence(60.0, 2.0, 200.0, 1.6) == 0.0
    assert np.isfinite(log_robin_surface_fluence(60.0, 2.0, 200.0, 1.6))
    with pytest.raises(FluoInputError, match="rho_mm"):
        robin_surface_fluence([3.0, np.nan], 0.01, 1.0, 1.37)
    with pytest.raises(FluoInputError, match="rho_mm"):
        robin_surface_fluence([], 0.01, 1.0, 1.37)


def test_robin_reflectance_matches_monte_carlo_from_5_mm():
    """Independent physics: MCX Monte Carlo R(rho) (mua 0.01, musp 1, n 1.37; the
    independent run stored with the Monte Carlo sets, made outside this code,
    8 x 5e5 photons, 0.3-1.9 % standard error).  Diffusion's exitance
    J = Phi / (2A) from 5 transport MFP' on (the near-source excess is
    diffusion's own, docs/validation.md):

    - the empirical A (3.050) is within 3 % plus 2 MC errors everywhere
      (measured -1.0 .. +3.1 %);
    - the Fresnel A (2.759, the default: it fits the interior fluence and the
      emission of a buried inclusion) is low beyond 8 mm (measured -1.2 ..
      -4.9 %): within 5 % plus 2 MC errors, and low on average.
    """
    import csv
    from pathlib import Path

    import FluoTomoLib.montecarlo as mc
    from FluoTomoLib.optics import boundary_method

    path = Path(mc.__file__).parent / "data" / "independent_reflectance_n137.csv"
    rows = list(csv.DictReader(line for line in path.read_text().splitlines()
                               if not line.startswith("#")))
    rho = np.array([float(r["rho_mm"]) for r in rows])
    R = np.array([float(r["R_per_mm2"]) for r in rows])
    se = np.array([float(r["se_cp_per_mm2"]) for r in rows])
    sel = rho >= 5
    for method, tol in (("empirical", 0.03), ("fresnel", 0.05)):
        with boundary_method(method):
            J = robin_surface_fluence(rho[sel], 0.01, 1.0, 1.37) / (2 * robin_A(1.37))
        dev = J / R[sel] - 1
        assert np.all(np.abs(dev) <= tol + 2 * se[sel] / R[sel]), method
    far = rho[sel] >= 8
    assert -0.05 < np.mean(dev[far]) < -0.01          # the Fresnel A's known deficit


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


def _classic_phi_1d(z, mua, musp, n):
    """Phi_x(z) = C e^{-mut z} + B e^{-me z} as docs/physics.md section 3.3 writes it (singular at musp = 2 mua)."""
    mut = mua + musp
    D, A, me = 1 / (3 * mut), robin_A(n), np.sqrt(3 * mua * mut)
    C = musp / (mua - D * mut ** 2)
    B = -C * (1 + 2 * A * D * mut) / (1 + 2 * A * D * me)
    return C * np.exp(-mut * np.asarray(z)) + B * np.exp(-me * np.asarray(z))


def test_musp_equal_two_mua_is_a_removable_singularity():
    z = np.array([0.0, 0.3, 1.0, 4.0])
    for mua, musp, n in ((0.016, 0.89, 1.33), (0.3, 1.0, 1.4), (1.0, 0.5, 1.0)):
        np.testing.assert_allclose(excitation_fluence_1d(z, mua, musp, n),
                                   _classic_phi_1d(z, mua, musp, n), rtol=1e-10)
    # at musp = 2 mua the classic form divides by zero; ours is finite, positive
    # and continuous, and still solves -D Phi'' + mua Phi = musp e^{-mut z}
    mua, musp, n = 0.5, 1.0, 1.33
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DiffusionValidityWarning)
        phi = excitation_fluence_1d(z, mua, musp, n)
        near = [excitation_fluence_1d(z, mua * (1 + e), musp, n) for e in (1e-7, -1e-7)]
        F = total_diffuse_fluorescence((mua, musp), (mua, musp), 1e-3, n)
        F_near = total_diffuse_fluorescence((mua * (1 + 1e-7), musp), (mua, musp), 1e-3, n)
    assert np.all(np.isfinite(phi)) and np.all(phi > 0)
    for v in near:
        np.testing.assert_allclose(phi, v, rtol=1e-6)
    assert np.isfinite(F) and F > 0 and F == pytest.approx(F_near, rel=1e-6)
    h, zz = 1e-3, 1.7
    p = excitation_fluence_1d([zz - h, zz, zz + h], mua, musp, n)
    D = diffusion_coefficient(mua, musp)
    residual = -D * (p[0] - 2 * p[1] + p[2]) / h ** 2 + mua * p[1]
    assert residual == pytest.approx(musp * np.exp(-(mua + musp) * zz), rel=1e-5)


def test_excitation_fluence_1d_validates_its_input():
    for args, field in (((1.0, -0.01, 1.0, 1.33), "mua_per_mm"), ((1.0, 0.01, 1.0, 0.2), "n"),
                        ((1.0, 0.01, 0.0, 1.33), "musp_per_mm"), ((-1.0, 0.01, 1.0, 1.33), "z_mm"),
                        ((np.nan, 0.01, 1.0, 1.33), "z_mm"), ((1.0, np.nan, 1.0, 1.33), "mua")):
        with pytest.raises(FluoInputError, match=field):
            excitation_fluence_1d(*args)
    with pytest.raises(FluoInputError, match="yield"):
        total_diffuse_fluorescence((0.01, 1.0), (0.01, 1.0), np.nan, 1.33)


def test_cli_analytic_flags_the_non_diffusive_regime(capsys):
    assert main(["analytic", "--mua", "0.5", "--musp", "1", "--yield", "1e-3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["diffusion_valid"] is False and np.isfinite(out["F"]) and out["F"] > 0
    assert any("musp/mua = 2" in w for w in out["warnings"])
    assert main(["analytic", "--mua", "0.1", "--musp", "1", "--rho", "0.5,10,30,60",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["diffusion_valid"] is True
    assert out["rho_diffusive"] == [False, True, True, True]
    assert all(v > 0 for v in out["robin_surface_fluence"])
    assert any("transport mean free paths" in w for w in out["warnings"])
    assert main(["analytic", "--mua", "2", "--musp", "200", "--n", "1.6", "--rho", "0.5,60",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["robin_surface_fluence"][1] == 0.0
    assert out["ln_robin_surface_fluence"][1] == pytest.approx(
        _branch_cut_log_fluence(60.0, 2.0, 200.0, 1.6), abs=1e-9)
    assert any("below 1e-308" in w for w in out["warnings"])
    assert main(["analytic", "--mua", "-0.1", "--musp", "1", "--json"]) == 2
    assert "mua_per_mm" in capsys.readouterr().err
