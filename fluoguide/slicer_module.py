"""What the three scripted modules share: the logic's parameter node, and the
desktop widget built from a Qt Designer file.

- :class:`FluoLogicMixin`: a logic class lists its parameters once
  (``PARAMETERS = {name: default}``); ``getParameterNode()`` returns the
  module's parameter node in the logic's *own* scene (Slicer's base class uses
  the global ``slicer.mrmlScene``; ours hold their scene), with the defaults
  filled in; ``parameter(name)`` reads one back typed.
- :class:`FluoModuleWidget`: loads ``<Module>/Resources/UI/<Module>.ui`` with
  ``slicer.util.loadUI``, binds the widgets named in ``BINDINGS`` to the
  parameter node both ways (so the panel is saved with the scene and restored
  with it), runs long work with a progress dialog whose Cancel button stops
  it, and shows errors in a dialog (never swallowed, never a traceback for
  bad input). A module widget adds its buttons in ``setupConnections``.
  Long work runs off Slicer's GUI thread (:meth:`FluoModuleWidget.runJob`):
  the scene is read on it, the logic's ``prepare*`` job computes on a worker
  thread (``fluoguide.jobs``), the logic's ``store*`` writes the nodes back on it.

Outside the Slicer application (``slicer_compat``) there is no Qt: ``setup``
returns before touching a widget, and everything else here is plain Python.
:meth:`FluoModuleWidget.setupHeadless` gives such a widget its logic and
parameter node without any widget, so its handlers run on the parameter node
(tests, scripts): long work runs without a dialog and errors are kept in
``errors`` (and logged) instead of shown.
Testing/Python/test_slicer_ui.py checks each ``.ui`` against the names the
module code uses.
"""

from __future__ import annotations

import logging

try:  # 3D Slicer
    from slicer.ScriptedLoadableModule import ScriptedLoadableModuleWidget
except ImportError:  # slicer-core or no Slicer at all
    from fluoguide.slicer_compat import ScriptedLoadableModuleWidget

from fluoguide import parameters

__all__ = ["FluoLogicMixin", "FluoModuleWidget", "BINDING_KINDS"]

log = logging.getLogger("fluoguide.slicer")

#: kind -> (Qt signal the widget emits on a change, widget classes allowed for it)
BINDING_KINDS = {
    "node": ("currentNodeChanged(vtkMRMLNode*)", ("qMRMLNodeComboBox",)),
    "text": ("textChanged(QString)", ("QLineEdit",)),
    "path": ("currentPathChanged(QString)", ("ctkPathLineEdit",)),
    "float": ("valueChanged(double)", ("QDoubleSpinBox", "ctkDoubleSpinBox", "ctkSliderWidget")),
    "int": ("valueChanged(int)", ("QSpinBox",)),
    "bool": ("toggled(bool)", ("QCheckBox",)),
    "choice": ("currentIndexChanged(int)", ("QComboBox",)),
}


class FluoLogicMixin:
    """Parameter node of a logic that holds its scene (``self.scene``)."""

    #: {parameter name: default}; the default's type is the parameter's type
    PARAMETERS = {}

    def getParameterNode(self):
        name = getattr(self, "moduleName", None) or self.__class__.__name__[: -len("Logic")]
        return parameters.parameter_node(self.scene, name, self.PARAMETERS)

    def setDefaultParameters(self, parameterNode):
        parameters.set_defaults(parameterNode, self.PARAMETERS)

    def parameter(self, name):
        """Parameter ``name`` of this module's parameter node, typed as its default."""
        return parameters.get(self.getParameterNode(), name, self.PARAMETERS[name])


class FluoModuleWidget(ScriptedLoadableModuleWidget):
    """Base class of the FluoGuide module widgets (see the module docstring).

    Subclasses set ``BINDINGS`` (``(widget name, parameter or node reference
    role, kind)``, kinds in :data:`BINDING_KINDS`), implement
    ``createLogic(scene)`` and ``setupConnections()``, and may override
    ``updateButtonStates()``.
    """

    BINDINGS = ()

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        self.logic = None
        self.ui = None
        self._parameterNode = None
        self._parameterObserver = None
        self._sceneObservers = []
        self._updatingGUI = False
        self.errors = []  # headless: the messages a dialog would have shown
        self.results = []  # the results the panel showed, newest last (what headless tests read)
        self._installOffer = None   # the panel's offer to install missing packages
        self._installText = None

    # -- the pieces a module supplies ------------------------------------------------
    def createLogic(self, scene):
        """The module's logic on ``scene``: every module widget defines it (FluoCalib,
        FluoNav and FluoTomo do); the base class cannot know which logic to make."""
        raise NotImplementedError(f"{type(self).__name__} must define createLogic(scene)")

    def setupConnections(self):
        """Connect the module's buttons (``self.ui.xxxButton.connect("clicked(bool)", ...)``)."""

    def updateButtonStates(self):
        """Enable or disable buttons from the parameter node (called after every change)."""

    # -- set-up ------------------------------------------------------------------------
    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        if self.layout is None:  # headless (slicer_compat): no Qt to lay out
            return
        from fluoguide.slicer_deps import install_summary

        required, optional = install_summary()
        if required or optional:
            # offered in the panel, never in a modal dialog: Slicer (and its
            # generic module tests) must not block on a question at start-up
            self._installOffer = self._packageOffer(required, optional)
            self.layout.addWidget(self._installOffer)
        if required:
            return
        self._buildPanel()

    def _packageOffer(self, required, optional):
        """A box in the panel: what is missing, what each optional package adds,
        and an Install button (each package on its own: one without a build for
        this platform does not stop the others)."""
        import qt

        box = qt.QGroupBox("Python packages")
        form = qt.QVBoxLayout(box)
        lines = []
        if required:
            lines.append("This module needs: " + ", ".join(required) + ".")
        for line, adds in optional:
            lines.append(f"Optional: {line} ({adds}).")
        text = qt.QLabel("\n".join(lines) + "\nInstall them into Slicer's Python (a few "
                         "minutes, needs the internet; docs/slicer.md)?")
        text.wordWrap = True
        form.addWidget(text)
        button = qt.QPushButton("Install")
        form.addWidget(button)
        self._installText = text
        button.connect("clicked(bool)", lambda _=False: self.onInstallPackages())
        return box

    def onInstallPackages(self):
        """Install what is missing, one package at a time; build the panel once
        every required package is there, and say what could not be installed."""
        import slicer

        from fluoguide.slicer_deps import install_requirements, install_summary

        required, optional = install_summary()
        with slicer.util.WaitCursor():
            failed = {k: v for k, v in install_requirements(
                required + [line for line, _ in optional], slicer.util.pip_install).items() if v}
        required, optional = install_summary()
        said = []
        if failed:
            said.append("Could not install: " + "; ".join(f"{k} ({v})" for k, v in failed.items()))
        if optional:
            said.append("Not available here: " + "; ".join(adds for _, adds in optional))
        if required:
            self._installText.text = "\n".join(said + ["The module still needs: "
                                                       + ", ".join(required)])
            return
        self._installText.text = "\n".join(said) or "Installed."
        if self.logic is None:
            self._buildPanel()

    def _buildPanel(self):
        import slicer

        self.logic = self.createLogic(slicer.mrmlScene)
        uiWidget = slicer.util.loadUI(self.resourcePath(f"UI/{self.moduleName}.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        # the .ui connects the top widget's mrmlSceneChanged to every MRML widget
        uiWidget.setMRMLScene(slicer.mrmlScene)
        for name, _role, kind in self.BINDINGS:
            getattr(self.ui, name).connect(BINDING_KINDS[kind][0], self.updateParameterNodeFromGUI)
        self.setupConnections()
        scene = slicer.mrmlScene
        self._sceneObservers = [
            scene.AddObserver(scene.StartCloseEvent, lambda caller, event: self.setParameterNode(None)),
            scene.AddObserver(scene.EndCloseEvent, self._onSceneEndClose),
        ]
        self.initializeParameterNode()
        self.layout.addStretch(1)

    def setupHeadless(self, scene):
        """No Qt (``setup`` built nothing): the logic on ``scene`` and its parameter
        node, so the handlers run on the parameter node alone. Returns the logic."""
        if self.ui is not None:
            raise RuntimeError("setupHeadless is for a widget without Qt")
        self.logic = self.createLogic(scene)
        self.setParameterNode(self.logic.getParameterNode())
        return self.logic

    def cleanup(self):
        import slicer

        self.setParameterNode(None)
        for tag in self._sceneObservers:
            slicer.mrmlScene.RemoveObserver(tag)
        self._sceneObservers = []

    def enter(self):
        if self.logic is not None:
            self.initializeParameterNode()

    def exit(self):
        self.setParameterNode(None)

    def _onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    # -- parameter node <-> widgets ----------------------------------------------------
    def initializeParameterNode(self):
        self.setParameterNode(self.logic.getParameterNode())

    def setParameterNode(self, node):
        import vtk

        if self._parameterNode is not None and self._parameterObserver is not None:
            self._parameterNode.RemoveObserver(self._parameterObserver)
        self._parameterNode, self._parameterObserver = node, None
        if node is not None:
            self.logic.setDefaultParameters(node)
            self._parameterObserver = node.AddObserver(vtk.vtkCommand.ModifiedEvent,
                                                       self.updateGUIFromParameterNode)
            self.updateGUIFromParameterNode()

    def updateGUIFromParameterNode(self, caller=None, event=None):
        node = self._parameterNode
        if node is None or self._updatingGUI or self.ui is None:
            return
        self._updatingGUI = True
        try:
            for name, role, kind in self.BINDINGS:
                widget = getattr(self.ui, name)
                if kind == "node":
                    widget.setCurrentNode(node.GetNodeReference(role))
                    continue
                text = node.GetParameter(role)
                if not text:
                    continue
                if kind == "text":
                    widget.text = text
                elif kind == "path":
                    widget.currentPath = text
                elif kind in ("float", "int", "bool"):
                    widget_value = parameters.get(node, role, {"float": 0.0, "int": 0,
                                                               "bool": False}[kind])
                    if kind == "bool":
                        widget.checked = widget_value
                    else:
                        widget.value = widget_value
                elif kind == "choice":
                    index = widget.findText(text)
                    if index >= 0:
                        widget.setCurrentIndex(index)
            self.updateButtonStates()
        finally:
            self._updatingGUI = False

    def updateParameterNodeFromGUI(self, *args):
        node = self._parameterNode
        if node is None or self._updatingGUI:
            return
        was = node.StartModify()
        try:
            for name, role, kind in self.BINDINGS:
                widget = getattr(self.ui, name)
                if kind == "node":
                    node.SetNodeReferenceID(role, widget.currentNodeID)
                elif kind == "text":
                    parameters.set_value(node, role, widget.text)
                elif kind == "path":
                    parameters.set_value(node, role, widget.currentPath)
                elif kind == "float":
                    parameters.set_value(node, role, float(widget.value))
                elif kind == "int":
                    parameters.set_value(node, role, int(widget.value))
                elif kind == "bool":
                    parameters.set_value(node, role, bool(widget.checked))
                elif kind == "choice":
                    parameters.set_value(node, role, widget.currentText)
        finally:
            node.EndModify(was)

    # -- long work, errors -----------------------------------------------------------
    def runWithProgress(self, title, work, background=False):
        """Run ``work(progress, cancel)`` with a progress dialog; its Cancel button
        sets the cancel token, which the Lib checks between steps.

        ``background``: the work is pure computation (a logic's ``prepare*`` job:
        no MRML, no Qt) and runs on a worker thread (``fluoguide.jobs``) while
        Slicer's event loop keeps running: the application repaints, the dialog
        shows each step and how long it has run, and Cancel answers at once.
        Otherwise the work runs here and Slicer answers only when it reports.

        Returns the result, or None when the work failed (the error is shown)
        or was cancelled (said in the status bar). Headless: no dialog, no
        progress, the error kept in ``errors``.
        """
        from fluoguide.errors import FluoCancelled
        from fluoguide.progress import CancelToken

        if self.ui is None:
            try:
                return work(None, CancelToken())
            except FluoCancelled:
                return None
            except Exception as exc:
                self.showError(title, exc)
                return None
        import qt
        import slicer

        dialog = slicer.util.createProgressDialog(parent=self.parent, value=0, maximum=100,
                                                  labelText=title, windowTitle=title)
        dialog.setWindowModality(qt.Qt.WindowModal)
        if background:
            return self._runInBackground(title, work, dialog)
        token = CancelToken()
        dialog.connect("canceled()", token.cancel)

        def progress(fraction, message=""):
            dialog.setValue(int(round(100.0 * fraction)))
            if message:
                dialog.setLabelText(f"{title}: {message}")
            slicer.app.processEvents()

        try:
            return work(progress, token)
        except FluoCancelled:
            slicer.util.showStatusMessage(f"{title}: cancelled", 5000)
            return None
        except Exception as exc:
            self.showError(title, exc)
            return None
        finally:
            dialog.close()

    def runJob(self, title, prepare):
        """Long work the panel way (issue #33), in three steps.

        ``prepare()`` runs here, on Slicer's thread: it reads the parameter node
        and the scene and returns ``(job, store)``, ``job`` a logic's ``prepare*``
        job ``job(progress, cancel)`` that touches no MRML node and no Qt. The job
        runs on a worker thread with the progress dialog
        (``runWithProgress(background=True)``), Slicer answering all along;
        ``store(result)`` writes its nodes, back on Slicer's thread.

        Returns what ``store`` returns, or None when a step failed (the error is
        shown) or the job was cancelled.
        """
        ready = self.run(title, prepare)
        if ready is None:
            return None
        job, store = ready
        result = self.runWithProgress(title, job, background=True)
        if result is None:
            return None
        return self.run(title, store, result)

    def _runInBackground(self, title, work, dialog):
        """``runWithProgress(background=True)``: the job on its thread, this thread in a
        local event loop that a 100 ms timer updates and ends."""
        import qt
        import slicer

        from fluoguide.jobs import BackgroundJob

        job = BackgroundJob(work, name=title).start()
        dialog.connect("canceled()", job.cancel)
        loop = qt.QEventLoop()
        timer = qt.QTimer()
        timer.setInterval(100)

        def tick():
            state = job.poll()
            dialog.setValue(int(round(100.0 * state.fraction)))
            step = f" ({state.step_seconds:.0f} s)" if state.step_seconds >= 2 else ""
            dialog.setLabelText(f"{title}: {state.message or 'starting'}{step}")
            if state.finished:
                loop.quit()

        timer.connect("timeout()", tick)
        timer.start()
        try:
            loop.exec_()
        finally:
            timer.stop()
            dialog.close()
        state = job.poll()
        if state.status == "done":
            return state.result
        if state.status == "cancelled":
            slicer.util.showStatusMessage(f"{title}: cancelled", 5000)
            return None
        self.showError(title, state.error)
        return None

    def showError(self, title, exc):
        """Bad input and device errors as their one-line message; anything else with
        its type, and its traceback in the application log. Headless: kept in
        ``errors`` and logged."""
        from fluoguide.errors import FluoError

        if isinstance(exc, FluoError):
            text = str(exc)
        else:
            log.exception("%s failed", title)
            text = f"{type(exc).__name__}: {exc}"
        if self.ui is None:
            self.errors.append(f"{title} failed: {text}")
            log.warning("%s failed: %s", title, text)
            return
        import slicer

        slicer.util.errorDisplay(f"{title} failed:\n\n{text}", windowTitle=self.moduleName)

    def run(self, title, fn, *args, **kwargs):
        """Call ``fn`` (short work, no progress); errors are shown. Returns its result or None."""
        try:
            if self.ui is None:
                return fn(*args, **kwargs)
            import slicer

            with slicer.util.WaitCursor():
                return fn(*args, **kwargs)
        except Exception as exc:
            self.showError(title, exc)
            return None
