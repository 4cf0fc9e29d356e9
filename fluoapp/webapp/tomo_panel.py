"""FluoTomo panel: CBCT -> segmentation -> mesh -> reconstruction -> overlay.

Every action calls :class:`FluoTomoLogic` (the same logic the desktop widget and
the tests use); the panel only holds UI state.
"""

from __future__ import annotations

from pathlib import Path

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
    # the inputs every button of the panel sends with its click (app.submit)
    FORM = ("tomo_phantom", "tomo_depth_mm", "tomo_cbct_path", "tomo_cbct_series",
            "tomo_own_labels", "tomo_own_optics", "tomo_own_acquisition", "tomo_plan_targets",
            "tomo_plan_positions", "tomo_seg_name", "tomo_seg_min", "tomo_seg_max",
            "tomo_labels_out", "tomo_mesh_method", "tomo_mesh_roi", "tomo_mesh_size_mm",
            "tomo_method", "tomo_lambda")

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
        # a CBCT of the user's: a volume file, a scene or a DICOM series folder
        s.tomo_cbct_path = ""
        s.tomo_cbct_series = ""        # SeriesInstanceUID when the folder holds several
        s.tomo_labels_out = "labels.nrrd"
        # the user's own scene: a label map file, optics.json, an acquisition folder
        s.tomo_own_labels = ""
        s.tomo_own_optics = ""
        s.tomo_own_acquisition = ""
        s.tomo_own = False             # the own-scene route is active
        s.tomo_own_info = ""
        s.tomo_own_result = None
        # the scan planner on the user's scene (issue #36): targets, positions, its result
        s.tomo_plan_targets = ""       # labels, comma-separated; empty: every inclusion
        s.tomo_plan_positions = 16
        s.tomo_plan_result = None
        self._own = None               # {"label": node id, "optics": Optics, "acquisition": ...}
        self._mesh_node_id = None
        c = app.ctrl
        g = app.guarded
        c.tomo_load = g(self.load_phantom)
        c.tomo_load_cbct = g(self.load_cbct)
        c.tomo_save_labels = g(self.save_labels)
        c.tomo_threshold_segment = g(self.threshold_segment)
        c.tomo_use_segmentation = g(self.use_segmentation)
        c.tomo_build_mesh = g(self.build_mesh)
        c.tomo_reconstruct = g(self.reconstruct)
        c.tomo_load_own = g(self.load_own)
        c.tomo_plan = g(self.plan_scan)
        s.change("tomo_threshold")(g(self._on_threshold))
        self._yield_node_name = None

    # -- actions -------------------------------------------------------------
    def _clear_cbct(self):
        """Remove the CBCT, its labels, segmentations and results shown."""
        for name in ("CBCT", "CBCTLabels", "FluoTomoMeshSurface", "FluoTomoSources",
                     "FluoTomoDetectors", "FluoTomoYieldSurface"):
            mrml_io.remove_node(self.app.scene, name)
        for n in list(mrml_io.nodes(self.app.scene, "vtkMRMLSegmentationNode")):
            self.app.scene.RemoveNode(n)

    def _cbct_shown(self):
        """The state after a CBCT (a phantom's or the user's) is loaded and shown."""
        s = self.app.state
        self.app.show_cbct()
        self._own = None
        self._mesh_node_id = None
        s.tomo_own = False
        s.tomo_own_result = None
        s.tomo_loaded = True
        s.tomo_has_labels = False
        s.tomo_segments = []
        s.tomo_regions = []
        s.tomo_result = None

    def load_phantom(self):
        s = self.app.state
        params = {"depth_mm": float(s.tomo_depth_mm)} if s.tomo_phantom == "cylinder-tube" else {}
        self._clear_cbct()
        truth = self.logic.loadPhantom(s.tomo_phantom, withLabels=False, **params)
        self._cbct_shown()
        self.app.notify(f"Loaded the {truth['phantom']} phantom CBCT "
                        f"({' x '.join(map(str, truth['shape_kji'][::-1]))} voxels). "
                        "Next: segment it by threshold.", "success")

    def load_cbct(self):
        """Load the user's CBCT: a volume file, a scene (its CBCT) or a DICOM
        series folder in the workspace (``FluoTomoLogic.importCbct``: the
        series by UID, slices along the normal, HU, geometry kept); read and
        checked before anything shown is replaced."""
        s = self.app.state
        text = str(s.tomo_cbct_path or "").strip()
        if not text:
            raise FluoInputError("give the CBCT's path (a file, a scene or a DICOM folder, "
                                 "relative to the workspace)", field="CBCT")
        path = self.app.workspace.path(text, "CBCT", what="path")
        if not path.exists():
            raise FluoInputError("CBCT not found", field="CBCT", value=text)
        series = str(s.tomo_cbct_series or "").strip() or None
        # read under another name first: a refused series leaves the scene as it was
        node = self.logic.importCbct(path, series, name="FluoTomoCBCTLoading")
        self._clear_cbct()
        node.SetName("CBCT")
        self._cbct_shown()
        fmt = mrml_io.get_json_attribute(node, "FluoGuide.Source", {}).get("format", "volume")
        dims = " x ".join(map(str, mrml_io.volume_array(node).shape[::-1]))
        self.app.notify(f"Loaded the CBCT {self.app.workspace.shown(path)} ({fmt}, {dims} "
                        "voxels). Next: segment it by threshold, then save the label map and "
                        "load it with optics.json and a recording (1b).", "success")

    def _phantom_only(self, step):
        """Refuse the phantom route's ``step`` on a CBCT without a phantom's truth
        (the user's): it has no simulated scan; its route is the saved label map
        with a recording (1b)."""
        cbct = mrml_io.get_node(self.app.scene, "CBCT", required=False)
        if cbct is not None and not mrml_io.get_json_attribute(cbct, "FluoGuide.Truth"):
            raise FluoInputError(f"your CBCT has no simulated scan to {step}: save its label "
                                 "map (step 2), then load it with optics.json and your "
                                 "recording or acquisition folder (1b)", field=step)

    def save_labels(self):
        """Write the label map made from the segmentation (``CBCTLabels``) to
        the workspace as NRRD, for the own-scene route (1b) and ``fluo tomo``."""
        s = self.app.state
        if mrml_io.get_node(self.app.scene, "CBCTLabels", required=False) is None:
            raise FluoInputError("no label map yet: use the segmentation as label map first",
                                 field="label map")
        path = self.app.workspace.path(s.tomo_labels_out, "label map file", writable=True)
        self.logic.writeLabelMapFile("CBCTLabels", path)
        shown = self.app.workspace.shown(path)
        s.tomo_own_labels = shown
        self.app.notify(f"Wrote the label map {shown}: give optics.json and a recording or "
                        "acquisition folder in 1b and load your scene.", "success")

    def load_own(self):
        """Load the user's label map file, optics.json and acquisition folder
        (paths relative to the workspace, as every path the UI takes);
        everything is checked now, one message if not."""
        s = self.app.state
        entries = {"label map": (s.tomo_own_labels, "file"), "optics": (s.tomo_own_optics, "file"),
                   "acquisition": (s.tomo_own_acquisition, "folder")}
        paths = {}
        for what, (text, kind) in entries.items():
            if not str(text or "").strip():
                raise FluoInputError(f"give the {what} path (relative to the workspace)",
                                     field=what)
            paths[what] = str(self.app.workspace.path(text, what, what=kind, must_exist=True))
        node = self.logic.loadLabelMap(paths["label map"])
        try:
            optics = self.logic.readOptics(paths["optics"])
            lm = self.logic.labelMap(node)
            optics.check_labels(lm.labels)
            frames_note = ""
            if (Path(paths["acquisition"]) / "recording.json").is_file():
                # a recorded laser scan (docs/recording.md): acquired here, every
                # frame not used named with its reason
                acq, _, info = self.logic.acquireRecording(node, optics, paths["acquisition"])
                rejected = "; ".join(f"{reason}: frames {', '.join(map(str, frames))}"
                                     for reason, frames in info["frames_rejected"].items())
                frames_note = (f"; recording: {info['frames_used']} of {info['frames']} frames "
                               "used" + (f" (not used, {rejected})" if rejected else ""))
            else:
                acq = self.logic.readAcquisition(paths["acquisition"], node, optics)
        except Exception:
            self.app.scene.RemoveNode(node)
            raise
        self._own = {"label": node.GetID(), "optics": optics, "acquisition": acq}
        self._mesh_node_id = None
        s.tomo_own = True
        s.tomo_has_labels = True
        s.tomo_loaded = True
        s.tomo_result = None
        s.tomo_own_result = None
        vols = lm.region_volumes()
        s.tomo_regions = [{"label": k, "name": optics.names.get(k, f"label {k}"),
                           "volume_mm3": round(v, 1)} for k, v in vols.items()]
        s.tomo_own_info = (f"{node.GetName()}: {' x '.join(map(str, lm.labels_kji.shape[::-1]))} "
                           f"voxels, labels {lm.labels}; {acq.n_measurements} measurements "
                           f"({len(acq.sources_ras_mm)} sources x "
                           f"{len(acq.detectors_ras_mm)} detectors){frames_note}")
        self.app.show_volume(node)
        self._show_own_labels(node, lm, optics)
        self.app.notify("Loaded your scene: " + s.tomo_own_info + ". Next: build the mesh.",
                        "success")

    def _show_own_labels(self, node, lm, optics):
        """The user's label map as a phantom's is shown: its tissue in grey tones
        (not the label table's saturated colours), each label as a segment with its
        outline in the slices and its surface in the 3D view from the start (the
        tissue translucent, the other labels solid)."""
        import vtk

        import slicer

        scene = self.app.scene
        top = max(lm.labels)
        target = lm.default_target()
        tones = mrml_io.get_node(scene, "FluoTomoLabelTones", required=False)
        if tones is None:
            tones = slicer.vtkMRMLColorTableNode()
            tones.SetName("FluoTomoLabelTones")
            tones.SetTypeToUser()
            scene.AddNode(tones)
        tones.SetNumberOfColors(top + 1)
        tones.SetColor(0, "air", 0.0, 0.0, 0.0, 0.0)
        for lab in range(1, top + 1):
            g = 0.6 if lab == target else 0.35
            tones.SetColor(lab, optics.names.get(lab, f"label {lab}"), g, g, g, 1.0)
        node.GetDisplayNode().SetAndObserveColorNodeID(tones.GetID())
        for old in list(mrml_io.nodes(scene, "vtkMRMLSegmentationNode")):
            if old.GetName() == f"{node.GetName()} segments":
                scene.RemoveNode(old)
        seg = slicer.vtkMRMLSegmentationNode()
        seg.SetName(f"{node.GetName()} segments")
        scene.AddNode(seg)
        seg.CreateDefaultDisplayNodes()
        seg.SetReferenceImageGeometryParameterFromVolumeNode(node)
        slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(node, seg)
        seg.CreateClosedSurfaceRepresentation()
        palette = [(0.95, 0.75, 0.2), (0.2, 0.85, 0.4), (0.95, 0.35, 0.35), (0.4, 0.6, 1.0)]
        display = seg.GetDisplayNode()
        segmentation = seg.GetSegmentation()
        ids = vtk.vtkStringArray()
        segmentation.GetSegmentIDs(ids)
        vols = lm.region_volumes()
        largest = max(vols, key=vols.get)
        for k in range(ids.GetNumberOfValues()):
            sid = ids.GetValue(k)
            segment = segmentation.GetSegment(sid)
            lab = int(segment.GetLabelValue()) if hasattr(segment, "GetLabelValue") else None
            if lab is None or lab not in vols:
                lab = lm.labels[k] if k < len(lm.labels) else largest
            segment.SetName(optics.names.get(lab, f"label {lab}"))
            tissue = lab == largest
            segment.SetColor(*((0.85, 0.65, 0.55) if tissue else palette[k % len(palette)]))
            display.SetSegmentOpacity3D(sid, 0.3 if tissue else 1.0)
        display.SetOpacity2DFill(0.0 if len(vols) > 1 else 0.2)
        display.SetOpacity2DOutline(1.0)
        self.app.show_in_3d(seg)
        self.app.render_all(reset_3d=True)

    def plan_scan(self):
        """Plan the laser's entry points on the user's scene (FluoTomoLogic.planScan)
        and draw them on the 3D surface with each target's predicted interval."""
        s = self.app.state
        node = self._own_label_node()
        lm = self.logic.labelMap(node)          # read on the event loop, not in the job
        optics = self._own["optics"]
        text = str(s.tomo_plan_targets or "").strip()
        try:
            targets = ([int(v) for v in text.split(",") if v.strip()] if text else
                       (lm.inclusion_labels()[:4] or [lm.default_target()]))
        except ValueError:
            raise FluoInputError("expected labels separated by commas", field="targets",
                                 value=text) from None
        try:
            positions = int(s.tomo_plan_positions)
        except (TypeError, ValueError):
            raise FluoInputError("must be an integer", field="positions",
                                 value=s.tomo_plan_positions) from None
        targets = self.logic.checkPlanInputs(lm, targets, positions)

        def job(progress=None, cancel=None):
            return self.logic.planScan(lm, optics, targets, positions, progress=progress,
                                       cancel=cancel)

        def done(plan):
            from fluoapp.webapp.scene_display import glyph_points_model

            scene = self.app.scene
            for name in ("FluoTomoPlannedSources", "FluoTomoPlannedDetectors"):
                mrml_io.remove_node(scene, name)
            src = glyph_points_model(scene, "FluoTomoPlannedSources", plan["sources_ras"],
                                     radius_mm=0.6, color=(0.85, 0.3, 0.9))
            det = glyph_points_model(scene, "FluoTomoPlannedDetectors", plan["detectors_ras"],
                                     radius_mm=0.3, color=(0.2, 0.9, 0.3))
            for m in (src, det):
                self.app.show_in_3d(m)
            hp = plan["predicted"]["HP"]
            dflt = (plan.get("default_scan_predicted") or {}).get("HP", {})
            rows = [{"label": t, "half_width": hp[t]["half_width_pct"],
                     "covered": hp[t]["covered"],
                     "default": (dflt.get(t) or {}).get("half_width_pct")} for t in hp]
            s.tomo_plan_result = {"positions": len(plan["sources_ras"]), "targets": rows,
                                  "pairs": int(plan["mask"].sum()),
                                  "warnings": "; ".join(plan["warnings"]) or "none"}
            self.app.render_all(reset_3d=False)
            text = ", ".join(f"label {r['label']} +-{r['half_width']:.3g} %" for r in rows)
            self.app.notify(f"Planned {len(plan['sources_ras'])} laser positions: predicted HP "
                            f"95 % interval (noise part) {text}"
                            + "".join(f"; warning: {w}" for w in plan["warnings"]),
                            "warning" if plan["warnings"] else "success")

        self.app.start_job("scan plan", job, on_done=done, owner="FluoTomo")

    def _own_label_node(self):
        node = self.app.scene.GetNodeByID(self._own["label"]) if self._own else None
        if node is None:
            raise FluoInputError("load a label map first", field="label map")
        return node

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
        # kept as fluo segment keeps a label: its largest component, holes filled
        kept, info = self.logic.cleanSegment(vox)
        if info["dropped_voxels"] or info["filled_voxels"]:
            editor.active_segment_modifier.set_segment_labelmap(sid, kept.astype(vox.dtype))
        n_vox = int(np.count_nonzero(kept))
        s.tomo_segments = editor.get_segment_names()
        # offer the next default segment
        names = [d[0] for d in DEFAULT_SEGMENTS]
        if name in names and names.index(name) + 1 < len(names):
            nxt = DEFAULT_SEGMENTS[names.index(name) + 1]
            s.tomo_seg_name, s.tomo_seg_min, s.tomo_seg_max = nxt
        self.app.render_all()
        self.app.notify(f"Segment '{name}': {n_vox} voxels in [{lo:g}, {hi:g}] HU (the largest "
                        f"of {info['components']} components, {info['dropped_voxels']} voxels "
                        f"dropped, {info['filled_voxels']} filled)", "success")

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
        if s.tomo_own:
            # the reconstruction mesh itself (its region of interest from the optodes)
            job = self.logic.prepareBuildMesh(self._own_label_node(), sizeMm=size,
                                              acquisition=self._own["acquisition"],
                                              optics=self._own["optics"], quality=quality)

            def done_own(built):
                node = self.logic.storeBuiltMesh(built)
                self._mesh_node_id = node.GetID()
                self._show_mesh(built["mesh_ras"], size, quality, used=not quality)

            self.app.start_job("mesh", job, on_done=done_own, owner="FluoTomo")
            return
        self._phantom_only("mesh")
        job = self.logic.prepareMesh(sizeMm=size, roi=self._roi(), quality=quality)

        def done(mesh):
            self.logic.storeMesh(mesh)
            self._show_mesh(mesh, size, quality, used=False)

        self.app.start_job("mesh", job, on_done=done, owner="FluoTomo")

    def _show_mesh(self, mesh, size, quality, used):
        """Mesh surface in 3D and its counts and region volumes in the panel; says
        whether the reconstruction uses this mesh or it is a preview."""
        s = self.app.state
        node = mrml_io.get_node(self.app.scene, "FluoTomoMeshSurface")
        node.GetDisplayNode().SetOpacity(0.35)
        self.app.show_in_3d(node)
        ref = mesh.meta.get("labelmap_volumes_mm3") or {}
        err = mesh.meta.get("volume_error_pct") or {}
        parts = []
        for label, r in sorted(ref.items()):
            parts.append(f"region {label}: {r:.0f} mm³ in the label map" + (
                f", mesh {err[label]:+.1f} % of the label map's" if label in err else ""))
        fit = mesh.meta.get("surface_fit_mm")
        if fit:
            parts.append(f"tissue-air nodes moved onto the smooth surface by up to "
                         f"{fit['max']:.2f} mm")
        role = ("the reconstruction uses this mesh" if used else
                "preview: the reconstruction meshes the scene itself (anchored and refined "
                "on the target; the mesh it used is shown after it runs)")
        s.tomo_mesh_info = (f"{mesh.n_nodes} nodes, {mesh.n_elements} tetrahedra at {size:g} mm "
                            f"({'fTetWild' if quality else 'structured'}); "
                            + "; ".join(parts) + f". {role}.")
        for w in mesh.meta.get("warnings", []):
            self.app.notify(w, "warning")
        self.app.render_all(reset_3d=True)

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
        if s.tomo_own:
            self._reconstruct_own(method, lam)
            return
        self._phantom_only("reconstruct")
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

        self.app.start_job(f"reconstruction {method}", job, on_done=done, owner="FluoTomo")

    def _reconstruct_own(self, method, lam):
        s = self.app.state
        mesh_node = (self.app.scene.GetNodeByID(self._mesh_node_id)
                     if self._mesh_node_id else None)
        job = self.logic.prepareReconstruction(self._own_label_node(), self._own["optics"],
                                               self._own["acquisition"], method=method, lam=lam,
                                               meshNode=mesh_node)

        def done(result):
            from fluoapp.webapp.scene_display import glyph_points_model

            node = self.logic.storeReconstructionResult(result)
            self._yield_node_name = node.GetName()
            sm = result["summary"]
            tgt = sm["target"]
            reg = sm["regions"].get(str(tgt), {}) if tgt is not None else {}
            s.tomo_own_result = {
                "method": method, "node": node.GetName(), "target": tgt,
                "yield": f"{reg.get('yield_per_mm', float('nan')):.4g}",
                "sd": f"{reg.get('sd_per_mm') or 0:.2g}",
                "ci95": ("not given (see the warnings)" if not reg.get("ci95_per_mm") else
                         "{:.3g} .. {:.3g}".format(*reg["ci95_per_mm"])),
                "peak": f"{sm['peak_yield_per_mm']:.4g}",
                "peak_ras": ", ".join(f"{v:.1f}" for v in sm["peak_ras_mm"]),
                "peak_label": sm["peak_label"],
                "centroid_ras": ", ".join(f"{v:.2f}" for v in (sm["target_centroid_ras_mm"] or [])),
                "nodes": sm["mesh"]["nodes"], "seconds": round(sm["seconds"], 1),
                "warnings": "; ".join(sm["warnings"]) or "none",
            }
            glyph_points_model(self.app.scene, "FluoTomoSources", result["sources_ras_mm"],
                               color=(1.0, 0.25, 0.2))
            glyph_points_model(self.app.scene, "FluoTomoDetectors", result["detectors_ras_mm"],
                               radius_mm=0.35, color=(0.2, 0.9, 0.3))
            self._show_yield()
            # a result with warnings is shown as one (it read "success" before)
            warnings = list(sm["warnings"])
            self.app.notify(f"{method}: label {tgt} yield {s.tomo_own_result['yield']} /mm, peak "
                            f"in label {sm['peak_label']}, {sm['seconds']:.1f} s"
                            + "".join(f"; warning: {w}" for w in warnings),
                            "warning" if warnings else "success")

        self.app.start_job(f"reconstruction {method}", job, on_done=done, owner="FluoTomo")

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
        """The panel's steps, top to bottom: the CBCT (a phantom or the user's,
        or a scene of one's own), planning, segmenting, the mesh, the
        reconstruction, the display."""
        from trame.widgets import html

        html.Div("FluoTomo", classes="text-h6")
        self._ui_cbct()
        self._ui_own_scene()
        self._ui_plan()
        self._ui_segment()
        self._ui_mesh()
        self._ui_reconstruct()
        self._ui_display()

    def _ui_cbct(self):
        """1: a digital phantom, or the user's CBCT (file, scene, DICOM folder)."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("1. CBCT", classes="text-subtitle-2 mt-2")
        v.VSelect(v_model=("tomo_phantom",), items=(["cylinder-tube", "oral-cavity", "slab"],),
                  label="Digital phantom", density="compact", hide_details=True, id="tomo-phantom")
        v.VTextField(v_model_number=("tomo_depth_mm",), type="number", label="Tube depth [mm]",
                     density="compact", hide_details=True, classes="mt-2",
                     v_if="tomo_phantom === 'cylinder-tube'", id="tomo-depth")
        v.VBtn("Load phantom", click=self.app.submit("tomo_load", self.FORM),
               block=True, classes="mt-2", color="primary", disabled=(busy,), id="tomo-load")
        # the workspace's CBCT: a DICOM series folder, a volume file or a scene
        v.VTextField(v_model=("tomo_cbct_path",), label="Or your CBCT: DICOM folder or file",
                     density="compact", hide_details=True, classes="mt-2", id="tomo-cbct-path")
        v.VTextField(v_model=("tomo_cbct_series",), label="DICOM series UID (if several)",
                     density="compact", hide_details=True, classes="mt-1",
                     id="tomo-cbct-series")
        v.VBtn("Load CBCT", click=self.app.submit("tomo_load_cbct", self.FORM),
               block=True, classes="mt-2", disabled=(busy,), id="tomo-load-cbct")

    def _ui_own_scene(self):
        """1b: the user's label map, optics.json and acquisition or recording."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("1b. Or your own scene (files on this computer)", classes="text-subtitle-2 mt-4")
        v.VTextField(v_model=("tomo_own_labels",),
                     label="Label map in the workspace (.nrrd, .seg.nrrd)",
                     density="compact", hide_details=True, id="tomo-own-labels")
        v.VTextField(v_model=("tomo_own_optics",), label="optics.json in the workspace",
                     density="compact",
                     hide_details=True, classes="mt-1", id="tomo-own-optics")
        v.VTextField(v_model=("tomo_own_acquisition",),
                     label="Acquisition or recording folder in the workspace",
                     density="compact", hide_details=True, classes="mt-1",
                     id="tomo-own-acquisition")
        v.VBtn("Load my scene", click=self.app.submit("tomo_load_own", self.FORM),
               block=True, classes="mt-2", disabled=(busy,), id="tomo-own-load")
        html.Div("{{ tomo_own_info }}", classes="text-caption", id="tomo-own-info")

    def _ui_plan(self):
        """1c: the scan planned on the user's scene."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("1c. Plan the scan (your scene)", classes="text-subtitle-2 mt-4")
        with v.VRow(dense=True):
            with v.VCol(cols=6):
                v.VTextField(v_model=("tomo_plan_targets",), label="Target labels (empty: "
                             "every inclusion)", density="compact", hide_details=True,
                             id="tomo-plan-targets")
            with v.VCol(cols=6):
                v.VTextField(v_model_number=("tomo_plan_positions",), type="number",
                             label="Laser positions", density="compact", hide_details=True,
                             id="tomo-plan-positions")
        v.VBtn("Plan the scan", click=self.app.submit("tomo_plan", self.FORM),
               block=True, classes="mt-2", disabled=("!tomo_own || " + busy,), id="tomo-plan")
        with html.Div(v_if="tomo_plan_result", classes="text-caption mt-1", id="tomo-plan-result"):
            html.Div("{{ tomo_plan_result.positions }} laser positions (violet in 3D), "
                     "{{ tomo_plan_result.pairs }} pairs; predicted HP 95 % interval, noise "
                     "part:")
            html.Div("label {{ r.label }}: +-{{ r.half_width }} % (default grid "
                     "+-{{ r.default }} %){{ r.covered ? '' : ', not covered' }}",
                     v_for="r in tomo_plan_result.targets")
            html.Div("warnings: {{ tomo_plan_result.warnings }}")

    def _ui_segment(self):
        """2: threshold segments, the label map, saving it."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
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
        v.VBtn("Add segment by threshold",
               click=self.app.submit("tomo_threshold_segment", self.FORM), block=True,
               classes="mt-2", disabled=("!tomo_loaded || " + busy,), id="tomo-threshold")
        html.Div("Segments: {{ tomo_segments.join(', ') || 'none' }}. Paint, erase, islands and "
                 "smoothing: the brush tool on the left.", classes="text-caption mt-1",
                 id="tomo-segments")
        v.VBtn("Use segmentation as label map",
               click=self.app.submit("tomo_use_segmentation", self.FORM), block=True,
               classes="mt-2", disabled=("!tomo_segments.length || " + busy,), id="tomo-labels")
        html.Div("{{ tomo_regions.map(r => r.label + ': ' + r.name + ' ' + r.volume_mm3 + "
                 "' mm³').join(', ') }}", classes="text-caption", id="tomo-regions")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=7):
                v.VTextField(v_model=("tomo_labels_out",), label="Save as (.nrrd, workspace)",
                             density="compact", hide_details=True, id="tomo-labels-out")
            with v.VCol(cols=5):
                v.VBtn("Save label map", click=self.app.submit("tomo_save_labels", self.FORM),
                       block=True, disabled=("!tomo_has_labels || tomo_own || " + busy,),
                       id="tomo-save-labels")

    def _ui_mesh(self):
        """3: the mesh."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("3. Mesh", classes="text-subtitle-2 mt-4")
        v.VTextField(v_model_number=("tomo_mesh_size_mm",), type="number",
                     label="Element size [mm] (structured, region-preserving)", density="compact",
                     hide_details=True, id="tomo-mesh-size")
        v.VBtn("Build mesh", click=self.app.submit("tomo_build_mesh", self.FORM),
               block=True, classes="mt-2",
               disabled=("!tomo_has_labels || " + busy,), id="tomo-mesh")
        v.VSelect(v_model=("tomo_mesh_method",),
                  items=(["fast (structured)", "quality (fTetWild, slower)"],), label="Mesher",
                  density="compact", hide_details=True, classes="mt-2", id="tomo-mesh-method")
        v.VTextField(v_model=("tomo_mesh_roi",), label="ROI x0,x1,y0,y1,z0,z1 [mm] (empty: "
                     "around the tube)", density="compact", hide_details=True, classes="mt-2",
                     id="tomo-mesh-roi")
        html.Div("{{ tomo_mesh_info }}", classes="text-caption", id="tomo-mesh-info")

    def _ui_reconstruct(self):
        """4: the reconstruction, its progress and result."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        busy = "job.running"
        html.Div("4. Reconstruct (phantom: simulated tracked laser scan; your scene: its "
                 "acquisition)", classes="text-subtitle-2 mt-4")
        with v.VRow(dense=True):
            with v.VCol(cols=6):
                v.VSelect(v_model=("tomo_method",), items=(["NP", "SP", "HP"],), label="Priors",
                          density="compact", hide_details=True, id="tomo-method")
            with v.VCol(cols=6):
                v.VTextField(v_model_number=("tomo_lambda",), type="number", label="lambda",
                             density="compact", hide_details=True, id="tomo-lambda")
        with v.VRow(dense=True, classes="mt-1"):
            with v.VCol(cols=8):
                v.VBtn("Reconstruct", click=self.app.submit("tomo_reconstruct", self.FORM),
                       block=True,
                       color="primary", disabled=("!tomo_has_labels || " + busy,), id="tomo-recon")
            with v.VCol(cols=4):
                v.VBtn("Cancel", click=self.app.ctrl.fluo_cancel_job, block=True,
                       disabled=("!" + busy,), id="tomo-cancel")
        v.VProgressLinear(model_value=("job.owner === 'FluoTomo' ? job.fraction * 100 : 0",),
                          height=6, classes="mt-2",
                          color=("job.error ? 'error' : 'primary'",), id="tomo-progress")
        html.Div("{{ job.name }} {{ job.message }} {{ job.running ? '(' + job.seconds + ' s)' : '' }}",
                 classes="text-caption", id="tomo-job", v_if="job.owner === 'FluoTomo'")
        with html.Div(v_if="tomo_result", classes="text-caption mt-1", id="tomo-result"):
            html.Div("{{ tomo_result.method }}: peak {{ tomo_result.peak }} /mm (true "
                     "{{ tomo_result.true_peak }}), error {{ tomo_result.peak_error_pct }} %")
            html.Div("centroid depth {{ tomo_result.centroid_mm }} mm (true "
                     "{{ tomo_result.true_centroid_mm }}), {{ tomo_result.seconds }} s")
            html.Div("warning: {{ w }}", v_for="w in tomo_result.warnings",
                     classes="text-warning")
        with html.Div(v_if="tomo_own_result", classes="text-caption mt-1", id="tomo-own-result"):
            html.Div("{{ tomo_own_result.method }} ({{ tomo_own_result.node }}): label "
                     "{{ tomo_own_result.target }} yield {{ tomo_own_result.yield }} /mm "
                     "(95 % interval {{ tomo_own_result.ci95 }} /mm, noise SD "
                     "{{ tomo_own_result.sd }}), peak {{ tomo_own_result.peak }} /mm at "
                     "RAS {{ tomo_own_result.peak_ras }} (label {{ tomo_own_result.peak_label }})")
            html.Div("half-maximum centroid RAS {{ tomo_own_result.centroid_ras }}; "
                     "{{ tomo_own_result.nodes }} nodes, {{ tomo_own_result.seconds }} s; "
                     "warnings: {{ tomo_own_result.warnings }}")

    def _ui_display(self):
        """5: the yield's display threshold and colour bar."""
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        html.Div("5. Display", classes="text-subtitle-2 mt-4")
        v.VSlider(v_model=("tomo_threshold",), min=0.0, max=0.95, step=0.05,
                  label="Threshold (fraction of max)", density="compact", hide_details=True,
                  disabled=("!(tomo_result || tomo_own_result)",), id="tomo-threshold-slider")
        # a reconstruction's yield, of the phantom or of the user's own scene
        with html.Div(v_if="tomo_result || tomo_own_result", id="tomo-colorbar", classes="mt-1"):
            html.Div(style=("{height: '14px', background: tomo_colorbar.gradient, "
                            "borderRadius: '3px'}",))
            with html.Div(style="display:flex; justify-content: space-between;",
                          classes="text-caption"):
                html.Span("{{ tomo_colorbar.min }}")
                html.Span("yield [1/mm], shown above {{ tomo_colorbar.threshold }}")
                html.Span("{{ tomo_colorbar.max }}")
