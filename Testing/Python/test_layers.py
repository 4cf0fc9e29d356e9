"""The layer rule, checked by walking every import of every source file, and the
application's short, named list of what it may import from the Libs.

foundation (``fluoguide``)  <-  FluoCalibLib  <-  FluoNavLib  <-  FluoTomoLib
    <-  module files (``FluoCalib.py`` ...)  <-  application (``fluoapp``, ``benchmarks``)

A file may import its own layer and the layers below it, never one above
(function-level imports included: a lazy import is still a dependency).
"""

import ast
import sys
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


def _module_names():
    """Dotted name -> source file of every project module (a package is its
    ``__init__.py``)."""
    names = {}
    for layer, path in _files():
        if layer in MODULE_FILES:
            names[layer] = path
            continue
        parts = (layer,) + path.relative_to(SOURCES[layer]).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def _lazy_exports(path):
    """Public name -> submodule of a package whose ``__init__`` hands its names
    out through ``fluoguide.lazy.attach`` (``from pkg import name`` imports
    ``pkg.submodule`` when used: a dependency on that submodule)."""
    exports = {}
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "attach"
                and len(node.args) == 2 and isinstance(node.args[1], ast.Dict)):
            for sub, names in zip(node.args[1].keys, node.args[1].values):
                for name in getattr(names, "elts", []):
                    exports[name.value] = sub.value
    return exports


def _import_edges(name, path, modules, lazy):
    """(line, imported project module) for every import in ``path`` (module
    ``name``), at any depth: module level, in functions, under ``if``.

    ``from a.b import c`` depends on ``a.b.c`` when that is a module, else on
    the module ``a.b`` (or on the submodule that ``a.b``'s lazy table names
    for ``c``); relative imports are resolved against the module's package;
    ``import_module_file("FluoTomo")`` depends on the module file. Imports of
    anything outside the project are dropped.
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        targets = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(base + ([node.module] if node.module else []))
            else:
                base = node.module
            for alias in node.names:
                full = f"{base}.{alias.name}"
                if full in modules:
                    targets.append(full)
                elif alias.name in lazy.get(base, {}):
                    targets.append(f"{base}.{lazy[base][alias.name]}")
                else:
                    targets.append(base)
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "import_module_file":
            if node.args and isinstance(node.args[0], ast.Constant):
                targets = [node.args[0].value]
        for target in targets:
            # ``import a.b.c`` names a.b.c; a name that is no module is an attribute
            # of the nearest enclosing one
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                yield node.lineno, target


def _import_graph():
    """Project module -> {imported project module: first line of that import}."""
    modules = _module_names()
    lazy = {n: _lazy_exports(p) for n, p in modules.items() if p.name == "__init__.py"}
    graph = {}
    for name, path in modules.items():
        edges = graph.setdefault(name, {})
        for lineno, target in _import_edges(name, path, modules, lazy):
            edges.setdefault(target, lineno)
    return graph


def _cycles(graph):
    """Strongly connected components of more than one module (Tarjan's
    algorithm, iterative: the graph has hundreds of modules), each as a list of
    module names, sorted."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def _describe(component, graph):
    """The component's imports among its own members, ``a:LINE -> b`` each."""
    members = set(component)
    return "; ".join(f"{a}:{line} -> {b}" for a in component
                     for b, line in sorted(graph[a].items()) if b in members)


def test_no_file_imports_a_higher_layer():
    violations = []
    for layer, path in _files():
        for lineno, top in _imported_tops(path):
            if top in RANK and RANK[top] > RANK[layer]:
                violations.append(f"{path.relative_to(ROOT)}:{lineno} ({layer}) imports {top}")
    assert not violations, "\n".join(violations)


# The application reaches the Libs through the logic classes (FluoCalibLogic,
# FluoNavLogic, FluoTomoLogic: issue #30); these I/O and formatting helpers are
# the only names it may import from a Lib directly ({module: names}).
APP_LIB_IMPORTS = {
    # the accuracy levels' settings and the simulator's fault kinds, named in --help
    # when the parser is built (before any command runs: no logic class, no scene)
    "FluoTomoLib.tomography.accuracy": {"LEVELS"},
    "FluoNavLib.devices.ndi_simulator": {"FAULT_KINDS"},
    # readers of calibration inputs: image globs, pose, intrinsics, matrix and point files
    "FluoCalibLib.geometry.files": {"image_files", "read_handeye_poses", "read_intrinsics",
                                    "read_matrix", "read_points"},
    # a corrected frame with its contour, as a PNG file
    "FluoNavLib.mapping.contours": {"overlay_png"},
}

# Debt still to move behind the logic classes (issue #30), file by file: what
# these files import today. Shrink it; never grow it.
APP_LIB_DEBT = {}

LIBS = ("FluoCalibLib", "FluoNavLib", "FluoTomoLib")


def _lib_imports(path):
    """(line, module, name) of every import of a Lib in ``path``, at any depth
    (``import FluoTomoLib.x`` gives the name ``*``)."""
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in LIBS:
                    yield node.lineno, alias.name, "*"
        elif (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
              and node.module.split(".")[0] in LIBS):
            for alias in node.names:
                yield node.lineno, node.module, alias.name


def _allowed_lib_imports(rel):
    allowed = {m: set(names) for m, names in APP_LIB_IMPORTS.items()}
    for prefix, debt in APP_LIB_DEBT.items():
        if rel.startswith(prefix):
            for module, names in debt.items():
                allowed.setdefault(module, set()).update(names)
    return allowed


def test_the_app_reaches_the_libs_through_the_logic_classes():
    stray = []
    for path in sorted(SOURCES["fluoapp"].rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        allowed = _allowed_lib_imports(rel)
        for lineno, module, name in _lib_imports(path):
            if name not in allowed.get(module, ()):
                stray.append(f"{rel}:{lineno} imports {module}.{name}")
    assert not stray, ("call a logic class method instead (or name an I/O or formatting "
                       "helper in APP_LIB_IMPORTS):\n" + "\n".join(stray))


def test_the_allow_list_names_what_is_imported():
    # a listed name nobody imports any more is dropped from the list, so the list
    # stays the true account of what the app takes from the Libs
    used = {}
    for path in sorted(SOURCES["fluoapp"].rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        for _, module, name in _lib_imports(path):
            used.setdefault(module, set()).add(name)
            for prefix in APP_LIB_DEBT:
                if rel.startswith(prefix):
                    used.setdefault((prefix, module), set()).add(name)
    unused = [f"{m}.{n}" for m, names in APP_LIB_IMPORTS.items() for n in names
              if n not in used.get(m, ())]
    unused += [f"{p}: {m}.{n}" for p, debt in APP_LIB_DEBT.items() for m, names in debt.items()
               for n in names if n not in used.get((p, m), ())]
    assert not unused, "listed but no longer imported (drop them):\n" + "\n".join(unused)


def test_the_app_import_check_sees_a_stray_import(tmp_path):
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from FluoTomoLib.tomography import reconstruct_labelmap\n"
                 "    import FluoNavLib.devices\n")
    found = [(m, n) for _, m, n in _lib_imports(f)]
    assert sorted(found) == [("FluoNavLib.devices", "*"),
                             ("FluoTomoLib.tomography", "reconstruct_labelmap")]
    assert "reconstruct_labelmap" not in _allowed_lib_imports("fluoapp/commands/x.py").get(
        "FluoTomoLib.tomography", ())


def test_the_walker_sees_lazy_imports(tmp_path):
    # the rule must catch an import hidden in a function body
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from fluoapp.cli import main\n")
    assert ("fluoapp" in {t for _, t in _imported_tops(f)})


def test_no_import_cycles():
    # a cycle hidden by imports inside functions still ties its modules together:
    # neither can be read, tested or moved without the other
    graph = _import_graph()
    cycles = _cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(_describe(c, graph) for c in cycles)


def test_the_cycle_finder_sees_lazy_and_relative_imports(tmp_path, monkeypatch):
    # a two-module cycle through a function-level relative import, and one through a
    # package's lazy table, must both be found; a one-way chain must not
    pkg = tmp_path / "fluoguide"
    (pkg / "sub").mkdir(parents=True)
    sources = {
        "__init__": "",
        "a": "from fluoguide.b import x\n",
        "b": "def f():\n    from . import a\n",
        "c": "import fluoguide.a\n",
        "sub/__init__": "from fluoguide.lazy import attach\n"
                        "__getattr__, __dir__, __all__ = attach(__name__, {'d': ['g']})\n",
        "sub/d": "def g():\n    from fluoguide.e import h\n",
        "e": "from fluoguide.sub import g\n",
    }
    for module, text in sources.items():
        (pkg / module).with_suffix(".py").write_text(text)
    monkeypatch.setitem(SOURCES, "fluoguide", pkg)
    for top in [t for t in SOURCES if t != "fluoguide"]:
        monkeypatch.setitem(SOURCES, top, tmp_path / "none")
    monkeypatch.setattr(sys.modules[__name__], "MODULE_FILES", {})
    assert _cycles(_import_graph()) == [["fluoguide.a", "fluoguide.b"],
                                        ["fluoguide.e", "fluoguide.sub.d"]]


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


#: the longest function a reader is asked to hold, ``def`` to its last line,
#: docstring included (issue #30)
MAX_FUNCTION_LINES = 120


def test_no_function_is_longer_than_a_reader_can_hold():
    files = [p for root in SOURCES.values() for p in sorted(root.rglob("*.py"))]
    files += list(MODULE_FILES.values())
    long = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, (f"split by concept (at most {MAX_FUNCTION_LINES} lines):\n"
                      + "\n".join(long))
