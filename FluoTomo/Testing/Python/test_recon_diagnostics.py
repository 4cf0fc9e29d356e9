"""Reconstruction diagnostics that do not lie (issue 18, item 6) and the
reconstruction's extremes matrix.

Every problem here is graded on data made independently of the
reconstruction's model: the data come from a 0.5 mm forward mesh with the
exact disc, the Jacobian from its own FEM model on a 1 mm mesh (not J_f
mapped: the discretisations differ, as a real measurement differs from any
model).  On the clean data HP is +6.9 %, SP -2.9 % (the 1 mm node regions
against the exact disc): the stated accuracy of a cell without warnings is
TOL = 15 % on the target region's mean yield, 2x the largest clean error.
"""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import dumps
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.meshing.structured import rectangle_mesh
from FluoTomoLib.recon.solver import RegionPrior, reconstruct

TARGET, BACKGROUND = 1.2e-3, 1.2e-4
TOL = 0.15
# NP (no prior) smears the target: its stated accuracy is the range measured in
# the thesis studies A-C (docs/reconstruction.md: -55 ... +116 %), a factor ~2
TOL_RANGE = {"NP": (-0.6, 1.2), "SP": (-TOL, TOL), "HP": (-TOL, TOL)}
NIRFAST = dict(log_data=True, normalise=True, x0=BACKGROUND)


@pytest.fixture(scope="module")
def meshes():
    """0.5 mm forward and 1 mm reconstruction meshes of a 40 x 16 mm section, each
    with its own FEM Jacobian (16 sources on top, pairs > 3 mm apart)."""
    fine = rectangle_mesh(np.linspace(-20, 20, 161), np.linspace(-16, 0, 65))
    coarse = rectangle_mesh(np.linspace(-20, 20, 41), np.linspace(-16, 0, 17))
    src = np.stack([(np.arange(16) - 7.5) * 2.5, np.zeros(16)], axis=1)
    p = dict(mua_per_mm=0.032, musp_per_mm=1.0, n=1.33)
    keep = np.linalg.norm(src[:, None] - src[None], axis=2).ravel() > 3.0
    J_f = FluorescenceModel(fine, p, p, src, src).jacobian_yield()[keep]
    J = FluorescenceModel(coarse, p, p, src, src).jacobian_yield()[keep]
    return fine, coarse, J_f, J


@pytest.fixture(scope="module")
def independent(meshes):
    """J on a 1 mm mesh; y from a 0.5 mm mesh with the exact 4 mm disc 3 mm deep."""
    fine, coarse, J_f, J = meshes
    y = J_f @ np.where(np.linalg.norm(fine.nodes_mm - [0, -5], axis=1) <= 2, TARGET, BACKGROUND)
    region = np.where(np.linalg.norm(coarse.nodes_mm - [0, -5], axis=1) <= 2, 2, 1)
    return J, y, RegionPrior(region)


def target_error(res):
    return res.region_confidence[2]["mean_yield_per_mm"] / TARGET - 1


def test_clean_independent_data_meet_the_stated_accuracy_without_warnings(independent):
    J, y, prior = independent
    for method, kw in (("HP", {}), ("HP", NIRFAST)):
        res = reconstruct(J, y, method, prior=prior, **kw)
        assert abs(target_error(res)) < TOL
        assert res.warnings == [], res.warnings
        d = res.diagnostics
        assert not d["underdetermined"] and not d["over_regularised"]
        assert d["relative_misfit"] < 0.01 and d["structure_F"] > 1e4
        assert 1.5 < d["effective_parameters"] <= 2.0 + 1e-9     # two region unknowns
    summary = json.loads(dumps(res.summary()))
    assert summary["warnings"] == [] and summary["diagnostics"]["measurements"] == len(y)


def test_one_measurement_is_flagged_under_determined(independent):
    """Was: HP with one measurement, SD ~1e-14 for a result +969,000 % wrong."""
    J, y, prior = independent
    res = reconstruct(J[:1], y[:1], "HP", prior=prior)
    assert abs(target_error(res)) > 1                # the data cannot tell the regions apart
    assert res.diagnostics["underdetermined"]
    assert res.diagnostics["residual_dof"] < 1
    assert any("under-determined" in w for w in res.warnings)
    sd = res.region_confidence[2]["sd_yield_per_mm"]
    assert sd == float("inf")                        # no confident SD
    assert json.loads(dumps(res.summary()))["region_confidence"]["2"]["sd_yield_per_mm"] is None


@pytest.mark.parametrize("lam", [1e3, 1e6, 1e12])
def test_over_regularised_run_is_not_called_converged(independent, lam):
    """Was: stopped after one iteration at -90 % as 'residual change < 2 %'."""
    J, y, prior = independent
    res = reconstruct(J, y, "HP", lam=lam, prior=prior, **NIRFAST)
    assert target_error(res) < -0.8
    assert res.diagnostics["over_regularised"]
    assert res.stop_reason.endswith("(stalled by the damping)")
    assert any("over-regularised" in w and "lower lambda" in w for w in res.warnings)


def test_noise_only_data_are_not_reported_as_a_confident_target(independent):
    """Was: noise-only data gave a +16,000 % target with a 20 % relative SD."""
    J, y, prior = independent
    rng = np.random.default_rng(0)
    sd = float(np.max(y))
    noise = np.abs(rng.normal(0.0, sd, y.shape))
    res = reconstruct(J, noise, "HP", prior=prior, **NIRFAST)
    assert abs(target_error(res)) > 10
    assert any("poor fit" in w for w in res.warnings)
    # with the noise model stated, the data are recognised as noise
    res = reconstruct(J, noise, "HP", prior=prior, noise_sd=sd, **NIRFAST)
    assert res.diagnostics["signal_to_noise"] < 3
    assert any("noise level" in w for w in res.warnings)


@pytest.mark.parametrize("lam", [1e-10, 1e-12])
def test_soft_prior_log_data_tiny_lambda_is_no_linalgerror(independent, lam):
    """Was: numpy's LinAlgError 'Matrix is not positive definite'."""
    J, y, prior = independent
    for kw in (dict(log_data=True), NIRFAST):
        res = reconstruct(J, y, "SP", lam=lam, prior=prior, **kw)
        assert np.all(np.isfinite(res.yield_per_mm)) and np.all(res.yield_per_mm >= 0)
        assert abs(target_error(res)) < TOL or res.warnings


def test_wrong_units_explained(independent):
    """Was: data 1e-6 too small with the NIRFAST scheme -> 'the Jacobian is zero'."""
    J, y, prior = independent
    with pytest.raises(FluoInputError, match="units") as exc:
        reconstruct(J, y * 1e-6, "HP", prior=prior, **NIRFAST)
    assert "1.33e-06 times what the model predicts" in str(exc.value)
    for factor in (1e-6, 1e6, 1e12):
        res = reconstruct(J, y * factor, "HP", prior=prior)
        assert any("implausible scale" in w for w in res.warnings), factor
    res = reconstruct(J, y * 1e6, "SP", prior=prior, **NIRFAST)
    assert any("times what the model predicts" in w for w in res.warnings)


def test_exact_rescaling_extreme_jacobian_units(independent):
    """J and y in units 2^-500 smaller: J^T J underflows in double precision (the old
    code said 'the Jacobian is zero'); the internal power-of-two rescaling gives the
    same result bit for bit."""
    J, y, prior = independent
    ref = reconstruct(J, y, "SP", prior=prior)
    s = 2.0 ** -500
    scaled = reconstruct(J * s, y * s, "SP", prior=prior)
    np.testing.assert_array_equal(scaled.yield_per_mm, ref.yield_per_mm)
    assert scaled.iterations == ref.iterations and scaled.stop_reason == ref.stop_reason
    assert scaled.warnings == ref.warnings
    # the residual itself is ~1e-308 in those units (subnormal): equal to 1e-6
    np.testing.assert_allclose(np.array(scaled.residual_history) / s ** 2,
                               ref.residual_history, rtol=1e-6)


def test_a_jacobian_in_ordinary_units_is_not_copied(independent):
    """The rescaling copies J only where its units need it: an SP Jacobian (M x N)
    in ordinary units is used as the caller gave it (a copy was one more M x N
    array at the solver's peak), never written to, and the result is bit for bit
    that of units 2^-500 smaller (which are rescaled)."""
    from FluoTomoLib.recon.solver import SCALE_FREE_EXP, _exact_scaling

    J, y, prior = independent
    for units in (1.0, 2.0 ** -90, 2.0 ** 90):
        Ju = J * units
        assert _exact_scaling(Ju, y, False)[0] is Ju
    assert _exact_scaling(J * 2.0 ** -(SCALE_FREE_EXP + 2), y, False)[0] is not J
    before = J.copy()
    res = reconstruct(J, y, "SP", prior=prior)
    np.testing.assert_array_equal(J, before)
    s = 2.0 ** -500
    np.testing.assert_array_equal(reconstruct(J * s, y, "SP", prior=prior).yield_per_mm,
                                  res.yield_per_mm / s)


def test_goodness_of_fit_against_the_noise_model(independent):
    """chi^2 per degree of freedom ~ 1 when the stated noise is the real one plus
    the small model error; > 4 (warned) when the noise is understated 20x."""
    J, y, prior = independent
    rng = np.random.default_rng(1)
    y_noisy = y * (1 + rng.normal(0.0, 0.02, y.shape))
    honest = reconstruct(J, y_noisy, "HP", prior=prior, noise_rel=0.02, **NIRFAST)
    assert 0.5 < honest.diagnostics["chi2_per_dof"] < 2.0
    assert not any("poor fit" in w for w in honest.warnings)
    assert abs(target_error(honest)) < TOL
    liar = reconstruct(J, y_noisy, "HP", prior=prior, noise_rel=0.001, **NIRFAST)
    assert liar.diagnostics["chi2_per_dof"] > 100
    assert any("poor fit" in w for w in liar.warnings)
    # an understated noise does not narrow the interval: the residual it cannot
    # explain goes into the model's error bound
    def width(res):
        lo, hi = res.region_confidence[2]["ci95_yield_per_mm"]
        return hi - lo

    assert liar.region_confidence[2]["model_error_bound_per_mm"] > 0
    assert width(liar) >= 0.8 * width(honest)
    with pytest.raises(FluoInputError, match="noise"):
        reconstruct(J, y, "HP", prior=prior, noise_rel=-0.1)
    with pytest.raises(FluoInputError, match="noise"):
        reconstruct(J, y, "HP", prior=prior, noise_sd=np.ones(3))


def test_wrong_prior_is_a_poor_fit(meshes):
    """Study C's situation on the independent problem: the prior is a filled disc,
    the truth an annulus; HP's region value is then far off, and the fit says so."""
    fine, coarse, J_f, J = meshes
    r_f = np.linalg.norm(fine.nodes_mm - [0, -8], axis=1)
    y = J_f @ np.where((r_f <= 6) & (r_f >= 5), TARGET, BACKGROUND)
    prior = RegionPrior(np.where(np.linalg.norm(coarse.nodes_mm - [0, -8], axis=1) <= 6, 2, 1))
    rng = np.random.default_rng(0)
    y = y * (1 + rng.normal(0.0, 0.01 / 3, y.shape))
    res = reconstruct(J, y, "HP", prior=prior, noise_rel=0.01 / 3, **NIRFAST)
    assert target_error(res) < -0.5
    assert any("poor fit" in w for w in res.warnings)


# --- the extremes matrix ------------------------------------------------------

SCHEMES = {"linear": {}, "nirfast": NIRFAST}
LAMBDAS = [1e-12, 1e-6, 1e-2, 10.0, 1e3, 1e6, 1e12]


def _grade(J, y, method, prior, cell="", **kw):
    """A cell passes when the result is finite and non-negative and either within
    its method's stated range or warned, or when it is refused with a
    FluoInputError."""
    try:
        res = reconstruct(J, y, method, prior=prior, **kw)
    except FluoInputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return "refused"
    assert np.all(np.isfinite(res.yield_per_mm)) and np.all(res.yield_per_mm >= 0)
    assert all(np.isfinite(v) for v in res.residual_history)
    text = dumps(res.summary())                     # JSON-clean: no NaN / inf
    assert "NaN" not in text and "Infinity" not in text
    err = target_error(res)
    if res.warnings:
        return "warned"
    lo, hi = TOL_RANGE[method]
    assert lo < err < hi, (cell, method, kw, err)
    return "within"


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
@pytest.mark.parametrize("method", ["NP", "SP", "HP"])
def test_extremes_matrix_lambda(independent, method, scheme):
    J, y, prior = independent
    outcomes = [_grade(J, y, method, prior, lam=lam, **SCHEMES[scheme]) for lam in LAMBDAS]
    if method == "HP":      # HP's damping decays: every lambda up to 10 is within TOL
        assert outcomes[:4] == ["within"] * 4, outcomes
    assert outcomes[-1] == "warned"                  # lambda 1e12 can never fit


@pytest.mark.parametrize("method", ["NP", "SP", "HP"])
def test_extremes_matrix_data(independent, method):
    J, y, prior = independent
    rng = np.random.default_rng(2)
    # one detector, noise only, wrong units, huge dynamic range, negative data
    cells = {
        "one detector": (J[:1], y[:1]),
        "two detectors": (J[:2], y[:2]),
        "noise only": (J, np.abs(rng.normal(0.0, float(np.max(y)), y.shape))),
        "units x1e-9": (J, y * 1e-9),
        "units x1e9": (J, y * 1e9),
        "dynamic range 1e-200": (J * np.logspace(0, -200, len(y))[:, None],
                                 y * np.logspace(0, -200, len(y))),
        "zero-mean noise": (J, rng.normal(0.0, float(np.max(y)), y.shape)),
    }
    for name, (Jc, yc) in cells.items():
        for scheme, kw in SCHEMES.items():
            if scheme == "nirfast" and np.any(yc <= 0):
                with pytest.raises(FluoInputError, match="log data"):
                    reconstruct(Jc, yc, method, prior=prior, **kw)
                continue
            outcome = _grade(Jc, yc, method, prior, cell=name, **kw)
            if name in ("one detector", "noise only", "units x1e-9", "units x1e9",
                        "zero-mean noise"):
                assert outcome in ("warned", "refused"), (name, scheme, outcome)


def test_extremes_matrix_refusals(independent):
    J, y, prior = independent
    bad = {"NaN in the data": (J, np.where(np.arange(len(y)) == 3, np.nan, y)),
           "inf in the Jacobian": (np.where(np.arange(J.shape[1]) == 5, np.inf, J), y),
           "all-zero data": (J, np.zeros_like(y)),
           "all-zero Jacobian": (np.zeros_like(J), y)}
    for name, (Jc, yc) in bad.items():
        for method in ("NP", "SP", "HP"):
            with pytest.raises(FluoInputError):
                reconstruct(Jc, yc, method, prior=prior)
    # log data with a dynamic range of 1e-200 are the same fit (row scaling cancels)
    w = np.logspace(0, -200, len(y))
    a = reconstruct(J, y, "HP", prior=prior, **NIRFAST)
    b = reconstruct(J * w[:, None], y * w, "HP", prior=prior, **NIRFAST)
    assert target_error(b) == pytest.approx(target_error(a), abs=1e-6)


def test_a_region_without_dye_at_the_bound_is_a_fit_not_a_warning(meshes):
    """HP on independent data of a dye-free background (1 % noise): noise pulls
    the background below zero, the solver clips it, and that is a fit. It used to
    warn 'their data are not fitted' on correct results (issue #33)."""
    fine, coarse, J_f, J = meshes
    rng = np.random.default_rng(5)
    inside = np.linalg.norm(fine.nodes_mm - [0, -5], axis=1) <= 2
    y_clean = J_f @ np.where(inside, TARGET, 0.0)
    region = np.where(np.linalg.norm(coarse.nodes_mm - [0, -5], axis=1) <= 2, 2, 1)
    prior = RegionPrior(region)
    clipped = 0
    for k in range(6):
        y = y_clean * (1 + 0.01 * rng.standard_normal(y_clean.shape))
        res = reconstruct(J, y, "HP", prior=prior, noise_rel=0.01)
        assert abs(target_error(res)) < TOL
        at_bound = res.diagnostics.get("at_zero_bound", {})
        if 1 in at_bound:
            clipped += 1
            assert at_bound[1]["consistent_with_zero"], at_bound
        assert not any("negative" in w or "not fitted" in w for w in res.warnings), res.warnings
    assert clipped >= 1          # the case happened


def test_a_background_the_data_want_negative_is_warned(meshes):
    """Data of tissue that absorbs more than the model says (mua 0.045 against
    0.032 /mm; the dye only in the target): far detectors see less light than the
    model can give with a dye-free background, the background's unconstrained
    yield is well below zero, and the clip at zero is said with its numbers."""
    fine, coarse, J_f, J = meshes
    src = np.stack([(np.arange(16) - 7.5) * 2.5, np.zeros(16)], axis=1)
    keep = np.linalg.norm(src[:, None] - src[None], axis=2).ravel() > 3.0
    p = dict(mua_per_mm=0.045, musp_per_mm=1.0, n=1.33)
    J_true = FluorescenceModel(fine, p, p, src, src).jacobian_yield()[keep]
    inside = np.linalg.norm(fine.nodes_mm - [0, -5], axis=1) <= 2
    y = J_true @ np.where(inside, TARGET, 0.0)
    y = y * (1 + 0.01 * np.random.default_rng(1).standard_normal(y.shape))
    region = np.where(np.linalg.norm(coarse.nodes_mm - [0, -5], axis=1) <= 2, 2, 1)
    res = reconstruct(J, y, "HP", prior=RegionPrior(region), noise_rel=0.01)
    at_bound = res.diagnostics["at_zero_bound"]
    assert not at_bound[1]["consistent_with_zero"], at_bound
    assert at_bound[1]["unconstrained"] < -3 * at_bound[1]["sd"]
    assert at_bound[1]["data_fraction"] > 0.02
    assert any("ask for a negative" in w and "region 1" in w for w in res.warnings), res.warnings


@pytest.mark.parametrize("method", ["NP", "SP"])
def test_intervals_replay_in_data_space_equals_the_iterations(independent, method):
    """NP's and SP's damping is the same every iteration, so the replay of what the
    iterations left unresolved (the intervals' resolution part) runs in data space
    (solver._unresolved_fixed); it must equal replaying the steps one by one."""
    from FluoTomoLib.recon import solver

    J, _, prior = independent
    rng = np.random.default_rng(3)
    V = np.column_stack([prior.K(), rng.random(J.shape[1])])
    n, lam = 17, 10.0
    _, _, _, RJt, ds = solver._step_system(method, prior, J, np.zeros(J.shape[1]), False, lam)
    step = V.copy()
    for _ in range(n):
        step = step - RJt @ ds.solve(J @ step)
    fast = solver._unresolved(method, prior, J, V, n, lam, 1.0, {lam: (RJt, ds)})
    # both accumulate rounding over the n steps (SP's 17: 3e-11 of V's unit columns)
    tol = 1e-9 * np.abs(V).max()
    assert np.abs(step).max() > 100 * tol and np.abs(fast - step).max() < tol
    # and without a cached system: it builds its own
    assert np.abs(solver._unresolved(method, prior, J, V, n, lam, 1.0, {}) - step).max() < tol


def test_low_rank_data_space_equals_the_dense_one():
    """HP's step systems (few region unknowns, many data) use the thin eigen-
    decomposition of G = J R^-1 J^T (solver._LowRankDataSpace): its solves,
    effective parameters and predicted residuals equal the dense Cholesky's,
    including a rank-deficient J (a region no datum sees)."""
    from FluoTomoLib.recon import solver
    from FluoTomoLib.recon.partial_volume import region_unknowns

    rng = np.random.default_rng(5)
    for J in (rng.random((200, 3)) * [1.0, 1e-3, 30.0],
              np.column_stack([rng.random(150), np.zeros(150)])):
        prior = region_unknowns(list(range(1, J.shape[1] + 1)))
        for lam in (10.0, 1e-4):
            *_, RJt, low = solver._step_system("HP", prior, J, np.zeros(J.shape[1]), False, lam)
            assert isinstance(low, solver._LowRankDataSpace)
            S = J @ RJt
            S[np.diag_indices_from(S)] += 1.0
            dense = solver._DataSpace(S)
            b = rng.standard_normal((len(J), 4))
            # both to rounding: cond(S) up to 2.5e4 here, the dense Cholesky 2e-12 off
            assert np.abs(low.solve(b) - dense.solve(b)).max() < 1e-10
            assert np.isclose(low.effective_parameters(), dense.effective_parameters(),
                              rtol=1e-9, atol=1e-9)
            for t in (1.0, 1e-4):
                assert np.isclose(low.predicted_rss(b[:, 0], t), dense.predicted_rss(b[:, 0], t),
                                  rtol=1e-9)
