"""FluoCalib: device calibration for image-guided fluorescence (Slicer scripted module).

Thin module file: the module, widget, logic and test classes of Slicer's
ScriptedLoadableModule pattern.  The computation lives in ``FluoCalibLib``;
the logic class is the API (the ``fluo calib`` commands, the web app's panel
and the desktop widget all call it). Loads in 3D Slicer, in plain Python with
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
            "and laser beam line. Results go on a calibration node (FluoCalibration) and, "
            "optionally, into a calibration JSON file. See docs/slicer.md.")
        self.parent.acknowledgementText = (
            "Method after M. J. Daly, University of Toronto, 2018; OpenCV calibration.")
        from fluoguide.slicer_samples import register_on_startup

        register_on_startup()  # the digital phantoms in Sample Data


#
# Widget
#

class FluoCalibWidget(FluoModuleWidget):
    """The desktop panel (``Resources/UI/FluoCalib.ui``) over :class:`FluoCalibLogic`.
    Outside Slicer the web app (``fluo app``) builds its panel
    (``fluoapp.webapp.calib_panel``) over the same logic class."""

    # (widget, parameter or node-reference role, kind): saved in the parameter node
    BINDINGS = (
        ("calibrationNodeSelector", "Calibration", "node"),
        ("calibrationJsonPathLineEdit", "CalibrationJson", "path"),
        ("cameraImagesLineEdit", "CameraImages", "text"),
        ("boardLineEdit", "Board", "text"),
        ("fisheyeCheckBox", "Fisheye", "bool"),
        ("fixK3CheckBox", "FixK3", "bool"),
        ("holdoutSpinBox", "Holdout", "int"),
        ("handEyeImagesLineEdit", "HandEyeImages", "text"),
        ("handEyePosesPathLineEdit", "HandEyePoses", "path"),
        ("handEyeMethodComboBox", "HandEyeMethod", "choice"),
        ("handEyeStoreMethodComboBox", "HandEyeStoreMethod", "choice"),
        ("handEyeHoldoutSpinBox", "HandEyeHoldout", "int"),
        ("handEyeTransformSelector", "HandEyeTransform", "node"),
        ("radiometryStackPathLineEdit", "RadiometryStack", "path"),
        ("bitDepthSpinBox", "BitDepth", "int"),
        ("illuminationFolderPathLineEdit", "IlluminationFolder", "path"),
        ("axisymmetricCheckBox", "Axisymmetric", "bool"),
        ("laserFolderPathLineEdit", "LaserFolder", "path"),
        ("laserHoldoutSpinBox", "LaserHoldout", "int"),
    )

    def createLogic(self, scene):
        return FluoCalibLogic(scene)

    def setupConnections(self):
        # the calibration node selector lists FluoGuide calibration nodes only
        self.ui.calibrationNodeSelector.addAttribute("vtkMRMLScriptedModuleNode",
                                                     "FluoGuide.Role", "Calibration")
        self.ui.loadJsonButton.connect("clicked(bool)", self.onLoadJson)
        self.ui.syntheticDataButton.connect("clicked(bool)", self.onSyntheticData)
        self.ui.calibrateCameraButton.connect("clicked(bool)", self.onCalibrateCamera)
        self.ui.calibrateHandEyeButton.connect("clicked(bool)", self.onCalibrateHandEye)
        self.ui.characterizeButton.connect("clicked(bool)", self.onCharacterize)
        self.ui.calibrateIlluminationButton.connect("clicked(bool)", self.onCalibrateIllumination)
        self.ui.calibrateLaserButton.connect("clicked(bool)", self.onCalibrateLaser)

    # -- helpers -------------------------------------------------------------------
    def _outputs(self):
        p = self._parameterNode
        return {"calibrationNode": p.GetNodeReference("Calibration"),
                "calibrationJson": self.logic.parameter("CalibrationJson") or None}

    def _afterStore(self):
        # a calibration node made by the logic becomes the selected one
        node = self.logic.calibrationNode(self._parameterNode.GetNodeReference("Calibration"))
        self._parameterNode.SetNodeReferenceID("Calibration", node.GetID())

    def _show(self, labelName, text):
        """A result's line: kept in ``results`` (headless callers, tests) and shown
        in the panel's label ``labelName``."""
        self.results.append(text)
        if self.ui is not None:
            getattr(self.ui, labelName).text = text

    # -- actions ---------------------------------------------------------------------
    # Every calibration runs as FluoModuleWidget.runJob does it: the parameters and
    # nodes are read on Slicer's thread, the logic's prepareX job computes on a
    # worker thread (Slicer keeps answering, Cancel works), storeX writes the
    # calibration node back on Slicer's thread. Each result goes to its label and
    # to ``results`` (headless, the only place).
    def onLoadJson(self):
        path = self.logic.parameter("CalibrationJson")
        if self.run("Load calibration JSON", self.logic.loadCalibrationJson, path,
                    calibrationNode=self._outputs()["calibrationNode"]) is not None:
            self._afterStore()
            self.results.append(f"Loaded {path}")
            if self.ui is not None:
                self.ui.statusLabel.text = f"Loaded {path}"

    def onSyntheticData(self):
        import tempfile

        def prepare():
            folder = tempfile.mkdtemp(prefix="FluoCalib-synthetic-")

            def job(progress, cancel):      # files only, no MRML node: the job as it is
                return self.logic.writeSyntheticData(folder, progress=progress, cancel=cancel)

            return job, lambda sets: (folder, sets)

        out = self.runJob("Synthetic calibration data", prepare)
        if out is None:
            return
        folder, sets = out
        node = self._parameterNode
        was = node.StartModify()
        for key, value in (("CameraImages", sets["board_images"]),
                           ("Board", sets["board"]),
                           ("HandEyeImages", sets["board_images"]),
                           ("HandEyePoses", sets["poses"]),
                           ("RadiometryStack", sets["stack"]),
                           ("IlluminationFolder", sets["illumination"]),
                           ("LaserFolder", sets["laser"])):
            node.SetParameter(key, value)
        node.EndModify(was)
        text = f"Synthetic data (known truth) in {folder}"
        self._show("statusLabel", text)

    def onCalibrateCamera(self):
        p = self.logic.parameter

        def prepare():
            outputs = self._outputs()
            job = self.logic.prepareCameraCalibration(
                p("CameraImages"), p("Board"), holdout=p("Holdout"),
                model="fisheye" if p("Fisheye") else "pinhole", fixK3=p("FixK3"))
            return job, lambda res: self.logic.storeCameraCalibration(res, **outputs)

        res = self.runJob("Camera calibration", prepare)
        if res is None:
            return
        self._afterStore()
        c = res.camera
        rejected = "; ".join(f"{v.name}: {v.reason}" for v in res.rejected)
        text = (f"fx {c.fx:.2f}, fy {c.fy:.2f} px, centre ({c.cx:.1f}, {c.cy:.1f}) px; "
                f"RMS {res.rms_px:.3f} px over {len(res.used)} views"
                + (f", held out {res.holdout_rms_px:.3f} px" if res.holdout else "")
                + (f"\nrejected: {rejected}" if rejected else ""))
        self._show("cameraResultLabel", text)

    def onCalibrateHandEye(self):
        from FluoCalibLib.geometry.files import read_handeye_poses

        p = self.logic.parameter

        def prepare():
            outputs = self._outputs()
            transform = self._parameterNode.GetNodeReference("HandEyeTransform")
            poses = read_handeye_poses(p("HandEyePoses"), field="HandEyePoses")
            job = self.logic.prepareHandEyeCalibration(
                p("HandEyeImages"), p("Board"), poses["tool_to_tracker"],
                camera=self.logic.cameraModel(outputs["calibrationNode"]),
                boardToTracker=poses["board_to_tracker"], methods=p("HandEyeMethod"),
                storeMethod=p("HandEyeStoreMethod"), holdout=p("HandEyeHoldout"),
                truthCameraToTool=poses["camera_to_tool"])
            return job, lambda out: self.logic.storeHandEyeCalibration(
                out, outputTransformNode=transform, **outputs)

        out = self.runJob("Hand-eye calibration", prepare)
        if out is None:
            return
        self._afterStore()
        self._parameterNode.SetNodeReferenceID("HandEyeTransform", out["transform_node_id"])
        row = out["methods"][out["method"]]
        text = (f"{out['method']}: 3D error {row['err3d_mean_mm']:.3f} mm, 2D error "
                f"{row['err2d_mean_px']:.2f} px over {len(out['views_used'])} views")
        if "translation_error_mm" in row:
            text += (f"; against the truth {row['translation_error_mm']:.3f} mm, "
                     f"{row['rotation_error_deg']:.3f} deg")
        self._show("handEyeResultLabel", text)

    def onCharacterize(self):
        p = self.logic.parameter

        def prepare():
            outputs = self._outputs()
            job = self.logic.prepareCameraCharacterization(p("RadiometryStack"),
                                                           bitDepth=p("BitDepth"))
            return job, lambda res: self.logic.storeCameraCharacterization(res, **outputs)

        res = self.runJob("Camera response", prepare)
        if res is None:
            return
        self._afterStore()
        text = (f"gain {res['gain_adu_per_e']:.4f} ADU/e-, read noise {res['read_noise_e']:.2f} "
                f"e-, dark current {res['dark_current_e_per_s']:.2f} e-/s, "
                f"non-linearity {res['nonlinearity_pct']:.2f} %")
        self._show("radiometryResultLabel", text)

    def onCalibrateIllumination(self):
        p = self.logic.parameter

        def prepare():
            outputs = self._outputs()
            job = self.logic.prepareIlluminationCalibration(
                p("IlluminationFolder"), tryAsymmetric=not p("Axisymmetric"))
            return job, lambda res: self.logic.storeIlluminationCalibration(res, **outputs)

        res = self.runJob("Illumination calibration", prepare)
        if res is None:
            return
        self._afterStore()
        text = (f"half-angle {res['half_angle_deg']:.2f} deg, alpha {res['alpha']:.3f}, gamma "
                f"{res['gamma_per_mm']:.4f} /mm; measured/model {res['ratio_mean']:.3f} "
                f"+- {res['ratio_sd']:.3f} ({res['model']})")
        self._show("illuminationResultLabel", text)

    def onCalibrateLaser(self):
        p = self.logic.parameter

        def prepare():
            outputs = self._outputs()
            job = self.logic.prepareLaserCalibration(p("LaserFolder"), holdout=p("LaserHoldout"))
            return job, lambda res: self.logic.storeLaserCalibration(res, **outputs)

        res = self.runJob("Laser calibration", prepare)
        if res is None:
            return
        self._afterStore()
        text = (f"held-out error {res['error_3d_mm']:.3f} mm (3D), {res['error_2d_px']:.2f} px "
                f"(2D); line fit RMS {res['line_fit_rms_mm']:.3f} mm")
        self._show("laserResultLabel", text)


#
# Logic
#

class FluoCalibLogic(FluoLogicMixin, ScriptedLoadableModuleLogic):
    """Calibrations on one MRML scene (passed in; never the global one).

    Every ``calibrateX`` call computes from the inputs given, stores its
    result on the calibration node (``calibrationNode``, default the scene's
    ``FluoCalibration``) and, when ``calibrationJson`` names a file, merges it
    into that JSON file; long calls take ``progress`` and ``cancel``. For a
    worker thread, ``prepareX`` returns the computation as a job
    ``job(progress, cancel)`` that touches no MRML node, and ``storeX`` puts
    its result on the scene (on the scene's thread); ``calibrateX`` is the two
    in one call. The pairs (the desktop panel runs each job off Slicer's GUI
    thread, ``FluoModuleWidget.runJob``):

    - :meth:`prepareCameraCalibration` / :meth:`storeCameraCalibration`
      (:meth:`calibrateCamera`)
    - :meth:`prepareHandEyeCalibration` / :meth:`storeHandEyeCalibration`
      (:meth:`calibrateHandEye`)
    - :meth:`prepareCameraCharacterization` / :meth:`storeCameraCharacterization`
      (:meth:`characterizeCamera`)
    - :meth:`prepareIlluminationCalibration` / :meth:`storeIlluminationCalibration`
      (:meth:`calibrateIllumination`)
    - :meth:`prepareLaserCalibration` / :meth:`storeLaserCalibration`
      (:meth:`calibrateLaser`)

    :meth:`writeSyntheticData` writes files only and is a job as it is. Nodes
    written are listed in docs/scene.md (section FluoCalib).
    """

    PARAMETERS = {
        "CalibrationJson": "",
        "CameraImages": "",
        "Board": "chessboard:9x6:25",
        "Fisheye": False,
        "FixK3": False,
        "Holdout": 0,
        "HandEyeImages": "",
        "HandEyePoses": "",
        "HandEyeMethod": "ALL",
        "HandEyeStoreMethod": "PAIRED_POINT",
        "HandEyeHoldout": 0,
        "RadiometryStack": "",
        "BitDepth": 14,
        "IlluminationFolder": "",
        "Axisymmetric": False,
        "LaserFolder": "",
        "LaserHoldout": 4,
    }

    def __init__(self, scene):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            raise ValueError("FluoCalibLogic needs an MRML scene")
        self.scene = scene

    # -- the calibration node and file -------------------------------------------------
    def calibrationNode(self, calibrationNode=None):
        """``calibrationNode`` if given, else the scene's ``FluoCalibration`` (made when missing)."""
        from FluoCalibLib.geometry.scene import calibration_node

        return calibration_node(self.scene, calibrationNode)

    def cameraModel(self, calibrationNode=None):
        """The camera intrinsics on the calibration node, or None when there are none."""
        from fluoguide import mrml_io
        from FluoCalibLib.geometry.camera_model import CameraModel
        from FluoCalibLib.geometry.scene import CALIBRATION_NODE, INTRINSICS_KEY

        node = calibrationNode or mrml_io.get_node(self.scene, CALIBRATION_NODE, required=False)
        doc = None if node is None else mrml_io.get_json_attribute(node, INTRINSICS_KEY)
        return None if doc is None else CameraModel.from_dict(doc)

    def _store(self, key, doc, calibrationNode=None, calibrationJson=None):
        from FluoCalibLib.radiometry.scene import store_calibration, write_calibration_json

        if calibrationJson:
            write_calibration_json(calibrationJson, key, doc)
        store_calibration(self.scene, key, doc, self.calibrationNode(calibrationNode))

    def loadCalibrationJson(self, path, calibrationNode=None):
        """Put a calibration JSON file (as written by ``fluo calib ... --calibration``)
        on the calibration node, one attribute ``FluoCalib.<key>`` per top-level key;
        a ``HandEye`` entry with ``camera_to_tool`` also sets the hand-eye transform."""
        import numpy as np

        from fluoguide import mrml_io
        from fluoguide.jsonable import read_json
        from FluoCalibLib.geometry.scene import store_handeye

        data = read_json(path)
        node = self.calibrationNode(calibrationNode)
        for key, value in data.items():
            mrml_io.set_json_attribute(node, f"FluoCalib.{key}", value)
        handeye = data.get("HandEye")
        if isinstance(handeye, dict) and handeye.get("camera_to_tool") is not None:
            store_handeye(self.scene, np.asarray(handeye["camera_to_tool"], float))
        return node

    # -- camera intrinsics -----------------------------------------------------------
    def prepareCameraCalibration(self, images, board="chessboard:9x6:25", holdout=2,
                                 model="pinhole", fixK3=False, rejectOutliers=True):
        """A job ``job(progress, cancel) -> IntrinsicsResult`` over board images
        (paths, a glob or a folder); it touches no scene node, so it may run on a
        worker thread. Hand the result to :meth:`storeCameraCalibration`."""
        from FluoCalibLib.geometry.files import image_files
        from FluoCalibLib.geometry.intrinsics import calibrate_camera

        if isinstance(images, str):
            images = image_files(images)
        images = [p if hasattr(p, "shape") else str(p) for p in images]  # arrays or paths

        def job(progress=None, cancel=None):
            return calibrate_camera(images, board, model, holdout, fix_k3=fixK3,
                                    reject_outliers=rejectOutliers, progress=progress,
                                    cancel=cancel)

        return job

    def storeCameraCalibration(self, result, calibrationNode=None, calibrationJson=None):
        """``FluoCalib.CameraIntrinsics`` on the calibration node (and in the JSON file)."""
        from FluoCalibLib.geometry.scene import INTRINSICS_KEY, intrinsics_doc

        doc = intrinsics_doc(result.camera, {"rms_px": result.rms_px, "board": result.board_spec})
        self._store(INTRINSICS_KEY, doc, calibrationNode, calibrationJson)
        return result

    def calibrateCamera(self, images, board="chessboard:9x6:25", model="pinhole", holdout=0,
                        fixK3=False, rejectOutliers=True, calibrationNode=None,
                        calibrationJson=None, progress=None, cancel=None):
        """Intrinsics and distortion from board images (Zhang's method via OpenCV).

        Parameters
        ----------
        images : glob or folder (str), or a list of image paths or arrays
        board : ``chessboard:COLSxROWS:SQUARE_MM`` or ``charuco:...``
        model : ``pinhole`` or ``fisheye``
        holdout : views kept out of the fit and scored separately
        """
        job = self.prepareCameraCalibration(images, board, holdout, model, fixK3, rejectOutliers)
        return self.storeCameraCalibration(job(progress, cancel), calibrationNode, calibrationJson)

    # -- hand-eye ----------------------------------------------------------------------
    def prepareHandEyeCalibration(self, images, board, toolToTracker, camera=None,
                                  boardToTracker=None, methods="ALL", storeMethod="PAIRED_POINT",
                                  holdout=0, truthCameraToTool=None):
        """A job ``job(progress, cancel) -> dict`` (no MRML): the result of
        :meth:`calibrateHandEye` before it is stored."""
        import numpy as np

        from fluoguide.errors import FluoInputError
        from fluoguide.progress import check_cancel, report, scaled
        from FluoCalibLib.geometry import handeye as he
        from FluoCalibLib.geometry.boards import parse_board
        from FluoCalibLib.geometry.files import image_files
        from FluoCalibLib.geometry.intrinsics import calibrate_camera, detect_views, view_poses

        board_obj = parse_board(board)
        if isinstance(images, str):
            images = image_files(images)
        images = list(images)
        poses = [np.asarray(T, dtype=float) for T in toolToTracker]
        if len(poses) != len(images):
            raise FluoInputError(f"{len(images)} images but {len(poses)} tool poses: each image "
                                 "needs one synchronised pose", field="tool_to_tracker",
                                 value=(len(images), len(poses)))
        if isinstance(methods, str):
            methods = he.METHODS if methods.upper() == "ALL" else (methods.upper(),)
        methods = tuple(m.upper() for m in methods)
        unknown = [m for m in methods if m not in he.METHODS]
        if unknown:
            raise FluoInputError(f"unknown hand-eye method (one of ALL, {', '.join(he.METHODS)})",
                                 field="method", value=unknown[0])
        best = methods[0] if len(methods) == 1 else str(storeMethod).upper()
        if best not in methods:
            raise FluoInputError("stored method was not run", field="--store-method", value=best)

        def job(progress=None, cancel=None):
            cam = camera
            if cam is None:
                report(progress, 0.05, "intrinsics from the same images")
                cam = calibrate_camera(images, board_obj, cancel=cancel).camera
            report(progress, 0.3, "detecting the board")
            views, _ = detect_views(images, board_obj, progress=scaled(progress, 0.3, 0.6),
                                    cancel=cancel)
            keep = [i for i, v in enumerate(views) if v.status == "used"]
            rejected = [{"name": v.name, "reason": v.reason} for v in views if v.status != "used"]
            views = view_poses(cam, board_obj, [views[i] for i in keep])
            A = [poses[i] for i in keep]
            B = [v.board_to_camera for v in views]
            check_cancel(cancel)
            report(progress, 0.6, "solving")
            G = boardToTracker
            if G is None:
                # no grid registration: estimate it from the first method's solution
                X0 = he.solve_handeye(B, A, "TSAI")
                G = he.estimate_board_to_tracker(B, A, X0)
            cmp = he.compare_methods(cam, board_obj, B, A,
                                     [(v.ids, v.image_points) for v in views], G, methods,
                                     truth_camera_to_tool=truthCameraToTool, holdout=holdout)
            report(progress, 1.0, "done")
            X = cmp[best]["camera_to_tool"]
            return {"camera_to_tool": X, "method": best, "views_used": [v.name for v in views],
                    "views_rejected": rejected, "methods": cmp}

        return job

    def storeHandEyeCalibration(self, out, outputTransformNode=None, calibrationNode=None,
                                calibrationJson=None):
        """The hand-eye transform (``CameraToCameraTool`` or the caller's node) and
        ``FluoCalib.HandEye`` (method and errors; in the JSON file also the matrix)."""
        from FluoCalibLib.geometry.scene import HANDEYE_KEY, store_handeye
        from FluoCalibLib.radiometry.scene import write_calibration_json

        row = out["methods"][out["method"]]
        info = {"method": out["method"], **{k: v for k, v in row.items() if k != "camera_to_tool"}}
        node = store_handeye(self.scene, out["camera_to_tool"], info,
                             node=self.calibrationNode(calibrationNode),
                             transform_node=outputTransformNode)
        if calibrationJson:
            write_calibration_json(calibrationJson, HANDEYE_KEY,
                                   {**info, "camera_to_tool": out["camera_to_tool"]})
        out["transform_node_id"] = node.GetID()
        return out

    def calibrateHandEye(self, images, board, toolToTracker, camera=None, boardToTracker=None,
                         methods="ALL", storeMethod="PAIRED_POINT", holdout=0,
                         truthCameraToTool=None, outputTransformNode=None, calibrationNode=None,
                         calibrationJson=None, progress=None, cancel=None):
        """Camera frame -> tracked camera-tool frame from board images and tool poses.

        Parameters
        ----------
        images : glob or folder (str), or list of image paths or arrays
        toolToTracker : one 4x4 tool pose [mm] per image (sorted as the images)
        camera : CameraModel, optional; default: calibrated from the same images
        boardToTracker : 4x4 grid registration, optional; default: estimated
        methods : ``ALL`` or one of TSAI, PARK, HORAUD, ANDREFF, DANIILIDIS, PAIRED_POINT
        storeMethod : the method whose result is stored when several ran
        holdout : views left out of every fit, errors reported separately
        truthCameraToTool : 4x4, optional: errors against it are reported (synthetic data)
        outputTransformNode : vtkMRMLLinearTransformNode, optional (default ``CameraToCameraTool``)

        Returns
        -------
        dict: ``camera_to_tool``, ``method``, ``views_used``, ``views_rejected``,
        ``methods`` (every method's errors), ``transform_node_id``.
        """
        job = self.prepareHandEyeCalibration(images, board, toolToTracker, camera, boardToTracker,
                                             methods, storeMethod, holdout, truthCameraToTool)
        return self.storeHandEyeCalibration(job(progress, cancel), outputTransformNode,
                                            calibrationNode, calibrationJson)

    def setHandEye(self, matrix, outputTransformNode=None):
        """Store a known hand-eye result (camera frame -> camera-tool frame, mm)."""
        from FluoCalibLib.geometry.scene import store_handeye

        node = store_handeye(self.scene, matrix, transform_node=outputTransformNode)
        logging.info("FluoCalib: %s updated", node.GetName())
        return node

    # -- tracker to CBCT registration --------------------------------------------------
    def registerTrackerToReference(self, moving, fixed, targetsMoving=None, targetsFixed=None,
                                   outputTransformNode=None, calibrationNode=None):
        """Paired-point registration of tracker points (``moving``, (N, 3) mm) to the
        same points in the CBCT (``fixed``); ``TrackerToReference`` (or the caller's
        node) and ``FluoCalib.Registration`` (FRE, and TRE when targets are given)."""
        from fluoguide.errors import FluoInputError
        from FluoCalibLib.geometry.registration import register_points, target_registration_error
        from FluoCalibLib.geometry.scene import store_registration

        res = register_points(moving, fixed)
        out = {"transform": res.transform, "fre_mm": res.fre_mm, "residuals_mm": res.residuals_mm}
        if targetsMoving is not None or targetsFixed is not None:
            if targetsMoving is None or targetsFixed is None:
                raise FluoInputError("give both --targets-moving and --targets-fixed",
                                     field="--targets-fixed")
            tre = target_registration_error(res.transform, targetsMoving, targetsFixed)
            out["tre_mm"] = tre
            out["tre_mean_mm"] = float(tre.mean())
        info = {k: v for k, v in out.items() if k in ("fre_mm", "tre_mean_mm")}
        store_registration(self.scene, res.transform, info, node=self.calibrationNode(calibrationNode),
                           transform_node=outputTransformNode)
        return out

    # -- radiometry ------------------------------------------------------------------
    def prepareCameraCharacterization(self, stack, bitDepth=14, plotsFolder=None):
        """A job ``job(progress, cancel) -> dict`` (no MRML) of :meth:`characterizeCamera`."""
        from fluoguide.progress import check_cancel, report
        from FluoCalibLib.radiometry.camera_response import characterize, load_stack

        def job(progress=None, cancel=None):
            report(progress, 0.1, "reading the stack")
            if isinstance(stack, (list, tuple)):
                frames, meta = list(stack), {}
            else:
                frames, meta = load_stack(stack)
            check_cancel(cancel)
            report(progress, 0.4, "photon transfer, linearity, dark signal")
            res = characterize(frames, bit_depth=bitDepth)
            if plotsFolder:
                from FluoCalibLib.radiometry.plots import plot_radiometry

                res["plots"] = plot_radiometry(res, plotsFolder)
            if "truth" in meta:
                res["truth"] = meta["truth"]
            report(progress, 1.0, "done")
            return res

        return job

    def storeCameraCharacterization(self, res, calibrationNode=None, calibrationJson=None):
        """``FluoCalib.Radiometry``: the numbers, without the curves and the truth."""
        from FluoCalibLib.radiometry.scene import RADIOMETRY_KEY

        keep = {k: v for k, v in res.items() if k not in ("ptc", "linearity", "dark", "truth")}
        self._store(RADIOMETRY_KEY, keep, calibrationNode, calibrationJson)
        return res

    def characterizeCamera(self, stack, bitDepth=14, plotsFolder=None, calibrationNode=None,
                           calibrationJson=None, progress=None, cancel=None):
        """Camera response (EMVA 1288 style): gain [ADU/e-], dark current, bias,
        read noise, linearity, saturation, dynamic range.

        Parameters
        ----------
        stack : folder with ``stack.json`` and the frames, or a list of ``Frame``
        bitDepth : A/D bit depth
        plotsFolder : folder for the photon-transfer, linearity and dark PNGs, optional

        Returns the full result (with the curves; ``truth`` when the stack has one).
        """
        job = self.prepareCameraCharacterization(stack, bitDepth, plotsFolder)
        return self.storeCameraCharacterization(job(progress, cancel), calibrationNode,
                                                calibrationJson)

    # -- illumination ----------------------------------------------------------------
    def prepareIlluminationCalibration(self, folder, tryAsymmetric=True, plotsFolder=None):
        """A job ``job(progress, cancel) -> dict`` (no MRML) of :meth:`calibrateIllumination`."""
        import numpy as np

        from fluoguide.progress import check_cancel, report, scaled
        from FluoCalibLib.geometry.camera_model import CameraModel
        from FluoCalibLib.radiometry.datasets import ILLUMINATION_KEYS, read_dataset
        from FluoCalibLib.radiometry.illumination_fit import calibrate_illumination

        def job(progress=None, cancel=None):
            report(progress, 0.1, "reading the images")
            images, doc = read_dataset(folder, "illumination.json", ILLUMINATION_KEYS)
            check_cancel(cancel)
            report(progress, 0.3, "fitting the cone")
            res = calibrate_illumination(images, CameraModel.from_dict(doc["camera"]),
                                         [np.asarray(T, float) for T in doc["phantom_to_camera"]],
                                         float(doc["rd"]), float(doc.get("offset_adu", 0.0)),
                                         try_asymmetric=tryAsymmetric,
                                         saturation_adu=float(doc.get("saturation_adu", 16383.0)),
                                         progress=scaled(progress, 0.3, 0.95), cancel=cancel)
            res["cone"] = res["cone"].to_dict()
            if plotsFolder:
                from FluoCalibLib.radiometry.plots import plot_ratio_images

                res["plots"] = plot_ratio_images(res["ratio_images"], plotsFolder,
                                                 doc["phantom_to_camera"])
            if "truth" in doc:
                res["truth"] = doc["truth"]
            report(progress, 1.0, "done")
            return res

        return job

    def storeIlluminationCalibration(self, res, calibrationNode=None, calibrationJson=None):
        """``FluoCalib.Illumination``: the cone and the fit numbers (no images, no truth)."""
        from FluoCalibLib.radiometry.scene import ILLUMINATION_KEY

        keep = {k: v for k, v in res.items() if k not in ("ratio_images", "truth")}
        self._store(ILLUMINATION_KEY, keep, calibrationNode, calibrationJson)
        return res

    def calibrateIllumination(self, folder, tryAsymmetric=True, plotsFolder=None,
                              calibrationNode=None, calibrationJson=None, progress=None,
                              cancel=None):
        """Broad-beam illumination cone (origin, axis, half-angle, alpha, gamma,
        system gain) from images of a flat phantom of known reflectance.

        ``folder`` holds ``illumination.json`` and the images (``fluo calib
        synth-light`` writes one). Returns the result with ``cone`` (a dict),
        ``ratio_images`` (measured / model) and ``truth`` when the set has one.
        """
        job = self.prepareIlluminationCalibration(folder, tryAsymmetric, plotsFolder)
        return self.storeIlluminationCalibration(job(progress, cancel), calibrationNode,
                                                 calibrationJson)

    # -- laser -----------------------------------------------------------------------
    def prepareLaserCalibration(self, folder, holdout=4):
        """A job ``job(progress, cancel) -> dict`` (no MRML) of :meth:`calibrateLaser`."""
        from fluoguide.progress import check_cancel, report
        from FluoCalibLib.geometry.camera_model import CameraModel
        from FluoCalibLib.radiometry.datasets import LASER_KEYS, read_dataset
        from FluoCalibLib.radiometry.laser_line import calibrate_laser

        def job(progress=None, cancel=None):
            report(progress, 0.1, "reading the spot images")
            images, doc = read_dataset(folder, "laser.json", LASER_KEYS)
            check_cancel(cancel)
            report(progress, 0.4, "fitting the beam line")
            res = calibrate_laser(images, CameraModel.from_dict(doc["camera"]),
                                  doc["camera_to_tracker"], doc["laser_to_tracker"],
                                  doc["phantom_to_tracker"], doc.get("pointer_origin_tool_mm"),
                                  holdout=holdout)
            if "truth" in doc:
                res["truth"] = doc["truth"]
            report(progress, 1.0, "done")
            return res

        return job

    def storeLaserCalibration(self, res, calibrationNode=None, calibrationJson=None):
        """``FluoCalib.Laser``: the beam line and its errors (no spot list, no truth)."""
        from FluoCalibLib.radiometry.scene import LASER_KEY

        keep = {k: v for k, v in res.items() if k not in ("spots_px", "truth")}
        self._store(LASER_KEY, keep, calibrationNode, calibrationJson)
        return res

    def calibrateLaser(self, folder, holdout=4, calibrationNode=None, calibrationJson=None,
                       progress=None, cancel=None):
        """Laser beam line in laser-tool coordinates from spot images on a tracked
        phantom; ``holdout`` images are kept out of the fit and give the accuracy.
        ``folder`` holds ``laser.json`` and the images."""
        job = self.prepareLaserCalibration(folder, holdout)
        return self.storeLaserCalibration(job(progress, cancel), calibrationNode, calibrationJson)

    # -- synthetic data with known truth -------------------------------------------------
    def writeSyntheticData(self, folder, boardViews=10, seed=0, progress=None, cancel=None):
        """Board images with tracked poses, a camera stack, illumination and laser
        sets, all with known truth, under ``folder`` (to try every calibration).
        It writes files and touches no MRML node, so it may run on a worker thread;
        it reports each board view as it renders it (about 0.7 s each).

        Returns {``board_images`` (glob), ``board``, ``poses``, ``stack``,
        ``illumination``, ``laser``}.
        """
        from pathlib import Path

        from fluoguide.progress import check_cancel, report, scaled
        from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

        root = Path(folder)
        board = "chessboard:9x6:20"
        report(progress, 0.0, "board images")
        make_dataset(root / "boards", default_camera(640, 480), board, boardViews, seed,
                     progress=scaled(progress, 0.0, 0.5, "board images"), cancel=cancel)
        check_cancel(cancel)
        self.writeSyntheticLight(root, seed, progress=scaled(progress, 0.5, 1.0),
                                 cancel=cancel)
        return {"board_images": str(root / "boards" / "*.png"), "board": board,
                "poses": str(root / "boards" / "truth.json"), "stack": str(root / "stack"),
                "illumination": str(root / "illumination"), "laser": str(root / "laser")}

    @staticmethod
    def writeCalibrationYaml(path, camera=None, cameraToTool=None, rmsPx=None):
        """The camera model and/or the camera-to-tool hand-eye (4x4, mm) as an
        OpenCV YAML file (``rmsPx``: the fit's RMS reprojection error [px])."""
        from FluoCalibLib.geometry.opencv_yaml import write_calibration_yaml

        write_calibration_yaml(path, camera, cameraToTool, rms_px=rmsPx)

    @staticmethod
    def pivotCalibration(toolToTracker):
        """Pivot calibration of a tracked pointer from its 4x4 poses (mm): the tip
        in tool coordinates, the pivot in tracker coordinates, the residuals."""
        import numpy as np

        from FluoCalibLib.geometry.registration import pivot_calibration

        return pivot_calibration([np.asarray(T, dtype=float) for T in toolToTracker])

    @staticmethod
    def writeSyntheticBoards(folder, board="chessboard:9x6:20", views=12, seed=0, width=800,
                             height=600, fisheye=False, blurPx=0.6, noise=2.0,
                             trackerNoiseMm=0.1, motion="general", progress=None):
        """Board images (``view_NNN.png``) and ``truth.json`` (camera, hand-eye,
        tool poses) of a synthetic camera of ``width`` x ``height`` px on a
        tracked tool; ``fisheye``: a wide-angle camera with the fisheye model;
        ``blurPx``, ``noise`` [grey levels], ``trackerNoiseMm``: SDs; ``motion``:
        general, translation or parallel. Returns {``images``, ``camera``,
        ``camera_to_tool``}."""
        from FluoCalibLib.geometry.camera_model import CameraModel
        from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

        cam = default_camera(width, height)
        if fisheye:
            cam = CameraModel(cam.fx * 0.7, cam.fy * 0.7, cam.cx, cam.cy,
                              (0.03, -0.01, 0.002, -0.0005), cam.width, cam.height, "fisheye")
        return make_dataset(folder, cam, board, views, seed, blur_sigma_px=blurPx,
                            noise_sigma=noise, tracker_noise_mm=trackerNoiseMm, motion=motion,
                            progress=progress)

    @staticmethod
    def writeSyntheticLight(folder, seed=0, lensSpectral=False, progress=None, cancel=None):
        """A camera stack, illumination and laser sets with known truth under
        ``folder`` (``stack/``, ``illumination/``, ``laser/``); files only, no
        MRML node (a worker thread may run it). ``lensSpectral``: the stack also
        holds frames at several f-numbers and wavelengths (seed ``seed + 1``).

        Returns {``stack``, ``illumination``, ``laser``: folders, ``frames``,
        ``illumination_images``, ``laser_images``: counts}.
        """
        from pathlib import Path

        from fluoguide.progress import check_cancel, report
        from FluoCalibLib.radiometry.camera_response import write_stack
        from FluoCalibLib.radiometry.synthetic import (
            synthetic_illumination,
            synthetic_laser,
            synthetic_lens_spectral_frames,
            synthetic_stack,
            write_illumination_set,
            write_laser_set,
        )

        root = Path(folder)
        report(progress, 0.0, "camera stack")
        frames, truth = synthetic_stack(seed=seed)
        if lensSpectral:
            extra, t_extra = synthetic_lens_spectral_frames(
                radiance_w_per_mm2_sr=truth["radiance_w_per_mm2_sr"], seed=seed + 1)
            frames, truth = frames + extra, {**truth, **t_extra}
        write_stack(root / "stack", frames, {"truth": truth})
        check_cancel(cancel)
        report(progress, 0.5, "illumination images")
        imgs, t_il = synthetic_illumination(seed=seed)
        write_illumination_set(root / "illumination", imgs, t_il)
        check_cancel(cancel)
        report(progress, 0.8, "laser images")
        limgs, t_la = synthetic_laser(seed=seed)
        write_laser_set(root / "laser", limgs, t_la)
        report(progress, 1.0, "done")
        return {"stack": str(root / "stack"), "illumination": str(root / "illumination"),
                "laser": str(root / "laser"), "frames": len(frames),
                "illumination_images": len(imgs), "laser_images": len(limgs)}


#
# Test
#

class FluoCalibTest(ScriptedLoadableModuleTest):
    """The module's workflow on synthetic data with known truth, through the
    logic calls. Runs in Slicer's self-test and under pytest (a unittest.TestCase).

    Tolerances: the synthetic boards are rendered with 0.6 px blur, 2 grey
    levels of noise and 0.1 mm tracker noise; at that noise Zhang's method
    recovers fx within 1 % and the paired-point hand-eye within 1 mm /
    0.5 deg (docs/calibration-geometry.md); the radiometric sets follow
    docs/calibration-radiometry.md (gain within 3 %, laser held-out error
    below 0.5 mm).
    """

    def setUp(self):
        import tempfile

        import slicer

        from fluoguide.slicer_compat import in_slicer_application

        if in_slicer_application():
            from fluoguide.slicer_deps import ensure_dependencies

            self.assertTrue(ensure_dependencies(ask=False), "FluoGuide's Python packages")
        self.scene = slicer.vtkMRMLScene()
        self.folder = tempfile.mkdtemp(prefix="FluoCalibTest-")

    def tearDown(self):
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)

    def runTest(self):
        self.setUp()
        try:
            self.test_calibration_workflow()
            self.test_old_hand_eye_name_is_read()
        finally:
            self.tearDown()

    def test_calibration_workflow(self):
        import json
        from pathlib import Path

        import numpy as np

        from fluoguide import mrml_io
        from FluoCalibLib.geometry.files import read_handeye_poses

        logic = FluoCalibLogic(self.scene)
        sets = logic.writeSyntheticData(self.folder, boardViews=8)
        truth = json.loads(Path(sets["poses"]).read_text())
        calib_json = Path(self.folder) / "calibration.json"

        res = logic.calibrateCamera(sets["board_images"], sets["board"], calibrationJson=calib_json)
        fx_true = truth["camera"]["fx"]
        self.assertLess(abs(res.camera.fx - fx_true) / fx_true, 0.01)
        self.assertIsNotNone(logic.cameraModel())

        poses = read_handeye_poses(sets["poses"])
        out = logic.calibrateHandEye(sets["board_images"], sets["board"], poses["tool_to_tracker"],
                                     camera=logic.cameraModel(), methods="PAIRED_POINT",
                                     truthCameraToTool=poses["camera_to_tool"],
                                     calibrationJson=calib_json)
        row = out["methods"]["PAIRED_POINT"]
        self.assertLess(row["translation_error_mm"], 1.0)
        self.assertLess(row["rotation_error_deg"], 0.5)
        np.testing.assert_allclose(mrml_io.get_transform(self.scene, "CameraToCameraTool"),
                                   out["camera_to_tool"])

        rad = logic.characterizeCamera(sets["stack"], calibrationJson=calib_json)
        k_true = rad["truth"]["camera"]["gain_adu_per_e"]
        self.assertLess(abs(rad["gain_adu_per_e"] - k_true) / k_true, 0.03)
        il = logic.calibrateIllumination(sets["illumination"], calibrationJson=calib_json)
        self.assertLess(abs(il["ratio_mean"] - 1.0), 0.05)
        la = logic.calibrateLaser(sets["laser"], calibrationJson=calib_json)
        self.assertLess(la["error_3d_mm"], 0.5)

        # every result is on the calibration node and in the JSON file, and the
        # file loads back into a fresh scene (hand-eye transform included)
        node = logic.calibrationNode()
        saved = json.loads(calib_json.read_text())
        for key in ("CameraIntrinsics", "HandEye", "Radiometry", "Illumination", "Laser"):
            self.assertIsNotNone(node.GetAttribute(f"FluoCalib.{key}"), key)
            self.assertIn(key, saved)
        import slicer

        other = FluoCalibLogic(slicer.vtkMRMLScene())
        other.loadCalibrationJson(calib_json)
        np.testing.assert_allclose(mrml_io.get_transform(other.scene, "CameraToCameraTool"),
                                   out["camera_to_tool"], atol=1e-12)
        self.assertAlmostEqual(other.cameraModel().fx, res.camera.fx)
        self.delayDisplay("FluoCalib workflow test passed")

    def test_old_hand_eye_name_is_read(self):
        """A scene saved with the old name ``CameraToTracker`` still gives its hand-eye."""
        import numpy as np

        import slicer

        from fluoguide import mrml_io
        from FluoCalibLib.geometry.scene import load_handeye

        scene = slicer.vtkMRMLScene()
        m = np.eye(4)
        m[:3, 3] = [10.0, -2.5, 31.0]
        mrml_io.set_transform(scene, "CameraToTracker", m)
        np.testing.assert_allclose(load_handeye(scene), m)
        FluoCalibLogic(scene).setHandEye(m)
        self.assertIsNone(mrml_io.get_node(scene, "CameraToTracker", required=False))
        np.testing.assert_allclose(mrml_io.get_transform(scene, "CameraToCameraTool"), m)
        self.delayDisplay("FluoCalib old-name test passed")
