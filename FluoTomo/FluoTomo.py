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
    from fluoguide.slicer_compat import (ScriptedLoadableModule,
                                         ScriptedLoadableModuleLogic,
                                         ScriptedLoadableModuleTest,
                                         ScriptedLoadableModuleWidget)


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
    (``fluo app``) builds its panel from the same logic."""

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

    def loadPhantom(self, name, **params):
        """Add a digital phantom's ``CBCT`` and ``CBCTLabels`` nodes; returns its truth dict."""
        from fluoguide.phantoms import add_phantom_to_scene, make_phantom

        phantom = make_phantom(name, **params)
        add_phantom_to_scene(self.scene, phantom)
        logging.info("FluoTomo: loaded phantom %s", name)
        return phantom.truth()

    def buildMesh(self, sizeMm=1.0, roi=None, labelNodeName="CBCTLabels"):
        """Tetrahedral mesh of a label map (structured, fast path); shows its surface
        as ``FluoTomoMeshSurface`` and returns the Mesh."""
        from fluoguide import mrml_io
        from FluoTomoLib.tomo_scene import store_mesh_surface
        from FluoTomoLib.voxel_mesh import mesh_labelmap_structured

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        geo = mrml_io.volume_geometry(node)
        mesh = mesh_labelmap_structured(mrml_io.volume_array(node), geo["spacing"], geo["origin"],
                                        sizeMm, roi=roi, direction=geo["direction"])
        store_mesh_surface(self.scene, mesh)
        self.mesh = mesh
        return mesh

    def reconstructTubePhantom(self, depthMm=4.7, methods=("NP", "SP", "HP"), seed=0,
                               progress=None, cancel=None):
        """Simulated tracked acquisition of the cylinder-tube phantom and its NP/SP/HP
        reconstructions; adds the phantom (if absent) and ``FluoTomoYield*`` volumes."""
        from fluoguide import mrml_io
        from fluoguide.phantoms import add_phantom_to_scene, make_phantom
        from FluoTomoLib.igft import simulate_and_reconstruct
        from FluoTomoLib.tomo_scene import store_reconstructions

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
