"""The parts of Slicer's scripted-module API that slicer-core lacks.

In 3D Slicer, module files import ``slicer.ScriptedLoadableModule`` and get the
real base classes.  In plain Python with slicer-core there is real MRML but no
``ScriptedLoadableModule``, no ``qt`` and no ``slicer.mrmlScene``; this module
provides base classes with the same names and the same small surface, so the
module files run unchanged under pytest, in the ``fluo`` CLI and in the web app.

Module files do::

    try:
        from slicer.ScriptedLoadableModule import (ScriptedLoadableModule,
            ScriptedLoadableModuleWidget, ScriptedLoadableModuleLogic,
            ScriptedLoadableModuleTest)
    except ImportError:
        from fluoguide.slicer_compat import ...

Logic classes take the scene explicitly; nothing here creates a global scene.
"""

from __future__ import annotations

import unittest


def in_slicer_application():
    """True inside the 3D Slicer desktop application (Qt and a main window exist)."""
    try:
        import slicer

        return hasattr(slicer, "app") and hasattr(slicer, "mrmlScene")
    except ImportError:
        return False


class _Parent:
    """Stand-in for the ``qSlicerScriptedLoadableModule`` the real base class wraps."""

    def __init__(self):
        self.title = ""
        self.categories = []
        self.dependencies = []
        self.contributors = []
        self.helpText = ""
        self.acknowledgementText = ""
        self.hidden = False


def _module_folder(python_module_name):
    import sys
    from pathlib import Path

    module = sys.modules.get(python_module_name)
    path = getattr(module, "__file__", None)
    return Path(path).resolve().parent if path else None


class ScriptedLoadableModule:
    """Module descriptor: title, categories, help text (no GUI outside Slicer)."""

    def __init__(self, parent=None):
        self.parent = parent if parent is not None else _Parent()
        self.moduleName = self.__class__.__name__

    def resourcePath(self, filename):
        """``<module folder>/Resources/<filename>``, as in Slicer."""
        return str(_module_folder(self.__class__.__module__) / "Resources" / filename)

    def getDefaultModuleDocumentationLink(self, docPage=None):
        return "See docs/ in the FluoGuide repository."

    def runTest(self, msec=100, **kwargs):
        """Run the module's ``<Module>Test`` class, as Slicer's self-test button does."""
        import importlib
        import sys

        module = sys.modules.get(self.__class__.__module__) or importlib.import_module(
            self.__class__.__module__)
        test_class = getattr(module, self.moduleName + "Test")
        suite = unittest.TestSuite()
        suite.addTest(test_class("runTest"))
        result = unittest.TextTestRunner(verbosity=2).run(suite)
        return result.wasSuccessful()


class ScriptedLoadableModuleWidget:
    """Panel base class.  Outside Slicer there is no Qt layout: ``setup`` only
    records that it ran, and the web app builds its own panel from the logic."""

    def __init__(self, parent=None):
        self.parent = parent
        self.layout = None
        self.moduleName = self.__class__.__name__
        if self.moduleName.endswith("Widget"):
            self.moduleName = self.moduleName[: -len("Widget")]
        self.developerMode = False

    def resourcePath(self, filename):
        """``<module folder>/Resources/<filename>``, as in Slicer."""
        return str(_module_folder(self.__class__.__module__) / "Resources" / filename)

    def setup(self):
        self._setup_done = True

    def cleanup(self):
        pass

    def onReload(self):
        pass


class ScriptedLoadableModuleLogic:
    """Logic base class.  Real Slicer's takes no scene; ours neither, and the
    FluoGuide logics take ``scene`` in their own constructor."""

    def __init__(self, parent=None):
        self.parent = parent
        self.moduleName = self.__class__.__name__
        if self.moduleName.endswith("Logic"):
            self.moduleName = self.moduleName[: -len("Logic")]
        self.isSingletonParameterNode = True

    def getParameterNode(self):
        """The module's parameter node in the logic's own scene (``self.scene``),
        made as Slicer's base class makes it (``fluoguide.parameters``)."""
        from fluoguide.parameters import parameter_node

        scene = getattr(self, "scene", None)
        if scene is None:
            raise RuntimeError(f"{self.__class__.__name__} has no scene for its parameter node")
        return parameter_node(scene, self.moduleName)


class ScriptedLoadableModuleTest(unittest.TestCase):
    """Test base class: a unittest.TestCase, so pytest collects subclasses too."""

    def delayDisplay(self, message, msec=0):
        # In Slicer this shows a message box for msec; headless it is a log line.
        print(message)

    def setUp(self):
        pass


def import_module_file(name):
    """Import a module file (``FluoTomo`` from ``FluoTomo/FluoTomo.py``) the way
    Slicer does, by putting its folder on ``sys.path``.

    The web app uses the same module files (their Widget classes build its
    panels); module folders sit at the repository root next to ``fluoguide/``.
    """
    import importlib
    import sys
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / name
    if not (folder / f"{name}.py").is_file():
        raise ImportError(f"module file {name}.py not found in {folder}")
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    return importlib.import_module(name)
