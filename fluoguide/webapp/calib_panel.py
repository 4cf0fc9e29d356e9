"""FluoCalib panel: camera calibration from board images, with progress, errors
and a per-view plot; results go on the scene's ``FluoCalibration`` node."""

from __future__ import annotations

from pathlib import Path

from fluoguide.errors import FluoInputError

__all__ = ["CalibPanel", "bundled_board_images"]


def bundled_board_images():
    """OpenCV's chessboard photos shipped with FluoCalib (9x6 inner corners)."""
    root = Path(__file__).resolve().parents[2] / "FluoCalib" / "Resources" / "TestData" / "opencv_left"
    return sorted(root.glob("left*.jpg"))


class CalibPanel:
    key = "FluoCalib"
    title = "FluoCalib: camera calibration"
    icon = "mdi-camera-iris"

    def __init__(self, app, logic):
        self.app = app
        self.logic = logic
        s = app.state
        s.calib_images = str(bundled_board_images()[0].parent / "left*.jpg") if bundled_board_images() else ""
        s.calib_board = "chessboard:9x6:25"
        s.calib_result = None
        s.calib_plot = ""
        s.calib_save_path = str(Path.cwd() / "fluoguide-session" / "scene.mrml")
        app.ctrl.calib_run = app.guarded(self.run)
        app.ctrl.calib_save = app.guarded(self.save)

    def _images(self):
        import glob

        pattern = str(self.app.state.calib_images or "").strip()
        files = sorted(glob.glob(pattern))
        if len(files) < 3:
            raise FluoInputError(f"need at least 3 board images, found {len(files)}",
                                 field="images", value=pattern)
        return files

    def run(self):
        from .plots import bar_chart

        s = self.app.state
        job = self.logic.prepareCameraCalibration(self._images(), s.calib_board)

        def done(res):
            self.logic.storeCameraCalibration(res)
            c = res.camera
            s.calib_result = {"fx": round(c.fx, 2), "fy": round(c.fy, 2), "cx": round(c.cx, 2),
                              "cy": round(c.cy, 2), "dist": [round(d, 4) for d in c.dist],
                              "rms_px": round(res.rms_px, 3),
                              "holdout_rms_px": round(res.holdout_rms_px, 3),
                              "used": len(res.used), "holdout": len(res.holdout),
                              "rejected": [f"{Path(v.name).name}: {v.reason}" for v in res.rejected]}
            views = [v for v in res.views if v.status != "rejected"]
            s.calib_plot = bar_chart([Path(v.name).stem for v in views], [v.rms_px for v in views],
                                     "RMS reprojection [px]", "Per-view error (used and held out)",
                                     hline=res.rms_px, hline_label="overall RMS")
            self.app.notify(f"Camera calibrated: RMS {res.rms_px:.3f} px over {len(res.used)} views",
                            "success")

        self.app.start_job("camera calibration", job, on_done=done)

    def save(self):
        from fluoguide import mrml_io

        path = Path(str(self.app.state.calib_save_path))
        mrml_io.save_scene(self.app.scene, path)
        self.app.notify(f"Scene saved to {path}", "success")

    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("FluoCalib", classes="text-h6")
        html.Div("Camera intrinsics from board images", classes="text-subtitle-2 mt-2")
        v.VTextField(v_model=("calib_images",), label="Images (glob)", density="compact",
                     hide_details=True, id="calib-images")
        v.VTextField(v_model=("calib_board",), label="Board (chessboard:COLSxROWS:SQUARE_MM)",
                     density="compact", hide_details=True, classes="mt-2", id="calib-board")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Calibrate", click=self.app.ctrl.calib_run, block=True, color="primary",
                       disabled=(busy,), id="calib-run")
            with v.VCol(cols=4):
                v.VBtn("Cancel", click=self.app.ctrl.fluo_cancel_job, block=True,
                       disabled=("!" + busy,))
        v.VProgressLinear(model_value=("job.fraction * 100",), height=6, classes="mt-2")
        html.Div("{{ job.name }} {{ job.message }}", classes="text-caption")
        with html.Div(v_if="calib_result", classes="text-caption mt-2", id="calib-result"):
            html.Div("fx {{ calib_result.fx }}, fy {{ calib_result.fy }} px; centre "
                     "({{ calib_result.cx }}, {{ calib_result.cy }}) px")
            html.Div("distortion {{ calib_result.dist.join(', ') }}")
            html.Div("RMS {{ calib_result.rms_px }} px, held out {{ calib_result.holdout_rms_px }} px; "
                     "{{ calib_result.used }} views used, {{ calib_result.holdout }} held out")
            html.Div("rejected: {{ calib_result.rejected.join('; ') }}",
                     v_if="calib_result.rejected.length")
            html.Img(src=("calib_plot",), style="width: 100%; background: white;", classes="mt-1")
        html.Div("Save", classes="text-subtitle-2 mt-4")
        v.VTextField(v_model=("calib_save_path",), label="Scene file (.mrml)", density="compact",
                     hide_details=True, id="calib-save-path")
        v.VBtn("Save scene", click=self.app.ctrl.calib_save, block=True, classes="mt-2",
               disabled=(busy,), id="calib-save")
