"""The web app's server side without a browser: the job runner, and the FluoTomo
panel's workflow driven through the same callbacks the buttons call."""

import json
import time
from pathlib import Path

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel
from fluoapp.webapp.jobs import JobRunner


def _wait(runner, timeout_s=60):
    t0 = time.time()
    while runner.busy and time.time() - t0 < timeout_s:
        runner.wait(0.05)
    assert not runner.busy


def test_job_runner_reports_progress_result_and_runs_on_done_on_poll():
    runner = JobRunner()
    seen = []

    def work(progress, cancel):
        for k in range(5):
            progress(k / 5, f"step {k}")
        return 42

    runner.start("count", work, on_done=seen.append)
    _wait(runner)
    assert seen == [42]
    assert runner.state.fraction == 1.0 and runner.state.message == "done" and not runner.state.error


def test_job_runner_cancel_and_errors_become_state_not_exceptions():
    runner = JobRunner()
    errors = []

    def slow(progress, cancel):
        for _ in range(2000):
            time.sleep(0.005)
            check_cancel(cancel)
        return "finished"

    runner.start("slow", slow, on_done=lambda r: errors.append(("done", r)),
                 on_error=lambda kind, text: errors.append((kind, text)))
    with pytest.raises(Exception, match="still running"):
        runner.start("second", slow)
    runner.cancel()
    _wait(runner)
    assert errors == [("cancelled", "cancelled by the user")]
    assert runner.state.message == "cancelled" and runner.state.error == ""

    def bad(progress, cancel):
        raise FluoInputError("no tissue", field="labels")

    runner.start("bad", bad, on_error=lambda kind, text: errors.append((kind, text)))
    _wait(runner)
    assert errors[-1][0] == "error" and "no tissue" in errors[-1][1]
    assert "no tissue" in runner.state.error

    def ok(progress, cancel):
        return 1

    def broken_apply(result):
        raise RuntimeError("apply failed")

    runner.start("apply", ok, on_done=broken_apply)
    _wait(runner)
    assert "apply failed" in runner.state.error and not runner.busy


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from fluoapp.webapp.app import create_app

    return create_app(workspace=tmp_path_factory.mktemp("workspace"))


def _panel(app, key):
    return next(p for p in app.panels if p.key == key)


def test_every_message_is_shown_even_when_the_last_one_still_reads_shown(app):
    """The page closes a message after 8 s on its own; the server may not have
    heard of it when the next message comes. Each message pushes "shown" again, or
    it stays hidden (a browser test waited 60 s for one in CI)."""
    s = app.state
    app.notify("first")
    assert s.fluo_message_visible is True
    # what trame records once it has pushed "first" to a page (no page here)
    s._pushed_state.update(s._pending_update)
    s._pending_update.clear()
    app.notify("second")      # the server still reads "shown": the page may not
    assert s._pending_update.get("fluo_message_visible") is True


def test_app_has_one_panel_per_module_over_the_module_logic(app):
    assert [p.key for p in app.panels] == ["FluoCalib", "FluoTomo", "FluoNav"]
    import FluoTomo

    assert isinstance(_panel(app, "FluoTomo").logic, FluoTomo.FluoTomoLogic)
    assert _panel(app, "FluoTomo").logic.scene is app.scene


def test_tomo_workflow_segment_label_mesh_in_the_app_scene(app):
    tomo = _panel(app, "FluoTomo")
    s = app.state
    # before a CBCT exists, segmenting is refused with a message, not an exception
    app.ctrl.tomo_threshold_segment()
    assert "load a CBCT first" in s.fluo_message and s.fluo_message_color == "error"
    s.tomo_depth_mm = 4.7
    app.ctrl.tomo_load()
    assert mrml_io.get_node(app.scene, "CBCT") is not None
    assert mrml_io.get_node(app.scene, "CBCTLabels", required=False) is None
    app.ctrl.tomo_threshold_segment()      # liquid (-500..3000 HU)
    app.ctrl.tomo_threshold_segment()      # tube (60..3000 HU)
    assert s.tomo_segments == ["liquid", "tube"]
    # segment colours are fixed and cool: a warm one would read as fluorescence
    seg = app.slicer_app.segmentation_editor.active_segmentation_node.GetSegmentation()
    for k in range(seg.GetNumberOfSegments()):
        r, g, b = seg.GetNthSegment(k).GetColor()
        assert b > r or g > r, (seg.GetNthSegment(k).GetName(), (r, g, b))
    s.tomo_seg_name, s.tomo_seg_min, s.tomo_seg_max = "nothing", 5000, 6000
    app.ctrl.tomo_threshold_segment()
    assert "no voxel" in s.fluo_message and s.tomo_segments == ["liquid", "tube"]
    app.ctrl.tomo_use_segmentation()
    regions = {r["name"]: r["volume_mm3"] for r in s.tomo_regions}
    truth = mrml_io.get_json_attribute(mrml_io.get_node(app.scene, "CBCT"), "FluoGuide.Truth")
    for label, name in ((1, "liquid"), (2, "tube")):
        true_v = truth["regions"][str(label)]["analytic_volume_mm3"]
        assert abs(regions[name] - true_v) / true_v < 0.06, (name, regions[name], true_v)
    labels = mrml_io.volume_array(mrml_io.get_node(app.scene, "CBCTLabels"))
    assert set(np.unique(labels)) == {0, 1, 2}
    s.tomo_mesh_size_mm = 50
    app.ctrl.tomo_build_mesh()
    assert "mesh size" in s.fluo_message and not app.jobs.busy
    s.tomo_mesh_size_mm = 1.5
    app.ctrl.tomo_build_mesh()
    _wait(app.jobs)
    assert "nodes" in s.tomo_mesh_info
    assert mrml_io.get_node(app.scene, "FluoTomoMeshSurface") is not None


# the tube phantom reconstructed by the app (fast, graded mesh): the job 17 s and 1.2 GB
# (0.6 GB of growth) on 2026-11-28; on the uniform grid it was 89 s and 3.2 GB
@pytest.mark.slow
def test_tomo_reconstruction_job_overlays_the_result(app):
    tomo = _panel(app, "FluoTomo")
    if mrml_io.get_node(app.scene, "CBCTLabels", required=False) is None:
        test_tomo_workflow_segment_label_mesh_in_the_app_scene(app)
    app.state.tomo_method = "HP"
    app.ctrl.tomo_reconstruct()
    _wait(app.jobs, 300)
    res = app.state.tomo_result
    assert res is not None and res["method"] == "HP", app.state.fluo_message
    # HP on the user's threshold segmentation: the thesis's HP band is ~16 %
    assert abs(res["peak_error_pct"]) < 35
    assert abs(res["centroid_mm"] - res["true_centroid_mm"]) < 1.0
    node = mrml_io.get_node(app.scene, "FluoTomoYieldHP")
    views = app.slicer_app.view_manager.get_slice_views()
    assert views and all(v.get_foreground_volume_id() == node.GetID() for v in views)
    assert node.GetDisplayNode().GetApplyThreshold()
    assert mrml_io.get_node(app.scene, "FluoTomoYieldSurface") is not None
    assert float(app.state.tomo_colorbar["max"]) > 0
    # the one warning allowed is the segmentation test's: the panel's segments are a
    # threshold of a blurred, noisy CBCT (specks dropped), the simulated scan's beam
    # points carry the tracker's error (docs/recording.md: the beam's point against
    # the spot), and the test may read either as a boundary that is off
    odd = [w for w in res["warnings"] if not w.startswith("the prior's regions fit the data")]
    assert odd == [], res["warnings"]
    assert app.state.fluo_message_color == ("success" if not res["warnings"] else "warning")
    # an over-regularised run is shown with its warning, not as a success: checked on
    # the own scene's route (test_own_label_map_from_files_..., a second tube case here
    # cost 100 s)


def test_nav_stream_from_the_simulated_tracker(app):
    # The stream runs until Stop; the test stops it once the page has shown two
    # frames. (A 2 s stream showed one frame on a loaded machine: the first
    # frame's compile and render ate the window, and frames that arrive between
    # two polls show as one.)
    app.state.nav_seconds = 600
    app.ctrl.nav_stream()
    t0 = time.time()
    while app.jobs.busy and app.state.nav_frames_shown < 2 and time.time() - t0 < 300:
        app.poll()
        time.sleep(0.1)
    assert app.jobs.busy, app.jobs.state.error      # still streaming when stopped
    app.ctrl.fluo_cancel_job()                     # the Stop button
    while app.jobs.busy and time.time() - t0 < 360:
        app.poll()
        time.sleep(0.1)
    app.poll()
    assert not app.jobs.busy and not app.jobs.state.error, app.jobs.state.error
    assert app.state.nav_frames_shown >= 2
    assert "Stream stopped after" in app.state.fluo_message
    frame = app.state.nav_frame
    assert frame["raw"].startswith("data:image/png;base64,") and frame["miss_corrected"] < 5
    assert mrml_io.get_node(app.scene, "FluoNavCamera") is not None
    assert "unreported losses: 0" in app.state.fluo_message


def test_calib_panel_runs_the_light_calibrations(app):
    app.ctrl.calib_light_synth()
    _wait(app.jobs)
    app.poll()
    from pathlib import Path

    root = Path(app.state.calib_light_folder).parent
    for kind, key in (("radiometry", "gain_adu_per_e"), ("illumination", "alpha"),
                      ("laser", "error_3d_mm")):
        app.state.calib_light_kind = kind
        app.state.calib_light_folder = str(root / ("stack" if kind == "radiometry" else kind))
        app.ctrl.calib_light_run()
        _wait(app.jobs, 120)
        app.poll()
        assert not app.jobs.state.error, app.jobs.state.error
        assert key in app.state.calib_light_result
    from FluoCalibLib.radiometry import scene as light_scene

    assert light_scene.load_calibration(app.scene, light_scene.LASER_KEY)["error_3d_mm"] < 0.5
    app.state.calib_light_folder = "nonexistent"
    app.ctrl.calib_light_run()
    assert "folder not found" in app.state.fluo_message


def test_a_click_carries_the_panel_inputs_it_reads(app):
    """The browser pushes typed values only between requests but sends a click at
    once (CI: 'Add segment by threshold' ran on the old 60..3000 HU while the page
    showed 0.5..100). Each action button sends its panel's inputs with the click;
    they are applied before the action, and only the panel's inputs are."""
    html = app.ui.layout.html
    for name in ("calib_run", "calib_save", "nav_stream", "tomo_build_mesh", "tomo_reconstruct",
                 "tomo_threshold_segment"):
        trigger = app.server.trigger_name(getattr(app.ctrl, name))
        assert f"trigger('{trigger}', [], {{fluo_form: {{" in html, name
    assert "tomo_seg_min: tomo_seg_min, tomo_seg_max: tomo_seg_max" in html
    app.state.tomo_mesh_roi = ""
    app.ctrl.tomo_build_mesh(fluo_form={"tomo_mesh_roi": "1,2,3", "fluo_message_color": "x"})
    assert "ROI" in app.state.fluo_message and not app.jobs.busy
    assert app.state.tomo_mesh_roi == "1,2,3" and app.state.fluo_message_color == "error"
    app.state.tomo_mesh_roi = ""


def test_mesh_roi_is_validated(app):
    app.state.tomo_mesh_roi = "1,2,3"
    app.ctrl.tomo_build_mesh()
    assert "ROI" in app.state.fluo_message and not app.jobs.busy
    app.state.tomo_mesh_roi = "-10,10,-10,10,-8,0"
    tomo = _panel(app, "FluoTomo")
    assert tomo._roi() == (-10.0, 10.0, -10.0, 10.0, -8.0, 0.0)
    app.state.tomo_mesh_roi = ""


@pytest.mark.slow
def test_quality_mesher_from_the_panel(app):
    if mrml_io.get_node(app.scene, "CBCTLabels", required=False) is None:
        test_tomo_workflow_segment_label_mesh_in_the_app_scene(app)
    app.state.tomo_mesh_method = "quality (fTetWild, slower)"
    app.state.tomo_mesh_size_mm = 3.0
    app.state.tomo_mesh_roi = "-12,12,-12,12,-12,0"
    app.ctrl.tomo_build_mesh()
    _wait(app.jobs, 300)
    assert not app.jobs.state.error, app.jobs.state.error
    assert "fTetWild" in app.state.tomo_mesh_info
    app.state.tomo_mesh_method = "fast (structured)"
    app.state.tomo_mesh_roi = ""


def test_own_label_map_from_files_mesh_is_the_one_used_and_reconstructed(app, own_scene):
    """The user's own scene in the panel: a label map file (not the tube, any
    direction), optics.json and an acquisition folder; the mesh built in step
    3 is the reconstruction's (its node count is the result's), region volumes
    are shown, and the yield overlay peaks in the inclusion."""
    import shutil

    sc = own_scene.sc
    # the UI takes paths inside its workspace (issue #21)
    tmp_path = app.workspace.root / "own"
    tmp_path.mkdir(exist_ok=True)
    for f in ("labels.nrrd", "optics.json"):
        shutil.copy(own_scene.dir / f, tmp_path / f)
    shutil.copytree(own_scene.acq, tmp_path / "acq", dirs_exist_ok=True)
    s = app.state
    s.tomo_own_labels = "own/missing.nrrd"
    s.tomo_own_optics = "own/optics.json"
    s.tomo_own_acquisition = "own/acq"
    app.ctrl.tomo_load_own()
    assert "missing.nrrd" in s.fluo_message and s.fluo_message_color == "error"
    s.tomo_own_labels = str(tmp_path.parent.parent / "labels.nrrd")      # outside: refused
    app.ctrl.tomo_load_own()
    assert "inside the workspace" in s.fluo_message and s.fluo_message_color == "error"
    s.tomo_own_labels = "own/labels.nrrd"
    app.ctrl.tomo_load_own()
    assert s.tomo_own and "labels [3, 7]" in s.tomo_own_info, s.fluo_message
    # shown as a phantom is (issue #33): grey tones, each label an outlined segment,
    # their surfaces in the 3D view from the start
    labels = mrml_io.get_node(app.scene, "labels")
    assert labels.GetDisplayNode().GetColorNode().GetName() == "FluoTomoLabelTones"
    seg = mrml_io.get_node(app.scene, "labels segments")
    names = {seg.GetSegmentation().GetNthSegment(k).GetName()
             for k in range(seg.GetSegmentation().GetNumberOfSegments())}
    optics_names = json.loads((own_scene.optics).read_text()).get("names", {})
    assert names == {optics_names.get(k, f"label {k}") for k in ("3", "7")}, names
    d = seg.GetDisplayNode()
    assert d.GetOpacity2DOutline() == 1.0 and d.GetVisibility3D()
    assert seg.GetSegmentation().ContainsRepresentation("Closed surface")
    s.tomo_mesh_size_mm = 1.5
    s.tomo_mesh_method = "fast (structured)"
    app.ctrl.tomo_build_mesh()
    _wait(app.jobs, 300)
    app.poll()
    assert "reconstruction uses this mesh" in s.tomo_mesh_info, s.tomo_mesh_info
    assert "region 7:" in s.tomo_mesh_info and "% of the label map's" in s.tomo_mesh_info
    nodes = int(s.tomo_mesh_info.split()[0])
    s.tomo_method = "HP"
    s.tomo_lambda = 10.0
    app.ctrl.tomo_reconstruct()
    _wait(app.jobs, 600)
    app.poll()
    res = s.tomo_own_result
    assert res is not None, s.fluo_message
    assert res["nodes"] == nodes and res["peak_label"] == 7
    assert abs(float(res["yield"]) - 2.6e-3) / 2.6e-3 < 0.25, res
    node = mrml_io.get_node(app.scene, res["node"])
    g = mrml_io.volume_geometry(node)
    assert np.allclose(g["direction"], sc["direction"]) and np.allclose(g["origin"],
                                                                        sc["origin_mm"])
    views = app.slicer_app.view_manager.get_slice_views()
    assert views and all(v.get_foreground_volume_id() == node.GetID() for v in views)
    # shown as a warning exactly when the result carries one
    assert s.fluo_message_color == ("success" if res["warnings"] == "none" else "warning"), res
    assert "over-regularised" not in res["warnings"], res
    # an over-regularised run is shown with its warning, not as a success
    s.tomo_lambda = 1e6
    app.ctrl.tomo_reconstruct()
    _wait(app.jobs, 600)
    app.poll()
    res = s.tomo_own_result
    assert "over-regularised" in res["warnings"], res
    # the colour bar and the threshold follow the user's result as the phantom's
    assert float(s.tomo_colorbar["max"]) > 0 and s.tomo_colorbar["gradient"]
    assert s.job["owner"] == "FluoTomo"
    assert s.fluo_message_color == "warning"
    assert "over-regularised" in s.fluo_message
    s.tomo_lambda = 10.0
    # back to the phantom route: its mesh step says plainly that it is a preview
    app.ctrl.tomo_load()
    assert not s.tomo_own


def test_plan_scan_on_the_own_scene_draws_the_points(app, own_scene):
    """Issue #36 in the app: the planned laser positions on the 3D surface, with each
    target's predicted interval; bad input is a message, not an exception."""
    import shutil

    tmp_path = app.workspace.root / "plan"
    tmp_path.mkdir(exist_ok=True)
    for f in ("labels.nrrd", "optics.json"):
        shutil.copy(own_scene.dir / f, tmp_path / f)
    shutil.copytree(own_scene.acq, tmp_path / "acq", dirs_exist_ok=True)
    s = app.state
    s.tomo_own_labels, s.tomo_own_optics = "plan/labels.nrrd", "plan/optics.json"
    s.tomo_own_acquisition = "plan/acq"
    app.ctrl.tomo_load_own()
    assert s.tomo_own, s.fluo_message
    s.tomo_plan_targets, s.tomo_plan_positions = "5", 8
    app.ctrl.tomo_plan()
    assert s.fluo_message_color == "error" and "not in the label map" in s.fluo_message
    s.tomo_plan_targets = ""
    app.ctrl.tomo_plan()
    _wait(app.jobs, 120)
    app.poll()
    res = s.tomo_plan_result
    assert res is not None and res["positions"] == 8, s.fluo_message
    assert [r["label"] for r in res["targets"]] == ["7"] and res["targets"][0]["covered"]
    node = mrml_io.get_node(app.scene, "FluoTomoPlannedSources")
    assert node is not None and node.GetDisplayNode().GetVisibility3D()
    assert "Planned 8 laser positions" in s.fluo_message


def test_ui_paths_stay_in_the_workspace_and_messages_show_no_server_path(app, tmp_path):
    """Issue #21: a scripted client made the server write scene.mrml anywhere, list
    /etc through the image glob's message and read files outside a stack folder."""
    ws = app.workspace.root
    s = app.state
    outside = tmp_path / "outside"
    outside.mkdir()
    for target in (str(outside / "evil.mrml"), "../evil.mrml", "/etc/fluo-evil.mrml"):
        s.calib_save_path = target
        app.ctrl.calib_save()
        assert "inside the workspace" in s.fluo_message and s.fluo_message_color == "error"
    assert list(outside.iterdir()) == [] and not (ws.parent / "evil.mrml").exists()
    s.calib_save_path = "session/scene.mrml"
    app.ctrl.calib_save()
    assert (ws / "session" / "scene.mrml").is_file()
    assert s.fluo_message == "Scene saved to session/scene.mrml"
    for pattern in ("/etc/*", "../*", str(outside / "*")):
        s.calib_images = pattern
        app.ctrl.calib_run()
        assert "relative to the workspace" in s.fluo_message and not app.jobs.busy
    # a hostile manifest names a file outside its folder: refused, nothing read
    (outside / "secret.png").write_bytes(b"not for you")
    (ws / "hostile").mkdir()
    (ws / "hostile" / "stack.json").write_text(json.dumps(
        {"frames": [{"file": str(outside / "secret.png"), "exposure_s": 0.01}]}))
    s.calib_light_kind, s.calib_light_folder = "radiometry", "hostile"
    app.ctrl.calib_light_run()
    _wait(app.jobs)
    app.poll()
    assert "must be inside its folder" in s.fluo_message
    # a Lib error names its file: shown relative to the workspace, no server path
    (ws / "empty").mkdir()
    s.calib_light_folder = "empty"
    app.ctrl.calib_light_run()
    _wait(app.jobs)
    app.poll()
    assert "empty/stack.json" in s.fluo_message
    for text in (s.fluo_message, json.dumps(s.job)):
        assert str(ws) not in text and str(outside) not in text, text
    s.calib_images = "bundled:opencv_left/left*.jpg"
    assert len(app.workspace.glob(s.calib_images, "images")) >= 3


def test_a_5000_character_path_is_a_message_not_a_traceback(app, caplog, capfd):
    """Issue #34 item 5: pathlib's ``is_dir`` raises ENAMETOOLONG (it is not one
    of the errors it swallows): the light-folder field put a traceback in the log."""
    import logging

    s = app.state
    caplog.set_level(logging.DEBUG)
    long = "a" * 5000
    for field, value, call in (("calib_light_folder", long, app.ctrl.calib_light_run),
                               ("calib_light_folder", "/".join(["b" * 200] * 25),
                                app.ctrl.calib_light_run),
                               ("calib_save_path", long + ".mrml", app.ctrl.calib_save)):
        setattr(s, field, value)
        call()
        _wait(app.jobs)
        app.poll()
        assert "name too long" in s.fluo_message and s.fluo_message_color == "error", \
            s.fluo_message
        assert len(s.fluo_message) < 300, s.fluo_message
    s.calib_light_folder, s.calib_save_path = "", "fluoguide-session/scene.mrml"
    assert "Traceback" not in caplog.text and "Traceback" not in capfd.readouterr().err
    assert not any(r.exc_info for r in caplog.records)


def test_panels_show_only_their_own_jobs_and_fluonav_finds_any_label_map(own_scene, tmp_path):
    """A job of the tomography panel is shown by that panel only (the FluoCalib panel
    showed 'reconstruction HP done'); FluoNav's surface comes from whatever label map
    the scene holds ('CBCTLabels: node not found in scene' on a user's own scene)."""
    import shutil

    from fluoapp.webapp.app import create_app

    app = create_app(workspace=tmp_path / "ws")
    own = app.workspace.root / "own"
    shutil.copytree(own_scene.dir, own)
    s = app.state
    s.nav_target_triangles = 0
    app.ctrl.nav_build_surface()                        # nothing loaded yet: said so
    assert s.fluo_message_color == "error" and "no label map" in s.fluo_message
    s.tomo_own_labels, s.tomo_own_optics, s.tomo_own_acquisition = (
        "own/labels.nrrd", "own/optics.json", "own/acq")
    app.ctrl.tomo_load_own()
    app.ctrl.nav_build_surface()
    assert s.fluo_message_color == "success", s.fluo_message
    assert "TissueSurface of labels" in s.nav_surface_info
    s.tomo_mesh_size_mm = 2.0
    s.tomo_mesh_method = "fast (structured)"
    app.ctrl.tomo_build_mesh()
    _wait(app.jobs, 300)
    app.poll()
    assert s.job["owner"] == "FluoTomo" and s.job["name"] == "mesh"
    # the templates: each panel's job line is bound to its own jobs
    from fluoapp.webapp import calib_panel, tomo_panel

    for module, key in ((calib_panel, "FluoCalib"), (tomo_panel, "FluoTomo")):
        assert f"job.owner === '{key}'" in Path(module.__file__).read_text()
    # the colour bar and the threshold slider exist for the user's result too
    ui = Path(tomo_panel.__file__).read_text()
    assert 'v_if="tomo_result || tomo_own_result", id="tomo-colorbar"' in ui
    assert '"!(tomo_result || tomo_own_result)",), id="tomo-threshold-slider"' in ui


def test_the_user_s_dicom_cbct_segmented_as_fluo_segment_does_and_saved(app, tmp_path):
    """The FluoTomo panel takes the user's CBCT as a DICOM folder (issue #35):
    two series and no UID is one message listing them, the scene unchanged;
    with the UID the geometry comes back as written. The threshold tool keeps a
    segment as ``fluo segment`` keeps a label (largest component, holes
    filled); the label map saved to the workspace reads back; the phantom
    route's mesh is refused with the way forward."""
    from dicom_cases import rotation, write_series
    from FluoTomoLib.tomography import threshold_labels

    tomo = _panel(app, "FluoTomo")
    s = app.state
    # this app's own callbacks: app.ctrl is the trame server's, which a later app
    # made in this process (another test) takes over
    ctrl = {name: app.guarded(getattr(tomo, name)) for name in (
        "load_phantom", "load_cbct", "threshold_segment", "use_segmentation", "save_labels",
        "build_mesh")}
    k, j, i = np.indices((24, 28, 30))
    body = (k - 12) ** 2 / 100 + (j - 14) ** 2 / 144 + (i - 15) ** 2 / 169 < 1
    stored = np.where(body, 40, -1000).astype(np.int16)
    stored[12, 14, 15] = -1000                       # a hole inside the body
    stored[1, 1, 1] = 40                             # a speck apart from it
    direction = rotation(10.0, -5.0, 30.0)
    ws = app.workspace.root
    write_series(ws / "dicom", stored, (0.7, 0.8, 1.25), (-20.0, 15.0, 100.0), direction,
                 uid="1.2.826.0.1.3680043.2.1125.77.11", description="CBCT")
    write_series(ws / "dicom", stored[:, ::-1], (0.7, 0.8, 1.25), (0.0, 0.0, 0.0), np.eye(3),
                 uid="1.2.826.0.1.3680043.2.1125.77.12", description="scout", prefix="SC")
    s.tomo_depth_mm = 4.7
    ctrl["load_phantom"]()                             # a phantom shown before
    before = mrml_io.get_node(app.scene, "CBCT")
    s.tomo_cbct_path, s.tomo_cbct_series = "dicom", ""
    ctrl["load_cbct"]()
    assert s.fluo_message_color == "error" and "77.11" in s.fluo_message, s.fluo_message
    assert mrml_io.get_node(app.scene, "CBCT") is before
    s.tomo_cbct_series = "1.2.826.0.1.3680043.2.1125.77.11"
    ctrl["load_cbct"]()
    assert s.fluo_message_color == "success" and "DICOM" in s.fluo_message, s.fluo_message
    node = mrml_io.get_node(app.scene, "CBCT")
    geo = mrml_io.volume_geometry(node)
    np.testing.assert_allclose(geo["spacing"], (0.7, 0.8, 1.25), atol=1e-6)
    np.testing.assert_allclose(geo["origin"], (-20.0, 15.0, 100.0), atol=1e-5)
    np.testing.assert_allclose(geo["direction"], direction, atol=1e-6)
    assert np.array_equal(mrml_io.volume_array(node), stored.astype(float))
    s.tomo_seg_name, s.tomo_seg_min, s.tomo_seg_max = "tissue", -200, 3000
    ctrl["threshold_segment"]()
    assert "of 2 components, 1 voxels dropped, 1 filled" in s.fluo_message, s.fluo_message
    ctrl["use_segmentation"]()
    labels = mrml_io.volume_array(mrml_io.get_node(app.scene, "CBCTLabels"))
    headless, _ = threshold_labels(stored, "1:-200:3000")
    assert np.array_equal(labels, headless)          # what fluo segment writes
    s.tomo_labels_out = "mine/labels.nrrd"
    ctrl["save_labels"]()
    assert s.fluo_message_color == "success" and s.tomo_own_labels == "mine/labels.nrrd"
    back = tomo.logic.labelMap(tomo.logic.loadLabelMap(str(ws / "mine" / "labels.nrrd")))
    assert np.array_equal(back.labels_kji, headless)
    np.testing.assert_allclose(back.direction, direction, atol=1e-6)
    ctrl["build_mesh"]()
    assert "no simulated scan" in s.fluo_message and not app.jobs.busy
