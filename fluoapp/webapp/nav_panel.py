"""FluoNav panel: the tissue surface in 3D, and a stream of tracked frames
(simulated NDI tracker + rendered oral-cavity frames) shown raw and corrected
side by side with their 40 % contours, the tracked camera in 3D."""

from __future__ import annotations

import queue

import numpy as np

from fluoguide import mrml_io

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
        model = self.logic.buildSurface(targetTriangles=target)
        model.GetDisplayNode().SetOpacity(0.6)
        self.app.show_in_3d(model)
        poly = model.GetPolyData()
        s.nav_surface_info = (f"TissueSurface: {poly.GetNumberOfCells()} triangles, "
                              f"{poly.GetNumberOfPoints()} points")
        self.app.render_all(reset_3d=True)
        self.app.notify(s.nav_surface_info, "success")

    def stream(self):
        """Track with the simulated NDI tracker and render/correct frames of the
        oral-cavity phantom at the tracked pose (background job) for ``nav_seconds``
        or until Stop: stopping a stream ends it normally, with its summary."""
        from FluoCalibLib.geometry import transforms as tf
        from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera
        from FluoNavLib.mapping.contours import miss_rate
        from FluoNavLib.mapping.flux_map import transport_image
        from FluoNavLib.mapping.synthetic import (
            coupled_light,
            open_field_camera,
            oral_cavity_surface,
            render_view,
        )
        from FluoNavLib.devices.ndi_client import NDIClient
        from FluoNavLib.devices.ndi_simulator import NDISimulator, SimTool

        from fluoguide.errors import check_number

        seconds = check_number("seconds", float(self.app.state.nav_seconds or 0), 0.0, 3600.0,
                               lo_open=True)
        frames = self._frames
        self.app.state.nav_frames_shown = 0     # counts this stream's frames

        def work(progress, cancel):
            caster, poly = oral_cavity_surface(20000)
            cam = open_field_camera(binning=8)
            cone = coupled_light()
            rc = RadiometricCamera(gain_adu_per_e=1.0)
            # the simulated camera tool circles 120 mm above the cavity
            tool = SimTool("CameraTool", centre_mm=(0.0, 0.0, 100.0), amplitude_mm=(25.0, 25.0, 5.0),
                           period_s=(6.0, 6.0, 9.0), noise_mm=0.05)
            sim = NDISimulator(tools=[tool])
            port = sim.start()
            shown = 0
            stopped = False
            try:
                with NDIClient(port) as client:
                    client.initialize([b"camera tool" * 4])
                    client.start()
                    import time

                    t_end = time.monotonic() + seconds
                    while time.monotonic() < t_end:
                        if cancel is not None and cancel.cancelled:
                            stopped = True      # Stop ends a live stream; it is no failure
                            break
                        reply = None
                        while reply is None:
                            reply = client.poll()
                        p = reply.tools.get(1)
                        if p is None or p.state != "OK":
                            continue
                        eye = p.translation_mm
                        pose = tf.look_at(eye, [0.0, 0.0, -20.0], up=(0.0, 1.0, 0.0))
                        counts, hits, vm = render_view(caster, cam, pose, cone, 0.3, rc, seed=shown)
                        S = counts - rc.offset_adu
                        T, ok = transport_image(S, vm, cone)
                        raw, rc_in, _ = miss_rate(S, hits.visible)
                        cor, ct_in, _ = miss_rate(T, ok)
                        item = {"raw": _image_url(S, hits.visible, rc_in, f"raw (miss {raw:.1f} %)"),
                                "corrected": _image_url(T, ok, ct_in, f"corrected T (miss {cor:.1f} %)"),
                                "frame": int(p.frame), "pose": pose.tolist(),
                                "miss_raw": round(raw, 1), "miss_corrected": round(cor, 1)}
                        try:
                            frames.put_nowait(item)
                        except queue.Full:
                            pass          # the UI is behind: drop, counted below
                        shown += 1
                        progress(min(1.0, 1 - (t_end - time.monotonic()) / seconds), f"frame {p.frame}")
                    client.stop()
                    stats = client.stats
            finally:
                sim.stop()
            return {"frames": shown, "tracker_frames": stats.frames,
                    "lost_unreported": stats.lost_unreported(), "stopped": stopped}

        def done(result):
            how = "Stream stopped after" if result["stopped"] else "Streamed"
            self.app.notify(f"{how} {result['frames']} corrected frames from "
                            f"{result['tracker_frames']} tracker frames (unreported losses: "
                            f"{result['lost_unreported']})", "success")

        self.app.start_job("tracked stream", work, on_done=done)

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
        m = np.asarray(item["pose"])
        mrml_io.set_transform(self.app.scene, "CameraToolToTracker", m)
        cam = mrml_io.get_node(self.app.scene, "FluoNavCamera", required=False)
        if cam is None:
            import vtk

            cone = vtk.vtkConeSource()
            cone.SetHeight(20.0)
            cone.SetRadius(8.0)
            cone.SetDirection(0, 0, -1)
            cone.SetCenter(0, 0, 10.0)
            cone.Update()
            cam = mrml_io.add_model(self.app.scene, "FluoNavCamera", cone.GetOutput(), color=(0.2, 0.8, 1.0))
            cam.SetAndObserveTransformNodeID(mrml_io.get_node(self.app.scene, "CameraToolToTracker").GetID())
            self.app.show_in_3d(cam)
        self.app.render_all()

    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        html.Div("FluoNav", classes="text-h6")
        html.Div("Tissue surface (for per-pixel ray casting)", classes="text-subtitle-2 mt-2")
        v.VTextField(v_model_number=("nav_target_triangles",), type="number",
                     label="Target triangles (0 = keep all)", density="compact", hide_details=True,
                     id="nav-triangles")
        v.VBtn("Surface from CBCTLabels", click=self.app.ctrl.nav_build_surface, block=True,
               classes="mt-2", disabled=("job.running",), id="nav-surface")
        html.Div("{{ nav_surface_info }}", classes="text-caption", id="nav-surface-info")
        html.Div("Tracked fluorescence (simulated NDI tracker, oral-cavity phantom)",
                 classes="text-subtitle-2 mt-4")
        v.VTextField(v_model_number=("nav_seconds",), type="number", label="Seconds",
                     density="compact", hide_details=True, id="nav-seconds")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Stream", click=self.app.ctrl.nav_stream, block=True, color="primary",
                       disabled=("job.running",), id="nav-stream")
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
