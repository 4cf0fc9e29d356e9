"""NP / SP / HP reconstruction on small problems with known answers."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.forward import FluorescenceModel
from FluoTomoLib.profile_metrics import depth_profile, peak_and_centroid
from FluoTomoLib.recon import RegionPrior, reconstruct
from FluoTomoLib.structured_mesh import rectangle_mesh


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
