"""The optodes' gains as unknowns of HP's fit (recon.coupling): each source and
detector read a few per cent off by the model is a factor common to all its
pairs; fitted beside the region values, it leaves the noise in the residual and
the yield's scale with the model."""

from __future__ import annotations

import numpy as np
import pytest


def _scan(seed, S=12, D=30, R=3, gain_sd=0.05, noise=0.01):
    """Region sensitivities falling with a made-up source-detector distance, the
    data of known values through known gains (zero-mean logs) with relative noise."""
    rng = np.random.default_rng(seed)
    src, det = np.meshgrid(np.arange(S), np.arange(D), indexing="ij")
    src, det = src.ravel(), det.ravel()
    dist = 3.0 + np.abs(rng.normal(0, 1, S))[src] + np.abs(rng.normal(0, 4, D))[det]
    A = np.exp(-0.3 * dist)[:, None] * rng.uniform(0.2, 1.0, (S * D, R))
    v = rng.uniform(0.5, 2.0, R)
    a, b = rng.normal(0, gain_sd, S), rng.normal(0, gain_sd, D)
    a -= a.mean()
    b -= b.mean()
    y = (A @ v) * np.exp(a[src] + b[det]) * (1 + noise * rng.standard_normal(S * D))
    return A, y, src, det, v, a, b


@pytest.mark.parametrize("seed", range(5))
def test_the_gains_and_values_come_back_from_their_product(seed):
    from FluoTomoLib.recon.coupling import optode_coupling

    A, y, src, det, v, a, b = _scan(seed)
    c = optode_coupling(A, y, src, det)
    # each gain from 30 (sources) or 12 (detectors) pairs at 1 % noise: within
    # 4 standard errors (1 % / sqrt(12) = 0.3 %), against gains of 5 % sd
    assert np.max(np.abs(c.source_log - a)) < 0.012
    assert np.max(np.abs(c.detector_log - b)) < 0.012
    fit = np.linalg.lstsq(A * c.factors[:, None], y, rcond=None)[0]
    plain = np.linalg.lstsq(A, y, rcond=None)[0]
    rel = np.abs(fit / v - 1)
    # the values with the gains: within 2 %; the residual at the noise
    assert np.max(rel) < 0.02
    r_fit = (A * c.factors[:, None]) @ fit / y - 1
    r_plain = A @ plain / y - 1
    assert np.sqrt(np.mean(r_fit ** 2)) < 0.013 < np.sqrt(np.mean(r_plain ** 2))
    assert c.parameters == 12 - 1 + 30 - 1
    assert c.rss == pytest.approx(float(np.sum((r_fit * y) ** 2)), rel=1e-6)


def test_no_gains_where_they_would_take_the_data_s_place():
    from FluoTomoLib.recon.coupling import optode_coupling

    # one source: its gain is the yield's scale, the detectors' the data's shape
    A, y, src, det, *_ = _scan(0, S=1, D=30)
    c = optode_coupling(A, y, src, det)
    assert c is None or c.parameters == 29
    # 4 x 5 pairs for 3 values and 7 gains: too few per unknown
    A, y, src, det, *_ = _scan(1, S=4, D=5)
    assert optode_coupling(A, y, src, det) is None


def test_an_optode_far_off_its_model_stands_out():
    from FluoTomoLib.recon.coupling import optode_coupling

    A, y, src, det, *_ = _scan(2, gain_sd=0.0)
    y = np.where(det == 7, 1.6 * y, y)
    c = optode_coupling(A, y, src, det)
    assert np.argmax(np.abs(c.detector_log)) == 7
    # that detector's gain read above +40 %; the gains explain over 90 % of the residual
    assert np.expm1(c.detector_log[7]) > 0.40 and c.rss < 0.1 * c.rss_plain


def test_hp_keeps_its_fit_and_reports_the_fit_with_gains():
    from FluoTomoLib.recon.partial_volume import region_unknowns
    from FluoTomoLib.recon.solver import reconstruct

    A, y, src, det, v, *_ = _scan(3)
    prior = region_unknowns([1, 2, 3])
    with_gains = reconstruct(A, y, "HP", prior=prior, noise_rel=0.01, optodes=(src, det))
    without = reconstruct(A, y, "HP", prior=prior, noise_rel=0.01)
    assert with_gains.coupling is not None and without.coupling is None
    # the reconstruction's own fit is the same; the record says what gains leave
    np.testing.assert_array_equal(with_gains.yield_per_mm, without.yield_per_mm)
    c = with_gains.coupling
    assert c.rss < 0.25 * c.rss_plain
    assert c.rss_plain == pytest.approx(without.residual, rel=0.05)
    assert np.max(np.abs(c.values / v - 1)) < 0.02


def test_data_the_gains_cannot_read_give_none_not_an_error():
    from FluoTomoLib.recon.coupling import optode_coupling

    A, y, src, det, *_ = _scan(4)
    assert optode_coupling(A, np.full_like(y, -1.0), src, det) is None   # no positive data
    bad = y.copy()
    bad[3] = np.nan
    assert optode_coupling(A, bad, src, det) is None
