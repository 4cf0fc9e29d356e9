"""FluoCalib: device calibration for image-guided fluorescence (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The real code lives in ``FluoCalibLib``.
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


class FluoCalib(ScriptedLoadableModule):
    def __init__(self, parent=None):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "FluoCalib"
        self.parent.categories = ["FluoGuide"]
        self.parent.dependencies = []
        self.parent.contributors = ["FluoGuide developers"]
        self.parent.helpText = (
            "Calibration of the tracked fluorescence devices: camera intrinsics and "
            "distortion, hand-eye, radiometric camera model, broad-beam illumination cone "
            "and laser beam line.")
        self.parent.acknowledgementText = (
            "Method after M. J. Daly, University of Toronto, 2018; OpenCV calibration.")


class FluoCalibWidget(ScriptedLoadableModuleWidget):
    """In Slicer: a Qt form over FluoCalibLogic.  Outside Slicer the web app
    (``fluo app``) builds its panel (``fluoapp.webapp.calib_panel``) over the same logic class."""

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        if self.layout is None:
            return
        import qt
        import slicer

        self.logic = FluoCalibLogic(slicer.mrmlScene)
        form = qt.QFormLayout()
        self.layout.addLayout(form)
        self.jsonPath = qt.QLineEdit()
        form.addRow("Calibration JSON:", self.jsonPath)
        load = qt.QPushButton("Load calibration into scene")
        load.connect("clicked(bool)", self.onLoad)
        form.addRow(load)
        self.layout.addStretch(1)

    def onLoad(self):
        import slicer

        try:
            self.logic.loadCalibrationJson(self.jsonPath.text)
        except Exception as exc:
            slicer.util.errorDisplay(str(exc))


class FluoCalibLogic(ScriptedLoadableModuleLogic):
    """Calibration results on one MRML scene (passed in; never the global one).

    Nodes written are listed in docs/scene.md (section FluoCalib).
    """

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoCalibLogic needs an MRML scene")
        self.scene = scene

    def setCameraToTracker(self, matrix):
        """Store the hand-eye result (camera frame -> tracker tool frame, mm)."""
        from fluoguide import mrml_io

        node = mrml_io.set_transform(self.scene, "CameraToTracker", matrix)
        logging.info("FluoCalib: CameraToTracker updated")
        return node

    def prepareCameraCalibration(self, images, board="chessboard:9x6:25", holdout=2):
        """A job ``job(progress, cancel) -> IntrinsicsResult`` over board images
        (paths); it touches no scene node, so it may run on a worker thread.
        Hand the result to :meth:`storeCameraCalibration`."""
        from FluoCalibLib.geometry.intrinsics import calibrate_camera

        images = [str(p) for p in images]

        def job(progress=None, cancel=None):
            return calibrate_camera(images, board, holdout=holdout, progress=progress,
                                    cancel=cancel)

        return job

    def storeCameraCalibration(self, result):
        """``FluoCalib.CameraIntrinsics`` on the ``FluoCalibration`` node."""
        from FluoCalibLib.geometry.scene import store_intrinsics

        store_intrinsics(self.scene, result.camera, {"rms_px": result.rms_px,
                                                     "board": result.board_spec})
        return result

    def loadCalibrationJson(self, path):
        """Put a calibration JSON file (as written by ``fluo calib ...``) on the
        ``FluoCalibration`` node as attributes, one per top-level key."""
        import json
        from pathlib import Path

        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError

        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except FileNotFoundError:
            raise FluoInputError("calibration file not found", file=p) from None
        except json.JSONDecodeError as exc:
            raise FluoInputError(f"not valid JSON ({exc.msg}, line {exc.lineno})", file=p) from None
        if not isinstance(data, dict):
            raise FluoInputError("calibration JSON must be an object", file=p)
        node = mrml_io.get_node(self.scene, "FluoCalibration", required=False)
        if node is None:
            import slicer

            node = slicer.vtkMRMLScriptedModuleNode()
            node.SetName("FluoCalibration")
            self.scene.AddNode(node)
        for key, value in data.items():
            mrml_io.set_json_attribute(node, f"FluoCalib.{key}", value)
        return node


class FluoCalibTest(ScriptedLoadableModuleTest):
    """Runs in Slicer's self-test and under pytest (a unittest.TestCase)."""

    def runTest(self):
        self.setUp()
        self.test_hand_eye_round_trip()

    def test_hand_eye_round_trip(self):
        import numpy as np
        import slicer

        from fluoguide import mrml_io

        scene = slicer.vtkMRMLScene()
        logic = FluoCalibLogic(scene)
        m = np.eye(4)
        m[:3, 3] = [10.0, -2.5, 31.0]
        logic.setCameraToTracker(m)
        np.testing.assert_allclose(mrml_io.get_transform(scene, "CameraToTracker"), m)
        self.delayDisplay("FluoCalib test passed")
