"""FluoTomo: image-guided fluorescence tomography (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The real code lives in ``FluoTomoLib``; the
logic class is the API (the ``fluo tomo`` commands, the web app's panel and
the desktop widget all call it). Loads in 3D Slicer, in plain Python with
slicer-core, and under pytest.
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


class FluoTomo(ScriptedLoadableModule):
    def __init__(self, parent=None):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "FluoTomo"
        self.parent.categories = ["FluoGuide"]
        self.parent.dependencies = []
        self.parent.contributors = ["FluoGuide developers"]
        self.parent.helpText = (
            "Fluorescence tomography from a tracked laser and camera: CBCT label map to "
            "tetrahedral mesh, FEM diffusion for excitation and emission, adjoint Jacobians, "
            "and reconstruction of fluorescence yield with no, soft or hard CBCT priors.")
        self.parent.acknowledgementText = (
            "Method after M. J. Daly, 'An Image-Guided Computational Framework for "
            "Intraoperative Fluorescence Quantification', University of Toronto, 2018.")


#
# Widget
#

class FluoTomoWidget(FluoModuleWidget):
    """The desktop panel (``Resources/UI/FluoTomo.ui``) over :class:`FluoTomoLogic`:
    a label map (picked, made from a segmentation, or a digital phantom's) ->
    mesh -> a simulated or loaded acquisition -> NP/SP/HP reconstruction into
    a yield volume shown over the slices. Outside Slicer the web app
    (``fluo app``) builds its panel (``fluoapp.webapp.tomo_panel``) over the
    same logic class.

    The acquisition (simulated or read) and what each mesh was built for are
    kept for the session, not in the parameter node (the logic keeps its
    meshes likewise): a reconstruction uses the chosen mesh only if it was
    built for the same label map, acquisition, accuracy and target, and
    otherwise meshes the acquisition's region of interest itself and says so.
    """

    # (widget, parameter or node-reference role, kind): saved in the parameter node
    BINDINGS = (
        ("labelMapSelector", "LabelMap", "node"),
        ("segmentationSelector", "Segmentation", "node"),
        ("referenceVolumeSelector", "ReferenceVolume", "node"),
        ("phantomComboBox", "Phantom", "choice"),
        ("accuracyComboBox", "Accuracy", "choice"),
        ("targetSpinBox", "Target", "int"),
        ("meshModelSelector", "Mesh", "node"),
        ("opticsPathLineEdit", "OpticsFile", "path"),
        ("yieldLineEdit", "YieldByLabel", "text"),
        ("noiseSpinBox", "NoisePct", "float"),
        ("seedSpinBox", "Seed", "int"),
        ("acquisitionPathLineEdit", "AcquisitionFolder", "path"),
        ("methodComboBox", "Method", "choice"),
        ("lambdaSpinBox", "Lambda", "float"),
        ("outputVolumeSelector", "OutputVolume", "node"),
    )

    def __init__(self, parent=None):
        FluoModuleWidget.__init__(self, parent)
        self.acquisition = None  # {"acquisition", "label_id", "serial", "what"}: the last one made
        self._serial = 0
        self._meshFor = {}       # mesh node ID -> (label map ID, acquisition serial, accuracy, target)
        self.results = []        # what the results box shows, one block per step

    def createLogic(self, scene):
        return FluoTomoLogic(scene)

    def setupConnections(self):
        self.ui.segmentationToLabelsButton.connect("clicked(bool)", self.onSegmentationToLabels)
        self.ui.loadPhantomButton.connect("clicked(bool)", self.onLoadPhantom)
        self.ui.buildMeshButton.connect("clicked(bool)", self.onBuildMesh)
        self.ui.simulateButton.connect("clicked(bool)", self.onSimulate)
        self.ui.loadAcquisitionButton.connect("clicked(bool)", self.onLoadAcquisition)
        self.ui.reconstructButton.connect("clicked(bool)", self.onReconstruct)

    # -- helpers -------------------------------------------------------------------
    def _node(self, role):
        return self._parameterNode.GetNodeReference(role)

    def _setNodes(self, **roles):
        node = self._parameterNode
        was = node.StartModify()
        for role, target in roles.items():
            node.SetNodeReferenceID(role, None if target is None else target.GetID())
        node.EndModify(was)

    def _labelNode(self):
        from fluoguide.errors import FluoInputError

        node = self._node("LabelMap")
        if node is None:
            raise FluoInputError("choose a label map (or make one from a segmentation or a "
                                 "phantom)", field="Label map")
        return node

    def _optics(self):
        from fluoguide.errors import FluoInputError

        path = self.logic.parameter("OpticsFile")
        if not path:
            raise FluoInputError("choose the optical properties file (optics.json)",
                                 field="Optics")
        return self.logic.readOptics(path)

    def _acquisitionFor(self, labelNode):
        """The session's acquisition if it was made for ``labelNode``, else None."""
        acq = self.acquisition
        return acq if acq is not None and acq["label_id"] == labelNode.GetID() else None

    def _meshKey(self, labelNode, acq):
        p = self.logic.parameter
        return (labelNode.GetID(), None if acq is None else acq["serial"], p("Accuracy"),
                p("Target"))

    def _keepAcquisition(self, labelNode, acquisition, what):
        self._serial += 1
        self.acquisition = {"acquisition": acquisition, "label_id": labelNode.GetID(),
                            "serial": self._serial, "what": what}

    def say(self, lines):
        """One block of results (and warnings) in the results box, newest last."""
        self.results.append("\n".join(lines))
        if self.ui is not None:
            self.ui.resultsTextEdit.setPlainText("\n\n".join(self.results))
            bar = self.ui.resultsTextEdit.verticalScrollBar()
            bar.setValue(bar.maximum)

    # -- label map -----------------------------------------------------------------
    def onSegmentationToLabels(self):
        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError

        def work():
            seg, ref = self._node("Segmentation"), self._node("ReferenceVolume")
            if seg is None:
                raise FluoInputError("choose a segmentation", field="Segmentation")
            if ref is None:
                raise FluoInputError("choose the volume whose grid the label map takes",
                                     field="Reference volume")
            regions = self.logic.segmentationToLabels(seg, referenceName=ref.GetName())
            return regions, mrml_io.get_node(self.logic.scene, "CBCTLabels")

        out = self.run("Segmentation to label map", work)
        if out is None:
            return
        regions, labels = out
        self._setNodes(LabelMap=labels)
        self.say([f"Label map {labels.GetName()} from {self._node('Segmentation').GetName()}:"]
                 + [f"  label {k} = {name}: {vol:.1f} mm^3" for k, (name, vol) in
                    sorted(regions.items())])

    def onLoadPhantom(self):
        import json
        import tempfile
        from pathlib import Path

        from fluoguide import mrml_io
        from FluoTomoLib.tomography import optics_from_phantom

        name = self.logic.parameter("Phantom")
        truth = self.run("Load phantom", self.logic.loadPhantom, name)
        if truth is None:
            return
        scene = self.logic.scene
        self._setNodes(LabelMap=mrml_io.get_node(scene, "CBCTLabels"),
                       ReferenceVolume=mrml_io.get_node(scene, "CBCT"))
        regions = truth["regions"]
        lines = [f"Phantom {name}: CBCT and CBCTLabels"] + [
            f"  label {k} = {r['name']}: {r['labelmap_volume_mm3']:.1f} mm^3"
            for k, r in sorted(regions.items(), key=lambda kv: int(kv[0]))]
        if all("optics" in r for r in regions.values()):
            # its true optical properties and yields, as a user would give them
            optics = optics_from_phantom({int(k): r["optics"] for k, r in regions.items()})
            optics.names = {int(k): r["name"] for k, r in regions.items()}
            path = Path(tempfile.mkdtemp(prefix="FluoTomo-phantom-")) / "optics.json"
            path.write_text(json.dumps(optics.to_json(), indent=2))
            yields = ",".join(f"{k}:{r['optics']['yield_per_mm']:.6g}" for k, r in
                              sorted(regions.items(), key=lambda kv: int(kv[0]))
                              if r["optics"].get("yield_per_mm", 0.0) > 0)
            node = self._parameterNode
            was = node.StartModify()
            node.SetParameter("OpticsFile", str(path))
            node.SetParameter("YieldByLabel", yields)
            node.EndModify(was)
            lines.append(f"  its optical properties: {path}; " + (
                f"its true yields {yields} /mm" if yields else
                "no region fluoresces (give a yield per label to simulate)"))
        self.say(lines)

    # -- mesh ------------------------------------------------------------------------
    def onBuildMesh(self):
        from fluoguide import mrml_io

        p = self.logic.parameter

        def prepare():          # the scene is read here, on Slicer's thread
            label = self._labelNode()
            acq = self._acquisitionFor(label)
            optics = self._optics() if acq is not None or p("OpticsFile") else None
            job = self.logic.prepareBuildMesh(
                label, target=p("Target") or None,
                acquisition=None if acq is None else acq["acquisition"], optics=optics,
                accuracy=p("Accuracy"))
            return job, lambda built: (label, acq, self.logic.storeBuiltMesh(
                built, self._node("Mesh")))

        done = self.runJob("Build mesh", prepare)
        if done is None:
            return
        label, acq, node = done
        self._meshFor[node.GetID()] = self._meshKey(label, acq)
        self._setNodes(Mesh=node)
        info = mrml_io.get_json_attribute(node, "FluoTomo.Mesh") or {}
        roi = info.get("region_of_interest") or {}
        where = (f"the region of interest of {acq['what']}" + (
            f" (cut changes the data by at most {roi['truncation_max_pct']:.2g} %)"
            if roi.get("truncation_max_pct") is not None else "")
            if acq is not None else
            "the whole label map (no acquisition for it yet: build again after simulating or "
            "loading one to mesh its region of interest, which the reconstruction uses)")
        lines = [f"Mesh {node.GetName()} ({p('Accuracy')}): {info.get('nodes')} nodes, "
                 f"{info.get('elements')} tetrahedra over {where}"]
        for lab, (mesh_v, ref_v, err) in sorted(self.logic.meshRegionVolumes(node).items()):
            lines.append(f"  label {lab}: {mesh_v:.1f} mm^3 in the mesh" + (
                f", {ref_v:.1f} mm^3 in the label map ({err:+.2f} %)"
                if ref_v is not None and err is not None else ""))
        lines += [f"  warning: {w}" for w in info.get("warnings", [])]
        self.say(lines)

    # -- acquisition -------------------------------------------------------------------
    def onSimulate(self):
        from fluoguide.parameters import parse_yields

        p = self.logic.parameter

        def prepare():          # the scene is read here, on Slicer's thread
            label = self._labelNode()
            yields = parse_yields(p("YieldByLabel"), field="Yield per label")
            job = self.logic.prepareSimulation(label, self._optics(), yields,
                                               noise=p("NoisePct"), seed=p("Seed"),
                                               accuracy=p("Accuracy"))
            return job, lambda acq: (label, acq)       # kept by the panel, no node

        done = self.runJob("Simulate acquisition", prepare)
        if done is None:
            return
        label, acq = done
        info = acq.meta.get("simulation", {})
        what = (f"the acquisition simulated on {label.GetName()} (yield {p('YieldByLabel')}, "
                f"noise {p('NoisePct'):g} %, seed {p('Seed')})")
        self._keepAcquisition(label, acq, what)
        lines = [f"Simulated: {len(acq.sources_ras_mm)} sources x {len(acq.detectors_ras_mm)} "
                 f"detectors, {int(acq.mask.sum())} measurements used; FEM on the whole label "
                 f"map ({info.get('mesh_nodes')} nodes, {p('Accuracy')}) in "
                 f"{info.get('seconds', float('nan')):.1f} s"]
        lines += [f"  warning: {w}" for w in info.get("warnings", [])]
        self.say(lines)

    def onLoadAcquisition(self):
        from fluoguide.errors import FluoInputError

        folder = self.logic.parameter("AcquisitionFolder")

        def work():
            if not folder:
                raise FluoInputError("choose the acquisition folder", field="Acquisition folder")
            label = self._labelNode()
            return label, self.logic.readAcquisition(folder, label, self._optics())

        out = self.run("Load acquisition", work)
        if out is None:
            return
        label, acq = out
        self._keepAcquisition(label, acq, f"the acquisition {folder}")
        self.say([f"Acquisition {folder} on {label.GetName()}: {len(acq.sources_ras_mm)} "
                  f"sources x {len(acq.detectors_ras_mm)} detectors, {int(acq.mask.sum())} "
                  f"measurements used"])

    # -- reconstruction ----------------------------------------------------------------
    def onReconstruct(self):
        from fluoguide.display import style_yield_volume
        from fluoguide.errors import FluoInputError
        from fluoguide.slicer_compat import in_slicer_application

        p = self.logic.parameter

        def prepare():          # the scene is read here, on Slicer's thread
            label = self._labelNode()
            optics = self._optics()
            acq = self._acquisitionFor(label)
            if acq is None:
                raise FluoInputError("simulate or load an acquisition for this label map first",
                                     field="Acquisition", value=label.GetName())
            mesh = self._node("Mesh")
            if mesh is not None and self._meshFor.get(mesh.GetID()) != self._meshKey(label, acq):
                mesh = None
            job = self.logic.prepareReconstruction(
                label, optics, acq["acquisition"], method=p("Method"), lam=p("Lambda"),
                target=p("Target") or None, meshNode=mesh, accuracy=p("Accuracy"))
            return job, lambda result: (acq, mesh, result, self.logic.storeReconstructionResult(
                result, self._node("OutputVolume")))

        done = self.runJob("Reconstruction", prepare)
        if done is None:
            return
        acq, mesh, result, node = done
        s = result["summary"]
        style_yield_volume(self.logic.scene, node)
        if in_slicer_application():
            import slicer

            slicer.util.setSliceViewerLayers(foreground=node, foregroundOpacity=0.6)
        peak = ", ".join(f"{v:.1f}" for v in s["peak_ras_mm"])
        lines = [f"{s['method']} (lambda {p('Lambda'):g}) into {node.GetName()} from "
                 f"{acq['what']}: peak {s['peak_yield_per_mm']:.4g} /mm at RAS ({peak}) in "
                 f"label {s['peak_label']}; {s['mesh']['nodes']} mesh nodes ("
                 + (f"the mesh {mesh.GetName()}" if mesh is not None else
                    "meshed for this acquisition: the chosen mesh was not built for it")
                 + f"); {s['seconds']:.1f} s"]
        for lab, r in sorted(s["regions"].items(), key=lambda kv: int(kv[0])):
            ci = r.get("ci95_per_mm")
            lines.append(f"  label {lab}{' (target)' if str(s['target']) == lab else ''}: "
                         f"yield {r['yield_per_mm']:.4g} /mm"
                         + (f" (95 % interval {ci[0]:.3g} .. {ci[1]:.3g})" if ci else
                            " (no interval: see the warnings)"))
        lines += [f"  warning: {w}" for w in s.get("warnings", [])]
        self.say(lines)

class FluoTomoLogic(FluoLogicMixin, ScriptedLoadableModuleLogic):
    """Tomography on one MRML scene (passed in; never the global one).

    Long calls come in two halves too: ``prepareX`` reads the scene and returns
    the computation as a job ``job(progress, cancel)`` that touches no MRML
    node (the desktop panel runs it on a worker thread), ``storeX`` writes its
    result into the scene (on the scene's thread):

    - :meth:`prepareBuildMesh` / :meth:`storeBuiltMesh` (:meth:`buildMesh`)
    - :meth:`prepareSimulation` (:meth:`simulateAcquisition`; the acquisition
      is no node: nothing to store)
    - :meth:`prepareReconstruction` / :meth:`storeReconstructionResult`
      (:meth:`reconstruct`)
    - :meth:`prepareMesh` / :meth:`storeMesh` and :meth:`prepareTubeReconstruction`
      / :meth:`storeReconstruction` (the web app's cylinder-tube phantom route)

    Nodes read and written are listed in docs/scene.md (section FluoTomo).
    ``PARAMETERS``: the desktop panel's state in the module's parameter node.
    """

    PARAMETERS = {
        "Phantom": "cylinder-tube",
        "Accuracy": "balanced",
        "Target": 0,                 # 0: the default target (smallest region not the largest)
        "OpticsFile": "",
        "YieldByLabel": "",          # LABEL:VALUE[,...] [1/mm], for a simulated acquisition
        "NoisePct": 1.0,
        "Seed": 0,
        "AcquisitionFolder": "",
        "Method": "HP",
        "Lambda": 10.0,
    }

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoTomoLogic needs an MRML scene")
        self.scene = scene
        self._meshes = {}       # model node ID -> what buildMesh made (local-frame mesh)

    def loadPhantom(self, name, withLabels=True, **params):
        """Add a digital phantom's ``CBCT`` (and ``CBCTLabels`` unless ``withLabels``
        is False, when the user is to segment the CBCT); returns its truth dict."""
        from fluoguide import mrml_io
        from fluoguide.phantoms import add_phantom_to_scene, make_phantom

        phantom = make_phantom(name, **params)
        add_phantom_to_scene(self.scene, phantom)
        cbct = mrml_io.get_node(self.scene, "CBCT")
        mrml_io.set_json_attribute(cbct, "FluoGuide.Truth", phantom.truth())
        if not withLabels:
            mrml_io.remove_node(self.scene, "CBCTLabels")
        logging.info("FluoTomo: loaded phantom %s", name)
        return phantom.truth()

    def segmentationToLabels(self, segmentationNode, outName="CBCTLabels", referenceName="CBCT"):
        """Label map ``outName`` on the ``CBCT`` grid from a segmentation: segment
        n (in the segmentation's order) becomes label n + 1; later segments win
        where segments overlap (an inclusion drawn after its tissue stays an
        inclusion).  Returns {label: (segment name, volume mm^3)}."""
        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError

        ref = mrml_io.get_node(self.scene, referenceName, "vtkMRMLScalarVolumeNode")
        seg = segmentationNode.GetSegmentation()
        n = seg.GetNumberOfSegments()
        if n == 0:
            raise FluoInputError("segmentation has no segments", field=segmentationNode.GetName())
        geo = mrml_io.volume_geometry(ref)
        shape = mrml_io.volume_array(ref).shape
        labels = np.zeros(shape, np.uint8)
        info = {}
        for i in range(n):
            sid = seg.GetNthSegmentID(i)
            arr = _segment_array(self.scene, segmentationNode, sid, ref)
            labels[arr > 0] = i + 1
            info[i + 1] = seg.GetNthSegment(i).GetName()
        if not labels.any():
            raise FluoInputError("segmentation is empty (no voxel in any segment)",
                                 field=segmentationNode.GetName())
        old = mrml_io.get_node(self.scene, outName, required=False)
        if old is not None:
            self.scene.RemoveNode(old)
        node = mrml_io.add_volume(self.scene, outName, labels, geo["spacing"], geo["origin"],
                                  direction=geo["direction"], labelmap=True)
        node.SetAttribute("FluoTomo.SourceSegmentation", segmentationNode.GetName())
        vox = float(np.prod(geo["spacing"]))
        return {k: (name, float((labels == k).sum() * vox)) for k, name in info.items()}

    # ------------------------------------------------------- CBCT in, labels out
    # A CBCT from the scanner's files (a DICOM folder) or a volume file, and the
    # headless threshold segmentation (docs/scene.md, "DICOM input").

    @staticmethod
    def readCbct(path, series=None):
        """``(array_kji [HU], spacing_mm, origin_mm, direction, source)`` of a CBCT:
        a DICOM folder (``series``: its SeriesInstanceUID, needed when the folder
        holds several), a volume file (NRRD, NIfTI) or a scene (``.mrml``: its
        ``CBCT``); geometry in RAS (``fluoguide.labelmap_io.read_cbct``)."""
        from fluoguide.labelmap_io import read_cbct

        return read_cbct(path, series=series)

    def importCbct(self, path, series=None, name="CBCT"):
        """Read a CBCT (as :meth:`readCbct` takes it) into the scalar volume node
        ``name`` (replaced when there), its origin, spacing and direction kept;
        attribute ``FluoGuide.Source``: what was read. Returns the node."""
        from fluoguide import mrml_io

        arr, spacing, origin, direction, source = self.readCbct(path, series)
        node = mrml_io.add_volume(self.scene, name, arr, spacing, origin, direction=direction)
        mrml_io.set_json_attribute(node, "FluoGuide.Source", source)
        logging.info("FluoTomo: CBCT %s from %s", name, source)
        return node

    def importCbctToScene(self, path, outputFolder, series=None):
        """A scene folder (``scene.mrml``, ``CBCT.nrrd``) holding the CBCT of
        ``path`` as the node ``CBCT`` (``fluo scene import``): read and checked
        first, then written as one step (``fluoguide.atomic``: nothing of it on
        a refusal; an existing folder's scene is replaced). Returns a summary."""
        from pathlib import Path

        from fluoguide import atomic, mrml_io

        atomic.check_writable(outputFolder, field="--out", folder=True)
        arr, spacing, origin, direction, source = self.readCbct(path, series)
        out = Path(outputFolder)
        with atomic.staged_folder(out, last=("scene.mrml",)) as stage:
            scene = mrml_io.new_scene()
            node = mrml_io.add_volume(scene, "CBCT", arr, spacing, origin, direction=direction)
            mrml_io.set_json_attribute(node, "FluoGuide.Source", source)
            mrml_io.save_scene(scene, stage / "scene.mrml")
        return {"scene": str(out / "scene.mrml"), "source": source,
                "dimensions_ijk": list(arr.shape[::-1]), "spacing_mm": list(map(float, spacing)),
                "origin_mm": list(map(float, origin)),
                "direction": [list(map(float, row)) for row in direction],
                "voxel_type": str(arr.dtype),
                "hu_range": [float(arr.min()), float(arr.max())]}

    def segmentCbct(self, thresholds, cbctNode=None, outName="CBCTLabels", outputLabelNode=None,
                    progress=None, cancel=None):
        """Label map of the CBCT by HU thresholds, as the app's threshold tool
        and :meth:`segmentationToLabels` make it: each label's range (both ends
        included), its largest connected component, its holes filled, later
        labels over earlier ones (``FluoTomoLib.tomography.threshold_labels``).

        Parameters
        ----------
        thresholds : "LABEL:MIN:MAX[,...]" [HU], a .json file path, a dict
            {label: [min, max]} or (label, min, max) triples
        cbctNode : the scalar volume (default: the node ``CBCT``)
        outName : name of the new label map (replaced when there), unless
            ``outputLabelNode`` is given

        Returns
        -------
        (label-map node on the CBCT's grid, report per label: voxels,
        volume_mm3, components, dropped_voxels, filled_voxels)
        """
        from fluoguide import mrml_io
        from FluoTomoLib.tomography import threshold_labels

        node = cbctNode or mrml_io.get_node(self.scene, "CBCT", "vtkMRMLScalarVolumeNode")
        geo = mrml_io.volume_geometry(node)
        labels, report = threshold_labels(mrml_io.volume_array(node), thresholds, geo["spacing"],
                                          progress=progress, cancel=cancel)
        if outputLabelNode is not None:
            out = mrml_io.set_volume_array(outputLabelNode, labels, geo["spacing"], geo["origin"],
                                           geo["direction"])
        else:
            out = mrml_io.add_volume(self.scene, outName, labels, geo["spacing"], geo["origin"],
                                     direction=geo["direction"], labelmap=True)
        mrml_io.set_json_attribute(out, "FluoTomo.Thresholds", report)
        return out, report

    @staticmethod
    def cleanSegment(mask):
        """One thresholded segment kept as :meth:`segmentCbct` keeps each label
        (the app's threshold tool calls this): its largest 6-connected
        component, its holes filled (``FluoTomoLib.tomography.clean_mask``).
        ``mask``: (K, J, I) array, nonzero inside. Returns (bool mask, info:
        components, dropped_voxels, filled_voxels)."""
        from FluoTomoLib.tomography import clean_mask

        return clean_mask(mask)

    def writeLabelMapFile(self, labelNode, outputFile):
        """Write a label-map node (or its name) as NRRD, its origin, spacing and
        direction kept (what :meth:`loadLabelMap` and ``fluo tomo`` read).
        Returns the path."""
        from pathlib import Path

        from fluoguide import mrml_io
        from fluoguide.labelmap_io import write_volume_nrrd

        _check_labelmap_output(outputFile, "label map file")
        node = (mrml_io.get_node(self.scene, labelNode, "vtkMRMLLabelMapVolumeNode")
                if isinstance(labelNode, str) else labelNode)
        geo = mrml_io.volume_geometry(node)
        write_volume_nrrd(outputFile, mrml_io.volume_array(node), geo["spacing"], geo["origin"],
                          geo["direction"])
        return Path(outputFile)

    def segmentCbctToFile(self, cbct, thresholds, outputFile, series=None, progress=None,
                          cancel=None):
        """``fluo segment``: the label map of a CBCT (as :meth:`readCbct` takes
        it) by :meth:`segmentCbct`'s rules, written to ``outputFile`` (NRRD,
        gzip; on the CBCT's grid: same origin, spacing and direction) in one
        step after every check. Returns the summary (per label: voxels,
        volume_mm3, components, dropped_voxels, filled_voxels)."""
        from fluoguide.labelmap_io import write_volume_nrrd
        from FluoTomoLib.tomography import parse_thresholds, threshold_labels

        _check_labelmap_output(outputFile, "--out")
        entries = parse_thresholds(thresholds)              # refused before the CBCT is read
        arr, spacing, origin, direction, source = self.readCbct(cbct, series)
        labels, report = threshold_labels(arr, entries, spacing, progress=progress, cancel=cancel)
        write_volume_nrrd(outputFile, labels, spacing, origin, direction)
        return {"labels_file": str(outputFile), "cbct": source,
                "dimensions_ijk": list(labels.shape[::-1]), "spacing_mm": list(map(float, spacing)),
                "labels": report}

    def prepareTubeReconstruction(self, methods=("NP", "SP", "HP"), lam=10.0, seed=0,
                                  labelNodeName="CBCTLabels", accuracy="fast",
                                  grading="bisection"):
        """A job ``job(progress, cancel) -> run`` that simulates the tracked
        acquisition of the cylinder-tube phantom in the scene (its truth is on
        ``CBCT``) and reconstructs on a mesh of the scene's label map (through
        the public label-map path, ``accuracy`` "fast" by default in the app;
        ``grading`` the reconstruction mesh's, graded by bisection as the demo's
        tube cases and ``fluo tomo reconstruct`` are: the uniform grid, which
        this job used until 2026-11-28, took the app's job 89 s and 3.2 GB).

        Everything is read from the scene here, on the caller's thread, so the
        job itself touches no MRML node and can run on a worker thread; hand its
        result to :meth:`storeReconstruction` on the scene's thread.
        """
        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError
        from fluoguide.phantoms import make_phantom
        from FluoTomoLib.pipelines.tube import simulate_and_reconstruct

        cbct = mrml_io.get_node(self.scene, "CBCT")
        truth = mrml_io.get_json_attribute(cbct, "FluoGuide.Truth")
        if not truth or truth.get("phantom") != "cylinder-tube":
            raise FluoInputError("the CBCT is not the cylinder-tube phantom (load it first)",
                                 field="CBCT", value=None if not truth else truth.get("phantom"))
        lab = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode", required=False)
        if lab is None:
            raise FluoInputError("no label map: segment the CBCT first", field=labelNodeName)
        labels = mrml_io.volume_array(lab).copy()
        geo = mrml_io.volume_geometry(lab)
        if not np.any(labels > 0):
            raise FluoInputError("label map has no tissue", field=labelNodeName)
        params = dict(truth.get("params", {}))
        methods = tuple(methods)

        def job(progress=None, cancel=None):
            phantom = make_phantom("cylinder-tube", **params)
            return simulate_and_reconstruct(
                phantom, methods=methods, lam=lam, seed=seed, progress=progress, cancel=cancel,
                accuracy=accuracy, grading=grading,
                recon_labels=(labels, np.asarray(geo["spacing"]), np.asarray(geo["origin"]),
                              np.asarray(geo["direction"])))

        job.grid = (mrml_io.volume_array(cbct).shape, mrml_io.volume_geometry(cbct))
        return job

    def storeReconstruction(self, run, grid):
        """Write ``FluoTomoYield*`` (on the CBCT grid) and ``FluoTomoMeshSurface``."""
        from FluoTomoLib.scene import store_reconstructions

        shape, geo = grid
        return store_reconstructions(self.scene, run["coarse"], run["results"], shape,
                                     geo["spacing"], geo["origin"], geo.get("direction"))

    def prepareMesh(self, sizeMm=1.0, roi=None, labelNodeName="CBCTLabels", quality=False):
        """A job ``job(progress, cancel) -> Mesh`` of the label map (read now, meshed
        later on any thread); hand the mesh to :meth:`storeMesh`.  ``quality``
        uses the fTetWild mesher (smooth conforming interfaces, tens of seconds)
        instead of the structured one (a second)."""
        from fluoguide import mrml_io
        from fluoguide.progress import check_cancel, report
        from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality
        from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        geo = mrml_io.volume_geometry(node)
        labels = mrml_io.volume_array(node).copy()

        def job(progress=None, cancel=None):
            report(progress, 0.05, "meshing the label map")
            if quality:
                mesh = mesh_labelmap_quality(labels, geo["spacing"], geo["origin"], sizeMm, roi=roi,
                                             direction=geo["direction"], progress=progress,
                                             cancel=cancel)
            else:
                mesh = mesh_labelmap_structured(labels, geo["spacing"], geo["origin"], sizeMm,
                                                roi=roi, direction=geo["direction"])
            check_cancel(cancel)
            report(progress, 1.0, "mesh done")
            return mesh

        return job

    def storeMesh(self, mesh):
        """Show a mesh's surface as ``FluoTomoMeshSurface`` and keep the mesh."""
        from FluoTomoLib.scene import store_mesh_surface

        store_mesh_surface(self.scene, mesh)
        self.mesh = mesh
        return mesh

    def labelVolumes(self, labelNodeName="CBCTLabels"):
        """Volume [mm^3] of each label of a label-map node."""
        import numpy as np

        from fluoguide import mrml_io

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        arr = mrml_io.volume_array(node)
        vox = float(np.prod(mrml_io.volume_geometry(node)["spacing"]))
        labels, counts = np.unique(arr, return_counts=True)
        return {int(k): float(c * vox) for k, c in zip(labels, counts) if k != 0}

    # ------------------------------------------------------------ any label map
    # The general path (docs/tomography-own-scene.md): MRML node objects in,
    # caller-chosen output nodes out (a second run never overwrites the first).

    def labelMap(self, labelNode):
        """The label map with its geometry (FluoTomoLib ``LabelMap``) of a volume
        node, of a file (a path: .nrrd, .nii(.gz), .seg.nrrd, .mrml), or a
        ``LabelMap`` as is."""
        from os import PathLike

        from FluoTomoLib.tomography import LabelMap

        if isinstance(labelNode, LabelMap):
            return labelNode
        if isinstance(labelNode, (str, PathLike)):
            return LabelMap.from_file(labelNode)
        return LabelMap.from_node(labelNode)

    def loadLabelMap(self, path, name=None):
        """Read a label map file (.nrrd, .nii(.gz), .seg.nrrd: segment n -> label
        n + 1) into a new label-map node (its direction, spacing and origin
        kept); returns the node."""
        from pathlib import Path

        import numpy as np

        from fluoguide import mrml_io
        from FluoTomoLib.scene import unique_name
        from FluoTomoLib.tomography import LabelMap

        lm = LabelMap.from_file(path)
        stem = Path(path).name.split(".")[0] or "Labels"
        node = mrml_io.add_volume(self.scene, unique_name(self.scene, name or stem),
                                  lm.labels_kji.astype(np.int16 if lm.labels_kji.max() > 255
                                                       else np.uint8),
                                  lm.spacing_mm, lm.origin_mm, direction=lm.direction,
                                  labelmap=True)
        node.SetAttribute("FluoTomo.SourceFile", str(path))
        return node

    @staticmethod
    def readOptics(optics):
        """An Optics object from ``optics.json`` (a path), a dict, or as is."""
        from FluoTomoLib.tomography import Optics, optics_from_dict, read_optics

        if isinstance(optics, Optics):
            return optics
        if isinstance(optics, dict):
            return optics_from_dict(optics)
        return read_optics(optics)

    def readAcquisition(self, acquisition, labelNode, optics, checkOptodes=False):
        """An Acquisition from a folder (a path) or as is.

        ``checkOptodes``: also refuse, naming the file, sources or detectors
        too far from the label map's tissue surface (the check a reconstruction
        makes, made here before any work)."""
        from FluoTomoLib.tomography import Acquisition, place_on_surface, read_acquisition

        if isinstance(acquisition, Acquisition) and not checkOptodes:
            return acquisition
        lm = self.labelMap(labelNode)
        if not isinstance(acquisition, Acquisition):
            acquisition = read_acquisition(acquisition, labelmap=lm,
                                           optics=self.readOptics(optics))
        if checkOptodes:
            for what, points in (("sources", acquisition.sources_ras_mm),
                                 ("detectors", acquisition.detectors_ras_mm)):
                place_on_surface(lm, points, what, file=acquisition.file_of(what))
        return acquisition

    def readPoints(self, path, field, labelNode=None, what=None):
        """Points (N, 3) [RAS mm] from a CSV file of ``x,y,z`` rows.

        With a label map (``labelNode``: node, path or LabelMap), the points are
        also checked to lie on its tissue surface (``what``: "sources" or
        "detectors"), refused naming the file otherwise."""
        from FluoTomoLib.tomography import place_on_surface, read_points_csv

        points = read_points_csv(path, field)
        if labelNode is not None:
            place_on_surface(self.labelMap(labelNode), points, what or field, file=path)
        return points

    def checkScanTargets(self, labelNode, targets, field="scan targets"):
        """The labels the default scan is to cover (``scan_targets`` of
        :meth:`simulateToFolder`), checked before any work: at most
        ``MAX_SCAN_PATCHES``, each in the label map; refused in one line naming
        ``field`` otherwise. Returns them as a list (None: every inclusion)."""
        from FluoTomoLib.tomography import check_scan_targets

        return check_scan_targets(self.labelMap(labelNode), targets, field=field)

    # ------------------------------------------------------ folders in and out
    # The ``fluo tomo`` commands: files and folders in, folders out.

    def simulateToFolder(self, labelNode, optics, yieldByLabel, outputFolder, sources=None,
                         detectors=None, noise=1.0, seed=0, engine="fem", accuracy="balanced",
                         progress=None, cancel=None, **options):
        """A simulated acquisition of a label map written to ``outputFolder``
        (acquisition.json, sources.csv, detectors.csv, data.csv).

        Parameters
        ----------
        labelNode : label-map node, path or LabelMap
        optics : optics.json path, dict or Optics
        yieldByLabel : {label: yield [1/mm]}
        sources, detectors : (S, 3), (D, 3) RAS mm, or None for the default scan
        noise : relative Gaussian noise per measurement [%]
        options : exclude_mm, simulate_mm, target, scan_targets, photons,
            executor, mc_store, threads (``simulate_acquisition``)

        Returns
        -------
        (Acquisition, info dict: engine, mesh nodes, noise, warnings, ...)
        """
        from FluoTomoLib.tomography import simulate_acquisition, write_acquisition

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        yields = {int(k): float(v) for k, v in dict(yieldByLabel).items()}
        acq, info = simulate_acquisition(lm, optics, yields, sources, detectors,
                                         noise_pct=noise, seed=seed, engine=engine,
                                         accuracy=accuracy, progress=progress, cancel=cancel,
                                         **options)
        write_acquisition(outputFolder, acq, simulation=info)
        return acq, info

    def readScanRecording(self, recording):
        """A recording folder of a tracked laser scan, read and checked
        (``FluoTomoLib.tomography.recording.read_scan_recording``; docs/recording.md)."""
        from FluoTomoLib.tomography.recording import read_scan_recording

        return read_scan_recording(recording)

    def readCalibration(self, calibration):
        """The calibrations an acquisition needs (camera intrinsics, hand-eye,
        TrackerToReference, laser beam line, radiometric gain) from a FluoCalib
        calibration JSON file or a scene (.mrml)."""
        from FluoTomoLib.tomography.recording import read_calibration

        return read_calibration(calibration)

    def acquireRecording(self, labelNode, optics, recording, outputFolder=None, calibration=None,
                         spotToleranceMm=None, sourceFrom="spot", progress=None, cancel=None):
        """A recorded tracked laser scan turned into an acquisition: per frame the
        poses at the frame's time, the beam on the label map's surface, the laser
        spot checked against it, saturation; the usable frames' detector
        readings as boundary fluence per watt, each frame's source where its
        spot is (``sourceFrom="spot"``) or where its tracked beam meets the
        surface (``"beam"``). Written to ``outputFolder`` (with
        the per-frame report ``frames.json``) when given.

        Parameters
        ----------
        labelNode : label-map node, path or LabelMap
        optics : optics.json path, dict or Optics
        recording : recording folder (docs/recording.md)
        calibration : calibration JSON file or scene (.mrml); None: the one
            recording.json names
        spotToleranceMm : how far the spot may lie from the beam [mm]
            (default ``recording.SPOT_TOLERANCE_MM``)
        sourceFrom : ``"spot"`` (the spot's surface point, seen with the same
            camera pose as the frame's readings, docs/recording.md) or
            ``"beam"``

        Returns
        -------
        (Acquisition, per-frame report rows, info: frames_used, frames_rejected,
        warnings, ...)
        """
        from FluoTomoLib.tomography.recording import (SPOT_TOLERANCE_MM, acquire_recording,
                                                      write_recorded_acquisition)

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        optics.check_labels(lm.labels)
        acq, rows, info = acquire_recording(
            lm, optics, recording, calibration,
            SPOT_TOLERANCE_MM if spotToleranceMm is None else float(spotToleranceMm),
            source_from=sourceFrom, progress=progress, cancel=cancel)
        if outputFolder is not None:
            write_recorded_acquisition(outputFolder, acq, rows, info)
        return acq, rows, info

    def recordScan(self, labelNode, optics, yieldByLabel, outputFolder, trackingErrorMm=0.5,
                   handEyeErrorMm=0.3, seed=0, accuracy="fast", progress=None, cancel=None,
                   **faults):
        """A recording of a tracked laser raster scan rendered from a label map's
        truth (docs/recording.md): camera frames from the camera's true pose,
        tool poses with ``trackingErrorMm`` (3D RMS) of error, the hand-eye
        calibration ``handEyeErrorMm`` off, written to ``outputFolder`` with
        the calibrations. ``faults``: ``missing_pose``, ``saturated``,
        ``spot_off`` (lists of frame numbers), ``tracking_error_deg``.
        Returns record_scan's dict (folder, frames, truth, seconds)."""
        from FluoTomoLib.tomography.recording import record_scan

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        yields = {int(k): float(v) for k, v in dict(yieldByLabel).items()}
        return record_scan(lm, optics, yields, outputFolder, tracking_error_mm=trackingErrorMm,
                           hand_eye_error_mm=handEyeErrorMm, seed=seed, accuracy=accuracy,
                           progress=progress, cancel=cancel, **faults)

    def checkPlanInputs(self, labelNode, targets, positions, **options):
        """The scan planner's input (:meth:`planScan`) checked before any work:
        targets in the label map, positions, spacing, visibility, assumed yields;
        refused in one line naming the field. Returns the targets (list of int)."""
        from FluoTomoLib.tomography import check_plan_inputs

        return check_plan_inputs(self.labelMap(labelNode), targets, positions, **options)

    def planScan(self, labelNode, optics, targets, positions=None, progress=None, cancel=None,
                 **options):
        """Plan a scan: the laser entry points on the visible skin that minimise
        the targets' predicted HP 95 % intervals (docs/tomography-own-scene.md,
        "Planning the scan"; docs/physics.md section 8.6).

        Parameters
        ----------
        labelNode : label-map node, path or LabelMap
        optics : optics.json path, dict or Optics
        targets : int or list of int, the labels the scan is for
        positions : int, laser positions (None: as many as the default scan)
        options : min_spacing_mm, noise_pct, visible_from, max_angle_deg,
            camera_ras, yield_by_label, time_budget_s, reach_mm, exclude_mm,
            detectors_per_side (``tomography.plan.plan_scan``)

        Returns
        -------
        dict: sources_ras (N, 3), detectors_ras (D, 3), mask (N, D), approach_ras
        (N, 3), predicted {"HP": {label: interval}, "SP": None}, ...
        """
        from FluoTomoLib.tomography import plan_scan

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        return plan_scan(lm, optics, targets, positions, progress=progress, cancel=cancel,
                         **options)

    def planScanToFolder(self, labelNode, optics, targets, outputFolder, positions=None,
                         progress=None, cancel=None, **options):
        """:meth:`planScan` written to ``outputFolder`` (sources.csv, detectors.csv
        for ``simulateToFolder``'s sources/detectors, plan.json) as one
        transaction; returns plan.json's content."""
        from FluoTomoLib.tomography import write_plan

        plan = self.planScan(labelNode, optics, targets, positions, progress, cancel, **options)
        return write_plan(outputFolder, plan)

    def reconstructToFolder(self, labelNode, optics, acquisition, outputFolder, method="HP",
                            lam=None, target=None, accuracy="balanced", progress=None,
                            cancel=None, **options):
        """Yield of a label map from an acquisition written to ``outputFolder``:
        ``yield.nrrd`` [1/mm] on the label map's grid (same origin, spacing and
        direction) and ``reconstruction.json``; returns the summary.

        ``options``: size_mm, roi_ras, truncation_pct, data_model,
        self_absorption, grading, noise_pct, segmentation_mm
        (``reconstruct_labelmap``)."""
        from FluoTomoLib.tomography import reconstruct_labelmap, write_reconstruction

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        acq = self.readAcquisition(acquisition, lm, optics)
        result = reconstruct_labelmap(lm, optics, acq, method=method, lam=lam, target=target,
                                      accuracy=accuracy, progress=progress, cancel=cancel,
                                      **options)
        return write_reconstruction(outputFolder, lm, result)

    @staticmethod
    def loadBatch(path, methods=None, lam=None, accuracy=None):
        """Every case of a batch file (.csv, .json, .yaml), each row and input
        checked and read once; ``methods``, ``lam``, ``accuracy``: for the rows
        that name none."""
        from FluoTomoLib.tomography.batch import load_batch

        return load_batch(path, methods=methods, lam=lam, accuracy=accuracy)

    @staticmethod
    def runBatch(cases, outputFolder, executor=None, threads=1, resume=False, progress=None,
                 cancel=None):
        """Reconstruct the cases of :meth:`loadBatch` on the run engine into
        ``outputFolder`` (table.csv, cases/NAME/METHOD/...); returns the run's
        summary (tasks, failures, seconds)."""
        from FluoTomoLib.tomography.batch import run_batch

        return run_batch(cases, outputFolder, executor=executor, threads=threads,
                         resume=resume, progress=progress, cancel=cancel)

    def buildMesh(self, labelNode, sizeMm=None, roi=None, target=None, acquisition=None,
                  optics=None, accuracy="balanced", quality=False, outputModelNode=None,
                  grading=None, progress=None, cancel=None):
        """Tetrahedral mesh of a label map as a model node (a volume mesh: cell
        array ``region`` = label, RAS mm) -> the node.

        ``sizeMm``: the element size (near the optodes when an acquisition is
        given; default: the ``accuracy`` level's).  The structured mesh is the
        reconstruction mesh :meth:`reconstruct` uses when given this node
        (``meshNode``): anchored at and refined across
        the ``target`` label (default: the smallest region that is not the
        largest), its tissue-air nodes on the smooth surface; with an
        ``acquisition`` (and ``optics``) its region of interest is the one
        chosen from the light's decay length, else ``roi`` (RAS box) or the
        tissue's box.  ``quality`` builds the fTetWild mesh instead: a preview
        (smooth interfaces), which reconstructions do not use.
        """
        job = self.prepareBuildMesh(labelNode, sizeMm, roi, target, acquisition, optics,
                                    accuracy, quality, grading)
        return self.storeBuiltMesh(job(progress, cancel), outputModelNode)

    def prepareBuildMesh(self, labelNode, sizeMm=None, roi=None, target=None, acquisition=None,
                         optics=None, accuracy="balanced", quality=False, grading=None):
        """:meth:`buildMesh` split for a worker thread: read the scene now,
        return ``job(progress, cancel) -> built``; hand ``built`` to
        :meth:`storeBuiltMesh` on the scene's thread."""
        import numpy as np

        from fluoguide.errors import FluoInputError
        from fluoguide.progress import check_cancel, report

        lm = self.labelMap(labelNode)
        acq = None
        if acquisition is not None:
            if optics is None:
                raise FluoInputError("an acquisition's region of interest needs the optics",
                                     field="optics")
            optics = self.readOptics(optics)
            acq = self.readAcquisition(acquisition, labelNode, optics)
        elif optics is not None:
            optics = self.readOptics(optics)
        size = None if sizeMm is None else float(sizeMm)
        if size is not None and not (np.isfinite(size) and 0.2 <= size <= 10.0):
            raise FluoInputError("element size must be within 0.2..10 mm", field="sizeMm",
                                 value=sizeMm)
        if grading not in (False, None, True, "grid", "bisection"):
            raise FluoInputError("grading must be none, grid or bisection", field="grading",
                                 value=grading)
        if grading is None:
            from FluoTomoLib.tomography.reconstruct import DEFAULT_GRADING

            grading = DEFAULT_GRADING if acq is not None else False
        if grading and acq is None and not quality:
            raise FluoInputError("a graded mesh is graded from the optodes: give the "
                                 "acquisition", field="grading", value=grading)

        def job(progress=None, cancel=None):
            from FluoTomoLib.tomography.accuracy import accuracy_settings, cap_at_burial
            from FluoTomoLib.tomography.labelmap import place_on_surface
            from FluoTomoLib.tomography.model import reconstruction_mesh
            from FluoTomoLib.tomography.reconstruct import labelmap_mesh
            from FluoTomoLib.tomography.roi import roi_from_ras

            if not quality:             # the structured mesher's checks are compiled
                from FluoTomoLib.fem.kernels import prepare_kernels

                prepare_kernels(progress, 0.0, cancel)
            report(progress, 0.05, "meshing the label map")
            settings = accuracy_settings(accuracy, recon_mm=size)
            h, mfp = settings["recon_mm"], None
            if optics is not None:
                h, mfp = cap_at_burial(h, optics, lm.labels)
            if quality:
                from FluoTomoLib.meshing.tetwild import mesh_labelmap_quality

                mesh = mesh_labelmap_quality(lm.labels_kji, lm.spacing_mm, lm.origin_mm, h,
                                             roi=roi, direction=lm.direction, progress=progress,
                                             cancel=cancel)
                mesh.meta["preview"] = True
                return {"mesh_ras": mesh, "mesh_local": None, "labelmap": lm,
                        "preview": True, "roi_info": None}
            tgt = lm.default_target() if target is None else int(target)
            roi_info = None
            if acq is not None:
                # the mesh reconstruct() would build for this acquisition (one path)
                src, _ = place_on_surface(lm, acq.sources_ras_mm, "sources",
                                          file=acq.file_of("sources"))
                det, _ = place_on_surface(lm, acq.detectors_ras_mm, "detectors",
                                          file=acq.file_of("detectors"))
                mesh, roi_info, _ = labelmap_mesh(
                    lm, optics, src, det, acq.mask, tgt, settings, grading, roi,
                    progress=progress, cancel=cancel)
            else:
                box = None if roi is None else roi_from_ras(lm, roi)
                check_cancel(cancel)
                mesh = reconstruction_mesh(lm.labels_kji, lm.spacing_mm, h, box, tgt,
                                           settings["refine_factor"], surface=lm.surface(),
                                           burial_mm=mfp, cancel=cancel)
            report(progress, 1.0, "mesh done")
            return {"mesh_ras": lm.mesh_to_ras(mesh), "mesh_local": mesh, "labelmap": lm,
                    "preview": False, "roi_info": roi_info, "accuracy": settings}

        return job

    def storeBuiltMesh(self, built, outputModelNode=None):
        """The built mesh into ``outputModelNode`` or a new ``FluoTomoMesh*``
        node (and ``FluoTomoMeshSurface`` for display); returns the node."""
        from fluoguide import mrml_io
        from FluoTomoLib.scene import store_mesh_model, store_mesh_surface

        mesh = built["mesh_ras"]
        node = store_mesh_model(self.scene, mesh, outputModelNode)
        self._meshes[node.GetID()] = built
        mrml_io.set_json_attribute(node, "FluoTomo.Mesh", {
            "preview": bool(built["preview"]), "nodes": mesh.n_nodes, "elements": mesh.n_elements,
            "size_mm": mesh.meta.get("size_mm"),
            "region_volumes_mm3": {str(k): v for k, v in mesh.region_measures().items()},
            "labelmap_volumes_mm3": {str(k): v for k, v in
                                     mesh.meta.get("labelmap_volumes_mm3", {}).items()},
            "volume_error_pct": {str(k): v for k, v in
                                 mesh.meta.get("volume_error_pct", {}).items()},
            "warnings": list(mesh.meta.get("warnings", [])),
            "region_of_interest": built.get("roi_info")})
        store_mesh_surface(self.scene, mesh)
        self.mesh = mesh
        return node

    def meshToFile(self, labelNode, outputFile, sizeMm=1.6, roi=None, quality=True,
                   refine=None, threads=None, optodes=None, fineSizeMm=None, progress=None):
        """Mesh a label map into a tetrahedral .vtu file (cell array ``region`` =
        label, RAS mm) and return its quality report (``fluo mesh``).

        Parameters
        ----------
        labelNode : label-map node, or a path (.nrrd, .nii(.gz), .seg.nrrd, .mrml)
        sizeMm : element size [mm] (away from the optodes when graded)
        roi : [x0, x1, y0, y1, z0, z1] RAS mm: crop first (default: the whole map)
        quality : the fTetWild mesher (smooth interfaces) instead of the
            structured one (staircase surfaces, a second)
        refine : quality mesher: ("sphere", x, y, z, r, size) or ("box", x0, x1,
            y0, y1, z0, z1, size) [mm]
        threads : quality mesher: fTetWild's threads (default: all)
        optodes : structured mesher: CSV paths of x,y,z [RAS mm] rows, or an
            (N, 3) array: grid lines ``fineSizeMm`` (x, y, z) [mm] at their
            coordinates (checked as field ``optodes``)

        Returns
        -------
        dict: counts, per-region volumes against the label map, dihedral
        angles, bad elements, ``file``, ``method``
        """
        from os import PathLike

        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.labelmap_io import read_labelmap
        from FluoTomoLib.fem.mesh_data import read_points
        from FluoTomoLib.meshing.to_file import mesh_to_file

        if isinstance(labelNode, (str, PathLike)):
            labels, spacing, origin, direction = read_labelmap(labelNode)
        else:
            geo = mrml_io.volume_geometry(labelNode)
            labels = mrml_io.volume_array(labelNode).copy()
            spacing, origin, direction = geo["spacing"], geo["origin"], geo["direction"]
        if optodes is not None and not isinstance(optodes, np.ndarray):
            optodes = np.concatenate([read_points(f, "optodes") for f in optodes])
        return mesh_to_file(labels, spacing, origin, direction, sizeMm, outputFile, roi=roi,
                            quality=quality, refine=refine, threads=threads, optodes=optodes,
                            fine_mm=fineSizeMm, progress=progress)

    def meshRegionVolumes(self, meshNode):
        """{label: (mesh volume, label-map volume, error %)} of a built mesh."""
        from fluoguide import mrml_io

        info = mrml_io.get_json_attribute(meshNode, "FluoTomo.Mesh") or {}
        mesh = info.get("region_volumes_mm3", {})
        ref = info.get("labelmap_volumes_mm3", {})
        err = info.get("volume_error_pct", {})
        return {int(k): (v, ref.get(k), err.get(k)) for k, v in mesh.items()}

    def forward(self, labelOrMesh, optics, sources, detectors, yieldVolumeNode=None,
                sizeMm=None, accuracy="balanced", force=False):
        """Excitation and fluorescence boundary data of a label map (meshed
        whole, as a simulation is) or of a mesh node built by :meth:`buildMesh`.

        ``sources``, ``detectors``: (S, 3), (D, 3) RAS mm on the tissue surface.
        ``yieldVolumeNode``: the yield [1/mm] as a volume (any grid; sampled at
        the mesh nodes); without it only the excitation is computed.
        A mesh too coarse for the optics (the resolution guard, as ``fluo
        forward`` applies it) is refused unless ``force``.
        Returns {"excitation": (S, D), "fluorescence": (S, D) or None} per watt
        [1/mm^2]."""
        import numpy as np

        from fluoguide import mrml_io
        from FluoTomoLib.fem.forward import FluorescenceModel
        from FluoTomoLib.tomography.accuracy import accuracy_settings
        from FluoTomoLib.tomography.labelmap import place_on_surface
        from FluoTomoLib.tomography.model import membership
        from FluoTomoLib.tomography.simulate import simulation_mesh

        optics = self.readOptics(optics)
        built_mesh = labelOrMesh is not None and labelOrMesh.IsA("vtkMRMLModelNode")
        if built_mesh:
            built = self._built(labelOrMesh)
            lm, mesh = built["labelmap"], built["mesh_local"]
        else:
            lm = self.labelMap(labelOrMesh)
            mesh = None
        optics.check_labels(lm.labels)
        src, _ = place_on_surface(lm, np.atleast_2d(np.asarray(sources, float)), "sources")
        det, _ = place_on_surface(lm, np.atleast_2d(np.asarray(detectors, float)), "detectors")
        if mesh is None:
            s = accuracy_settings(accuracy, simulate_mm=sizeMm)
            mesh = simulation_mesh(lm, np.vstack([src, det]), lm.default_target(),
                                   s["simulate_mm"], s["simulate_coarse_mm"], 4.0)
        labs, F = membership(mesh, lm.labels_kji, lm.spacing_mm)
        y = None
        if yieldVolumeNode is not None:
            from scipy import ndimage

            geo = mrml_io.volume_geometry(yieldVolumeNode)
            arr = mrml_io.volume_array(yieldVolumeNode).astype(float)
            ras = lm.to_ras(mesh.nodes_mm)
            ijk = (ras - geo["origin"]) @ geo["direction"] / geo["spacing"]
            y = ndimage.map_coordinates(arr, ijk[:, ::-1].T, order=1, mode="nearest")
        px, pm = optics.nodal(labs, F, yield_nodes=y)
        fm = FluorescenceModel(mesh, px, pm, src, det,
                               source_normals=lm.surface().closest(src)[1],
                               cut_facets=lm.cut_facets(mesh))
        refuse = fm.accuracy()["refuse"]
        if refuse and not force:
            from fluoguide.errors import FluoInputError

            raise FluoInputError("; ".join(refuse) + " (force=True to compute the data anyway)",
                                 field=labelOrMesh.GetName() if built_mesh else "sizeMm",
                                 value=None if built_mesh else sizeMm)
        return {"excitation": fm.excitation_data(),
                "fluorescence": None if y is None else fm.emission_data(y),
                "mesh_nodes": mesh.n_nodes}

    def forwardMesh(self, mesh, sources, detectors, optics=None, mua=None, musp=None, n=1.33,
                    yieldByLabel=None, model="auto", solver="auto", jacobian=False, force=False,
                    forceName="force"):
        """Boundary data of sources and detectors on a mesh file (the
        ``fluo forward`` computation): the exact half-space answer where it
        applies, else the diffusion FEM, which refuses a mesh too coarse for its
        optics unless ``force``.

        Parameters
        ----------
        mesh : path (.vtu with a cell array ``region``, NIRFAST stem) or Mesh
        sources, detectors : CSV paths of ``x,y[,z]`` [mm] rows, or (N, dim) arrays
        optics : optics.json path, dict or Optics per region; or None and
            ``mua``, ``musp`` [1/mm], ``n`` of one material (the half-space
            answer applies to this case only)
        yieldByLabel : {region: yield [1/mm]}: also the fluorescence data
        model : "auto", "fem" or "analytic"
        solver : the FEM's linear solver (``operators.SOLVERS`` or "auto")
        jacobian : also the Jacobians (arrays ``jacobian_mua``, ``jacobian_yield``)
        forceName : how the caller names ``force``, in the refusal's message

        Returns
        -------
        dict
            nodes, elements, sources, detectors, regions, reoriented_elements,
            then the data (``mesh_data.mesh_boundary_data``): detector_fluence
            [1/mm^2 per W], accuracy, warnings, ...
        """
        from os import PathLike

        import numpy as np

        from FluoTomoLib.fem.mesh_data import (check_optodes, mesh_boundary_data,
                                               read_forward_mesh, read_points)
        from FluoTomoLib.fem.operators import check_solver
        from FluoTomoLib.optics import check_properties
        from FluoTomoLib.tomography import homogeneous_optics

        check_solver(solver, field="solver")
        file = mesh if isinstance(mesh, (str, PathLike)) else None
        mesh, flipped = read_forward_mesh(mesh) if file is not None else (mesh, 0)
        pts = {}
        for name, value in (("sources", sources), ("detectors", detectors)):
            path = value if isinstance(value, (str, PathLike)) else None
            pts[name] = check_optodes(mesh, read_points(path, name) if path is not None
                                      else np.atleast_2d(np.asarray(value, float)), name, path)
        half_space = None
        if optics is None:
            check_properties(mua, musp, n, where="properties", warn=False)
            optics = homogeneous_optics(mua, musp, n, labels=mesh.regions)
            half_space = (mua, musp, n)
        else:
            optics = self.readOptics(optics)
        yields = None if yieldByLabel is None else {int(k): float(v)
                                                    for k, v in dict(yieldByLabel).items()}
        out = {"nodes": mesh.n_nodes, "elements": mesh.n_elements,
               "sources": len(pts["sources"]), "detectors": len(pts["detectors"]),
               "regions": [int(r) for r in mesh.regions], "reoriented_elements": flipped}
        out.update(mesh_boundary_data(mesh, optics, pts["sources"], pts["detectors"], yields,
                                      model=model, solver=solver, jacobian=jacobian, force=force,
                                      half_space=half_space, file=file, force_name=forceName))
        return out

    @staticmethod
    def analytic(mua, musp, n=1.33, rho=None, yieldPerMm=None, muaM=None, muspM=None,
                 unscattered=False):
        """Closed-form diffusion theory of a homogeneous semi-infinite medium
        (docs/physics.md section 3): Rd, mueff [1/mm], penetration depth [mm],
        D [mm], A; with ``rho`` (distances [mm]) R(rho) and the exact Robin
        surface fluence; with ``yieldPerMm`` the total diffuse fluorescence F
        (emission ``muaM``, ``muspM`` [1/mm], default the excitation's).
        Checks name the fields ``properties``, ``rho`` and ``emission``."""
        from FluoTomoLib.analytic import diffusion_summary

        return diffusion_summary(mua, musp, n, rho, yieldPerMm, muaM, muspM, unscattered)

    @staticmethod
    def checkStudy(mapping, file=None):
        """The study spec of a study-file mapping (``study`` A/B/C, ``sweep``,
        ``targets``, grid axes; docs/scale.md) with every task's parameters
        checked before any work (``file``: where the mapping came from, for
        messages)."""
        from FluoTomoLib.studies.spec import spec_from_mapping, study_tasks

        spec = spec_from_mapping(mapping, file=file)
        study_tasks(spec)
        spec.warnings.clear()       # the checks' warnings: the run says them again
        return spec

    @staticmethod
    def runStudy(spec, outputFolder=None, executor=None, threads=1, resume=False,
                 progress=None):
        """Run a study spec of :meth:`checkStudy` (rows: true against
        reconstructed yield and centroid per target, method and lambda), into
        ``outputFolder`` when given (table.csv, tasks/, figures)."""
        from FluoTomoLib.studies.run import run_spec

        return run_spec(spec, out_dir=outputFolder, progress=progress, executor=executor,
                        resume=resume, threads=threads)

    @staticmethod
    def checkMonteCarloEngine(engine="auto"):
        """Load the Monte Carlo engine (``auto``, ``mcxcl``, ``mcx``): a missing
        one is refused in one line before any run or cluster starts."""
        from FluoTomoLib.montecarlo.engine import load_engine

        return load_engine(engine)

    @staticmethod
    def validateTubeMonteCarlo(outputFolder, depths=None, mcIn=None, simulate=False,
                               photons=None, methods=("NP", "SP", "HP"), accuracy="fast",
                               executor=None, threads=1, resume=False, progress=None,
                               figureName="validate_mc_tomography.png", simulateFem=False,
                               grading="bisection"):
        """The cylinder-tube phantom reconstructed from Monte Carlo data and from
        diffusion-FEM data of the same optodes (docs/validation.md).

        ``depths`` [mm]: the tube's (default: the stored sets'); ``mcIn``: a
        folder of ``depth_<d>mm`` acquisitions (default: the stored ones);
        ``simulate``: run the Monte Carlo here (``photons`` per run) into
        ``outputFolder``/mc; ``simulateFem``: compute the diffusion-FEM data here
        (whole phantom) into ``outputFolder``/mc/depth_<d>mm/fem instead of
        reading the stored ones; ``grading``: the reconstruction mesh's
        (:meth:`reconstruct`'s; default the graded one, the demo's). Returns the rows (yield and centroid errors per
        depth, method and data) and writes the figure ``figureName`` to
        ``outputFolder`` (``figure``: its path)."""
        from pathlib import Path

        from FluoTomoLib.pipelines import tube_mc

        depths = list(tube_mc.DEPTHS_MM) if depths is None else list(depths)
        res = tube_mc.validate_tube_mc(
            depths, mc_root=mcIn, simulate=simulate, photons=photons or tube_mc.PHOTONS,
            out_dir=outputFolder, methods=list(methods), accuracy=accuracy, executor=executor,
            threads=threads, resume=resume, progress=progress, simulate_fem=simulateFem,
            grading=grading)
        Path(outputFolder).mkdir(parents=True, exist_ok=True)
        res["figure"] = tube_mc.figure(res, Path(outputFolder) / figureName)
        return res

    @staticmethod
    def tomographyCaseTasks(tubeDepthsMm=(), oral=False, seed=0, tubeOptions=None,
                            oralOptions=None):
        """The run-engine tasks of the tomography cases (``fluo demo``'s): a
        simulated tracked acquisition and its NP/SP/HP reconstructions of the
        cylinder-tube phantom per depth, then the oral cavity's.

        Parameters
        ----------
        tubeDepthsMm : sequence of float
            Depth of the tube [mm], one case each.
        oral : bool
            Add the oral-cavity case.
        seed : int
            Each case's noise seed (and its phantom's).
        tubeOptions, oralOptions : dict, optional
            Options of the cases over their own (``fine_mm`` [mm],
            ``n_sources``, ``accuracy``, ...); an unknown name is a
            FluoInputError before any work.

        Returns
        -------
        list of fluoguide.runs.Task
            For :meth:`runTomographyCases`.
        """
        from FluoTomoLib.pipelines.cases import case_tasks

        return case_tasks(tubeDepthsMm, oral=oral, seed=seed, tube_options=tubeOptions,
                          oral_options=oralOptions)

    @staticmethod
    def writeTubeTruth(surfaceTruth, folder):
        """Write a tube case's simulated true fields (a case run with the tube
        option ``truth="simulate"``) as ``folder/depth_<d>mm.npz``, the layout
        of the stored sets the cases read (``fluo demo --simulate-truth``).

        Parameters
        ----------
        surfaceTruth : FluoTomoLib.pipelines.tube_truth.SurfaceTruth
        folder : path

        Returns
        -------
        pathlib.Path
            The file written.
        """
        from FluoTomoLib.pipelines.tube_truth import truth_file, write_truth

        return write_truth(truth_file(surfaceTruth.info["depth_mm"], folder), surfaceTruth)

    @staticmethod
    def runTomographyCases(tasks, recordFolder, resume=False, executor=None, threads=None,
                           progress=None, cancel=None, label="tomography cases"):
        """Run the tasks of :meth:`tomographyCaseTasks` on the run engine, each
        case recorded in ``recordFolder`` as it finishes.

        Parameters
        ----------
        tasks : list of fluoguide.runs.Task
        recordFolder : path
            Where the cases' records go; ``resume`` reuses the finished ones.
        executor, threads
            Where the cases run (None: serially in this process) and the
            library threads of each (None: the process's).
        label : str
            The run's name in progress messages.

        Returns
        -------
        dict
            The run's account (``tasks``, ``computed``, ``reused``,
            ``failures``, ``seconds`` [s], ``executor``, ``workers``,
            ``failed``: each failed case's ``params`` and ``error``), ``store``
            (the records folder) and ``cases``: each case as the tomography
            pipeline returns it (``results``, ``coarse``, ``sections``, ...), in
            task order; empty when a case failed.
        """
        from fluoguide.runs import RunStore, run_tasks
        from FluoTomoLib.pipelines.cases import case_of_record

        store = RunStore(recordFolder, resume=resume)
        run = run_tasks(tasks, store=store, executor=executor, threads=threads,
                        progress=progress, cancel=cancel, label=label)
        run["store"] = str(store.dir)
        run["cases"] = [] if run["failed"] else [case_of_record(rec, store.arrays(rec))
                                                 for rec in run["records"]]
        return run

    @staticmethod
    def writeReconstructionMesh(case, path, methods=("NP", "SP", "HP")):
        """A case's reconstruction mesh as a VTU file, each method's yield
        [1/mm] as point data (``case``: one of :meth:`runTomographyCases`)."""
        from FluoTomoLib.meshing.vtu_io import write_vtu

        write_vtu(case["coarse"], path,
                  point_data={m: case["results"][m]["yield"] for m in methods})

    # -- the diffusion model against Monte Carlo (fluo validate mc, mc-fluorescence) ------
    @staticmethod
    def halfSpaceMonteCarlo(outputFolder, mua=None, musp=None, n=None, g=None, mcIn=None,
                            photons=250_000, runs=4, seed=1, engine="auto", executor=None,
                            threads=1, resume=False, commandLine=None, progress=None):
        """Monte Carlo of a pencil beam on a semi-infinite medium (a 160 x 160 x
        80 mm box of 1 mm voxels), run here or read from a stored set.

        Parameters
        ----------
        outputFolder : path
            Where the runs' records go (``mc_runs``, ``resume`` continues them)
            and the set ``mc_halfspace.json`` (created when Monte Carlo runs).
        mua, musp : float, optional
            Absorption and reduced scattering [1/mm] (default 0.01, 1.0).
        n, g : float, optional
            Refractive index of the tissue (outside air; default 1.37) and
            anisotropy (default 0.9).
        mcIn : path, optional
            A stored half-space set (JSON) instead of running Monte Carlo; the
            properties given must then be the set's own.
        photons, runs, seed : int
            Photons per run, independent runs, the first run's seed.
        engine : str
            ``auto``, ``mcxcl`` or ``mcx`` (:meth:`checkMonteCarloEngine`).
        commandLine : str, optional
            The command that made the set, stored with it.

        Returns
        -------
        dict
            ``medium`` (HalfSpace), ``merged`` (the merged runs: reflectance
            [1/mm^2], fluence, standard errors, energy balance, ...) and
            ``mc_source`` (the set read, or "this run").
        """
        from pathlib import Path

        import numpy as np

        from fluoguide import atomic
        from fluoguide.errors import FluoInputError
        from fluoguide.runs.store import RunStore
        from FluoTomoLib.montecarlo import reference
        from FluoTomoLib.montecarlo.halfspace import HalfSpace, simulate_halfspace

        if mcIn is not None:        # '' is a (bad) file name, not 'run Monte Carlo'
            data = reference.read_set(mcIn)
            if data["kind"] != "halfspace":
                raise FluoInputError("is not a half-space set", file=mcIn, field="kind",
                                     value=data["kind"])
            for name, given, key in (("--n", n, "n_inside"), ("--mua", mua, "mua_per_mm"),
                                     ("--musp", musp, "musp_per_mm"), ("--g", g, "g")):
                if given is not None and not np.isclose(given, data["medium"][key]):
                    raise FluoInputError(f"differs from the set's medium ({data['medium'][key]:g})",
                                         file=mcIn, field=name, value=given)
            return {"medium": reference.medium_of_set(data),
                    "merged": reference.merged_of_set(data), "mc_source": str(mcIn)}
        medium = HalfSpace(0.01 if mua is None else mua, 1.0 if musp is None else musp,
                           1.37 if n is None else n, g=0.9 if g is None else g)
        # every run is a task of the run engine: written to mc_runs as it finishes
        # (resume continues a killed set); a seed draws the same photons wherever it runs
        merged = simulate_halfspace(medium, photons, runs=runs, seed=seed, engine=engine,
                                    progress=progress, executor=executor, threads=threads,
                                    store=RunStore(Path(outputFolder) / "mc_runs", resume=resume))
        out = atomic.make_folder(outputFolder)
        reference.write_json_atomic(out / "mc_halfspace.json",
                                    reference.halfspace_set(medium, merged, commandLine))
        return {"medium": medium, "merged": merged, "mc_source": "this run"}

    @staticmethod
    def validateHalfSpace(outputFolder, monteCarlo, boundaries=("empirical", "fresnel"),
                          meshLevel="normal", reference=None, progress=None):
        """The FEM (one solve per boundary constant A), the dipole and the exact
        Robin half-space against a Monte Carlo half-space set; the independent
        stored run is the check of the Monte Carlo where the medium is its own.

        Parameters
        ----------
        outputFolder : path
            Where ``validate_mc.png`` goes (created when missing).
        monteCarlo : dict
            :meth:`halfSpaceMonteCarlo`'s result.
        boundaries : tuple of str
            ``empirical`` and/or ``fresnel``.
        meshLevel : str
            The FEM mesh of the quarter box: ``test``, ``coarse`` or ``normal``.
        reference : path, optional
            An independent R(rho) CSV to check the Monte Carlo against.

        Returns
        -------
        dict
            The medium, the Monte Carlo's account (photons, runs, seeds,
            device, engine, seconds [s], energy balance), ``A``,
            ``agree_from_mm`` [mm], ``rows`` (reflectance per distance [mm]:
            Monte Carlo, FEM, dipole, in %), ``fluence_rows``, ``warnings`` and
            ``figure`` (the PNG's path).
        """
        import numpy as np

        from fluoguide import atomic
        from fluoguide.errors import FluoInputError
        from FluoTomoLib.montecarlo import compare
        from FluoTomoLib.montecarlo import reference as references
        from FluoTomoLib.montecarlo.plots import validation_figure

        medium, merged = monteCarlo["medium"], monteCarlo["merged"]
        ref = None
        if reference:
            ref = references.read_independent_reflectance(reference)
        elif (np.isclose(medium.n, 1.37) and np.isclose(medium.mua, 0.01)
              and np.isclose(medium.musp, 1.0) and np.isclose(medium.g, 0.9)
              and np.allclose(medium.size_mm, (160, 160, 80)) and medium.voxel_mm == 1.0):
            ref = references.read_independent_reflectance()
        if ref is not None and not np.isclose(ref["n_inside"], medium.n):
            raise FluoInputError("the reference run's n differs from the medium's",
                                 field="--reference", value=ref["n_inside"])
        res = compare.validate_halfspace(medium, merged, boundaries=tuple(boundaries),
                                         level=meshLevel, reference=ref, progress=progress)
        text = f"mua {medium.mua:g}/mm, musp {medium.musp:g}/mm, g {medium.g:g}, n {medium.n:g}"
        figure = atomic.make_folder(outputFolder) / "validate_mc.png"
        validation_figure(res, text, figure)
        return {
            "medium": medium.metadata()["medium"], "volume_mm": list(medium.size_mm),
            "voxel_mm": medium.voxel_mm, "mc_source": monteCarlo["mc_source"],
            "photons": merged["photons"], "runs": merged["runs"], "seeds": merged["seeds"],
            "mc_executor": merged.get("executor"), "device": merged["device"],
            "engine": merged["engine"],
            "engine_version": merged["engine_version"], "mc_seconds": merged["seconds"],
            "energy": merged["energy"], "A": res["A"], "boundary_default": res["boundary"],
            "agree_within_pct": compare.AGREE_PCT, "agree_from_mm": res["agree_from_mm"],
            "reference": res["reference"], "fem_nodes": res["fem_nodes"],
            "fem_seconds": res["fem_seconds"], "rows": res["rows"],
            "fluence_rows": res["fluence_rows"], "warnings": res["warnings"],
            "figure": str(figure),
        }

    @staticmethod
    def fluorescenceMonteCarlo(outputFolder, mcIn=None, photons=100_000, runs=3, seed=3001,
                               engine="auto", executor=None, threads=1, resume=False,
                               commandLine=None, progress=None):
        """Monte Carlo of the stored fluorescence case (three optodes over a 4 mm
        sphere 7 mm deep): excitation from each source, emission by reciprocity;
        run here or read from a stored set.

        Parameters
        ----------
        outputFolder : path
            Where the runs' records go (``mc_runs``, ``resume`` continues them)
            and the set ``mc_fluorescence.json`` (when Monte Carlo runs).
        mcIn : path, optional
            A stored fluorescence set (JSON) instead of running Monte Carlo.
        photons, runs, seed : int
            Photons per run, per optode and wavelength; independent runs; the
            first run's seed.
        engine : str
            ``auto``, ``mcxcl`` or ``mcx``.
        commandLine : str, optional
            The command that made the set, stored with it.

        Returns
        -------
        dict
            ``case`` (the label map, optics and optodes), ``mc``
            (``excitation``, ``emission`` and their standard errors, (S, D),
            [1/mm^2 per W]), ``meta`` (the set's account: photons, runs,
            device, engine) and ``detector_radius_mm`` [mm].
        """
        from pathlib import Path

        import numpy as np

        from fluoguide import atomic
        from fluoguide.errors import FluoInputError
        from fluoguide.runs.store import RunStore
        from FluoTomoLib.montecarlo import reference
        from FluoTomoLib.montecarlo.acquisition import simulate_acquisition

        case = reference.fluorescence_case()
        keys = ("excitation", "excitation_se", "emission", "emission_se")
        if mcIn is not None:        # '' is a (bad) file name, not 'run Monte Carlo'
            data = reference.read_set(mcIn)
            if data["kind"] != "fluorescence":
                raise FluoInputError("is not a fluorescence set", file=mcIn, field="kind",
                                     value=data["kind"])
            return {"case": case, "mc": {k: np.asarray(data[k], float) for k in keys},
                    "meta": data, "detector_radius_mm": data["detector_radius_mm"]}
        radius = 2.0
        res = simulate_acquisition(
            *[case[k] for k in ("labels_kji", "ijk_to_ras", "optics_x", "optics_m",
                                "sources_ras", "detectors_ras", "yield_per_label")],
            photons=photons, seed=seed, runs=runs, detector_radius_mm=radius, engine=engine,
            progress=progress, executor=executor, threads=threads,
            store=RunStore(Path(outputFolder) / "mc_runs", resume=resume))
        data = reference.fluorescence_set(case, res, commandLine)
        reference.write_json_atomic(atomic.make_folder(outputFolder)
                                    / "mc_fluorescence.json", data)
        return {"case": case, "mc": {k: np.asarray(res[k], float) for k in keys}, "meta": data,
                "detector_radius_mm": radius}

    @staticmethod
    def validateFluorescence(monteCarlo, boundaries=("empirical", "fresnel")):
        """The FEM's excitation and emission data of the fluorescence case
        against :meth:`fluorescenceMonteCarlo`'s, per source-detector pair.

        Parameters
        ----------
        monteCarlo : dict
            :meth:`fluorescenceMonteCarlo`'s result.
        boundaries : tuple of str
            ``empirical`` and/or ``fresnel`` (the FEM's boundary constant A).

        Returns
        -------
        dict
            ``case`` (its description), the Monte Carlo's account, ``A`` per
            boundary, ``rows`` (per pair: distance [mm], Monte Carlo and FEM
            data [1/mm^2 per W], FEM vs Monte Carlo [%]) and ``warnings``.
        """
        import numpy as np

        from FluoTomoLib.montecarlo import compare, reference
        from FluoTomoLib.optics import robin_A

        case, mc, meta = monteCarlo["case"], monteCarlo["mc"], monteCarlo["meta"]
        n = float(case["optics_x"][1][2])
        fem = {b: compare.fem_acquisition(case, A=robin_A(n, b),
                                          detector_radius_mm=monteCarlo["detector_radius_mm"])
               for b in boundaries}
        src = np.asarray(case["sources_ras"])
        det = np.asarray(case["detectors_ras"])
        rows = []
        for s in range(len(src)):
            for d in range(len(det)):
                row = {"source": s, "detector": d,
                       "distance_mm": float(np.linalg.norm(src[s] - det[d])),
                       "mc_excitation": float(mc["excitation"][s, d]),
                       "mc_excitation_se": float(mc["excitation_se"][s, d]),
                       "mc_emission": float(mc["emission"][s, d]),
                       "mc_emission_se": float(mc["emission_se"][s, d])}
                for b, f in fem.items():
                    for kind in ("excitation", "emission"):
                        row[f"fem_{b}_{kind}"] = float(f[kind][s, d])
                        row[f"fem_{b}_{kind}_vs_mc_pct"] = compare._pct(f[kind][s, d],
                                                                        mc[kind][s, d])
                rows.append(row)
        warnings = ["excitation pairs closer than 5 mm (a source's own position) are "
                    "diffusion's near-source regime: not a test of the model"]
        doc = reference.fluorescence_case.__doc__.strip().split("\n\n")[1].replace("\n", " ")
        return {"case": doc, "photons_per_run": meta["photons_per_run"], "runs": meta["runs"],
                "device": meta["device"], "engine_version": meta["engine_version"],
                "A": {b: f["A"] for b, f in fem.items()}, "rows": rows, "warnings": warnings}

    def simulateAcquisition(self, labelNode, optics, yieldByLabel, scan=None, noise=1.0, seed=0,
                            sources=None, detectors=None, accuracy="balanced", engine="fem",
                            outputFolder=None, progress=None, cancel=None):
        """A simulated acquisition of a label map (its own mesh of the whole map,
        finer than a reconstruction's) -> Acquisition; written to
        ``outputFolder`` when given.  ``scan``: DEFAULT_SCAN keys for the default
        grid over the target, or ``sources``/``detectors`` (RAS mm)."""
        job = self.prepareSimulation(labelNode, optics, yieldByLabel, scan, noise, seed, sources,
                                     detectors, accuracy, engine, outputFolder)
        return job(progress, cancel)

    def prepareSimulation(self, labelNode, optics, yieldByLabel, scan=None, noise=1.0, seed=0,
                          sources=None, detectors=None, accuracy="balanced", engine="fem",
                          outputFolder=None):
        """:meth:`simulateAcquisition` split for a worker thread: reads the label map
        and the optics now, returns ``job(progress, cancel) -> Acquisition`` (no MRML
        inside; it writes ``outputFolder`` when given)."""
        from FluoTomoLib.tomography import simulate_acquisition, write_acquisition

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        yields = {int(k): float(v) for k, v in dict(yieldByLabel).items()}

        def job(progress=None, cancel=None):
            acq, info = simulate_acquisition(lm, optics, yields, sources, detectors, scan=scan,
                                             noise_pct=noise, seed=seed, engine=engine,
                                             accuracy=accuracy, progress=progress,
                                             cancel=cancel)
            if outputFolder is not None:
                write_acquisition(outputFolder, acq, simulation=info)
            return acq

        return job

    def reconstruct(self, labelNode, optics, acquisition, method="HP", lam=None, target=None,
                    outputVolumeNode=None, meshNode=None, accuracy="balanced", progress=None,
                    cancel=None, **options):
        """Yield of a label map from an acquisition -> (summary dict, volume node).

        ``optics``: optics.json path, dict or Optics; ``acquisition``: folder or
        Acquisition.  The yield volume lies on the label map's grid (same
        origin, spacing and direction) in ``outputVolumeNode`` or a new
        ``FluoTomoYield<method>`` node (``_1``, ``_2``... on later runs), with
        the summary as its ``FluoTomo.Reconstruction`` attribute.  ``meshNode``:
        a mesh built by :meth:`buildMesh` for this label map, used as the
        reconstruction mesh.  ``options``: size_mm, roi_ras, truncation_pct,
        data_model, self_absorption (reconstruct_labelmap)."""
        job = self.prepareReconstruction(labelNode, optics, acquisition, method, lam, target,
                                         meshNode, accuracy, **options)
        result = job(progress, cancel)
        node = self.storeReconstructionResult(result, outputVolumeNode)
        return result["summary"], node

    def prepareReconstruction(self, labelNode, optics, acquisition, method="HP", lam=None,
                              target=None, meshNode=None, accuracy="balanced", **options):
        """:meth:`reconstruct` split for a worker thread: reads the scene now,
        returns ``job(progress, cancel) -> result`` (no MRML inside); hand the
        result to :meth:`storeReconstructionResult` on the scene's thread."""
        from fluoguide.errors import FluoInputError
        from FluoTomoLib.tomography import reconstruct_labelmap

        lm = self.labelMap(labelNode)
        optics = self.readOptics(optics)
        acq = self.readAcquisition(acquisition, labelNode, optics)
        mesh = None
        if meshNode is not None:
            built = self._built(meshNode)
            if built["preview"]:
                raise FluoInputError("this mesh is a preview (fTetWild): reconstructions use "
                                     "the structured mesh", field=meshNode.GetName())
            if built["labelmap"] is not None and built["labelmap"].labels_kji.shape != \
                    lm.labels_kji.shape:
                raise FluoInputError("the mesh was built from another label map",
                                     field=meshNode.GetName())
            mesh = built["mesh_local"]

        def job(progress=None, cancel=None):
            result = reconstruct_labelmap(lm, optics, acq, method=method, lam=lam,
                                          target=target, accuracy=accuracy, mesh=mesh,
                                          progress=progress, cancel=cancel, **options)
            result["labelmap"] = lm
            return result

        return job

    def storeReconstructionResult(self, result, outputVolumeNode=None):
        """The yield volume of a reconstruction into the scene; returns the node."""
        from FluoTomoLib.scene import store_yield_volume

        lm = result["labelmap"]
        s = result["summary"]
        return store_yield_volume(self.scene, result["yield_kji"], lm.spacing_mm, lm.origin_mm,
                                  lm.direction, s, outputVolumeNode,
                                  base_name=f"FluoTomoYield{s['method']}")

    def _built(self, meshNode):
        """What :meth:`buildMesh` made for a model node (or the mesh read back from
        it, in the label map's frame, when the scene was saved and loaded)."""
        from fluoguide.errors import FluoInputError

        built = self._meshes.get(meshNode.GetID())
        if built is None:
            raise FluoInputError("this model node was not built by FluoTomoLogic.buildMesh in "
                                 "this session: build the mesh again", field=meshNode.GetName())
        return built


def _segment_array(scene, segmentationNode, segmentId, referenceVolume):
    """Binary array (K, J, I) of one segment on a reference volume's grid."""
    import slicer
    import vtk

    from fluoguide import mrml_io
    from fluoguide.errors import FluoInputError

    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    tmp = slicer.vtkMRMLLabelMapVolumeNode()
    scene.AddNode(tmp)
    try:
        ids = vtk.vtkStringArray()
        ids.InsertNextValue(segmentId)
        if not logic.ExportSegmentsToLabelmapNode(segmentationNode, ids, tmp, referenceVolume):
            raise FluoInputError("cannot rasterise segment", field=segmentId)
        return mrml_io.volume_array(tmp).copy()
    finally:
        scene.RemoveNode(tmp)


def _check_labelmap_output(outputFile, field):
    """Refuse, before any work, a label-map output that is not a writable
    ``.nrrd`` file name (``fluo segment``'s ``--out``, the app's saved map)."""
    from fluoguide import atomic
    from fluoguide.errors import FluoInputError

    if not str(outputFile).endswith(".nrrd"):
        raise FluoInputError("the label map is written as NRRD: name it .nrrd", field=field,
                             value=str(outputFile))
    atomic.check_writable(outputFile, field=field)


class FluoTomoTest(ScriptedLoadableModuleTest):
    """The module's workflow through the logic calls on synthetic data with
    known truth. Runs in Slicer's self-test and under pytest (a unittest.TestCase).

    The own-scene workflow: a small ellipsoidal body (label 3) with a 6 mm
    inclusion (label 7, yield 0.0026 /mm) 2.5 mm under its top, on a
    0.8 x 0.9 x 1.0 mm grid, read from a file; the acquisition is simulated
    on the simulation's own graded mesh of the whole label map and
    reconstructed on the region-of-interest mesh ``buildMesh`` made (a
    different mesh). Tolerance: HP within 15 % of the true yield, peak in the
    inclusion within 3 mm of its centre (the small end-to-end test of
    FluoTomo/Testing/Python/test_own_scene.py; measured here: +0.2 %, peak 1.5 mm
    from the centre).
    """

    def _scene(self):
        import slicer

        return slicer.vtkMRMLScene()

    def setUp(self):
        from fluoguide.slicer_compat import in_slicer_application

        if in_slicer_application():
            from fluoguide.slicer_deps import ensure_dependencies

            self.assertTrue(ensure_dependencies(ask=False), "FluoGuide's Python packages")

    def runTest(self):
        self.setUp()
        self.test_load_phantom_volumes()
        self.test_own_label_map_workflow()

    def test_own_label_map_workflow(self):
        import json
        import tempfile
        from pathlib import Path

        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.labelmap_io import write_volume_nrrd
        from fluoguide.phantoms import ellipsoid_inclusion_labelmap

        sc = ellipsoid_inclusion_labelmap(spacing_mm=(0.8, 0.9, 1.0),
                                          semi_axes_mm=(12.0, 10.0, 7.0), inclusion_gap_mm=2.5,
                                          inclusion_offset_mm=(1.0, -1.0))
        optics = {"n": 1.37,
                  "excitation": {"3": {"mua_per_mm": 0.01, "musp_per_mm": 1.0},
                                 "7": {"mua_per_mm": 0.012, "musp_per_mm": 1.1}},
                  "emission": {"3": {"mua_per_mm": 0.008, "musp_per_mm": 0.9},
                               "7": {"mua_per_mm": 0.01, "musp_per_mm": 1.0}}}
        truth = 2.6e-3
        with tempfile.TemporaryDirectory(prefix="FluoTomoTest-") as folder:
            folder = Path(folder)
            write_volume_nrrd(folder / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"],
                              sc["origin_mm"], sc["direction"])
            (folder / "optics.json").write_text(json.dumps(optics))
            logic = FluoTomoLogic(self._scene())
            labels = logic.loadLabelMap(folder / "labels.nrrd")
            acq = logic.simulateAcquisition(labels, folder / "optics.json", {7: truth}, noise=1.0,
                                            seed=0, accuracy="fast")
            mesh = logic.buildMesh(labels, acquisition=acq, optics=folder / "optics.json",
                                   accuracy="fast")
            for label, (_, ref, err) in logic.meshRegionVolumes(mesh).items():
                self.assertLess(abs(err), 1.0, f"label {label}: mesh volume vs {ref} mm^3")
            summary, node = logic.reconstruct(labels, folder / "optics.json", acq, method="HP",
                                              meshNode=mesh, accuracy="fast")
        self.assertEqual(summary["mesh"]["nodes"],
                         mrml_io.get_json_attribute(mesh, "FluoTomo.Mesh")["nodes"])
        self.assertLess(abs(summary["regions"]["7"]["yield_per_mm"] / truth - 1), 0.15)
        self.assertEqual(summary["peak_label"], 7)
        self.assertLess(np.linalg.norm(np.array(summary["peak_ras_mm"])
                                       - sc["inclusion_centre_ras_mm"]), 3.0)
        self.assertEqual(mrml_io.volume_array(node).shape, sc["labels_kji"].shape)
        self.delayDisplay("FluoTomo own label map test passed")

    def test_load_phantom_volumes(self):
        logic = FluoTomoLogic(self._scene())
        truth = logic.loadPhantom("cylinder-tube", depth_mm=3.7)
        volumes = logic.labelVolumes()
        for label, region in truth["regions"].items():
            analytic = region["analytic_volume_mm3"]
            self.assertLess(abs(volumes[int(label)] - analytic) / analytic, 0.02)
        self.delayDisplay("FluoTomo phantom test passed")
