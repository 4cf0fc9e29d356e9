"""The three module files load outside Slicer and their Test classes pass."""

import importlib

import pytest

MODULES = ["FluoCalib", "FluoNav", "FluoTomo"]


@pytest.mark.parametrize("name", MODULES)
def test_module_has_slicer_classes(name):
    mod = importlib.import_module(name)
    for suffix in ("", "Widget", "Logic", "Test"):
        assert hasattr(mod, name + suffix), name + suffix
    module = getattr(mod, name)()
    assert module.parent.title == name
    assert "FluoGuide" in module.parent.categories
    widget = getattr(mod, name + "Widget")()
    widget.setup()  # headless: no Qt, must not fail


@pytest.mark.parametrize("name", MODULES)
def test_logic_requires_scene(name):
    mod = importlib.import_module(name)
    with pytest.raises(ValueError):
        getattr(mod, name + "Logic")(None)


@pytest.mark.parametrize("name", MODULES)
def test_self_test_runs(name):
    mod = importlib.import_module(name)
    assert getattr(mod, name)().runTest()


def test_lib_imports_without_slicer():
    import subprocess
    import sys

    code = ("import sys; sys.modules['slicer'] = None\n"
            "import FluoCalibLib, FluoNavLib, FluoTomoLib\n"
            "from FluoTomoLib.meshing import mesh\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr
