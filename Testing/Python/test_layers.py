"""The layer rule, checked by walking every import of every source file.

foundation (``fluoguide``)  <-  FluoCalibLib  <-  FluoNavLib  <-  FluoTomoLib
    <-  module files (``FluoCalib.py`` ...)  <-  application (``fluoapp``, ``benchmarks``)

A file may import its own layer and the layers below it, never one above
(function-level imports included: a lazy import is still a dependency).
"""

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# layer rank of each top-level importable name (higher may import lower)
RANK = {"fluoguide": 0, "FluoCalibLib": 1, "FluoNavLib": 2, "FluoTomoLib": 3,
        "FluoCalib": 4, "FluoNav": 4, "FluoTomo": 4, "fluoapp": 5, "benchmarks": 5}

SOURCES = {
    "fluoguide": ROOT / "fluoguide",
    "FluoCalibLib": ROOT / "FluoCalib" / "FluoCalibLib",
    "FluoNavLib": ROOT / "FluoNav" / "FluoNavLib",
    "FluoTomoLib": ROOT / "FluoTomo" / "FluoTomoLib",
    "fluoapp": ROOT / "fluoapp",
    "benchmarks": ROOT / "benchmarks",
}
MODULE_FILES = {name: ROOT / name / f"{name}.py" for name in ("FluoCalib", "FluoNav", "FluoTomo")}


def _imported_tops(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module.split(".")[0]
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "import_module_file":
            # fluoguide.slicer_compat.import_module_file("FluoTomo"): a module-file import
            if node.args and isinstance(node.args[0], ast.Constant):
                yield node.lineno, node.args[0].value


def _files():
    for layer, folder in SOURCES.items():
        for path in sorted(folder.rglob("*.py")):
            yield layer, path
    for layer, path in MODULE_FILES.items():
        yield layer, path


def test_no_file_imports_a_higher_layer():
    violations = []
    for layer, path in _files():
        for lineno, top in _imported_tops(path):
            if top in RANK and RANK[top] > RANK[layer]:
                violations.append(f"{path.relative_to(ROOT)}:{lineno} ({layer}) imports {top}")
    assert not violations, "\n".join(violations)


def test_the_walker_sees_lazy_imports(tmp_path):
    # the rule must catch an import hidden in a function body
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from fluoapp.cli import main\n")
    assert ("fluoapp" in {t for _, t in _imported_tops(f)})


@pytest.mark.parametrize("lib", ["FluoCalibLib", "FluoNavLib", "FluoTomoLib"])
def test_libs_are_split_by_concept(lib):
    folder = SOURCES[lib]
    subpackages = [p for p in folder.iterdir() if (p / "__init__.py").exists()]
    assert len(subpackages) >= 2, f"{lib} has no concept subpackages"
    loose = [p.name for p in folder.glob("*.py") if p.name != "__init__.py"]
    # a few cross-cutting modules may sit at the top of a Lib; the rest live in subpackages
    assert len(loose) <= 3, f"{lib} top level holds {loose}"
    for sub in subpackages:
        doc = ast.get_docstring(ast.parse((sub / "__init__.py").read_text()))
        assert doc and len(doc) > 40, f"{sub} has no docstring saying what it holds"


def test_every_package_folder_is_installed():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    found = set()
    for top, folder in SOURCES.items():
        if top == "benchmarks":
            continue
        for init in folder.rglob("__init__.py"):
            rel = init.parent.relative_to(folder).parts
            found.add(".".join((top,) + rel))
    assert found == listed


def test_public_names_of_each_subpackage_resolve():
    import importlib

    for top in ("FluoCalibLib", "FluoNavLib", "FluoTomoLib"):
        for init in sorted(SOURCES[top].rglob("__init__.py")):
            rel = init.parent.relative_to(SOURCES[top]).parts
            if not rel:
                continue
            pkg = importlib.import_module(".".join((top,) + rel))
            for name in getattr(pkg, "__all__", []):
                assert getattr(pkg, name) is not None, f"{pkg.__name__}.{name}"
