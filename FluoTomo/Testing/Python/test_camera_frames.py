"""Rendered fluorescence frames for tomography: pixels cast onto the surface,
nodal fields interpolated at the hits, ROI means back to boundary fluence."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.acquisition.camera_frames import (
    camera_pose_above,
    cast,
    detector_counts,
    expose,
    frame_radiance,
    surface_caster,
    surface_values,
    tomography_camera,
)
from FluoTomoLib.acquisition.noncontact_optodes import counts_to_boundary_fluence
from FluoTomoLib.meshing.structured import box_mesh


@pytest.fixture(scope="module")
def scene():
    mesh = box_mesh(np.linspace(-10, 10, 21), np.linspace(-15, 15, 31), np.linspace(-5, 0, 6))
    top = mesh.boundary_normals[:, 2] > 0.99
    caster, facets = surface_caster(mesh, top)
    camera = tomography_camera(4)
    pose = camera_pose_above((0.0, 0.0, 0.0), 150.0)
    return mesh, facets, camera, pose, cast(caster, camera, pose)


def test_linear_fields_are_interpolated_exactly_at_every_hit(scene):
    mesh, facets, camera, pose, hits = scene
    assert hits.visible.sum() > 5000          # the 20 x 30 mm top fills ~60 x 90 binned pixels
    x, y = mesh.nodes_mm[:, 0], mesh.nodes_mm[:, 1]
    nodal = np.stack([1.0 + 0.1 * x - 0.05 * y, np.full_like(x, 2.0)], axis=1)
    vals = surface_values(hits, facets, mesh.nodes_mm, nodal)
    p = hits.point_mm[hits.visible]
    assert np.allclose(vals[hits.visible, 0], 1.0 + 0.1 * p[:, 0] - 0.05 * p[:, 1], atol=1e-9)
    assert np.allclose(vals[hits.visible, 1], 2.0) and np.all(vals[~hits.visible] == 0)


def test_roi_counts_return_the_boundary_fluence(scene):
    mesh, facets, camera, pose, hits = scene
    A, power = 2.8, 0.01
    x, y = mesh.nodes_mm[:, 0], mesh.nodes_mm[:, 1]
    phi = np.stack([1e-3 * np.exp(-0.1 * np.hypot(x, y - c)) for c in (-5.0, 5.0)], axis=1)
    radiance = frame_radiance(hits, facets, mesh.nodes_mm, phi, A, power)
    gain = 0.6 * 16383 / radiance.max()
    rng = np.random.default_rng(0)
    frames, sat = expose(radiance, gain, 100.0, 2.0, rng)
    assert frames.shape == (2,) + hits.shape and not sat.any()
    det = np.array([[0.0, -8.0, 0.0], [0.0, 0.0, 0.0], [3.0, 6.0, 0.0]])
    counts, n_pix = detector_counts(frames, sat, hits, det)
    assert np.all(n_pix >= 8)                 # ~1 mm^2 at 0.32 mm per binned pixel
    y = counts_to_boundary_fluence(counts, 100.0, gain, A, power)
    truth = np.array([[1e-3 * np.exp(-0.1 * np.hypot(d[0], d[1] - c)) for d in det]
                      for c in (-5.0, 5.0)])
    assert np.allclose(y, truth, rtol=0.03), y / truth
    # a saturated frame loses its pixels: too few left in an ROI -> NaN, never a clipped mean
    frames2, sat2 = expose(radiance, 3.0 * gain, 100.0, 2.0, rng)
    c2, _ = detector_counts(frames2, sat2, hits, det)
    assert np.isnan(c2).any() and np.all(c2[np.isfinite(c2)] < 16383)
    with pytest.raises(FluoInputError, match="saturated"):
        detector_counts(frames2, np.ones_like(sat2), hits, det)
