"""Per-pixel ray casting, the navigated illumination model and contour
classification (issue #7): against exact geometry, at the extremes, and on the
oral-cavity phantom with homogeneous fluorescence."""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoCalibLib import transforms as tf
from FluoCalibLib.camera_model import CameraModel
from FluoCalibLib.illumination_model import IlluminationCone
from FluoCalibLib.radiometric_model import RadiometricCamera
from FluoNavLib.contour_classify import miss_rate
from FluoNavLib.flux_map import (accumulate_on_faces, forward_image, plane_hits, transport_image,
                                 view_model, view_weights)
from FluoNavLib.pixel_cast import SurfaceCaster, cast_camera


def _plane(half=200.0, z=0.0, n=20):
    x = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(x, x)
    pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])   # normals +z
    return pts, tris


CAM = CameraModel(300.0, 300.0, 79.5, 59.5, (-0.1, 0.02, 0.0, 0.0, 0.0), 160, 120)


def test_ray_cast_equals_the_closed_form_on_a_plane():
    pts, tris = _plane()
    caster = SurfaceCaster(pts, tris)
    pose = tf.look_at([10.0, -20.0, 150.0], [0.0, 0.0, 0.0], up=(0, 1, 0))
    hits = cast_camera(caster, CAM, pose)
    ref = plane_hits(CAM, pose, [0, 0, 0], [0, 0, 1])
    assert hits.visible.all() and ref.visible.all()
    np.testing.assert_allclose(hits.point_mm, ref.point_mm, atol=2e-3)       # float32 BVH
    np.testing.assert_allclose(hits.distance_mm, ref.distance_mm, rtol=1e-5)
    np.testing.assert_allclose(hits.normal, ref.normal)
    cone = IlluminationCone(half_angle_deg=60.0, alpha=2.0, gamma_per_mm=0.01, system_gain_adu=1e5)
    a = forward_image(view_model(hits, cone, pose), cone, 0.4)
    b = forward_image(view_model(ref, cone, pose), cone, 0.4)
    np.testing.assert_allclose(a, b, rtol=1e-4)


def test_extremes_are_masked_not_nan():
    pts, tris = _plane(half=1e4, n=4)
    caster = SurfaceCaster(pts, tris)
    # camera below the surface looking up: sees the back of every face (inside the tissue)
    inside = cast_camera(caster, CAM, tf.look_at([0, 0, -50.0], [0, 0, 0], up=(0, 1, 0)))
    assert not inside.visible.any() and (inside.reason == 2).all()
    # grazing: camera 0.5 mm above the plane looking along it
    graze = cast_camera(caster, CAM, tf.look_at([0, 0, 0.5], [1000.0, 0, 0.4], up=(0, 0, 1)))
    assert (graze.reason == 3).any() and np.all(np.isfinite(graze.point_mm))
    assert np.all(graze.cos_view[graze.visible] >= np.cos(np.radians(89.0)))
    # near (0.1 mm) and far (1 m) hits
    for h in (0.1, 1000.0):
        hits = cast_camera(caster, CAM, tf.look_at([0, 0, h], [0, 0, 0], up=(0, 1, 0)))
        assert hits.visible.all()
        np.testing.assert_allclose(hits.distance_mm[60, 80], h, rtol=1e-3)
    # empty view: looking away
    empty = cast_camera(caster, CAM, tf.look_at([0, 0, 10.0], [0, 0, 100.0], up=(0, 1, 0)))
    assert not empty.visible.any() and np.all(np.isinf(empty.distance_mm))
    # degenerate triangles are dropped from the BVH, ids stay aligned
    t2 = np.vstack([tris, [[0, 0, 1]], [[2, 2, 2]]])
    c2 = SurfaceCaster(pts, t2)
    assert c2.n_faces == len(tris) + 2 and c2.valid_face.sum() == len(tris)
    with pytest.raises(FluoInputError):
        SurfaceCaster(pts, [[0, 1, 10 ** 6]])
    with pytest.raises(FluoInputError):
        cast_camera(caster, CAM, np.full((4, 4), np.nan))


@pytest.fixture(scope="module")
def oral():
    from FluoNavLib.nav_synth import (coupled_light, open_field_camera, oral_cavity_surface,
                                      render_view, view_poses)

    caster, _ = oral_cavity_surface(62000)
    cam = open_field_camera(binning=4)
    cone = coupled_light()
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    views = [render_view(caster, cam, pose, cone, 0.3, rc, seed=k) + (pose,)
             for k, pose in enumerate(view_poses(3))]
    return caster, cone, rc, views


def test_oral_cavity_transport_within_5pct_and_miss_rate_below_5pct(oral):
    caster, cone, rc, views = oral
    for counts, hits, vm, pose in views:
        S = counts - rc.offset_adu
        T, ok = transport_image(S, vm, cone)
        within = ok & (np.abs(T / 0.3 - 1) < 0.05)
        assert within.sum() / hits.visible.sum() >= 0.90
        raw, _, _ = miss_rate(S, hits.visible)
        corrected, _, _ = miss_rate(T, ok)
        assert corrected < 5.0 and corrected < raw


def test_accumulation_on_the_mesh_over_views(oral):
    caster, cone, rc, views = oral
    items = []
    for counts, hits, vm, pose in views:
        T, ok = transport_image(counts - rc.offset_adu, vm, cone)
        items.append((hits.face, T, view_weights(hits, vm), ok))
    mean, weight = accumulate_on_faces(caster.n_faces, items)
    seen = weight > 0
    assert seen.sum() > 0.3 * caster.n_faces
    assert np.median(np.abs(mean[seen] / 0.3 - 1)) < 0.02
    assert np.all(mean[~seen] == 0)


def test_miss_rate_definition():
    img = np.zeros((10, 10))
    img[2:8, 2:8] = 1.0
    img[2:8, 2] = 0.3          # fluorescent (> 5 %) but below the 40 % contour: missed
    rate, inside, fluo = miss_rate(img, peak_percentile=100)
    assert fluo.sum() == 36 and inside.sum() == 30
    assert rate == pytest.approx(100 * 6 / 36)
    with pytest.raises(FluoInputError):
        miss_rate(np.zeros((4, 4)))


def test_cli_synth_and_correct(tmp_path, capsys):
    from fluoguide.cli import main

    assert main(["nav", "synth", "--out", str(tmp_path / "s"), "--views", "2", "--binning", "8",
                 "--triangles", "20000", "--json"]) == 0
    capsys.readouterr()
    assert main(["nav", "correct", "--scene", str(tmp_path / "s" / "scene.mrml"), "--frame", "1",
                 "--out", str(tmp_path / "o"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert abs(r["transport_median"] / 0.3 - 1) < 0.02
    assert r["miss_rate_corrected_pct"] < 5.0
    assert (tmp_path / "o" / "factors.png").stat().st_size > 5000
    assert main(["nav", "correct", "--scene", str(tmp_path / "s" / "scene.mrml"), "--frame", "9",
                 "--out", str(tmp_path / "o")]) == 2
