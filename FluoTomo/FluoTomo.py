"""FluoTomo: image-guided fluorescence tomography (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The real code lives in ``FluoTomoLib``.
Loads in 3D Slicer, in plain Python with slicer-core, and under pytest.
"""

import logging

try:  # 3D Slicer
    from slicer.ScriptedLoadableModule import (ScriptedLoadableModule,
                                               ScriptedLoadableModuleLogic,
                                               ScriptedLoadableModuleTest,
                                               ScriptedLoadableModuleWidget)
except ImportError:  # slicer-core or no Slicer at all
    from fluoguide.slicer_compat import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )


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


class FluoTomoWidget(ScriptedLoadableModuleWidget):
    """In Slicer: a Qt form over FluoTomoLogic.  Outside Slicer the web app
    (``fluo app``) builds its panel (``fluoapp.webapp.tomo_panel``) over the same logic class."""

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        if self.layout is None:  # headless: nothing to lay out
            return
        import qt
        import slicer

        self.logic = FluoTomoLogic(slicer.mrmlScene)
        form = qt.QFormLayout()
        self.layout.addLayout(form)
        self.phantomCombo = qt.QComboBox()
        self.phantomCombo.addItems(["cylinder-tube", "oral-cavity", "slab"])
        form.addRow("Digital phantom:", self.phantomCombo)
        load = qt.QPushButton("Load phantom")
        load.connect("clicked(bool)", self.onLoadPhantom)
        form.addRow(load)
        self.status = qt.QLabel("")
        form.addRow(self.status)
        self.layout.addStretch(1)

    def onLoadPhantom(self):
        import slicer

        try:
            self.logic.loadPhantom(self.phantomCombo.currentText)
            self.status.setText("Loaded " + self.phantomCombo.currentText)
        except Exception as exc:  # shown to the user, not swallowed
            slicer.util.errorDisplay(str(exc))


class FluoTomoLogic(ScriptedLoadableModuleLogic):
    """Tomography on one MRML scene (passed in; never the global one).

    Nodes read and written are listed in docs/scene.md (section FluoTomo).
    """

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoTomoLogic needs an MRML scene")
        self.scene = scene

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

    def prepareTubeReconstruction(self, methods=("NP", "SP", "HP"), lam=10.0, seed=0,
                                  labelNodeName="CBCTLabels"):
        """A job ``job(progress, cancel) -> run`` that simulates the tracked
        acquisition of the cylinder-tube phantom in the scene (its truth is on
        ``CBCT``) and reconstructs on a mesh of the scene's label map.

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
                recon_labels=(labels, np.asarray(geo["spacing"]), np.asarray(geo["origin"])))

        job.grid = (mrml_io.volume_array(cbct).shape, mrml_io.volume_geometry(cbct))
        return job

    def storeReconstruction(self, run, grid):
        """Write ``FluoTomoYield*`` (on the CBCT grid) and ``FluoTomoMeshSurface``."""
        from FluoTomoLib.scene import store_reconstructions

        shape, geo = grid
        return store_reconstructions(self.scene, run["coarse"], run["results"], shape,
                                     geo["spacing"], geo["origin"])

    def buildMesh(self, sizeMm=1.0, roi=None, labelNodeName="CBCTLabels"):
        """Tetrahedral mesh of a label map (structured, fast path); shows its surface
        as ``FluoTomoMeshSurface`` and returns the Mesh."""
        from fluoguide import mrml_io
        from FluoTomoLib.scene import store_mesh_surface
        from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        geo = mrml_io.volume_geometry(node)
        mesh = mesh_labelmap_structured(mrml_io.volume_array(node), geo["spacing"], geo["origin"],
                                        sizeMm, roi=roi, direction=geo["direction"])
        store_mesh_surface(self.scene, mesh)
        self.mesh = mesh
        return mesh

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

    def reconstructTubePhantom(self, depthMm=4.7, methods=("NP", "SP", "HP"), seed=0,
                               progress=None, cancel=None):
        """Simulated tracked acquisition of the cylinder-tube phantom and its NP/SP/HP
        reconstructions; adds the phantom (if absent) and ``FluoTomoYield*`` volumes."""
        from fluoguide import mrml_io
        from fluoguide.phantoms import add_phantom_to_scene, make_phantom
        from FluoTomoLib.pipelines.tube import simulate_and_reconstruct
        from FluoTomoLib.scene import store_reconstructions

        phantom = make_phantom("cylinder-tube", depth_mm=depthMm, seed=seed)
        run = simulate_and_reconstruct(phantom, methods=methods, seed=seed, progress=progress,
                                       cancel=cancel)
        if mrml_io.get_node(self.scene, "CBCTLabels", required=False) is None:
            add_phantom_to_scene(self.scene, phantom)
        store_reconstructions(self.scene, run["coarse"], run["results"], phantom.labels.shape,
                              phantom.spacing_mm, phantom.origin_mm)
        return run

    def labelVolumes(self, labelNodeName="CBCTLabels"):
        """Volume [mm^3] of each label of a label-map node."""
        import numpy as np

        from fluoguide import mrml_io

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        arr = mrml_io.volume_array(node)
        vox = float(np.prod(mrml_io.volume_geometry(node)["spacing"]))
        labels, counts = np.unique(arr, return_counts=True)
        return {int(k): float(c * vox) for k, c in zip(labels, counts) if k != 0}


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


class FluoTomoTest(ScriptedLoadableModuleTest):
    """Runs in Slicer's self-test and under pytest (a unittest.TestCase)."""

    def _scene(self):
        import slicer

        return slicer.vtkMRMLScene()

    def runTest(self):
        self.setUp()
        self.test_load_phantom_volumes()

    def test_load_phantom_volumes(self):
        logic = FluoTomoLogic(self._scene())
        truth = logic.loadPhantom("cylinder-tube", depth_mm=3.7)
        volumes = logic.labelVolumes()
        for label, region in truth["regions"].items():
            analytic = region["analytic_volume_mm3"]
            self.assertLess(abs(volumes[int(label)] - analytic) / analytic, 0.02)
        self.delayDisplay("FluoTomo phantom test passed")
