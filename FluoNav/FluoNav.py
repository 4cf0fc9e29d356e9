"""FluoNav: navigated fluorescence imaging (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The real code lives in ``FluoNavLib``.
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
            "optical transport and surface flux images, and contour-based classification.")
        self.parent.acknowledgementText = "Method after M. J. Daly, University of Toronto, 2018."


class FluoNavWidget(ScriptedLoadableModuleWidget):
    """In Slicer: a Qt form over FluoNavLogic.  Outside Slicer the web app
    (``fluo app``) builds its panel (``fluoapp.webapp.nav_panel``) over the same logic class."""

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        if self.layout is None:
            return
        import qt
        import slicer

        self.logic = FluoNavLogic(slicer.mrmlScene)
        form = qt.QFormLayout()
        self.layout.addLayout(form)
        build = qt.QPushButton("Surface model from CBCTLabels")
        build.connect("clicked(bool)", self.onBuildSurface)
        form.addRow(build)
        self.layout.addStretch(1)

    def onBuildSurface(self):
        import slicer

        try:
            self.logic.buildSurface()
        except Exception as exc:
            slicer.util.errorDisplay(str(exc))


class FluoNavLogic(ScriptedLoadableModuleLogic):
    """Navigation on one MRML scene (passed in; never the global one).

    Nodes read and written are listed in docs/scene.md (section FluoNav).
    """

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoNavLogic needs an MRML scene")
        self.scene = scene

    def buildSurface(self, labelNodeName="CBCTLabels", targetTriangles=None):
        """Air-tissue surface of a label map as model node ``TissueSurface``."""
        from fluoguide import mrml_io
        from FluoNavLib.mapping import surface

        node = mrml_io.get_node(self.scene, labelNodeName, "vtkMRMLLabelMapVolumeNode")
        poly = surface.surface_from_labelmap_node(node, target_triangles=targetTriangles)
        model = mrml_io.add_model(self.scene, "TissueSurface", poly)
        logging.info("FluoNav: TissueSurface with %d triangles", poly.GetNumberOfCells())
        return model


class FluoNavTest(ScriptedLoadableModuleTest):
    """Runs in Slicer's self-test and under pytest (a unittest.TestCase)."""

    def runTest(self):
        self.setUp()
        self.test_surface_from_phantom()

    def test_surface_from_phantom(self):
        import slicer

        from fluoguide.phantoms import add_phantom_to_scene, make_phantom

        scene = slicer.vtkMRMLScene()
        add_phantom_to_scene(scene, make_phantom("slab", voxel_mm=2.0))
        model = FluoNavLogic(scene).buildSurface()
        self.assertGreater(model.GetPolyData().GetNumberOfCells(), 100)
        self.delayDisplay("FluoNav surface test passed")
