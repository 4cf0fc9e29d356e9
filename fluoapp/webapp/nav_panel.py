"""FluoNav panel: the tissue surface in 3D, and a stream of tracked frames
(simulated NDI tracker + rendered oral-cavity frames) shown raw and corrected
side by side with their 40 % contours, the tracked camera in 3D."""

from __future__ import annotations

import queue

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError

__all__ = ["NavPanel"]


def _image_url(img, mask, contour, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fluoapp.webapp.plots import png_data_url

    fig, ax = plt.subplots(figsize=(3.4, 2.7))
    ax.imshow(np.where(mask, img, np.nan), cmap="magma")
    if contour.any():
        ax.contour(contour.astype(float), levels=[0.5], colors="cyan", linewidths=0.8)
    ax.set_title(title, fontsize=8)
    ax.axis("off")
    return png_data_url(fig)


class NavPanel:
    key = "FluoNav"
    title = "FluoNav: surface and navigation"
    icon = "mdi-crosshairs-gps"
    # the inputs every button of the panel sends with its click (app.submit)
    FORM = ("nav_target_triangles", "nav_seconds")

    def __init__(self, app, logic):
        self.app = app
        self.logic = logic
        s = app.state
        s.nav_target_triangles = 62000
        s.nav_surface_info = ""
        s.nav_frame = None
        s.nav_frames_shown = 0
        s.nav_seconds = 8
        self._frames = queue.Queue(maxsize=4)
        app.ctrl.nav_build_surface = app.guarded(self.build_surface)
        app.ctrl.nav_stream = app.guarded(self.stream)

    def build_surface(self):
        s = self.app.state
        target = int(s.nav_target_triangles) if s.nav_target_triangles else None
        # the scene's label map: the phantom's CBCTLabels, or the map the user
        # loaded in the tomography panel (whatever its name)
        labels = (mrml_io.get_node(self.app.scene, "CBCTLabels", "vtkMRMLLabelMapVolumeNode",
                                   required=False)
                  or next(iter(mrml_io.nodes(self.app.scene, "vtkMRMLLabelMapVolumeNode")), None))
        if labels is None:
            raise FluoInputError("the scene has no label map: load the phantom or your own "
                                 "label map (FluoTomo panel) first", field="label map")
        model = self.logic.buildSurface(targetTriangles=target, labelMapNode=labels)
        model.GetDisplayNode().SetOpacity(0.6)
        self.app.show_in_3d(model)
        poly = model.GetPolyData()
        s.nav_surface_info = (f"TissueSurface of {labels.GetName()}: {poly.GetNumberOfCells()} "
                              f"triangles, {poly.GetNumberOfPoints()} points")
        self.app.render_all(reset_3d=True)
        self.app.notify(s.nav_surface_info, "success")

    def stream(self):
        """Track with the simulated NDI tracker (``FluoNavLogic.connectTracker``)
        and show the oral-cavity phantom's frames rendered at the tracked pose and
        corrected (``FluoNavLogic.streamPhantomFrames``: the tracker's own loop),
        as a background job.

        The simulated operating room lives in a scene of its own, so the app's
        scene keeps the user's data; the app's scene gets the tracked camera
        (``CameraToolToTracker``, ``FluoNavCamera``). It runs for
        ``nav_seconds`` from its first frame or until Stop: stopping a stream ends
        it normally, with its summary."""
        from fluoguide.errors import check_number

        seconds = check_number("seconds", float(self.app.state.nav_seconds or 0), 0.0, 3600.0,
                               lo_open=True)
        frames = self._frames
        self.logic.connectTracker("ndi-sim", phantomCamera=True)
        self.app.state.nav_frames_shown = 0     # counts this stream's frames

        def show(frame):
            r, c = frame["result"], frame["contours"]
            raw, cor = c["miss_rate_raw_pct"], c["miss_rate_corrected_pct"]
            item = {"raw": _image_url(r.counts - r.offset_adu, r.hits.visible,
                                      c["raw_contour"], f"raw (miss {raw:.1f} %)"),
                    "corrected": _image_url(r.transport, r.mapped, c["corrected_contour"],
                                            f"corrected T (miss {cor:.1f} %)"),
                    "frame": frame["trackerFrame"], "pose": frame["cameraPose"].tolist(),
                    "miss_raw": round(raw, 1), "miss_corrected": round(cor, 1)}
            try:
                frames.put_nowait(item)
            except queue.Full:
                pass          # the UI is behind: drop

        def work(progress, cancel):
            try:
                return self.logic.streamPhantomFrames(seconds, show, progress, cancel)
            finally:
                self.logic.disconnect()     # on an error or cancel too

        def done(result):
            how = "Stream stopped after" if result["stopped"] else "Streamed"
            self.app.notify(f"{how} {result['frames']} corrected frames from "
                            f"{result['tracker_frames']} tracker frames (unreported losses: "
                            f"{result['lost_unreported']})", "success")

        self.app.start_job("tracked stream", work, on_done=done, owner="FluoNav")

    def on_poll(self):
        """Show the newest streamed frame (called by the app's poll loop)."""
        item = None
        while True:
            try:
                item = self._frames.get_nowait()
            except queue.Empty:
                break
        if item is None:
            return
        s = self.app.state
        s.nav_frame = {k: v for k, v in item.items() if k != "pose"}
        s.nav_frames_shown = int(s.nav_frames_shown or 0) + 1
        self.logic.applyPoses({"CameraToolToTracker": np.asarray(item["pose"])})
        if mrml_io.get_node(self.app.scene, "FluoNavCamera", required=False) is None:
            self.app.show_in_3d(self.logic.showTrackedCamera())
        self.app.render_all()

    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        html.Div("FluoNav", classes="text-h6")
        html.Div("Tissue surface (for per-pixel ray casting)", classes="text-subtitle-2 mt-2")
        v.VTextField(v_model_number=("nav_target_triangles",), type="number",
                     label="Target triangles (0 = keep all)", density="compact", hide_details=True,
                     id="nav-triangles")
        v.VBtn("Surface from the label map", click=self.app.submit("nav_build_surface", self.FORM),
               block=True, classes="mt-2", disabled=("job.running",), id="nav-surface")
        html.Div("{{ nav_surface_info }}", classes="text-caption", id="nav-surface-info")
        html.Div("Tracked fluorescence (simulated NDI tracker, oral-cavity phantom)",
                 classes="text-subtitle-2 mt-4")
        v.VTextField(v_model_number=("nav_seconds",), type="number", label="Seconds",
                     density="compact", hide_details=True, id="nav-seconds")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Stream", click=self.app.submit("nav_stream", self.FORM),
                       block=True, color="primary", disabled=("job.running",), id="nav-stream")
            with v.VCol(cols=4):
                v.VBtn("Stop", click=self.app.ctrl.fluo_cancel_job, block=True,
                       disabled=("!job.running",), id="nav-stop")
        html.Div("frames shown: {{ nav_frames_shown }}", classes="text-caption", id="nav-count")
        with html.Div(v_if="nav_frame", id="nav-images"):
            html.Div("tracker frame {{ nav_frame.frame }}: miss rate raw {{ nav_frame.miss_raw }} % "
                     "-> corrected {{ nav_frame.miss_corrected }} %", classes="text-caption")
            html.Img(src=("nav_frame.raw",), style="width: 100%; background: white;", id="nav-raw")
            html.Img(src=("nav_frame.corrected",), style="width: 100%; background: white;",
                     id="nav-corrected")
