"""Each module form loaded by Qt's own loader (PySide6's QUiLoader, offscreen).

What this checks that parsing the XML cannot: Qt builds the form; every widget
of a Qt class is created as that class, and every property set on it is one Qt
knows and can read (a bad enum or a value of the wrong type is a loader
warning, and any warning fails the test; a misspelt property name becomes a
silent dynamic property, which the test looks for); spin-box ranges and
defaults (integer and floating) and combo-box items are what the module code expects.

What it cannot: the CTK and Slicer classes (ctkCollapsibleButton,
ctkPathLineEdit, qMRMLNodeComboBox, qMRMLWidget) are unknown to plain Qt. The
loader makes them plain QWidgets, so their own properties (``nodeTypes``,
``filters``) and the ``mrmlSceneChanged`` connections are not checked here;
test_slicer_ui.py checks those from the XML, and only a Slicer build runs them.
The warnings the loader gives for exactly those classes, properties and
signals are the only ones allowed.
"""

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FORM_MODULES = [m for m in ("FluoCalib", "FluoNav", "FluoTomo")
                if (ROOT / m / "Resources" / "UI" / f"{m}.ui").is_file()]

LOADER = r"""
import json, sys
from PySide6 import QtCore, QtWidgets
from PySide6.QtUiTools import QUiLoader

messages = []
QtCore.qInstallMessageHandler(lambda mode, ctx, text: messages.append(text))
app = QtWidgets.QApplication([])
f = QtCore.QFile(sys.argv[1])
f.open(QtCore.QFile.ReadOnly)
form = QUiLoader().load(f)
out = {"loaded": form is not None, "messages": messages, "widgets": {}}
if form is not None:
    for w in form.findChildren(QtWidgets.QWidget):
        if not w.objectName():
            continue
        d = {"class": w.metaObject().className(),
             # a property the class does not have becomes a dynamic one, silently
             "dynamic": [n for n in (bytes(b).decode() for b in w.dynamicPropertyNames())
                         if not n.startswith("_")]}  # Qt's and PySide's own (_q_..., _PySide...)
        if isinstance(w, (QtWidgets.QSpinBox, QtWidgets.QDoubleSpinBox)):
            d.update(minimum=w.minimum(), maximum=w.maximum(), value=w.value())
        if isinstance(w, QtWidgets.QComboBox):
            d["items"] = [w.itemText(i) for i in range(w.count())]
        if isinstance(w, (QtWidgets.QLabel, QtWidgets.QAbstractButton)):
            d["text"] = w.text()
        out["widgets"][w.objectName()] = d
print(json.dumps(out))
"""


def _load(name):
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    r = subprocess.run([sys.executable, "-c", LOADER,
                        str(ROOT / name / "Resources" / "UI" / f"{name}.ui")],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _xml_widgets(name):
    root = ET.parse(ROOT / name / "Resources" / "UI" / f"{name}.ui").getroot()
    return {w.get("name"): w for w in root.iter("widget")}, root


@pytest.mark.parametrize("name", FORM_MODULES)
def test_qt_loads_the_form_with_no_warning_but_the_unknown_slicer_classes(name):
    out = _load(name)
    assert out["loaded"]
    xml, root = _xml_widgets(name)
    custom = {c.findtext("class") for c in root.iter("customwidget")}
    custom_props = {p.get("name") for w in xml.values() if w.get("class") in custom
                    for p in w.findall("property")}
    qt_props = {p.get("name") for w in xml.values() if w.get("class") not in custom
                for p in w.findall("property")}
    mrml_widgets = {n for n, w in xml.items() if w.get("class").startswith("qMRML")}
    allowed = set()
    for cls in custom:
        allowed.add(f"QFormBuilder was unable to create a custom widget of the class '{cls}'; "
                    "defaulting to base class 'QWidget'.")
    # set-type properties of the unknown classes (ctkPathLineEdit filters/options)
    for prop in custom_props - qt_props:
        allowed.add(f"Designer: The set-type property {prop} could not be read.")
    allowed.add("QObject::connect: No such signal QWidget::mrmlSceneChanged(vtkMRMLScene*)")
    allowed.add(f"QObject::connect:  (sender name:   '{name}')")
    for w in mrml_widgets - {name}:
        allowed.add(f"QObject::connect:  (receiver name: '{w}')")
    unexpected = [m for m in out["messages"] if m.strip('"') not in allowed]
    assert not unexpected, unexpected


@pytest.mark.parametrize("name", FORM_MODULES)
def test_qt_widgets_have_their_class_range_and_items(name):
    import importlib

    out = _load(name)
    xml, root = _xml_widgets(name)
    custom = {c.findtext("class") for c in root.iter("customwidget")}
    widgets = out["widgets"]
    for wname, elem in xml.items():
        cls = elem.get("class")
        if wname == name:
            continue
        assert wname in widgets, f"Qt did not create {wname}"
        # a Qt class is made as itself; a CTK/Slicer class falls back to QWidget
        assert widgets[wname]["class"] == ("QWidget" if cls in custom else cls), wname
        if cls not in custom:
            assert not widgets[wname]["dynamic"], f"{wname} ({cls}) has no property " \
                f"{widgets[wname]['dynamic']}"
    module = importlib.import_module(name)
    logic = getattr(module, name + "Logic")
    for wname, role, kind in getattr(module, name + "Widget").BINDINGS:
        w = widgets[wname]
        default = logic.PARAMETERS.get(role)
        if kind in ("int", "float") and "minimum" in w:  # a CTK slider is a plain QWidget here
            assert w["minimum"] <= default <= w["maximum"], (wname, default, w)
        if kind == "choice":
            assert default in w["items"], (wname, default, w["items"])
    # the form's own spin-box defaults are the logic's defaults (no surprise on first open)
    for wname, role, kind in getattr(module, name + "Widget").BINDINGS:
        if kind in ("int", "float") and any(p.get("name") == "value"
                                            for p in xml[wname].findall("property")):
            assert widgets[wname]["value"] == logic.PARAMETERS[role], wname
