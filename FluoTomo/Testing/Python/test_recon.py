"""NP / SP / HP reconstruction on small problems with known answers."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.recon.metrics import depth_profile, peak_and_centroid
from FluoTomoLib.recon.solver import RegionPrior, reconstruct, region_jacobian
from FluoTomoLib.meshing.structured import rectangle_mesh


@pytest.fixture(scope="module")
def problem():
    """2D 40 x 16 mm tissue, 16 sources on top, a 4 mm disc 3 mm deep (10:1 contrast)."""
    m = rectangle_mesh(np.linspace(-20, 20, 81), np.linspace(-16, 0, 33))
    xs = (np.arange(16) - 7.5) * 2.5
    src = np.stack([xs, np.zeros(16)], axis=1)
    p = dict(mua_per_mm=0.032, musp_per_mm=1.0, n=1.33)
    fm = FluorescenceModel(m, p, p, src, src)
    in_disc = np.linalg.norm(m.nodes_mm - [0.0, -5.0], axis=1) <= 2.0
    region = np.where(in_disc, 2, 1)
    truth = np.where(in_disc, 1.2e-3, 1.2e-4)
    J = fm.jacobian_yield()
    keep = np.linalg.norm(src[:, None] - src[None], axis=2).ravel() > 3.0
    return m, J[keep], (J @ truth)[keep], truth, region


def test_hard_prior_recovers_region_values(problem):
    m, J, y, truth, region = problem
    res = reconstruct(J, y, "HP", prior=RegionPrior(region))
    conf = res.region_confidence
    assert conf[2]["mean_yield_per_mm"] == pytest.approx(1.2e-3, rel=1e-3)
    assert conf[1]["mean_yield_per_mm"] == pytest.approx(1.2e-4, rel=1e-3)
    assert res.stop_reason.startswith("residual") and res.residual < 1e-6 * res.residual_history[0]


def test_soft_prior_beats_no_prior_on_peak(problem):
    m, J, y, truth, region = problem
    prior = RegionPrior(region)
    errors = {}
    for method in ("NP", "SP"):
        res = reconstruct(J, y, method, prior=prior)
        z, prof = depth_profile(m, res.yield_per_mm, 0.0, z_bottom_mm=-15.0)
        peak, centroid = peak_and_centroid(z, prof)
        errors[method] = abs(peak - 1.2e-3) / 1.2e-3
        assert np.all(res.yield_per_mm >= 0)  # non-negativity
        assert 1 <= res.iterations <= 40
    assert errors["SP"] < 0.1
    assert errors["NP"] > errors["SP"]


@pytest.mark.parametrize("lam", [1e-6, 1e-2, 1.0, 1e3, 1e6])
def test_lambda_extremes_stay_finite(problem, lam):
    m, J, y, truth, region = problem
    for method in ("NP", "SP", "HP"):
        res = reconstruct(J, y, method, lam=lam, prior=RegionPrior(region))
        assert np.all(np.isfinite(res.yield_per_mm))
        assert all(np.isfinite(v) for v in res.residual_history)


def test_soft_prior_operator_is_implicit_and_exact():
    rng = np.random.default_rng(0)
    region = rng.integers(1, 4, 200)
    prior = RegionPrior(region)
    # dense L for comparison
    L = np.zeros((200, 200))
    for r in np.unique(region):
        idx = np.flatnonzero(region == r)
        L[np.ix_(idx, idx)] = -1.0 / len(idx)
    np.fill_diagonal(L, 1.0)
    x = rng.normal(size=200)
    np.testing.assert_allclose(prior.apply_L(x), L @ x, atol=1e-12)
    np.testing.assert_allclose(prior.apply_L_inv(L @ x), x, atol=1e-10)
    np.testing.assert_allclose(prior.apply_LtL_inv(L.T @ (L @ x)), x, atol=1e-9)


def test_bad_input_is_explained(problem):
    m, J, y, truth, region = problem
    with pytest.raises(FluoInputError, match="all data are zero"):
        reconstruct(J, np.zeros_like(y), "NP")
    with pytest.raises(FluoInputError, match="needs the region prior"):
        reconstruct(J, y, "SP")
    with pytest.raises(FluoInputError, match="method"):
        reconstruct(J, y, "XX")
    with pytest.raises(FluoInputError, match="lambda"):
        reconstruct(J, y, "NP", lam=np.nan)
    with pytest.raises(FluoInputError, match="different number of nodes"):
        reconstruct(J, y, "HP", prior=RegionPrior(region[:-1]))
    with pytest.warns(UserWarning, match="single node"):
        RegionPrior(np.r_[np.ones(10, int), 2])


def test_region_jacobian_from_same_labels_matches_default(problem):
    m, J, y, truth, region = problem
    prior = RegionPrior(region)
    A = region_jacobian(J, region, prior.labels)
    np.testing.assert_allclose(A, J @ prior.K(), rtol=1e-12, atol=0)
    a = reconstruct(J, y, "HP", prior=prior)
    b = reconstruct(J, y, "HP", prior=prior, region_jacobian=A)
    np.testing.assert_allclose(a.yield_per_mm, b.yield_per_mm, rtol=1e-10)


def test_forward_level_hard_prior_basis_removes_the_interpolation_bias():
    """Data on a 0.5 mm mesh; HP on a 1 mm mesh.  The coarse 0/1 basis mapped through
    the interpolation (J_f P K) cannot represent the fine disc; J_f K_f can."""
    from FluoTomoLib.fem.locate import locator

    fine = rectangle_mesh(np.linspace(-20, 20, 81), np.linspace(-16, 0, 33))
    coarse = rectangle_mesh(np.linspace(-20, 20, 41), np.linspace(-16, 0, 17))
    src = np.stack([(np.arange(16) - 7.5) * 2.5, np.zeros(16)], axis=1)
    p = dict(mua_per_mm=0.032, musp_per_mm=1.0, n=1.33)
    J_f = FluorescenceModel(fine, p, p, src, src).jacobian_yield()
    keep = np.linalg.norm(src[:, None] - src[None], axis=2).ravel() > 3.0
    J_f = J_f[keep]
    P = locator(coarse).interpolation_matrix(fine.nodes_mm)
    J_c = np.asarray((P.T @ J_f.T).T)
    # a disc whose edge falls between coarse nodes (centre at half a coarse cell)
    in_f = np.linalg.norm(fine.nodes_mm - [0.0, -5.5], axis=1) <= 2.3
    in_c = np.linalg.norm(coarse.nodes_mm - [0.0, -5.5], axis=1) <= 2.3
    y = J_f @ np.where(in_f, 1.2e-3, 1.2e-4)
    prior = RegionPrior(np.where(in_c, 2, 1))
    coarse_basis = reconstruct(J_c, y, "HP", prior=prior).region_confidence[2]
    fine_basis = reconstruct(J_c, y, "HP", prior=prior, region_jacobian=region_jacobian(
        J_f, np.where(in_f, 2, 1), prior.labels)).region_confidence[2]
    assert fine_basis["mean_yield_per_mm"] == pytest.approx(1.2e-3, rel=1e-3)
    assert abs(coarse_basis["mean_yield_per_mm"] / 1.2e-3 - 1) > 0.02


@pytest.mark.parametrize("method", ["NP", "SP", "HP"])
def test_log_data_normalised_scheme(problem, method):
    """NIRFAST's scheme: log data, Jacobian scaled by the current yield, started from
    the background; stays non-negative and finite, residual goes down."""
    m, J, y, truth, region = problem
    prior = RegionPrior(region)
    res = reconstruct(J, y, method, prior=prior, log_data=True, normalise=True, x0=1.2e-4)
    assert np.all(np.isfinite(res.yield_per_mm)) and np.all(res.yield_per_mm >= 0)
    assert res.residual < 0.1 * res.residual_history[0]
    conf = res.region_confidence[2]
    assert np.isfinite(conf["sd_yield_per_mm"]) and conf["sd_yield_per_mm"] > 0
    if method == "HP":        # noise-free, exact regions: the log-LS fit is exact
        assert conf["mean_yield_per_mm"] == pytest.approx(1.2e-3, rel=1e-3)
    if method == "SP":
        z, prof = depth_profile(m, res.yield_per_mm, 0.0, z_bottom_mm=-15.0)
        assert peak_and_centroid(z, prof)[0] == pytest.approx(1.2e-3, rel=0.1)


def test_log_data_weights_deep_targets_more_for_soft_prior():
    """SP at depth: with linear data the damping lambda' = lambda max(diag(J^T J)) is set
    by the near-source surface nodes, and a deep target's constant barely moves before
    the 2 % rule stops; log data equalise the pairs and recover it."""
    m = rectangle_mesh(np.linspace(-20, 20, 41), np.linspace(-20, 0, 21))
    src = np.stack([(np.arange(16) - 7.5) * 2.5, np.zeros(16)], axis=1)
    p = dict(mua_per_mm=0.032, musp_per_mm=1.0, n=1.33)
    J = FluorescenceModel(m, p, p, src, src).jacobian_yield()
    J = J[~np.eye(16, dtype=bool).ravel()]
    in_disc = np.linalg.norm(m.nodes_mm - [0.0, -9.5], axis=1) <= 3.0
    y = J @ np.where(in_disc, 1.2e-3, 1.2e-4)
    prior = RegionPrior(np.where(in_disc, 2, 1))
    err = {}
    for log in (False, True):
        res = reconstruct(J, y, "SP", prior=prior, log_data=log, normalise=log,
                          x0=1.2e-4 if log else None)
        err[log] = abs(res.region_confidence[2]["mean_yield_per_mm"] / 1.2e-3 - 1)
    assert err[True] < 0.1 < err[False]


def test_default_start_for_log_data_is_the_homogeneous_fit(problem):
    m, J, y, truth, region = problem
    res = reconstruct(J, y, "NP", log_data=True, max_iter=1)
    # one step from the homogeneous fit: a positive field, not the zero start
    assert np.all(res.yield_per_mm > 0)


def test_new_options_explain_bad_input(problem):
    m, J, y, truth, region = problem
    prior = RegionPrior(region)
    y_bad = y.copy()
    y_bad[0] = 0.0
    with pytest.raises(FluoInputError, match="log data"):
        reconstruct(J, y_bad, "NP", log_data=True)
    with pytest.raises(FluoInputError, match="region_jacobian"):
        reconstruct(J, y, "HP", prior=prior, region_jacobian=np.ones((len(y), 3)))
    with pytest.raises(FluoInputError, match="no node"):
        region_jacobian(J, np.ones(J.shape[1], int), prior.labels)
    with pytest.raises(FluoInputError, match="one region label"):
        region_jacobian(J, region[:-1], prior.labels)
    with pytest.raises(FluoInputError, match="positive"):
        reconstruct(J, y, "NP", normalise=True, x0=0.0)


@pytest.mark.parametrize("max_iter", [0, -3, 2.5, True])
def test_no_iteration_budget_is_refused_in_one_line(max_iter):
    J = np.eye(3)
    with pytest.raises(FluoInputError, match="max_iter"):
        reconstruct(J, np.ones(3), method="NP", max_iter=max_iter)
