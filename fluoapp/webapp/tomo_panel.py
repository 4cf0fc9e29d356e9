"""FluoTomo panel: CBCT -> segmentation -> mesh -> reconstruction -> overlay.

Every action calls :class:`FluoTomoLogic` (the same logic the desktop widget and
the tests use); the panel only holds UI state.
"""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError

__all__ = ["TomoPanel"]

# Default threshold segments for the bundled cylinder-tube phantom [HU]: liquid
# (water, 0 HU) against air (-1000), and the ICG tube (150 HU) inside it; 60 HU
# rather than the midpoint keeps the blurred 2.4 mm tube at its true volume
# (390 vs 407 mm^3; 75 HU gives 312).
DEFAULT_SEGMENTS = [("liquid", -500.0, 3000.0), ("tube", 60.0, 3000.0)]

# Segment colours are cool (blue, green, cyan, violet): the yield overlay uses the
# warm Iron colour map, and a randomly coloured red or orange segment would be
# mistaken for fluorescence.  Cycled in order of creation.
SEGMENT_COLORS_RGB = [(0.62, 0.62, 0.92), (0.35, 0.85, 0.45), (0.30, 0.75, 0.85),
                      (0.60, 0.45, 0.85), (0.25, 0.50, 0.90), (0.45, 0.80, 0.70)]


class TomoPanel:
    key = "FluoTomo"
    title = "FluoTomo: segment, mesh, reconstruct"
    icon = "mdi-cube-scan"

    def __init__(self, app, logic):
        self.app = app
        self.logic = logic
        s = app.state
        s.tomo_phantom = "cylinder-tube"
        s.tomo_depth_mm = 4.7
        s.tomo_seg_name = DEFAULT_SEGMENTS[0][0]
        s.tomo_seg_min = DEFAULT_SEGMENTS[0][1]
        s.tomo_seg_max = DEFAULT_SEGMENTS[0][2]
        s.tomo_segments = []
        s.tomo_regions = []
        s.tomo_mesh_size_mm = 1.0
        s.tomo_mesh_roi = ""            # x0,x1,y0,y1,z0,z1 mm; empty = the phantom's default
        s.tomo_mesh_method = "fast (structured)"
        s.tomo_mesh_info = ""
        s.tomo_method = "HP"
        s.tomo_lambda = 10.0
        s.tomo_result = None
        s.tomo_threshold = 0.3
        s.tomo_colorbar = {"min": 0.0, "max": 1.0, "gradient": ""}
        s.tomo_loaded = False
        s.tomo_has_labels = False
        c = app.ctrl
        g = app.guarded
        c.tomo_load = g(self.load_phantom)
        c.tomo_threshold_segment = g(self.threshold_segment)
        c.tomo_use_segmentation = g(self.use_segmentation)
        c.tomo_build_mesh = g(self.build_mesh)
        c.tomo_reconstruct = g(self.reconstruct)
        s.change("tomo_threshold")(g(self._on_threshold))
        self._yield_node_name = None

    # -- actions -------------------------------------------------------------
    def load_phantom(self):
        s = self.app.state
        params = {"depth_mm": float(s.tomo_depth_mm)} if s.tomo_phantom == "cylinder-tube" else {}
        for name in ("CBCT", "CBCTLabels", "FluoTomoMeshSurface", "FluoTomoSources",
                     "FluoTomoDetectors", "FluoTomoYieldSurface"):
            mrml_io.remove_node(self.app.scene, name)
        for n in list(mrml_io.nodes(self.app.scene, "vtkMRMLSegmentationNode")):
            self.app.scene.RemoveNode(n)
        truth = self.logic.loadPhantom(s.tomo_phantom, withLabels=False, **params)
        self.app.show_cbct()
        s.tomo_loaded = True
        s.tomo_has_labels = False
        s.tomo_segments = []
        s.tomo_regions = []
        s.tomo_result = None
        self.app.notify(f"Loaded the {truth['phantom']} phantom CBCT "
                        f"({' x '.join(map(str, truth['shape_kji'][::-1]))} voxels). "
                        "Next: segment it by threshold.", "success")

    def _editor(self):
        return self.app.slicer_app.segmentation_editor

    def threshold_segment(self):
        """Add a segment from an HU range with trame-slicer's threshold effect."""
        from trame_slicer.segmentation import SegmentationEffectThreshold

        s = self.app.state
        lo, hi = float(s.tomo_seg_min), float(s.tomo_seg_max)
        if not lo < hi:
            raise FluoInputError("threshold minimum must be below the maximum", field="threshold",
                                 value=(lo, hi))
        editor = self._editor()
        if editor.active_segmentation_node is None:
            raise FluoInputError("load a CBCT first", field="CBCT")
        name = str(s.tomo_seg_name or f"segment {editor.n_segments + 1}")
        color = SEGMENT_COLORS_RGB[editor.n_segments % len(SEGMENT_COLORS_RGB)]
        sid = editor.add_empty_segment(segment_name=name, segment_color=list(color))
        editor.set_active_segment_id(sid)
        effect = editor.set_active_effect_type(SegmentationEffectThreshold)
        effect.set_threshold_min_max_values((lo, hi))
        effect.apply()
        editor.deactivate_effect()
        vox = editor.get_segment_labelmap(sid, as_numpy_array=True)
        n_vox = int(np.count_nonzero(vox)) if vox is not None else 0
        if n_vox == 0:
            editor.remove_segment(sid)
            raise FluoInputError("no voxel of the CBCT in this HU range", field="threshold",
                                 value=(lo, hi))
        s.tomo_segments = editor.get_segment_names()
        # offer the next default segment
        names = [d[0] for d in DEFAULT_SEGMENTS]
        if name in names and names.index(name) + 1 < len(names):
            nxt = DEFAULT_SEGMENTS[names.index(name) + 1]
            s.tomo_seg_name, s.tomo_seg_min, s.tomo_seg_max = nxt
        self.app.render_all()
        self.app.notify(f"Segment '{name}': {n_vox} voxels in [{lo:g}, {hi:g}] HU", "success")

    def use_segmentation(self):
        editor = self._editor()
        node = editor.active_segmentation_node
        if node is None:
            raise FluoInputError("no segmentation yet", field="segmentation")
        regions = self.logic.segmentationToLabels(node)
        s = self.app.state
        s.tomo_regions = [{"label": k, "name": v[0], "volume_mm3": round(v[1], 1)}
                          for k, v in regions.items()]
        s.tomo_has_labels = True
        self.app.notify("Label map CBCTLabels: " + ", ".join(
            f"{k} = {v[0]} ({v[1]:.0f} mm³)" for k, v in regions.items()), "success")

    def build_mesh(self):
        s = self.app.state
        size = float(s.tomo_mesh_size_mm)
        if not 0.3 <= size <= 5.0:
            raise FluoInputError("mesh size must be within 0.3..5 mm", field="mesh size", value=size)
        quality = str(s.tomo_mesh_method).startswith("quality")
        job = self.logic.prepareMesh(sizeMm=size, roi=self._roi(), quality=quality)

        def done(mesh):
            self.logic.storeMesh(mesh)
            node = mrml_io.get_node(self.app.scene, "FluoTomoMeshSurface")
            node.GetDisplayNode().SetOpacity(0.35)
            self.app.show_in_3d(node)
            s.tomo_mesh_info = (f"{mesh.n_nodes} nodes, {mesh.n_elements} tetrahedra "
                                f"at {size:g} mm ({'fTetWild' if quality else 'structured'})")
            self.app.render_all(reset_3d=True)

        self.app.start_job("mesh", job, on_done=done)

    def _roi(self):
        """The ROI typed by the user, else that of the cylinder-tube reconstruction."""
        text = str(self.app.state.tomo_mesh_roi or "").strip()
        if text:
            try:
                roi = [float(v) for v in text.split(",")]
            except ValueError:
                raise FluoInputError("expected x0,x1,y0,y1,z0,z1 in mm", field="ROI",
                                     value=text) from None
            if len(roi) != 6 or any(roi[2 * k] >= roi[2 * k + 1] for k in range(3)):
                raise FluoInputError("expected x0<x1, y0<y1, z0<z1 (six numbers, mm)",
                                     field="ROI", value=text)
            return tuple(roi)
        return self._default_roi()

    def _default_roi(self):
        """Region of interest of the cylinder-tube reconstruction (as in the demo)."""
        truth = mrml_io.get_json_attribute(mrml_io.get_node(self.app.scene, "CBCT"),
                                           "FluoGuide.Truth") or {}
        geo = truth.get("geometry", {})
        depth = float(geo.get("liquid_depth_mm", 20.0))
        return (-15.0, 15.0, -25.0, 25.0, -depth, 0.0)

    def reconstruct(self):
        s = self.app.state
        lam = float(s.tomo_lambda)
        if not (np.isfinite(lam) and lam > 0):
            raise FluoInputError("lambda must be a positive number", field="lambda", value=lam)
        method = str(s.tomo_method)
        job = self.logic.prepareTubeReconstruction(methods=(method,), lam=lam)

        def done(run):
            from fluoapp.webapp.scene_display import glyph_points_model

            self.logic.storeReconstruction(run, job.grid)
            res = run["results"][method]
            warnings = list(res.get("warnings") or [])
            self._yield_node_name = f"FluoTomoYield{method}"
            s.tomo_result = {
                "warnings": warnings,
                "method": method, "peak": f"{res['peak']:.4g}", "true_peak": f"{res['true_peak']:.4g}",
                "peak_error_pct": round(res["peak_error_pct"], 1),
                "centroid_mm": round(res["centroid_mm"], 2),
                "true_centroid_mm": round(res["true_centroid_mm"], 2),
                "seconds": round(run["timings"]["total"], 1),
            }
            glyph_points_model(self.app.scene, "FluoTomoSources", run["sources_reported_mm"],
                               color=(1.0, 0.25, 0.2))
            glyph_points_model(self.app.scene, "FluoTomoDetectors", run["detectors_mm"],
                               radius_mm=0.35, color=(0.2, 0.9, 0.3))
            self._show_yield()
            text = (f"{method}: peak yield error {res['peak_error_pct']:+.1f} %, "
                    f"centroid {res['centroid_mm']:.2f} mm (true "
                    f"{res['true_centroid_mm']:.2f}) in {run['timings']['total']:.1f} s")
            self.app.notify(text + "".join(f"; warning: {w}" for w in warnings),
                            "warning" if warnings else "success")

        self.app.start_job(f"reconstruction {method}", job, on_done=done)

    # -- display -------------------------------------------------------------
    def _show_yield(self):
        from fluoapp.webapp.scene_display import colormap_css_gradient, isosurface_model, style_yield_volume

        if not self._yield_node_name:
            return
        scene = self.app.scene
        node = mrml_io.get_node(scene, self._yield_node_name)
        vmin, vmax, thr = style_yield_volume(scene, node, float(self.app.state.tomo_threshold))
        self.app.show_foreground(node, opacity=0.8)
        # the segmentation's fill would hide the overlay: keep its outline only
        for seg in mrml_io.nodes(scene, "vtkMRMLSegmentationNode"):
            d = seg.GetDisplayNode()
            if d is not None:
                d.SetOpacity2DFill(0.0)
                d.SetOpacity2DOutline(0.5)
        # move every slice through the brightest voxel of the result
        arr = mrml_io.volume_array(node)
        k, j, i = np.unravel_index(int(np.argmax(arr)), arr.shape)
        import vtk

        m = vtk.vtkMatrix4x4()
        node.GetIJKToRASMatrix(m)
        ras = m.MultiplyPoint((float(i), float(j), float(k), 1.0))[:3]
        for sn in mrml_io.nodes(scene, "vtkMRMLSliceNode"):
            sn.JumpSliceByOffsetting(*ras)
        mrml_io.remove_node(scene, "FluoTomoYieldSurface")
        iso = isosurface_model(scene, "FluoTomoYieldSurface", node, thr)
        for name in ("FluoTomoMeshSurface", "FluoTomoSources", "FluoTomoDetectors"):
            m = mrml_io.get_node(scene, name, required=False)
            if m is not None:
                self.app.show_in_3d(m)
        if iso is not None:
            self.app.show_in_3d(iso)
        mesh = mrml_io.get_node(scene, "FluoTomoMeshSurface", required=False)
        if mesh is not None:
            mesh.GetDisplayNode().SetOpacity(0.25)
        self.app.state.tomo_colorbar = {"min": f"{vmin:.3g}", "max": f"{vmax:.3g}",
                                        "threshold": f"{thr:.3g}",
                                        "gradient": colormap_css_gradient(scene)}
        self.app.render_all(reset_3d=True)

    def _on_threshold(self, tomo_threshold=None, **_):
        if self._yield_node_name and mrml_io.get_node(self.app.scene, self._yield_node_name,
                                                      required=False) is not None:
            self._show_yield()

    # -- UI ------------------------------------------------------------------
    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("FluoTomo", classes="text-h6")
        html.Div("1. CBCT", classes="text-subtitle-2 mt-2")
        v.VSelect(v_model=("tomo_phantom",), items=(["cylinder-tube", "oral-cavity", "slab"],),
                  label="Digital phantom", density="compact", hide_details=True, id="tomo-phantom")
        v.VTextField(v_model_number=("tomo_depth_mm",), type="number", label="Tube depth [mm]",
                     density="compact", hide_details=True, classes="mt-2",
                     v_if="tomo_phantom === 'cylinder-tube'", id="tomo-depth")
        v.VBtn("Load phantom", click=self.app.ctrl.tomo_load, block=True, classes="mt-2",
               color="primary", disabled=(busy,), id="tomo-load")

        html.Div("2. Segment the CBCT", classes="text-subtitle-2 mt-4")
        with v.VRow(dense=True):
            with v.VCol(cols=4):
                v.VTextField(v_model=("tomo_seg_name",), label="Segment", density="compact",
                             hide_details=True, id="tomo-seg-name")
            with v.VCol(cols=4):
                v.VTextField(v_model_number=("tomo_seg_min",), type="number", label="min HU",
                             density="compact", hide_details=True, id="tomo-seg-min")
            with v.VCol(cols=4):
                v.VTextField(v_model_number=("tomo_seg_max",), type="number", label="max HU",
                             density="compact", hide_details=True, id="tomo-seg-max")
        v.VBtn("Add segment by threshold", click=self.app.ctrl.tomo_threshold_segment, block=True,
               classes="mt-2", disabled=("!tomo_loaded || " + busy,), id="tomo-threshold")
        html.Div("Segments: {{ tomo_segments.join(', ') || 'none' }}. Paint, erase, islands and "
                 "smoothing: the brush tool on the left.", classes="text-caption mt-1",
                 id="tomo-segments")
        v.VBtn("Use segmentation as label map", click=self.app.ctrl.tomo_use_segmentation,
               block=True, classes="mt-2", disabled=("!tomo_segments.length || " + busy,),
               id="tomo-labels")
        html.Div("{{ tomo_regions.map(r => r.label + ': ' + r.name + ' ' + r.volume_mm3 + "
                 "' mm³').join(', ') }}", classes="text-caption", id="tomo-regions")

        html.Div("3. Mesh", classes="text-subtitle-2 mt-4")
        v.VTextField(v_model_number=("tomo_mesh_size_mm",), type="number",
                     label="Element size [mm] (structured, region-preserving)", density="compact",
                     hide_details=True, id="tomo-mesh-size")
        v.VBtn("Build mesh", click=self.app.ctrl.tomo_build_mesh, block=True, classes="mt-2",
               disabled=("!tomo_has_labels || " + busy,), id="tomo-mesh")
        v.VSelect(v_model=("tomo_mesh_method",),
                  items=(["fast (structured)", "quality (fTetWild, slower)"],), label="Mesher",
                  density="compact", hide_details=True, classes="mt-2", id="tomo-mesh-method")
        v.VTextField(v_model=("tomo_mesh_roi",), label="ROI x0,x1,y0,y1,z0,z1 [mm] (empty: "
                     "around the tube)", density="compact", hide_details=True, classes="mt-2",
                     id="tomo-mesh-roi")
        html.Div("{{ tomo_mesh_info }}", classes="text-caption", id="tomo-mesh-info")

        html.Div("4. Reconstruct (simulated tracked laser scan)", classes="text-subtitle-2 mt-4")
        with v.VRow(dense=True):
            with v.VCol(cols=6):
                v.VSelect(v_model=("tomo_method",), items=(["NP", "SP", "HP"],), label="Priors",
                          density="compact", hide_details=True, id="tomo-method")
            with v.VCol(cols=6):
                v.VTextField(v_model_number=("tomo_lambda",), type="number", label="lambda",
                             density="compact", hide_details=True, id="tomo-lambda")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Reconstruct", click=self.app.ctrl.tomo_reconstruct, block=True,
                       color="primary", disabled=("!tomo_has_labels || " + busy,), id="tomo-recon")
            with v.VCol(cols=4):
                v.VBtn("Cancel", click=self.app.ctrl.fluo_cancel_job, block=True,
                       disabled=("!" + busy,), id="tomo-cancel")
        v.VProgressLinear(model_value=("job.fraction * 100",), height=6, classes="mt-2",
                          color=("job.error ? 'error' : 'primary'",), id="tomo-progress")
        html.Div("{{ job.name }} {{ job.message }} {{ job.running ? '(' + job.seconds + ' s)' : '' }}",
                 classes="text-caption", id="tomo-job")
        with html.Div(v_if="tomo_result", classes="text-caption mt-1", id="tomo-result"):
            html.Div("{{ tomo_result.method }}: peak {{ tomo_result.peak }} /mm (true "
                     "{{ tomo_result.true_peak }}), error {{ tomo_result.peak_error_pct }} %")
            html.Div("centroid depth {{ tomo_result.centroid_mm }} mm (true "
                     "{{ tomo_result.true_centroid_mm }}), {{ tomo_result.seconds }} s")
            html.Div("warning: {{ w }}", v_for="w in tomo_result.warnings",
                     classes="text-warning")

        html.Div("5. Display", classes="text-subtitle-2 mt-4")
        v.VSlider(v_model=("tomo_threshold",), min=0.0, max=0.95, step=0.05,
                  label="Threshold (fraction of max)", density="compact", hide_details=True,
                  disabled=("!tomo_result",), id="tomo-threshold-slider")
        with html.Div(v_if="tomo_result", id="tomo-colorbar", classes="mt-1"):
            html.Div(style=("{height: '14px', background: tomo_colorbar.gradient, "
                            "borderRadius: '3px'}",))
            with html.Div(style="display:flex; justify-content: space-between;",
                          classes="text-caption"):
                html.Span("{{ tomo_colorbar.min }}")
                html.Span("yield [1/mm], shown above {{ tomo_colorbar.threshold }}")
                html.Span("{{ tomo_colorbar.max }}")
