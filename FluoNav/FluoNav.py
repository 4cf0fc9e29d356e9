"""FluoNav: navigated fluorescence imaging (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The computation lives in ``FluoNavLib``; the
logic class is the API (the ``fluo nav``/``track``/``replay`` commands, the
web app's panel and the desktop widget all call it). Loads in 3D Slicer, in
plain Python with slicer-core, and under pytest.
"""

import logging
import os
import sys

try:
    import fluoguide  # noqa: F401  (installed beside the modules by the extension's CMake)
except ImportError:  # the module folders of a source checkout on Slicer's module paths
    sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

try:  # 3D Slicer
    from slicer.ScriptedLoadableModule import (ScriptedLoadableModule,
                                               ScriptedLoadableModuleLogic,
                                               ScriptedLoadableModuleTest)
except ImportError:  # slicer-core or no Slicer at all
    from fluoguide.slicer_compat import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
    )

from fluoguide.slicer_module import FluoLogicMixin, FluoModuleWidget

#: Tracker sources as the panel names them -> FluoNavLib.devices.tracker sources
TRACKER_SOURCES = {"NDI simulator": "ndi-sim", "NDI serial port": "ndi",
                   "OpenIGTLink server": "igtl", "Recording (replay)": "replay"}


class FluoNav(ScriptedLoadableModule):
    def __init__(self, parent=None):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "FluoNav"
        self.parent.categories = ["FluoGuide"]
        self.parent.dependencies = []
        self.parent.contributors = ["FluoGuide developers"]
        self.parent.helpText = (
            "Live navigated fluorescence: tracker poses, camera frames and time sync, "
            "per-pixel ray casting onto the CBCT surface, the navigated illumination model, "
            "optical transport and surface flux images, and contour-based classification. "
            "See docs/slicer.md.")
        self.parent.acknowledgementText = "Method after M. J. Daly, University of Toronto, 2018."
        from fluoguide.slicer_samples import register_on_startup

        register_on_startup()  # the digital phantoms in Sample Data


#
# Widget
#

class FluoNavWidget(FluoModuleWidget):
    """The desktop panel (``Resources/UI/FluoNav.ui``) over :class:`FluoNavLogic`.
    Outside Slicer the web app (``fluo app``) builds its panel
    (``fluoapp.webapp.nav_panel``) over the same logic class."""

    BINDINGS = (
        ("labelMapSelector", "LabelMap", "node"),
        ("targetTrianglesSpinBox", "TargetTriangles", "int"),
        ("surfaceModelSelector", "Surface", "node"),
        ("calibrationNodeSelector", "Calibration", "node"),
        ("trackerSourceComboBox", "TrackerSource", "choice"),
        ("trackerAddressLineEdit", "TrackerAddress", "text"),
        ("cameraToolTransformSelector", "CameraTool", "node"),
        ("showCameraCheckBox", "ShowCamera", "bool"),
        ("recordingPathLineEdit", "RecordingFolder", "path"),
        ("frameSpinBox", "Frame", "int"),
        ("transportVolumeSelector", "Transport", "node"),
        ("fluxVolumeSelector", "Flux", "node"),
        ("surfaceFluxModelSelector", "SurfaceFlux", "node"),
    )
    POLL_MS = 50

    def createLogic(self, scene):
        return FluoNavLogic(scene)

    def setupConnections(self):
        import qt

        self.ui.calibrationNodeSelector.addAttribute("vtkMRMLScriptedModuleNode",
                                                     "FluoGuide.Role", "Calibration")
        self.ui.buildSurfaceButton.connect("clicked(bool)", self.onBuildSurface)
        self.ui.connectButton.connect("clicked(bool)", self.onConnect)
        self.ui.disconnectButton.connect("clicked(bool)", self.onDisconnect)
        self.ui.importRecordingButton.connect("clicked(bool)", self.onImportRecording)
        self.ui.syntheticSceneButton.connect("clicked(bool)", self.onSyntheticScene)
        self.ui.correctFrameButton.connect("clicked(bool)", self.onCorrectFrame)
        self.ui.mapFramesButton.connect("clicked(bool)", self.onMapFrames)
        self.timer = qt.QTimer()
        self.timer.setInterval(self.POLL_MS)
        self.timer.connect("timeout()", self.onPoll)

    def cleanup(self):
        if getattr(self, "timer", None) is not None:
            self.timer.stop()
        if self.logic is not None:
            self.logic.disconnect()
        FluoModuleWidget.cleanup(self)

    def updateButtonStates(self):
        connected = self.logic is not None and self.logic.isConnected()
        self.ui.connectButton.enabled = not connected
        self.ui.disconnectButton.enabled = connected

    def _node(self, role):
        return self._parameterNode.GetNodeReference(role)

    # -- surface -----------------------------------------------------------------
    # Long work runs as FluoModuleWidget.runJob does it: the scene is read on
    # Slicer's thread, the logic's prepareX job computes on a worker thread
    # (Slicer keeps answering, Cancel works), storeX writes the nodes back on
    # Slicer's thread. Each result goes to its label and to ``results``.
    def onBuildSurface(self):
        p = self.logic.parameter

        def prepare():
            output = self._node("Surface")
            job = self.logic.prepareBuildSurface(labelMapNode=self._node("LabelMap"),
                                                 targetTriangles=p("TargetTriangles") or None)
            return job, lambda poly: self.logic.storeBuiltSurface(poly, outputModelNode=output)

        model = self.runJob("Surface from label map", prepare)
        if model is not None:
            self._parameterNode.SetNodeReferenceID("Surface", model.GetID())
            text = f"{model.GetName()}: {model.GetPolyData().GetNumberOfCells()} triangles"
            self.results.append(text)
            if self.ui is not None:
                self.ui.statusLabel.text = text

    # -- tracker -------------------------------------------------------------------
    def onConnect(self):
        p = self.logic.parameter
        source = TRACKER_SOURCES.get(p("TrackerSource"), p("TrackerSource"))
        session = self.run("Connect tracker", self.logic.connectTracker, source,
                           p("TrackerAddress") or None, cameraToolNode=self._node("CameraTool"))
        if session is None:
            return
        tool = self.logic.cameraToolNode(self._node("CameraTool"))
        self._parameterNode.SetNodeReferenceID("CameraTool", tool.GetID())
        if p("ShowCamera"):
            self.logic.showTrackedCamera(tool)
        self.timer.start()
        self.updateButtonStates()
        self.ui.trackerStatusLabel.text = f"Connected: {p('TrackerSource')}"

    def onPoll(self):
        try:
            self.logic.updateTracker()
        except Exception as exc:  # the device went away: stop polling, say why
            self.timer.stop()
            self.logic.disconnect()
            self.updateButtonStates()
            self.showError("Tracking", exc)

    def onDisconnect(self):
        self.timer.stop()
        self.logic.disconnect()
        self.updateButtonStates()
        self.ui.trackerStatusLabel.text = (f"Disconnected after {self.logic.posesApplied} poses")

    # -- frames ------------------------------------------------------------------
    def onImportRecording(self):
        n = self.run("Import recording", self.logic.importRecording,
                     self.logic.parameter("RecordingFolder"))
        if n is not None:
            self.ui.frameSpinBox.maximum = max(n - 1, 0)
            self.ui.statusLabel.text = f"Recording with {n} frames in the scene"

    def onSyntheticScene(self):
        def prepare():
            job = self.logic.prepareSyntheticAcquisition(views=4, binning=4)
            return job, self.logic.storeSyntheticAcquisition

        info = self.runJob("Synthetic navigated scene", prepare)
        if info is None:
            return
        node = self._parameterNode
        was = node.StartModify()
        node.SetNodeReferenceID("Surface", info["surface_node_id"])
        node.SetNodeReferenceID("Calibration", info["calibration_node_id"])
        node.EndModify(was)
        text = (f"Oral-cavity scene: {info['frames']} tracked frames of homogeneous tissue "
                f"(transport {info['transport_truth']})")
        self.results.append(text)
        if self.ui is not None:
            self.ui.frameSpinBox.maximum = info["frames"] - 1
            self.ui.statusLabel.text = text

    def onCorrectFrame(self):
        p = self.logic.parameter

        def prepare():
            outputs = {"transportNode": self._node("Transport"), "fluxNode": self._node("Flux")}
            job = self.logic.prepareCorrectFrame(p("Frame"), surfaceModelNode=self._node("Surface"),
                                                 calibration=self._node("Calibration"))
            return job, lambda r: self.logic.storeCorrectedFrame(r, **outputs)

        r = self.runJob("Correct frame", prepare)
        if r is None:
            return
        node = self._parameterNode
        was = node.StartModify()
        node.SetNodeReferenceID("Transport", r.nodes["transport"].GetID())
        node.SetNodeReferenceID("Flux", r.nodes["flux"].GetID())
        node.EndModify(was)
        self.logic.showFrameImage(r.nodes["transport"])
        n = r.numbers
        text = (f"frame {n['frame']}: {n['mapped']} of {n['pixels']} pixels mapped, transport "
                f"median {n['transport_median']:.3f}" if n["transport_median"] is not None
                else f"frame {n['frame']}: no pixel mapped")
        if n.get("miss_rate_corrected_pct") is not None:
            text += (f"; 40 % contour miss rate {n['miss_rate_raw_pct']:.1f} % raw -> "
                     f"{n['miss_rate_corrected_pct']:.1f} % corrected")
        self.results.append(text)
        if self.ui is not None:
            self.ui.frameResultLabel.text = text

    def onMapFrames(self):
        def prepare():
            output = self._node("SurfaceFlux")
            job = self.logic.prepareMapFrames(surfaceModelNode=self._node("Surface"),
                                              calibration=self._node("Calibration"))
            return job, lambda mapped: self.logic.storeMappedFrames(mapped,
                                                                     outputModelNode=output)

        out = self.runJob("Map frames onto the surface", prepare)
        if out is None:
            return
        self._parameterNode.SetNodeReferenceID("SurfaceFlux", out["model"].GetID())
        median = out["surface_transport_median"]
        text = (f"{len(out['frames_on_surface'])} frames on the surface, "
                f"{len(out['frames_skipped'])} without a valid pose skipped; "
                f"{out['faces_seen']} of {out['faces']} faces seen"
                + (f", transport median {median:.3f}" if median is not None else ""))
        self.results.append(text)
        if self.ui is not None:
            self.ui.mapResultLabel.text = text


#
# Logic
#

class FluoNavLogic(FluoLogicMixin, ScriptedLoadableModuleLogic):
    """Navigation on one MRML scene (passed in; never the global one).

    Inputs and outputs are node objects the caller picks (defaults: the nodes
    of docs/scene.md, section FluoNav). Tracking: :meth:`connectTracker`,
    :meth:`updateTracker` (one poll, poses into transform nodes),
    :meth:`trackFor`, :meth:`disconnect`. Frames: :meth:`correctFrame`
    (transport and surface-flux images), :meth:`mapFrames` (accumulated
    results on the surface model's point and cell data),
    :meth:`classifyContours`.

    Long calls are a ``prepareX`` that reads the scene and returns the
    computation as a job ``job(progress, cancel)`` touching no MRML node (the
    desktop panel runs it on a worker thread, ``FluoModuleWidget.runJob``), and
    a ``storeX`` that writes its result into the scene (on the scene's thread);
    the public call is the two in one:

    - :meth:`prepareBuildSurface` / :meth:`storeBuiltSurface` (:meth:`buildSurface`)
    - :meth:`prepareSyntheticAcquisition` / :meth:`storeSyntheticAcquisition`
      (:meth:`makeSyntheticAcquisition`)
    - :meth:`prepareCorrectFrame` / :meth:`storeCorrectedFrame` (:meth:`correctFrame`)
    - :meth:`prepareMapFrames` / :meth:`storeMappedFrames` (:meth:`mapFrames`)

    :meth:`prepareFrameCorrection` is for a live stream: a callable that
    corrects frame after frame on a worker thread; :meth:`streamPhantomFrames`
    is the web app's stream, through the tracker's own loop (:meth:`trackFor`).
    """

    PARAMETERS = {
        "TargetTriangles": 62000,
        "TrackerSource": "NDI simulator",
        "TrackerAddress": "",
        "ShowCamera": True,
        "RecordingFolder": "",
        "Frame": 0,
    }

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoNavLogic needs an MRML scene")
        self.scene = scene
        self.tracker = None
        self.toolNodes = {}
        self.posesApplied = 0
        self._context = None
        self._contextKey = None

    # -- surface -------------------------------------------------------------------
    def prepareBuildSurface(self, labelNodeName="CBCTLabels", targetTriangles=None,
                            labelMapNode=None):
        """A job ``job(progress, cancel) -> vtkPolyData`` (no MRML) of :meth:`buildSurface`:
        the label map's voxels and geometry are read now; the job extracts, smooths
        and decimates (a minute for a 0.4 mm CBCT decimated to 62,000 triangles).
        Hand its result to :meth:`storeBuiltSurface`."""
        from fluoguide import mrml_io
        from FluoNavLib.mapping.surface import surface_from_labelmap

        node = labelMapNode or mrml_io.get_node(self.scene, labelNodeName,
                                                "vtkMRMLLabelMapVolumeNode")
        labels = mrml_io.volume_array(node)                  # a copy: the job owns it
        ijk_to_ras = mrml_io.volume_geometry(node)["ijk_to_ras"]

        def job(progress=None, cancel=None):
            return surface_from_labelmap(labels, ijk_to_ras, target_triangles=targetTriangles,
                                         progress=progress, cancel=cancel)

        return job

    def storeBuiltSurface(self, poly, outputModelNode=None):
        """The surface into ``outputModelNode`` (else ``TissueSurface``); the model node."""
        from fluoguide import mrml_io

        if outputModelNode is None:
            model = mrml_io.add_model(self.scene, "TissueSurface", poly)
        else:
            model = mrml_io.set_model_polydata(outputModelNode, poly)
        logging.info("FluoNav: %s with %d triangles", model.GetName(), poly.GetNumberOfCells())
        return model

    def buildSurface(self, labelNodeName="CBCTLabels", targetTriangles=None, labelMapNode=None,
                     outputModelNode=None, progress=None, cancel=None):
        """Air-tissue surface of a label map (``labelMapNode``, else the node called
        ``labelNodeName``) into ``outputModelNode`` (else ``TissueSurface``),
        decimated to about ``targetTriangles`` (None: not decimated)."""
        job = self.prepareBuildSurface(labelNodeName, targetTriangles, labelMapNode)
        return self.storeBuiltSurface(job(progress, cancel), outputModelNode)

    # -- tracking ------------------------------------------------------------------
    def cameraToolNode(self, node=None):
        """The transform node of the tracked camera tool (``CameraToolToTracker``
        unless the caller picks one); nested under ``TrackerToReference`` when
        that registration exists."""
        from fluoguide import mrml_io

        if node is not None:
            return node
        node = mrml_io.get_node(self.scene, "CameraToolToTracker", "vtkMRMLLinearTransformNode",
                                required=False)
        if node is None:
            import numpy as np

            parent = ("TrackerToReference" if mrml_io.get_node(self.scene, "TrackerToReference",
                                                               required=False) else None)
            node = mrml_io.set_transform(self.scene, "CameraToolToTracker", np.eye(4), parent=parent)
        return node

    def connectTracker(self, source, address=None, cameraToolNode=None, phantomCamera=False,
                       **options):
        """Open a pose source and keep it until :meth:`disconnect`.

        Parameters
        ----------
        source : ``ndi`` (serial ``address``), ``ndi-sim`` (simulator), ``igtl``
            (``HOST:PORT``), ``replay`` (recording folder)
        cameraToolNode : vtkMRMLLinearTransformNode, optional
            Where the camera tool's pose goes (default ``CameraToolToTracker``);
            OpenIGTLink messages update the nodes of their own device names.
        phantomCamera : bool
            With ``ndi-sim``: the simulator's one tool is a camera circling
            120 mm above the oral-cavity phantom
            (``FluoNavLib.mapping.synthetic.stream_camera_tool``), the tracker of
            :meth:`streamPhantomFrames`.
        options : passed to the session (``inject_faults``, ``seed``, ``tools``,
            ``sim_tools``, ``rate_hz``, ``speed``)
        """
        from FluoNavLib.devices.tracker import open_tracker

        if phantomCamera:
            from FluoNavLib.mapping.synthetic import stream_camera_tool

            options.setdefault("sim_tools", [stream_camera_tool()])
            options.setdefault("roms", [b"camera tool" * 4])
        self.disconnect()
        self.tracker = open_tracker(source, address, scene=self.scene, **options)
        self.toolNodes = {"CameraToolToTracker": cameraToolNode}
        self.posesApplied = 0
        return self.tracker

    def isConnected(self):
        return self.tracker is not None

    def disconnect(self):
        """Close the pose source (safe to call when none is open)."""
        tracker, self.tracker = self.tracker, None
        if tracker is not None:
            tracker.close()

    def applyPoses(self, poses):
        """Write tracked poses ``{tool: 4x4 or None}`` into their transform nodes
        (a missing tool leaves its node at the last pose)."""
        from fluoguide import mrml_io
        from FluoNavLib.devices.tracker import finite_pose

        applied = 0
        for name, matrix in (poses or {}).items():
            if matrix is None or not finite_pose(matrix):
                continue
            node = self.toolNodes.get(name)
            if node is None and name == "CameraToolToTracker":
                node = self.toolNodes[name] = self.cameraToolNode()
            if node is None:
                node = mrml_io.set_transform(self.scene, name, matrix)
            else:
                mrml_io.set_transform_matrix(node, matrix)
            applied += 1
        self.posesApplied += applied
        return applied

    def updateTracker(self):
        """Poll the open source once and apply its poses; returns them (None: no new frame)."""
        from fluoguide.errors import FluoInputError

        if self.tracker is None:
            raise FluoInputError("no tracker connected", field="tracker")
        poses = self.tracker.poll()
        if poses and self.tracker.source != "igtl":  # OpenIGTLink wrote its nodes itself
            self.applyPoses(poses)
        return poses

    def trackFor(self, seconds, applyPoses=True, onPoses=None, stop=None):
        """Run the open source's live-tracking loop (``TrackerSession.track``, the
        one loop ``fluo track`` and the web app's stream run).

        Parameters
        ----------
        seconds : float or None
            How long [s] (a recording: to its end when None).
        applyPoses : bool
            Write the last poses into the transform nodes at the end (on the
            scene's thread only; False on a worker thread).
        onPoses : callable, optional
            ``onPoses(poses, tHost)`` per new tracker frame: ``{tool: 4x4 or
            None}`` and the host time [s]; it runs inside the loop, so a slow one
            slows the polling (the tracker's account still counts every frame).
        stop : callable, optional
            ``stop() -> bool``, asked before each read: true ends the loop early
            (no error when no frame came).

        Returns
        -------
        dict
            The session's account (``fluo track`` prints it).
        """
        from fluoguide.errors import FluoInputError

        if self.tracker is None:
            raise FluoInputError("no tracker connected", field="tracker")
        last = {}

        def on_poses(poses, t):
            if applyPoses:
                last.update({k: v for k, v in poses.items() if v is not None})
            if onPoses is not None:
                onPoses(poses, t)

        out = self.tracker.track(seconds, on_poses=on_poses, stop=stop)
        if applyPoses and last and self.tracker.source != "igtl":
            self.applyPoses(last)
        return out

    def showTrackedCamera(self, toolNode=None):
        """A cone glyph ``FluoNavCamera`` under the camera tool's transform."""
        import vtk

        from fluoguide import mrml_io

        tool = self.cameraToolNode(toolNode)
        cone = vtk.vtkConeSource()
        cone.SetHeight(20.0)
        cone.SetRadius(8.0)
        cone.SetDirection(0, 0, -1)
        cone.SetCenter(0, 0, 10.0)
        cone.Update()
        model = mrml_io.add_model(self.scene, "FluoNavCamera", cone.GetOutput(),
                                  color=(0.2, 0.8, 1.0))
        model.SetAndObserveTransformNodeID(tool.GetID())
        return model

    @staticmethod
    def checkSeconds(seconds, field="--seconds"):
        """A tracking duration [s]: finite, positive, at most a day; returns it."""
        from FluoNavLib.devices.tracker import check_seconds

        return check_seconds(seconds, field)

    @staticmethod
    def checkFaults(kinds):
        """The simulator's fault kinds (comma-separated names, "typical", or
        None), refused by name before any simulator starts."""
        from FluoNavLib.devices.ndi_simulator import Faults

        return Faults.named(kinds)

    @staticmethod
    def discoverDevices():
        """Attached NDI trackers and cameras (serial ports and USB devices)."""
        from FluoNavLib.devices.usb import discover

        return discover()

    @staticmethod
    def recordFrames(outputFolder, seconds=5.0, fps=20.0, frames=None, camera=None, width=348,
                     height=260, injectFaults=None, seed=0):
        """Record tracked camera frames to the new or empty ``outputFolder``
        through the live loop: the simulated NDI tracker (``injectFaults``:
        fault kinds) and images of the folder ``frames``, the OpenCV camera
        ``camera``, or synthetic ``width`` x ``height`` px frames, at ``fps``
        [1/s] for ``seconds`` [s]. Returns the account (frames, drops, latency
        [ms], the tracker's frames and faults, the folder)."""
        from FluoNavLib.devices.recording import record_simulated

        return record_simulated(outputFolder, seconds, fps, frames=frames, camera=camera,
                                width=width, height=height, inject_faults=injectFaults,
                                seed=seed)

    @staticmethod
    def benchmarkMapping(repeats=5, binning=10, progress=None):
        """Per-pixel surface-mapping speed and accuracy (full resolution,
        binned, decimated); medians of ``repeats`` timed runs."""
        from FluoNavLib.mapping.benchmark import run_mapping_benchmark

        return run_mapping_benchmark(repeats, binning, progress=progress)

    @staticmethod
    def validateSurfaceMapping(views=4, binning=4, seed=0, figureFile=None, progress=None,
                               cancel=None):
        """Surface mapping of the oral-cavity phantom (homogeneous fluorescence)
        graded on frames the software did not make (rendered on the analytic
        surface from the true poses, corrected with the CBCT mesh and tracked
        poses) and on its own mesh with exact poses (self-consistent).

        Parameters
        ----------
        views : int
            Tracked views looking into the cavity.
        binning : int
            Camera binning (4: 348 x 260 pixels).
        seed : int
            Noise and pose-error seed.
        figureFile : path, optional
            PNG of view 1: raw counts, the transport without and with the
            model-error guard, each with its 40 % contour.

        Returns
        -------
        dict
            Every case's transport and miss-rate numbers, guarded (``cases``)
            and not (``cases_unguarded``), ``miss_rate_raw_pct`` per view,
            ``images`` of view 1, and ``view_contours``: ``raw`` (counts above
            offset [ADU]) and ``self-consistent`` (transport T) of view 1, each
            ``image``, ``mask``, ``contour`` (40 % of the peak) and
            ``miss_rate_pct`` [%].
        """
        from FluoNavLib.mapping.contours import miss_rate
        from FluoNavLib.mapping.mismatch import mapping_under_mismatch, mismatch_figure

        res = mapping_under_mismatch(n_views=views, binning=binning, seed=seed, keep_images=True,
                                     progress=progress, cancel=cancel)
        contours = {}
        for name, (image, mask) in (("raw", res["images"]["raw"]),
                                    ("self-consistent",
                                     res["images"]["self-consistent"]["unguarded"])):
            rate, contour, _ = miss_rate(image, mask)
            contours[name] = {"image": image, "mask": mask, "contour": contour,
                              "miss_rate_pct": rate}
        res["view_contours"] = contours
        if figureFile is not None:
            mismatch_figure(figureFile, res)
        return res

    @staticmethod
    def timeSurfaceCast(triangles=62000, seed=0, repeats=3, binnedRepeats=10, binning=10,
                        progress=None):
        """Frame rate [1/s] of the per-pixel cast (every pixel's ray onto the
        surface; no illumination model) of the open-field camera (1392 x 1040
        px) into the oral-cavity phantom's surface of ``triangles`` triangles,
        at full resolution and ``binning`` x binned: the median of ``repeats``
        and ``binnedRepeats`` timed casts (the first includes compiling);
        ``progress(fraction, message)`` hears of each cast.

        Returns
        -------
        dict
            ``triangles``, ``frames_per_s_full``, ``frames_per_s_binned`` [1/s].
        """
        import time

        import numpy as np

        from fluoguide.progress import report
        from FluoNavLib.mapping.pixel_cast import cast_camera
        from FluoNavLib.mapping.synthetic import open_field_camera, oral_cavity_surface, view_poses

        report(progress, 0.0, f"the surface ({triangles} triangles)")
        caster, _ = oral_cavity_surface(triangles, seed=seed)
        camera = open_field_camera()
        pose = view_poses(2)[1]
        done, total = [0], repeats + binnedRepeats

        def median_s(n, **options):
            ts = []
            for _ in range(n):
                report(progress, 0.2 + 0.8 * done[0] / total, f"cast {done[0] + 1} of {total}")
                done[0] += 1
                t0 = time.perf_counter()
                cast_camera(caster, camera, pose, **options)
                ts.append(time.perf_counter() - t0)
            return float(np.median(ts))

        full = median_s(repeats)
        binned = median_s(binnedRepeats, binning=binning)
        return {"triangles": caster.n_faces, "frames_per_s_full": 1.0 / full,
                "frames_per_s_binned": 1.0 / binned}

    # -- recordings ------------------------------------------------------------------
    def importRecording(self, folder):
        """A recording folder (``fluo record``) as frame_store nodes in this scene;
        returns the number of frames."""
        from FluoNavLib.devices import frame_store
        from FluoNavLib.devices.recorder import to_scene

        to_scene(folder, self.scene)
        return frame_store.number_of_frames(self.scene)

    def prepareSyntheticAcquisition(self, views=4, binning=4, triangles=62000, transport=0.3,
                                    trackingMm=0.25, trackingDeg=0.1, handEyeMm=0.3,
                                    handEyeDeg=0.15):
        """A job ``job(progress, cancel) -> dict`` (no MRML) of
        :meth:`makeSyntheticAcquisition`: the CBCT surface and the rendered views
        (``FluoNavLib.mapping.synthetic.tracked_acquisition``, with ``transport``
        added). Hand its result to :meth:`storeSyntheticAcquisition`."""
        from FluoNavLib.mapping.synthetic import PoseError, tracked_acquisition

        tracking, hand_eye = PoseError(trackingMm, trackingDeg), PoseError(handEyeMm, handEyeDeg)

        def job(progress=None, cancel=None):
            acq = tracked_acquisition(views, binning, transport, tracking=tracking,
                                      hand_eye=hand_eye, surface_triangles=triangles,
                                      progress=progress, cancel=cancel)
            acq["transport"] = transport
            return acq

        return job

    def storeSyntheticAcquisition(self, acq):
        """The acquisition of :meth:`prepareSyntheticAcquisition`'s job in this scene:
        ``TissueSurface``, the calibration node, ``TrackerToReference``, the hand-eye
        and the recording. Returns what :meth:`makeSyntheticAcquisition` returns."""
        import numpy as np

        from fluoguide import mrml_io
        from FluoCalibLib.geometry.scene import calibration_node, store_handeye, store_intrinsics
        from FluoCalibLib.radiometry import scene as light_scene
        from FluoNavLib.devices import frame_store

        cam, rc = acq["camera"], acq["radiometric"]
        surface = mrml_io.add_model(self.scene, "TissueSurface", acq["surface"])
        store_intrinsics(self.scene, cam, {"rms_px": 0.0})
        light_scene.store_calibration(self.scene, light_scene.ILLUMINATION_KEY,
                                      {"cone": acq["cone"].to_dict()})
        light_scene.store_calibration(self.scene, light_scene.RADIOMETRY_KEY,
                                      {"camera": rc.to_dict()})
        mrml_io.set_transform(self.scene, "TrackerToReference", np.eye(4))
        store_handeye(self.scene, acq["hand_eye"])     # as calibrated: with its error
        frame_store.new_recording(self.scene)
        for k, (counts, tool) in enumerate(zip(acq["frames"], acq["tool_poses"])):
            frame_store.append_tracked_frame(self.scene, counts, 1.0 + k / 10,
                                             {"CameraToolToTracker": tool},
                                             exposure_s=rc.exposure_s)
        return {"frames": len(acq["frames"]), "transport_truth": acq["transport"],
                "triangles": int(acq["surface"].GetNumberOfPolys()),
                "image": [cam.width, cam.height],
                "rendered_on": "analytic phantom surface, true poses",
                "scene_holds": "CBCT-intensity surface, tracked poses, hand-eye with error",
                "surface_node_id": surface.GetID(),
                "calibration_node_id": calibration_node(self.scene).GetID()}

    def makeSyntheticAcquisition(self, views=4, binning=4, triangles=62000, transport=0.3,
                                 trackingMm=0.25, trackingDeg=0.1, handEyeMm=0.3,
                                 handEyeDeg=0.15, progress=None, cancel=None):
        """The oral-cavity phantom navigated with known truth, in this scene, as
        the operating room would give it: ``views`` tracked frames of homogeneous
        tissue (transport ``transport``) rendered on the phantom's analytic surface
        from the true poses, and what the software is told: ``TissueSurface``
        (extracted from the CBCT intensities, ``triangles`` triangles), the
        calibration (``FluoCalibration``: intrinsics, illumination cone,
        radiometric camera), ``TrackerToReference``, tool poses with tracking
        error (``trackingMm`` / ``trackingDeg`` SD per axis) and a hand-eye
        ``CameraToCameraTool`` off by ``handEyeMm`` / ``handEyeDeg``
        (``FluoNavLib.mapping.synthetic.tracked_acquisition``).
        """
        from fluoguide.progress import check_cancel, report, scaled

        job = self.prepareSyntheticAcquisition(views, binning, triangles, transport, trackingMm,
                                               trackingDeg, handEyeMm, handEyeDeg)
        acq = job(scaled(progress, 0.0, 0.9), cancel)
        check_cancel(cancel)
        info = self.storeSyntheticAcquisition(acq)
        report(progress, 1.0, "done")
        return info

    # -- correction --------------------------------------------------------------------
    @staticmethod
    def prepareKernels(progress=None, fraction=0.0, cancel=None):
        """Compile (first run after installing, about 15 s) or load the compiled
        surface-mapping kernels (ray casting, illumination), reporting at
        ``fraction`` of ``progress`` every second; a cancel stops the wait. Returns
        the seconds spent (0.0 when they are ready). The frame jobs call it first;
        a live stream calls it before its first frame."""
        from FluoNavLib.mapping.kernels import prepare_kernels

        return prepare_kernels(progress, fraction, cancel)

    def correctionContext(self, surfaceModelNode=None, calibration=None):
        """What every frame shares (camera, light, radiometric model, the surface's
        ray caster, the pose chain), read from the scene; reused while none of
        those nodes changed."""
        from fluoguide import mrml_io
        from FluoNavLib.mapping.correct import load_context

        surface = surfaceModelNode or mrml_io.get_node(self.scene, "TissueSurface",
                                                       "vtkMRMLModelNode")
        calib = calibration or mrml_io.get_node(self.scene, "FluoCalibration", required=False)
        stamp = [surface.GetID(), surface.GetMTime(),
                 surface.GetPolyData().GetMTime() if surface.GetPolyData() else 0]
        if calib is not None:
            stamp += [calib.GetID(), calib.GetMTime()]
        for name in ("TrackerToReference", "CameraToCameraTool", "CameraToTracker"):
            # the matrices themselves: setting a transform's matrix leaves the
            # node's MTime as it was, and a stale pose chain would be a wrong number
            node = mrml_io.get_node(self.scene, name, "vtkMRMLLinearTransformNode", required=False)
            stamp.append(None if node is None else mrml_io.transform_matrix(node).tobytes())
        if self._context is None or self._contextKey != stamp:
            self._context = load_context(self.scene, surface, calib)
            self._contextKey = stamp
        return self._context

    def prepareFrameCorrection(self, surfaceModelNode=None, calibration=None):
        """A callable ``correct(frame, cameraPose, index=0) -> FrameResult`` that
        touches no MRML node (for a live stream on a worker thread); the scene is
        read now. ``correct.context`` holds what it read."""
        from FluoNavLib.mapping.correct import correct_image

        ctx = self.correctionContext(surfaceModelNode, calibration)

        def correct(frame, cameraPose, index=0):
            return correct_image(ctx, frame, cameraPose, frame=index)

        correct.context = ctx
        return correct

    def streamPhantomFrames(self, seconds, onFrame, progress=None, cancel=None, binning=8,
                            triangles=20000, transport=0.3, contourFraction=0.4,
                            firstFrameWaitS=120.0):
        """Live corrected frames of the oral-cavity phantom at the tracked camera's
        pose, for a worker thread: the open tracker's loop (:meth:`trackFor`)
        calls ``onFrame`` with each corrected frame.

        The simulated operating room (surface, calibrations:
        :meth:`makeSyntheticAcquisition` without views) lives in a scene of its
        own, and this logic's scene is not touched (the caller shows the camera
        pose on the scene's thread, :meth:`applyPoses`). Each tracker frame with
        a camera-tool pose (:meth:`connectTracker` with ``phantomCamera``) is
        rendered from the tool's position looking into the cavity (homogeneous
        tissue, noise seeded by the frame's index), corrected
        (:meth:`prepareFrameCorrection`) and classified (:meth:`classifyContours`);
        a frame with no pixel on the surface is skipped.

        Parameters
        ----------
        seconds : float
            Streaming time [s], counted from the first corrected frame (the
            first also starts the caller's display: slow on a busy machine).
        onFrame : callable
            ``onFrame(frame)``, ``frame`` a dict: ``index`` (0, 1, ...),
            ``result`` (FrameResult), ``contours`` (:meth:`classifyContours`),
            ``cameraPose`` (CameraToWorld 4x4, mm), ``trackerFrame`` (the
            device's frame number).
        progress, cancel : optional
            The job's reporter and cancel token; a cancel (Stop) ends the stream
            normally, with its account.
        binning, triangles : int
            The room's camera binning and surface triangles.
        transport : float
            The tissue's optical transport T (dimensionless).
        contourFraction : float
            The contour level (fraction of the frame's maximum).
        firstFrameWaitS : float
            How long [s] the first frame may take (kernels, first plot) before
            ``seconds`` start.

        Returns
        -------
        dict
            ``frames`` (corrected frames shown), ``tracker_frames`` and
            ``lost_unreported`` (the tracker's account; 0 when every gap was
            reported), ``stopped`` (ended by the cancel).
        """
        import time

        from fluoguide import mrml_io
        from fluoguide.errors import FluoCancelled, FluoInputError
        from fluoguide.progress import report
        from FluoNavLib.mapping.synthetic import look_at_cavity, render_view

        seconds = self.checkSeconds(seconds, field="seconds")
        if self.tracker is None:
            raise FluoInputError("no tracker connected", field="tracker")
        report(progress, 0.0, "building the simulated operating room")
        room = type(self)(mrml_io.new_scene())      # touched by this thread only
        room.makeSyntheticAcquisition(views=0, binning=binning, triangles=triangles,
                                      transport=transport)
        correct = room.prepareFrameCorrection()
        ctx = correct.context
        # the ray caster's kernels compile here on a first run, reported as they
        # go, not silently inside the first frame
        try:
            room.prepareKernels(progress, 0.0, cancel)
        except FluoCancelled:
            pass            # Stop meanwhile: the loop ends the stream normally
        run = {"shown": 0, "t_end": None, "stopped": False}

        def stop():
            if cancel is not None and cancel.cancelled:
                run["stopped"] = True           # Stop ends a live stream; it is no failure
                return True
            return run["t_end"] is not None and time.monotonic() >= run["t_end"]

        def on_poses(poses, t_host):
            tool = (poses or {}).get("CameraToolToTracker")
            if tool is None:
                return
            shown = run["shown"]
            pose = look_at_cavity(tool[:3, 3])
            counts, _, _ = render_view(ctx.caster, ctx.camera, pose, ctx.cone, transport,
                                       ctx.radiometric, seed=shown)
            r = correct(counts, pose, index=shown)
            if not r.mapped.any():
                return
            onFrame({"index": shown, "result": r,
                     "contours": self.classifyContours(r, contourFraction), "cameraPose": pose,
                     "trackerFrame": getattr(self.tracker, "last_frame", None)})
            if not shown:
                run["t_end"] = time.monotonic() + seconds
            run["shown"] = shown + 1
            report(progress, 1 - (run["t_end"] - time.monotonic()) / seconds,
                   f"frame {shown + 1}")

        account = self.trackFor(seconds + firstFrameWaitS, applyPoses=False, onPoses=on_poses,
                                stop=stop)
        return {"frames": run["shown"], "tracker_frames": account.get("frames"),
                "lost_unreported": account.get("lost_unreported"), "stopped": run["stopped"]}

    def prepareCorrectFrame(self, frame, cameraPose=None, surfaceModelNode=None,
                            calibration=None, maxModelError="default"):
        """A job ``job(progress, cancel) -> FrameResult`` (no MRML) of :meth:`correctFrame`:
        the frame, its pose and the correction context are read now. Hand its
        result to :meth:`storeCorrectedFrame`."""
        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError
        from fluoguide.progress import check_cancel, report
        from FluoNavLib.mapping.correct import correct_image, read_frame
        from FluoNavLib.mapping.flux_map import DEFAULT_MAX_MODEL_ERROR

        if isinstance(maxModelError, str) and maxModelError == "default":
            maxModelError = DEFAULT_MAX_MODEL_ERROR
        ctx = self.correctionContext(surfaceModelNode, calibration)
        index = 0
        if isinstance(frame, (int, np.integer)):
            index = int(frame)
            frame, cameraPose = read_frame(self.scene, index)
        else:
            if hasattr(frame, "IsA"):
                frame = mrml_io.volume_array(frame)
                if frame.shape[0] != 1:
                    raise FluoInputError("frame volume must have one slice", field="frame",
                                         value=frame.shape)
                frame = frame[0]
            if cameraPose is None:
                raise FluoInputError("an image needs its camera pose", field="cameraPose")
            if hasattr(cameraPose, "IsA"):
                cameraPose = mrml_io.transform_matrix(cameraPose)
            frame = np.array(frame)          # the caller's array may change meanwhile

        def job(progress=None, cancel=None):
            check_cancel(cancel)
            self.prepareKernels(progress, 0.0, cancel)   # first run: compiled, reported
            report(progress, 0.0, f"ray casting and correcting frame {index}")
            r = correct_image(ctx, frame, cameraPose, frame=index, max_model_error=maxModelError)
            report(progress, 1.0, "done")
            return r

        return job

    def storeCorrectedFrame(self, result, transportNode=None, fluxNode=None, rawNode=None):
        """The frame images of a FrameResult (``FluoNavTransport``, ``FluoNavFlux``,
        ``FluoNavRaw``, or the caller's nodes); the result, with ``nodes`` =
        {"transport", "flux", "raw"} the output nodes."""
        from fluoguide import mrml_io
        from FluoNavLib.mapping.scene import FLUX_NODE, RAW_NODE, write_frame_images

        r = result
        S = r.counts - r.offset_adu
        transport = write_frame_images(self.scene, r.transport, r.mapped, S, dict(r.numbers),
                                       flux_w_per_mm2=r.flux_w_per_mm2,
                                       flux_mask=r.flux_valid & r.hits.visible,
                                       transport_node=transportNode, raw_node=rawNode,
                                       flux_node=fluxNode)
        r.nodes = {"transport": transport,
                   "flux": fluxNode or mrml_io.get_node(self.scene, FLUX_NODE),
                   "raw": rawNode or mrml_io.get_node(self.scene, RAW_NODE)}
        return r

    def correctFrame(self, frame, cameraPose=None, surfaceModelNode=None, calibration=None,
                     transportNode=None, fluxNode=None, rawNode=None, maxModelError="default",
                     progress=None, cancel=None):
        """Optical transport and surface-flux images of one camera frame.

        Parameters
        ----------
        frame : int (a frame of the scene's recording, whose pose is used) or an
            (H, W) array of counts [ADU] or a scalar volume node (one slice)
        cameraPose : 4x4 camera-tool pose ``CameraToolToTracker`` [mm] or a linear
            transform node; needed unless ``frame`` is a recorded frame
        surfaceModelNode : the tissue surface (default ``TissueSurface``)
        calibration : the calibration node (default ``FluoCalibration``)
        transportNode, fluxNode, rawNode : output volume nodes (defaults
            ``FluoNavTransport``, ``FluoNavFlux``, ``FluoNavRaw``)
        maxModelError : pixels whose predicted model error exceeds this fraction are
            not corrected (``flux_map.model_error``; "default":
            ``DEFAULT_MAX_MODEL_ERROR`` = 0.10; None: no guard, docs/surface-mapping.md
            says what that costs)

        Returns
        -------
        FrameResult (``transport``, ``flux_w_per_mm2``, masks, ``numbers``), with
        ``nodes`` = {"transport", "flux", "raw"} the output nodes.
        """
        job = self.prepareCorrectFrame(frame, cameraPose, surfaceModelNode, calibration,
                                       maxModelError)
        return self.storeCorrectedFrame(job(progress, cancel), transportNode, fluxNode, rawNode)

    def prepareMapFrames(self, surfaceModelNode=None, calibration=None, frames=None,
                         precomputed=()):
        """A job ``job(progress, cancel) -> dict`` (no MRML) of :meth:`mapFrames`:
        every frame's counts and pose and the correction context are read now
        (a frame without a valid pose is listed as skipped); the job corrects the
        frames, one report each, and accumulates them on the surface's faces.
        Hand its result to :meth:`storeMappedFrames`."""
        from fluoguide.errors import FluoInputError
        from FluoNavLib.devices import frame_store
        from FluoNavLib.mapping.correct import read_frame

        ctx = self.correctionContext(surfaceModelNode, calibration)
        precomputed = list(precomputed)
        done = {r.frame for r in precomputed}
        todo = (list(range(frame_store.number_of_frames(self.scene))) if frames is None
                else list(frames))
        # every frame is read here, on the scene's thread: the job owns copies
        # (a full-resolution recording of N frames holds N x 2.6 MB here)
        read, skipped = [], []
        for n in todo:
            if n in done:
                continue
            try:
                read.append((n, *read_frame(self.scene, n)))
            except FluoInputError as exc:          # no valid pose: not mapped, say so
                skipped.append({"frame": n, "reason": exc.problem})

        def job(progress=None, cancel=None):
            from fluoguide.progress import check_cancel, report
            from FluoNavLib.mapping.correct import correct_image, map_frames_to_surface

            results, refused = list(precomputed), list(skipped)
            if read:                # a frame to cast: first run compiles, reported
                self.prepareKernels(progress, 0.0, cancel)
            for k, (n, counts, pose) in enumerate(read):
                check_cancel(cancel)
                report(progress, 0.95 * k / max(len(read), 1),
                       f"correcting frame {n} ({k + 1} of {len(read)})")
                try:
                    results.append(correct_image(ctx, counts, pose, frame=n))
                except FluoInputError as exc:      # e.g. not the calibrated camera's size
                    refused.append({"frame": n, "reason": exc.problem})
            if not results:
                raise FluoInputError("no frame with a valid pose to map", field="frames",
                                     value=len(todo))
            check_cancel(cancel)
            report(progress, 0.95, f"accumulating {len(results)} frames on "
                                   f"{ctx.caster.n_faces:,} faces")
            T_face, J_face, w_face, views = map_frames_to_surface(ctx, results)
            report(progress, 1.0, "done")
            order = {n: i for i, n in reversed(list(enumerate(todo)))}
            return {"context": ctx, "results": results, "transport": T_face, "flux": J_face,
                    "weight": w_face, "views": views,
                    "skipped": sorted(refused, key=lambda s: order.get(s["frame"], 0))}

        return job

    def storeMappedFrames(self, mapped, outputModelNode=None):
        """The accumulated results of :meth:`prepareMapFrames`'s job on the surface
        model ``outputModelNode`` (default ``FluoNavSurfaceFlux``); returns what
        :meth:`mapFrames` returns."""
        import numpy as np

        from FluoNavLib.mapping.scene import write_surface_flux

        T_face, w_face = mapped["transport"], mapped["weight"]
        model = write_surface_flux(self.scene, mapped["context"].polydata, T_face, mapped["flux"],
                                   w_face, mapped["views"], node=outputModelNode)
        results = mapped["results"]
        seen = w_face > 0
        return {"model": model, "results": results,
                "frames_on_surface": [r.frame for r in results],
                "frames_skipped": mapped["skipped"],
                "faces_seen": int(seen.sum()), "faces": int(len(w_face)),
                "surface_transport_median": float(np.median(T_face[seen])) if seen.any() else None}

    def mapFrames(self, recording=None, surfaceModelNode=None, calibration=None,
                  outputModelNode=None, frames=None, precomputed=(), progress=None, cancel=None):
        """Accumulate the recorded frames' transport and surface flux on the surface.

        Parameters
        ----------
        recording : None (the scene's recording) or a recording folder to import first
        frames : frame numbers to map (default: every frame); a frame without a
            valid pose is skipped and listed with the reason
        precomputed : FrameResults already computed (not corrected again)
        outputModelNode : model node for the results (default ``FluoNavSurfaceFlux``)

        Returns
        -------
        dict: ``model`` (the output node), ``results`` (FrameResults in order),
        ``frames_on_surface``, ``frames_skipped``, ``faces_seen``, ``faces``,
        ``surface_transport_median``.
        """
        if recording is not None:
            self.importRecording(recording)
        job = self.prepareMapFrames(surfaceModelNode, calibration, frames, precomputed)
        return self.storeMappedFrames(job(progress, cancel), outputModelNode)

    def classifyContours(self, result, contourFraction=0.4):
        """Contour classification (docs/physics.md section 6.3) of a corrected frame: the
        ``contourFraction`` contour of the raw counts and of the transport image,
        and their miss rates [%] (None when no pixel was mapped)."""
        from FluoNavLib.mapping.contours import miss_rate

        r = result
        out = {"miss_rate_raw_pct": None, "miss_rate_corrected_pct": None,
               "raw_contour": None, "corrected_contour": None}
        if not r.mapped.any():
            return out
        S = r.counts - r.offset_adu
        valid = r.hits.visible & r.flux_valid
        out["miss_rate_raw_pct"], out["raw_contour"], _ = miss_rate(S, valid, contourFraction)
        out["miss_rate_corrected_pct"], out["corrected_contour"], _ = miss_rate(
            r.transport, r.mapped, contourFraction)
        return out

    def showFrameImage(self, volumeNode):
        """Show a frame image in the slice views (in Slicer; nothing headless)."""
        from fluoguide.slicer_compat import in_slicer_application

        if in_slicer_application():
            import slicer

            slicer.util.setSliceViewerLayers(background=volumeNode, fit=True)


#
# Test
#

class FluoNavTest(ScriptedLoadableModuleTest):
    """The module's workflow through the logic calls, on the synthetic oral
    cavity with known truth. Runs in Slicer's self-test and under pytest.

    The frames are rendered on a surface of 40000 triangles and corrected on
    a different one of 12000 (the data are not made by the mesh that corrects
    them); the tolerances are those the mapping tests hold the CLI to (2 %
    on the median transport of a frame, 5 % contour miss rate), measured
    here with that mesh difference (docs/slicer.md).
    """

    def setUp(self):
        import slicer

        from fluoguide.slicer_compat import in_slicer_application

        if in_slicer_application():
            from fluoguide.slicer_deps import ensure_dependencies

            self.assertTrue(ensure_dependencies(ask=False), "FluoGuide's Python packages")
        self.scene = slicer.vtkMRMLScene()

    def runTest(self):
        self.setUp()
        self.test_surface_from_phantom()
        self.test_tracker_to_transform_node()
        self.test_correct_and_map_frames()

    def test_surface_from_phantom(self):
        from fluoguide.phantoms import add_phantom_to_scene, make_phantom

        add_phantom_to_scene(self.scene, make_phantom("slab", voxel_mm=2.0))
        model = FluoNavLogic(self.scene).buildSurface()
        self.assertGreater(model.GetPolyData().GetNumberOfCells(), 100)
        self.delayDisplay("FluoNav surface test passed")

    def test_tracker_to_transform_node(self):
        """The simulated NDI tracker's pose reaches the camera-tool transform node."""
        import time

        import numpy as np

        from fluoguide import mrml_io

        logic = FluoNavLogic(self.scene)
        logic.connectTracker("ndi-sim")
        try:
            t_end = time.monotonic() + 5.0
            while logic.posesApplied < 5 and time.monotonic() < t_end:
                logic.updateTracker()
            stats = logic.trackFor(0.5)
        finally:
            logic.disconnect()
        self.assertGreaterEqual(logic.posesApplied, 5)
        self.assertEqual(stats["lost_unreported"], 0)
        m = mrml_io.get_transform(self.scene, "CameraToolToTracker")
        self.assertFalse(np.allclose(m, np.eye(4)))  # a real tracked pose, not the default
        self.assertFalse(logic.isConnected())
        self.delayDisplay("FluoNav tracker test passed")

    def test_correct_and_map_frames(self):
        import numpy as np

        import slicer
        from vtk.util import numpy_support as ns

        from fluoguide import mrml_io
        from FluoNavLib.devices.frame_store import read_tracked_frame

        scene = slicer.vtkMRMLScene()
        logic = FluoNavLogic(scene)
        # rendered on the analytic surface from the true poses; corrected with the
        # CBCT surface, tracked poses and a hand-eye with error
        info = logic.makeSyntheticAcquisition(views=3, binning=8, triangles=12000, transport=0.3)
        r = logic.correctFrame(0)
        self.assertLess(abs(r.numbers["transport_median"] / 0.3 - 1), 0.02)
        classes = logic.classifyContours(r)
        self.assertLess(classes["miss_rate_corrected_pct"], 5.0)
        self.assertGreater(classes["miss_rate_raw_pct"], classes["miss_rate_corrected_pct"])
        # the same frame as an image plus a pose node gives the same transport
        img, _, poses = read_tracked_frame(scene, 0)
        pose = mrml_io.set_transform(scene, "TestPose", poses["CameraToolToTracker"])
        r2 = logic.correctFrame(img, pose)
        np.testing.assert_allclose(r2.transport, r.transport)
        out = logic.mapFrames()
        self.assertEqual(out["frames_on_surface"], list(range(info["frames"])))
        self.assertLess(abs(out["surface_transport_median"] / 0.3 - 1), 0.02)
        poly = out["model"].GetPolyData()
        point_T = ns.vtk_to_numpy(poly.GetPointData().GetArray("transport"))
        point_w = ns.vtk_to_numpy(poly.GetPointData().GetArray("view_weight"))
        self.assertEqual(len(point_T), poly.GetNumberOfPoints())
        self.assertLess(abs(np.median(point_T[point_w > 0]) / 0.3 - 1), 0.02)
        self.delayDisplay("FluoNav correction and mapping test passed")
