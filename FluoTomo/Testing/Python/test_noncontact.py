"""Non-contact sources/detectors and the counts -> fluence chain."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.acquisition.noncontact_optodes import (
    boundary_fluence_to_counts,
    counts_to_boundary_fluence,
    detector_mask,
    ray_triangle_intersect,
    roi_mean_counts,
    virtual_detectors,
)


def _plane(z=0.0, half=50.0):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_beam_hits_plane_and_misses():
    v, t = _plane(z=-2.0)
    o = np.array([[1.0, 2.0, 100.0], [0.0, 0.0, 100.0], [0.0, 0.0, 100.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.3, 0.0, -1.0], [0.0, 0.0, 1.0]])
    p, dist, face = ray_triangle_intersect(o, d, v, t)
    np.testing.assert_allclose(p[0], [1.0, 2.0, -2.0])
    assert dist[0] == pytest.approx(102.0)
    np.testing.assert_allclose(p[1], [0.3 * 102.0, 0.0, -2.0], atol=1e-9)
    assert face[2] == -1 and np.isinf(dist[2]) and np.all(np.isnan(p[2]))


def test_grazing_beam_is_defined():
    v, t = _plane()
    p, dist, face = ray_triangle_intersect([[0, 0, 1.0]], [[1.0, 0.0, -0.025]], v, t)
    assert face[0] >= 0 and p[0, 0] == pytest.approx(40.0)


def test_virtual_detectors_interpolate_and_exclude():
    src = np.stack([np.arange(16) * 2.5, np.zeros(16), np.zeros(16)], axis=1)
    det = virtual_detectors(src, factor=2)
    assert len(det) == 31
    np.testing.assert_allclose(det[1], [1.25, 0, 0])
    mask = detector_mask(src, det, exclude_mm=3.0)
    # source 5 at 12.5 mm: detectors within 3 mm are 10, 11.25, 12.5, 13.75, 15 mm
    assert mask.shape == (16, 31) and (~mask[5]).sum() == 5
    with pytest.raises(FluoInputError):
        virtual_detectors(src, factor=0)


def test_counts_fluence_round_trip_and_units():
    A = 2.5
    y = np.array([1e-6, 1e-3, 0.2])
    s = boundary_fluence_to_counts(y, 100.0, 3.6e7, A, 0.05)
    np.testing.assert_allclose(counts_to_boundary_fluence(s, 100.0, 3.6e7, A, 0.05), y)
    # hand check: Phi = 2A * pi * (S - offset)/G / P
    assert counts_to_boundary_fluence(100.0 + 3.6e7, 100.0, 3.6e7, A, 1.0) == pytest.approx(2 * A * np.pi)
    with pytest.raises(FluoInputError, match="laser_power_w"):
        counts_to_boundary_fluence(s, 0, 1, A, 0.0)


def test_roi_mean_uses_surface_disc():
    h, w = 40, 40
    yy, xx = np.mgrid[0:h, 0:w]
    hits = np.stack([xx * 0.25, yy * 0.25, np.zeros_like(xx, float)], axis=2)
    img = (xx + 100.0)
    valid = np.ones((h, w), bool)
    valid[:, :4] = False
    mean, n = roi_mean_counts(img, hits, valid, np.array([[5.0, 5.0, 0.0], [0.1, 5.0, 0.0]]))
    assert n[0] >= 12 and mean[0] == pytest.approx(120.0, abs=0.5)
    assert np.isnan(mean[1])  # its ROI is on invalid pixels


def test_roi_standard_error_is_the_pixels_noise_not_the_light_s_slope():
    """A tilted surface patch whose light falls steeply (30 % across a 1 mm^2
    ROI) with Gaussian noise of a known SD: each ROI mean's standard error
    comes out as SD / sqrt(n) (pooled over many ROIs, within 10 %); with no
    noise only the light's curvature is left (the plane takes its slope): a
    fifth of that noise at the median ROI, 0.6 of it at the steepest."""
    h, w = 60, 60
    yy, xx = np.mgrid[0:h, 0:w] * 0.25
    hits = np.stack([xx, yy, 0.5 * xx], axis=2)            # a tilted plane [mm]
    light = 1000.0 * np.exp(-0.3 * xx) + 50.0 * yy
    det = np.array([[x, y, 0.5 * x] for x in np.arange(2.0, 13.0, 1.5)
                    for y in np.arange(2.0, 13.0, 1.5)])
    valid = np.ones((h, w), bool)
    rng = np.random.default_rng(3)
    img = light + rng.normal(0.0, 4.0, light.shape)
    mean, n, se = roi_mean_counts(img, hits, valid, det, with_se=True)
    ratio = np.sqrt(np.mean(se ** 2 * n)) / 4.0
    assert 0.9 < ratio < 1.1, ratio
    _, _, se0 = roi_mean_counts(light, hits, valid, det, with_se=True)
    noise_se = 4.0 / np.sqrt(n)
    assert np.median(se0 / noise_se) < 0.2 and np.all(se0 < 0.65 * noise_se)
    # without it, the old two-value form
    assert len(roi_mean_counts(img, hits, valid, det)) == 2
