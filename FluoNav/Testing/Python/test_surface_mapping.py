"""Per-pixel ray casting, the navigated illumination model and contour
classification (issue #7): against exact geometry, at the extremes, and on the
oral-cavity phantom with homogeneous fluorescence."""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera
from FluoNavLib.mapping.contours import miss_rate
from FluoNavLib.mapping.flux_map import (
    accumulate_on_faces,
    forward_image,
    plane_hits,
    transport_image,
    view_model,
    view_weights,
)
from FluoNavLib.mapping.pixel_cast import SurfaceCaster, cast_camera, reference_cast


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


def _spheres():
    """A sphere with a small one in front of it (silhouettes, occlusion)."""
    import vtk
    from vtk.util import numpy_support as ns

    out_p, out_t = [], []
    for centre, r, res in (((0.0, 0.0, 0.0), 30.0, 24), ((5.0, 8.0, 35.0), 8.0, 12)):
        s = vtk.vtkSphereSource()
        s.SetCenter(*centre)
        s.SetRadius(r)
        s.SetThetaResolution(res)
        s.SetPhiResolution(res)
        s.Update()
        p = s.GetOutput()
        out_t.append(ns.vtk_to_numpy(p.GetPolys().GetConnectivityArray()).reshape(-1, 3)
                     + sum(len(q) for q in out_p))
        out_p.append(ns.vtk_to_numpy(p.GetPoints().GetData()).astype(float))
    return np.vstack(out_p), np.vstack(out_t)


SMALL = CameraModel(60.0, 61.0, 23.7, 17.4, (0.0, 0.0, 0.0, 0.0, 0.0), 48, 36)


def _reference_hits(pts, tris, cam, pose):
    rays = cam.pixel_grid_rays() @ pose[:3, :3].T
    face, dist = reference_cast(pts, tris, pose[:3, 3], rays.reshape(-1, 3))
    face = face.reshape(cam.height, cam.width)
    n = SurfaceCaster(pts, tris).face_normals[np.where(face >= 0, face, 0)]
    cos = -np.einsum("hwi,hwi->hw", n, rays)
    visible = (face >= 0) & (cos >= np.cos(np.radians(89.0)))
    return face, dist.reshape(face.shape), visible


@pytest.mark.parametrize("eye", [[10.0, -20.0, 150.0], [70.0, 10.0, 25.0], [0.0, 45.0, 45.0]])
def test_fast_casts_match_the_exact_reference(eye):
    pts, tris = _spheres()
    caster = SurfaceCaster(pts, tris)
    pose = tf.look_at(eye, [0.0, 0.0, 0.0], up=(0, 0, 1) if eye[0] == 0 else (0, 1, 0))
    face, dist, visible = _reference_hits(pts, tris, SMALL, pose)
    assert 200 < visible.sum()
    raster = cast_camera(caster, SMALL, pose)                 # no distortion: exact raster path
    assert caster.ray_grid(SMALL, 1).exact
    np.testing.assert_array_equal(raster.visible, visible)
    np.testing.assert_array_equal(raster.face[visible], face[visible])
    np.testing.assert_allclose(raster.distance_mm[visible], dist[visible], rtol=1e-9)
    emb = cast_camera(caster, SMALL, pose, method="embree")   # float32 BVH
    assert (emb.visible == visible).mean() > 0.995
    both = emb.visible & visible
    np.testing.assert_allclose(emb.distance_mm[both], dist[both], atol=1e-3)


@pytest.mark.parametrize("eye", [[70.0, 10.0, 25.0], [10.0, -20.0, 150.0]])
def test_distorted_camera_raster_matches_the_exact_reference(eye):
    pts, tris = _spheres()
    caster = SurfaceCaster(pts, tris)
    cam = CameraModel(60.0, 61.0, 23.7, 17.4, (-0.2, 0.05, 0.001, -0.002, 0.0), 48, 36)
    pose = tf.look_at(eye, [0.0, 0.0, 0.0], up=(0, 1, 0))
    face, dist, visible = _reference_hits(pts, tris, cam, pose)
    hits = cast_camera(caster, cam, pose)                     # auto: pixel-space raster
    grid = caster.ray_grid(cam, 1)
    assert not grid.exact and grid.pixel_space
    assert (hits.visible == visible).mean() > 0.995
    both = hits.visible & visible
    assert (hits.face[both] == face[both]).mean() > 0.995
    np.testing.assert_allclose(np.median(np.abs(hits.distance_mm[both] - dist[both])), 0, atol=1e-9)
    # a big plane (triangles of tens of pixels, tessellated) seen with the same lens
    pp, pt = _plane()
    plane = SurfaceCaster(pp, pt)
    ppose = tf.look_at([10.0, -20.0, 150.0], [0.0, 0.0, 0.0], up=(0, 1, 0))
    ref = plane_hits(cam, ppose, [0, 0, 0], [0, 0, 1])
    got = cast_camera(plane, cam, ppose)
    assert got.visible.all() and ref.visible.all()
    np.testing.assert_allclose(got.point_mm, ref.point_mm, atol=1e-6)


@pytest.mark.parametrize("method", ["raster", "embree"])
def test_extremes_are_masked_not_nan(method):
    pts, tris = _plane(half=1e4, n=4)
    caster = SurfaceCaster(pts, tris)
    cast = lambda cam, pose: cast_camera(caster, cam, pose, method=method)    # noqa: E731
    # camera inside a closed surface: every pixel sees a back face
    sp, st = _spheres()
    ball = SurfaceCaster(sp, st)
    inside_ball = cast_camera(ball, SMALL, tf.look_at([0, 0, 5.0], [0, 0, 0], up=(0, 1, 0)),
                              method=method)
    assert not inside_ball.visible.any() and (inside_ball.reason == 2).all()
    # camera below the surface looking up: sees the back of every face (inside the tissue)
    inside = cast(CAM, tf.look_at([0, 0, -50.0], [0, 0, 0], up=(0, 1, 0)))
    assert not inside.visible.any() and (inside.reason == 2).all()
    # grazing: camera 0.5 mm above the plane looking along it
    graze = cast(CAM, tf.look_at([0, 0, 0.5], [1000.0, 0, 0.4], up=(0, 0, 1)))
    assert (graze.reason == 3).any() and np.all(np.isfinite(graze.point_mm))
    assert np.all(graze.cos_view[graze.visible] >= np.cos(np.radians(89.0)))
    # near (0.1 mm) and far (1 m) hits
    for h in (0.1, 1000.0):
        hits = cast(CAM, tf.look_at([0, 0, h], [0, 0, 0], up=(0, 1, 0)))
        assert hits.visible.all()
        np.testing.assert_allclose(hits.distance_mm[60, 80], h, rtol=1e-3)
    # empty view: looking away
    empty = cast(CAM, tf.look_at([0, 0, 10.0], [0, 0, 100.0], up=(0, 1, 0)))
    assert not empty.visible.any() and np.all(np.isinf(empty.distance_mm))
    assert np.all(np.isfinite(empty.point_mm)) and (empty.reason == 1).all()
    # degenerate triangles are dropped from the BVH, ids stay aligned
    t2 = np.vstack([tris, [[0, 0, 1]], [[2, 2, 2]]])
    c2 = SurfaceCaster(pts, t2)
    assert c2.n_faces == len(tris) + 2 and c2.valid_face.sum() == len(tris)
    # a surface of degenerate triangles only: every pixel masked as a miss, no NaN
    flat = SurfaceCaster(pts, np.vstack([t2, [[3, 3, 4]]]))
    deg_only = SurfaceCaster(np.vstack([pts, [[0, 0, 0], [1, 1, 0]]]),
                             [[len(pts), len(pts), len(pts) + 1]] * 3 + [[0, 1, 2]])
    hits = cast_camera(deg_only, CAM, tf.look_at([500.0, 500.0, 50.0], [500.0, 500.0, 0], up=(0, 1, 0)),
                       method=method)
    assert not hits.visible.any() and np.all(np.isfinite(hits.normal))
    assert flat.valid_face.sum() == len(tris)
    with pytest.raises(FluoInputError):
        SurfaceCaster(pts, [[0, 1, 10 ** 6]])
    with pytest.raises(FluoInputError):
        cast_camera(caster, CAM, np.full((4, 4), np.nan))


@pytest.fixture(scope="module")
def oral():
    from FluoNavLib.mapping.synthetic import (
        coupled_light,
        open_field_camera,
        oral_cavity_surface,
        render_view,
        view_poses,
    )

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
    from fluoapp.cli import main

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


def test_cli_writes_the_results_into_the_scene(tmp_path, capsys):
    from fluoguide import mrml_io
    from fluoapp.cli import main
    from vtk.util import numpy_support as ns

    assert main(["nav", "synth", "--out", str(tmp_path / "s"), "--views", "3", "--binning", "8",
                 "--triangles", "20000", "--json"]) == 0
    capsys.readouterr()
    assert main(["nav", "correct", "--scene", str(tmp_path / "s" / "scene.mrml"), "--frame", "0",
                 "--all-frames", "--out", str(tmp_path / "o"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames_on_surface"] == [0, 1, 2] and r["faces_seen"] > 0
    scene = mrml_io.load_scene(r["scene"])
    poly = mrml_io.get_node(scene, "FluoNavSurfaceFlux").GetPolyData()
    T = ns.vtk_to_numpy(poly.GetCellData().GetArray("transport"))
    w = ns.vtk_to_numpy(poly.GetCellData().GetArray("view_weight"))
    views = ns.vtk_to_numpy(poly.GetCellData().GetArray("views"))
    assert len(T) == poly.GetNumberOfCells() and np.all(np.isfinite(T))
    assert abs(np.median(T[w > 0]) / 0.3 - 1) < 0.01 and views.max() == 3
    J = ns.vtk_to_numpy(poly.GetCellData().GetArray("surface_flux_w_per_mm2"))
    assert np.all(J[w > 0] > 0)
    node = mrml_io.get_node(scene, "FluoNavTransport")
    img = mrml_io.volume_array(node)[0]
    assert img.shape == (130, 174)
    doc = mrml_io.get_json_attribute(node, "FluoNav.Mapping")
    assert doc["frame"] == 0 and doc["miss_rate_corrected_pct"] < 5.0
    raw = mrml_io.volume_array(mrml_io.get_node(scene, "FluoNavRaw"))[0]
    assert raw.max() > 1000


@pytest.mark.slow
def test_full_resolution_oral_cavity_acceptance():
    from FluoNavLib.mapping.synthetic import (
        coupled_light,
        open_field_camera,
        oral_cavity_surface,
        render_view,
        view_poses,
    )

    caster, _ = oral_cavity_surface(62000)
    cam = open_field_camera()
    cone = coupled_light()
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    for k, pose in enumerate(view_poses(4)):
        counts, hits, vm = render_view(caster, cam, pose, cone, 0.3, rc, seed=k)
        S = counts - rc.offset_adu
        T, ok = transport_image(S, vm, cone)
        assert (ok & (np.abs(T / 0.3 - 1) < 0.05)).sum() / hits.visible.sum() >= 0.90
        raw, _, _ = miss_rate(S, hits.visible)
        corrected, _, _ = miss_rate(T, ok)
        assert corrected < 5.0 and corrected < raw


@pytest.mark.slow
def test_cli_bench_mapping(capsys):
    from fluoapp.cli import main

    assert main(["bench", "mapping", "--repeats", "1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["triangles"] == 62000 and r["pixels"] == 1392 * 1040
    assert r["fps_full"] > 0 and r["fps_binned"] > r["fps_full"]
    assert r["reference_accuracy"]["raster"]["face_agreement"] > 0.99
    assert r["transport_accuracy"]["full"]["visible_within_5pct"] >= 0.9


@pytest.mark.parametrize("cone_kw", [
    dict(half_angle_deg=50.0, alpha=2.0, gamma_per_mm=0.01),
    dict(half_angle_deg=35.0, alpha=0.0, gamma_per_mm=0.0),                      # neutral terms
    dict(half_angle_deg=45.0, alpha=1.5, gamma_per_mm=0.02, asym_amplitude=0.3, asym_phase_rad=0.7),
])
def test_compiled_model_equals_the_cone_model(cone_kw):
    from FluoNavLib.mapping.pixel_cast import PixelHits

    pts, tris = _spheres()
    caster = SurfaceCaster(pts, tris)
    pose = tf.look_at([20.0, -30.0, 120.0], [0.0, 0.0, 0.0], up=(0, 1, 0))
    light = tf.look_at([-40.0, 10.0, 100.0], [0.0, 0.0, 0.0], up=(0, 1, 0))     # tracked separately
    cone = IlluminationCone(system_gain_adu=1e5, **cone_kw)
    hits = cast_camera(caster, SMALL, pose)
    numpy_hits = PixelHits(hits.face, hits.distance_mm, hits.cos_view, hits.visible, hits.reason,
                           hits.camera_center_mm, point_mm=hits.point_mm, normal=hits.normal)
    for lw in (None, light):
        a = view_model(hits, cone, pose, lw)
        b = view_model(numpy_hits, cone, pose, lw)
        assert a.lit.sum() > 100
        np.testing.assert_array_equal(a.lit, b.lit)
        for k in ("angular", "foreshortening", "distance", "intensity"):
            np.testing.assert_allclose(getattr(a, k), getattr(b, k), atol=1e-12)
