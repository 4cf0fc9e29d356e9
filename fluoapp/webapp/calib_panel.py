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
    # the inputs every button of the panel sends with its click (app.submit)
    FORM = ("calib_images", "calib_board", "calib_light_kind", "calib_light_folder",
            "calib_save_path")

    def __init__(self, app, logic):
        self.app = app
        self.logic = logic
        s = app.state
        # paths are relative to the app's workspace; bundled:... is the shipped example data
        s.calib_images = "bundled:opencv_left/left*.jpg" if bundled_board_images() else ""
        s.calib_board = "chessboard:9x6:25"
        s.calib_result = None
        s.calib_plot = ""
        s.calib_save_path = "fluoguide-session/scene.mrml"
        s.calib_light_kind = "radiometry"
        s.calib_light_folder = ""
        s.calib_light_result = None
        s.calib_light_plot = ""
        app.ctrl.calib_run = app.guarded(self.run)
        app.ctrl.calib_save = app.guarded(self.save)
        app.ctrl.calib_light_synth = app.guarded(self.light_synth)
        app.ctrl.calib_light_run = app.guarded(self.light_run)

    def _images(self):
        pattern = str(self.app.state.calib_images or "").strip()
        files = self.app.workspace.glob(pattern, "images")
        if len(files) < 3:
            raise FluoInputError(f"need at least 3 board images, found {len(files)}",
                                 field="images", value=pattern)
        return files

    def run(self):
        from fluoapp.webapp.plots import bar_chart

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

        self.app.start_job("camera calibration", job, on_done=done, owner="FluoCalib")

    def light_synth(self):
        """Write synthetic stack / illumination / laser sets (known truth) and point the
        folder field at the chosen one."""
        root = self.app.workspace.path("synthetic-light", "folder", what="folder", writable=True)

        def work(progress, cancel):
            self.logic.writeSyntheticLight(root, progress=progress, cancel=cancel)
            return root

        def done(folder):
            kind = self.app.state.calib_light_kind
            shown = self.app.workspace.shown
            self.app.state.calib_light_folder = shown(folder / ("stack" if kind == "radiometry" else kind))
            self.app.notify(f"Synthetic data sets in {shown(folder)}", "success")

        self.app.start_job("synthetic light data", work, on_done=done, owner="FluoCalib")

    def light_run(self):
        """Radiometry, illumination or laser calibration of the folder (background job
        over the logic's ``prepare...`` call; stored by its ``store...`` call)."""
        import numpy as np

        s = self.app.state
        kind = str(s.calib_light_kind)
        folder = self.app.workspace.path(s.calib_light_folder, "folder", what="folder",
                                         must_exist=True)
        calls = {"radiometry": (self.logic.prepareCameraCharacterization,
                                self.logic.storeCameraCharacterization),
                 "illumination": (self.logic.prepareIlluminationCalibration,
                                  self.logic.storeIlluminationCalibration),
                 "laser": (self.logic.prepareLaserCalibration, self.logic.storeLaserCalibration)}
        if kind not in calls:
            raise FluoInputError("unknown calibration", field="kind", value=kind)
        prepare, store = calls[kind]
        job = prepare(folder)

        def done(res):
            from fluoapp.webapp.plots import png_data_url

            store(res)
            plot = ""
            if kind == "radiometry":
                keys = ("gain_adu_per_e", "dark_current_e_per_s", "bias_e", "read_noise_e",
                        "linearity_r2", "nonlinearity_pct", "dynamic_range")
                import matplotlib

                matplotlib.use("Agg")
                import matplotlib.pyplot as plt

                fig, ax = plt.subplots(figsize=(4.2, 2.8))
                mu, var = np.array(res["ptc"]["mean_adu"]), np.array(res["ptc"]["var_adu2"])
                ax.plot(mu, var, "o", ms=4)
                ax.plot(mu, res["gain_adu_per_e"] * mu, "-")
                ax.set_xlabel("mean above dark [ADU]")
                ax.set_ylabel("variance [ADU²]")
                ax.set_title(f"Photon transfer: K = {res['gain_adu_per_e']:.3f} ADU/e-", fontsize=9)
                plot = png_data_url(fig)
            elif kind == "illumination":
                keys = ("half_angle_deg", "alpha", "gamma_per_mm", "system_gain_adu", "ratio_mean",
                        "ratio_sd", "model")
                import matplotlib

                matplotlib.use("Agg")
                import matplotlib.pyplot as plt

                fig, ax = plt.subplots(figsize=(4.2, 3.0))
                im = ax.imshow(res["ratio_images"][0], vmin=0.8, vmax=1.2, cmap="coolwarm")
                ax.set_title("measured / model (nearest view)", fontsize=9)
                ax.axis("off")
                fig.colorbar(im, ax=ax, shrink=0.8, label="measured / model (dimensionless)")
                plot = png_data_url(fig)
            else:
                keys = ("error_3d_mm", "error_2d_px", "line_fit_rms_mm")
            s.calib_light_result = {k: (round(float(res[k]), 4) if isinstance(res[k], (int, float))
                                        else str(res[k])) for k in keys if k in res}
            s.calib_light_plot = plot
            self.app.notify(f"{kind} calibration stored on FluoCalibration", "success")

        self.app.start_job(f"{kind} calibration", job, on_done=done, owner="FluoCalib")

    def save(self):
        from fluoguide import mrml_io

        path = self.app.workspace.path(self.app.state.calib_save_path, "scene file", writable=True)
        mrml_io.save_scene(self.app.scene, path)
        self.app.notify(f"Scene saved to {self.app.workspace.shown(path)}", "success")

    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("FluoCalib", classes="text-h6")
        html.Div("Camera intrinsics from board images", classes="text-subtitle-2 mt-2")
        v.VTextField(v_model=("calib_images",), label="Images (glob in the workspace, or "
                     "bundled:...)", density="compact",
                     hide_details=True, id="calib-images")
        v.VTextField(v_model=("calib_board",), label="Board (chessboard:COLSxROWS:SQUARE_MM)",
                     density="compact", hide_details=True, classes="mt-2", id="calib-board")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Calibrate", click=self.app.submit("calib_run", self.FORM),
                       block=True, color="primary", disabled=(busy,), id="calib-run")
            with v.VCol(cols=4):
                v.VBtn("Cancel", click=self.app.ctrl.fluo_cancel_job, block=True,
                       disabled=("!" + busy,))
        # the job's progress and outcome are shown by the panel that started it only
        v.VProgressLinear(model_value=("job.fraction * 100",), height=6, classes="mt-2",
                          v_if="job.owner === 'FluoCalib'")
        html.Div("{{ job.name }} {{ job.message }}", classes="text-caption",
                 v_if="job.owner === 'FluoCalib'", id="calib-job")
        with html.Div(v_if="calib_result", classes="text-caption mt-2", id="calib-result"):
            html.Div("fx {{ calib_result.fx }}, fy {{ calib_result.fy }} px; centre "
                     "({{ calib_result.cx }}, {{ calib_result.cy }}) px")
            html.Div("distortion {{ calib_result.dist.join(', ') }}")
            html.Div("RMS {{ calib_result.rms_px }} px, held out {{ calib_result.holdout_rms_px }} px; "
                     "{{ calib_result.used }} views used, {{ calib_result.holdout }} held out")
            html.Div("rejected: {{ calib_result.rejected.join('; ') }}",
                     v_if="calib_result.rejected.length")
            html.Img(src=("calib_plot",), style="width: 100%; background: white;", classes="mt-1")
        html.Div("Radiometry, illumination, laser", classes="text-subtitle-2 mt-4")
        v.VSelect(v_model=("calib_light_kind",), items=(["radiometry", "illumination", "laser"],),
                  label="Calibration", density="compact", hide_details=True, id="calib-light-kind")
        v.VTextField(v_model=("calib_light_folder",), label="Folder (stack.json / illumination.json "
                     "/ laser.json)", density="compact", hide_details=True, classes="mt-2",
                     id="calib-light-folder")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=6):
                v.VBtn("Synthetic data", click=self.app.submit("calib_light_synth", self.FORM),
                       block=True, disabled=(busy,), id="calib-light-synth")
            with v.VCol(cols=6):
                v.VBtn("Calibrate", click=self.app.submit("calib_light_run", self.FORM),
                       block=True, color="primary", disabled=(busy,), id="calib-light-run")
        with html.Div(v_if="calib_light_result", classes="text-caption mt-1", id="calib-light-result"):
            html.Div("{{ Object.entries(calib_light_result).map(([k, v]) => k + ' ' + v).join(', ') }}")
            html.Img(src=("calib_light_plot",), v_if="calib_light_plot",
                     style="width: 100%; background: white;")
        html.Div("Save", classes="text-subtitle-2 mt-4")
        v.VTextField(v_model=("calib_save_path",), label="Scene file (.mrml, in the workspace)",
                     density="compact",
                     hide_details=True, id="calib-save-path")
        v.VBtn("Save scene", click=self.app.submit("calib_save", self.FORM),
               block=True, classes="mt-2", disabled=(busy,), id="calib-save")
