"""The desktop widgets, checked without a Slicer binary.

What can be checked here: each module's Qt Designer form parses; it holds
every widget the module code uses (``self.ui.<name>`` and the parameter
bindings) with a class that fits the use; it uses only Qt, CTK and Slicer
classes, declares the custom ones, and connects the scene to every MRML
widget; the bindings name parameters the logic declares, with defaults the
widgets can show; and the parameter node comes back from a saved scene.
What cannot: that Slicer's PythonQt builds the form and the signals fire
(that needs the Slicer application; docs/slicer.md says so).
"""

import ast
import importlib
import inspect
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from fluoguide import mrml_io, parameters
from fluoguide.errors import FluoInputError
from fluoguide.slicer_module import BINDING_KINDS, FluoModuleWidget

ROOT = Path(__file__).resolve().parents[2]
MODULES = ["FluoCalib", "FluoNav", "FluoTomo"]

QT_CLASSES = {"QWidget", "QLabel", "QPushButton", "QToolButton", "QLineEdit", "QCheckBox",
              "QRadioButton", "QComboBox", "QSpinBox", "QDoubleSpinBox", "QGroupBox", "QFrame",
              "QTextEdit", "QPlainTextEdit", "QProgressBar", "QSlider", "QTabWidget",
              "QTableWidget", "QListWidget", "QScrollArea", "QSplitter", "QStackedWidget"}
CTK_CLASSES = {"ctkCollapsibleButton", "ctkCollapsibleGroupBox", "ctkPathLineEdit",
               "ctkSliderWidget", "ctkRangeWidget", "ctkDoubleSpinBox", "ctkCheckBox",
               "ctkComboBox", "ctkColorPickerButton", "ctkMenuButton"}
SLICER_CLASSES = {"qMRMLWidget", "qMRMLNodeComboBox", "qMRMLSubjectHierarchyComboBox",
                  "qMRMLSegmentSelectorWidget", "qMRMLSliceWidget", "qMRMLThreeDWidget",
                  "qMRMLRangeWidget", "qMRMLSliderWidget", "qMRMLSpinBox",
                  "qMRMLCheckableNodeComboBox", "qMRMLSequenceBrowserPlayWidget",
                  "qSlicerWidget"}
LAYOUTS = {"QVBoxLayout", "QHBoxLayout", "QFormLayout", "QGridLayout"}
#: value type of a binding kind's parameter
KIND_TYPES = {"text": str, "path": str, "choice": str, "int": int, "float": float, "bool": bool}


def _module(name):
    return importlib.import_module(name)


def _widget_class(name):
    return getattr(_module(name), name + "Widget")


def _with_form():
    return [m for m in MODULES if issubclass(_widget_class(m), FluoModuleWidget)]


def _form(name):
    path = ROOT / name / "Resources" / "UI" / f"{name}.ui"
    tree = ET.parse(path)  # raises on malformed XML
    return tree.getroot()


def _widgets(root):
    """{name: element} of every widget in the form (names must be unique)."""
    seen = {}
    for w in root.iter("widget"):
        name = w.get("name")
        assert name not in seen, f"widget name {name} used twice"
        seen[name] = w
    return seen


def _ui_names_used(cls):
    """Names of ``self.ui.<name>`` in a widget class's source."""
    tree = ast.parse(inspect.getsource(cls))
    names = set()
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
                and node.value.attr == "ui" and isinstance(node.value.value, ast.Name)
                and node.value.value.id == "self"):
            names.add(node.attr)
    return names


#: modules whose widget is a FluoModuleWidget (a .ui form): every test below runs on each
FORM_MODULES = _with_form()


def test_every_module_has_a_form():
    # every widget derives from FluoModuleWidget, so every form test here covers all three
    assert FORM_MODULES == MODULES


@pytest.mark.parametrize("name", FORM_MODULES)
def test_form_parses_and_is_an_mrml_widget(name):
    root = _form(name)
    assert root.tag == "ui" and root.findtext("class") == name
    top = root.find("widget")
    assert top.get("class") == "qMRMLWidget" and top.get("name") == name


@pytest.mark.parametrize("name", FORM_MODULES)
def test_form_uses_only_qt_ctk_and_slicer_classes(name):
    root = _form(name)
    known = QT_CLASSES | CTK_CLASSES | SLICER_CLASSES
    used = {w.get("class") for w in root.iter("widget")}
    assert used <= known, used - known
    assert {lay.get("class") for lay in root.iter("layout")} <= LAYOUTS
    declared = {c.findtext("class"): c for c in root.iter("customwidget")}
    for cls in used - QT_CLASSES:
        assert cls in declared, f"{cls} not declared in <customwidgets>"
        assert declared[cls].findtext("header") == f"{cls}.h"
        assert declared[cls].findtext("extends") in QT_CLASSES


@pytest.mark.parametrize("name", FORM_MODULES)
def test_every_widget_the_code_uses_is_in_the_form(name):
    cls = _widget_class(name)
    widgets = _widgets(_form(name))
    used = _ui_names_used(cls)
    missing = sorted(used - set(widgets))
    assert not missing, f"{name}.py uses widgets its .ui lacks: {missing}"
    for wname in used:
        if wname.endswith("Button"):
            assert widgets[wname].get("class") in ("QPushButton", "QToolButton"), wname
        if wname.endswith("Label"):
            assert widgets[wname].get("class") == "QLabel", wname
        if wname.endswith("Selector"):
            assert widgets[wname].get("class") == "qMRMLNodeComboBox", wname
    # and every button in the form does something
    buttons = {n for n, w in widgets.items() if w.get("class") == "QPushButton"}
    assert buttons <= used, f"buttons nobody connects: {sorted(buttons - used)}"


@pytest.mark.parametrize("name", FORM_MODULES)
def test_bindings_fit_the_widgets_and_the_logic_parameters(name):
    cls = _widget_class(name)
    logic_cls = getattr(_module(name), name + "Logic")
    widgets = _widgets(_form(name))
    assert cls.BINDINGS, "a form with no parameter bindings saves nothing"
    for wname, role, kind in cls.BINDINGS:
        assert kind in BINDING_KINDS, (wname, kind)
        assert wname in widgets, f"binding to a widget the form lacks: {wname}"
        wclass = widgets[wname].get("class")
        assert wclass in BINDING_KINDS[kind][1], (wname, wclass, kind)
        if kind == "node":
            assert role not in logic_cls.PARAMETERS, f"{role}: a node reference, not a parameter"
            types = [s.text for s in widgets[wname].iter("string")
                     if s.text and s.text.startswith("vtkMRML")]
            assert types, f"{wname} has no nodeTypes"
            continue
        assert role in logic_cls.PARAMETERS, f"{wname} binds {role}, which the logic lacks"
        default = logic_cls.PARAMETERS[role]
        assert type(default) is KIND_TYPES[kind], (role, type(default), kind)
        if kind == "choice":
            items = [i.findtext("property/string") for i in widgets[wname].findall("item")]
            assert default in items, f"{role} default {default!r} is not an item of {wname}"


@pytest.mark.parametrize("name", FORM_MODULES)
def test_every_mrml_widget_gets_the_scene(name):
    root = _form(name)
    mrml = {n for n, w in _widgets(root).items()
            if w.get("class").startswith("qMRML") and n != name}
    wired = {c.findtext("receiver") for c in root.iter("connection")
             if c.findtext("sender") == name
             and c.findtext("signal") == "mrmlSceneChanged(vtkMRMLScene*)"
             and c.findtext("slot") == "setMRMLScene(vtkMRMLScene*)"}
    assert mrml <= wired, f"MRML widgets without a scene: {sorted(mrml - wired)}"


@pytest.mark.parametrize("name", MODULES)
def test_parameter_node_is_a_singleton_of_the_logic_scene(name):
    scene = mrml_io.new_scene()
    logic = getattr(_module(name), name + "Logic")(scene)
    node = logic.getParameterNode()
    assert node.IsA("vtkMRMLScriptedModuleNode") and node.GetSingletonTag() == name
    assert node.GetAttribute("ModuleName") == name
    assert logic.getParameterNode() is node          # one per scene
    other = mrml_io.new_scene()
    assert getattr(_module(name), name + "Logic")(other).getParameterNode() is not node


@pytest.mark.parametrize("name", FORM_MODULES)
def test_parameter_node_round_trips_through_a_saved_scene(name, tmp_path):
    Logic = getattr(_module(name), name + "Logic")
    scene = mrml_io.new_scene()
    logic = Logic(scene)
    node = logic.getParameterNode()
    # every declared parameter gets a value that differs from its default
    changed = {}
    for key, default in Logic.PARAMETERS.items():
        kind = type(default)
        value = (not default if kind is bool else default + 3 if kind is int
                 else default + 0.25 if kind is float else f"{default}-changed")
        parameters.set_value(node, key, value)
        changed[key] = value
    target = mrml_io.add_model(scene, "ChosenModel", np.eye(3), np.array([[0, 1, 2]]))
    role = next(r for _, r, k in _widget_class(name).BINDINGS if k == "node")
    node.SetNodeReferenceID(role, target.GetID())
    path = mrml_io.save_scene(scene, tmp_path / "scene.mrml")

    loaded = Logic(mrml_io.load_scene(path))
    again = loaded.getParameterNode()
    assert again.GetSingletonTag() == name
    for key, value in changed.items():
        assert loaded.parameter(key) == value, key
    assert again.GetNodeReference(role).GetName() == "ChosenModel"


def test_defaults_fill_only_what_is_unset_and_bad_values_are_named():
    from FluoCalib import FluoCalibLogic

    scene = mrml_io.new_scene()
    logic = FluoCalibLogic(scene)
    node = logic.getParameterNode()
    node.SetParameter("Holdout", "7")
    logic.setDefaultParameters(node)
    assert logic.parameter("Holdout") == 7 and logic.parameter("Board") == "chessboard:9x6:25"
    node.SetParameter("Holdout", "seven")
    with pytest.raises(FluoInputError, match="Holdout"):
        logic.parameter("Holdout")
    node.SetParameter("Fisheye", "yes")
    with pytest.raises(FluoInputError, match="true or false"):
        logic.parameter("Fisheye")


@pytest.mark.parametrize("name", FORM_MODULES)
def test_headless_widget_setup_builds_nothing(name):
    widget = _widget_class(name)()
    widget.setup()
    assert widget.ui is None and widget.logic is None   # no Qt here: nothing to bind
