"""The extension as Slicer would install it, checked without a Slicer build.

CMake itself configures the repository's ``CMakeLists.txt`` files against a
stand-in ``SlicerConfig.cmake`` whose ``slicerMacroBuildScriptedModule``
records, instead of copying, every script and resource it is given (with the
real macro's check that each exists). The recorded files are copied into a
``qt-scripted-modules`` folder laid out as Slicer lays it out, and a fresh
Python with only that folder for our code (the editable install's finder
removed) imports the three module files and every shipped module, and
resolves every import of our packages that any shipped file makes, lazy ones
included. So a file the modules need but CMake does not install fails here.

The stand-in cannot show that Slicer's real macros byte-compile and package
the files (docs/slicer.md says what was not checked).
"""

import ast
import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from fluoguide.errors import FluoInputError
from fluoguide.slicer_deps import FORBIDDEN, missing_requirements, read_requirements

ROOT = Path(__file__).resolve().parents[2]
OUR_PACKAGES = ("fluoguide", "FluoCalibLib", "FluoNavLib", "FluoTomoLib")
MODULE_FILES = ("FluoCalib", "FluoNav", "FluoTomo")

STUB_CONFIG = r"""
# Stand-in for SlicerConfig.cmake: the scripted-module macros record their files.
set(Slicer_FOUND TRUE)
set(Slicer_USE_PYTHONQT TRUE)
set(Slicer_QTSCRIPTEDMODULES_LIB_DIR "lib/Slicer-5.8/qt-scripted-modules")
set(Slicer_INSTALL_QTSCRIPTEDMODULES_LIB_DIR "${Slicer_QTSCRIPTEDMODULES_LIB_DIR}")
set(Slicer_USE_FILE "${CMAKE_CURRENT_LIST_DIR}/UseSlicer.cmake")
set(Slicer_EXTENSION_GENERATE_CONFIG "${CMAKE_CURRENT_LIST_DIR}/Empty.cmake")
set(Slicer_EXTENSION_CPACK "${CMAKE_CURRENT_LIST_DIR}/Empty.cmake")
"""

STUB_USE = r"""
set(FLUO_MANIFEST "${CMAKE_BINARY_DIR}/manifest.txt")
macro(slicerMacroBuildScriptedModule)
  cmake_parse_arguments(MY_SLICER "WITH_GENERIC_TESTS;WITH_SUBDIR;VERBOSE" "NAME"
                        "SCRIPTS;RESOURCES" ${ARGN})
  if(MY_SLICER_UNPARSED_ARGUMENTS)
    message(FATAL_ERROR "unknown arguments: ${MY_SLICER_UNPARSED_ARGUMENTS}")
  endif()
  foreach(kind SCRIPTS RESOURCES)
    foreach(value ${MY_SLICER_${kind}})
      set(file "${value}")
      if(kind STREQUAL "SCRIPTS" AND NOT file MATCHES "\\.py$")
        set(file "${file}.py")
      endif()
      if(NOT EXISTS "${CMAKE_CURRENT_SOURCE_DIR}/${file}")
        message(FATAL_ERROR "slicerMacroBuildScriptedModule(${kind}) given nonexistent file '${file}'")
      endif()
      file(APPEND "${FLUO_MANIFEST}" "${MY_SLICER_NAME}\t${file}\t${CMAKE_CURRENT_SOURCE_DIR}/${file}\n")
    endforeach()
  endforeach()
endmacro()
macro(slicer_add_python_unittest)
endmacro()
"""


def _third_party_imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0]


def _shipped_sources():
    files = sorted((ROOT / "fluoguide").glob("*.py"))
    for m in MODULE_FILES:
        files.append(ROOT / m / f"{m}.py")
        files += sorted((ROOT / m / f"{m}Lib").rglob("*.py"))
    return files


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """{install path relative to qt-scripted-modules: source path} per CMake."""
    cmake = shutil.which("cmake")
    if cmake is None:
        pytest.skip("cmake is not installed (Debian package cmake)")
    tmp = tmp_path_factory.mktemp("cmake")
    stub = tmp / "slicer-stub"
    stub.mkdir()
    (stub / "SlicerConfig.cmake").write_text(STUB_CONFIG)
    (stub / "UseSlicer.cmake").write_text(STUB_USE)
    (stub / "Empty.cmake").write_text("")
    build = tmp / "build"
    r = subprocess.run([cmake, "-S", str(ROOT), "-B", str(build), f"-DSlicer_DIR={stub}",
                        "-DBUILD_TESTING=OFF"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    out = {}
    for line in (build / "manifest.txt").read_text().splitlines():
        target, rel, src = line.split("\t")
        # each module's CMakeLists installs relative to its folder, the shared
        # package relative to the repository root: all land in qt-scripted-modules
        assert rel not in out or out[rel] == src, f"two files install as {rel}"
        out[rel] = src
    return out


@pytest.fixture(scope="module")
def tree(installed, tmp_path_factory):
    root = tmp_path_factory.mktemp("slicer") / "qt-scripted-modules"
    for rel, src in installed.items():
        dest = root / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dest)
    return root


def test_cmake_installs_every_module_and_the_shared_package(installed):
    rels = set(installed)
    for m in MODULE_FILES:
        assert f"{m}.py" in rels and f"Resources/Icons/{m}.png" in rels
    for m in MODULE_FILES:
        if (ROOT / m / "Resources" / "UI" / f"{m}.ui").is_file():
            assert f"Resources/UI/{m}.ui" in rels, f"{m}'s form is not installed"
    assert "fluoguide/__init__.py" in rels and "fluoguide/slicer_requirements.txt" in rels
    # every source file of the foundation and the Libs, and nothing of the application
    for src in _shipped_sources():
        assert str(src) in installed.values(), f"{src.relative_to(ROOT)} is not installed"
    assert not any(r.startswith(("fluoapp", "benchmarks", "Testing")) for r in rels)


IMPORT_CHECK = r"""
import ast, importlib, importlib.util, json, sys
from pathlib import Path
tree = Path(sys.argv[1]).resolve()
sys.path.insert(0, str(tree))
# the repository's editable install must not stand in for a file CMake missed
sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
problems = []
ours = ("fluoguide", "FluoCalibLib", "FluoNavLib", "FluoTomoLib", "FluoCalib", "FluoNav", "FluoTomo")
names = ["FluoCalib", "FluoNav", "FluoTomo"]
for path in sorted(tree.rglob("*.py")):
    rel = path.relative_to(tree).with_suffix("")
    if rel.parts[0] in ours[:4]:
        names.append(".".join(p for p in rel.parts if p != "__init__") if rel.name == "__init__"
                     else ".".join(rel.parts))
    # every absolute import of our packages, lazy ones included, must resolve in the tree
    for node in ast.walk(ast.parse(path.read_text())):
        mods = []
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            mods = [node.module] + [node.module + "." + a.name for a in node.names]
        for mod in mods:
            if mod.split(".")[0] not in ours:
                continue
            try:
                spec = importlib.util.find_spec(mod)
            except ModuleNotFoundError:
                spec = None
            if spec is None:
                parent = mod.rpartition(".")[0]
                if mod != node.module and parent:   # "from pkg import name": a name, not a module
                    continue
                problems.append(f"{path.relative_to(tree)}: {mod} not installed")
            elif spec.origin and not Path(spec.origin).resolve().is_relative_to(tree):
                problems.append(f"{path.relative_to(tree)}: {mod} comes from {spec.origin}")
for name in names:
    mod = importlib.import_module(name)
    if not Path(mod.__file__).resolve().is_relative_to(tree):
        problems.append(f"{name} imported from {mod.__file__}")
print(json.dumps({"imported": len(names), "problems": problems}))
"""


def test_the_installed_tree_alone_imports_everything_the_modules_need(tree):
    import os

    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", IMPORT_CHECK, str(tree)], capture_output=True,
                       text=True, timeout=600, env=env, cwd=str(tree))
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert not out["problems"], "\n".join(out["problems"])
    assert out["imported"] > 50


def test_the_walker_catches_a_missing_file(tree, tmp_path):
    """The import check fails when CMake leaves out a file a module imports."""
    import os

    broken = tmp_path / "qt-scripted-modules"
    shutil.copytree(tree, broken)
    (broken / "FluoNavLib" / "mapping" / "correct.py").unlink()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", IMPORT_CHECK, str(broken)], capture_output=True,
                       text=True, timeout=600, env=env, cwd=str(broken))
    problems = json.loads(r.stdout.strip().splitlines()[-1])["problems"]
    assert any("FluoNavLib.mapping.correct" in p for p in problems), problems


# ------------------------------------------------------------------ requirements for Slicer

#: what Slicer's own Python has (never to be installed by us)
SLICER_PROVIDED = {"vtk", "numpy", "slicer", "qt", "ctk", "mrml", "vtkAddon", "vtkITK",
                   "vtkSegmentationCore", "SampleData", "SimpleITK",
                   # pip (and the packaging it vendors) is how Slicer installs packages;
                   # slicer_deps reads markers with either, and without both lets pip decide
                   "pip", "packaging"}
# Optional engines, imported only when asked for, behind a one-line error that names
# what to install: the Monte Carlo reference (FluoTomoLib/montecarlo, the `mc` extra;
# never on a module's main path, and pmcxcl needs a system OpenCL driver pip cannot
# install into Slicer).  test_montecarlo.py checks that error.
OPTIONAL_ENGINES = {"pmcx", "pmcxcl"}


def _pyproject_requirements():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    out = {}
    for d in deps:
        name = re.match(r"[A-Za-z0-9._-]+", d).group(0)
        out[re.sub(r"[-_.]+", "-", name).lower()] = d.replace(" ", "")
    return out


def test_slicer_requirements_exclude_vtk_slicer_core_and_the_web_stack():
    reqs = dict(read_requirements())
    assert not set(reqs) & FORBIDDEN
    assert {"vtk", "slicer-core", "trame", "trame-slicer", "pyvista"} <= FORBIDDEN
    pyproject = _pyproject_requirements()
    for name, line in reqs.items():
        # the same range as the development environment, never a stricter pin
        assert name in pyproject, f"{name} is not a dependency in pyproject.toml"
        assert line.replace(" ", "") == pyproject[name], (line, pyproject[name])


def test_slicer_requirements_cover_every_import_of_the_shipped_files():
    from importlib.metadata import packages_distributions

    dists = packages_distributions()
    reqs = dict(read_requirements())
    stdlib = set(sys.stdlib_module_names)
    missing = {}
    for path in _shipped_sources():
        for top in _third_party_imports(path):
            if (top in stdlib or top in SLICER_PROVIDED or top in OUR_PACKAGES
                    or top in MODULE_FILES or top in OPTIONAL_ENGINES or top == "__future__"):
                continue
            names = {re.sub(r"[-_.]+", "-", d).lower() for d in dists.get(top, [])}
            if not names & set(reqs):
                missing.setdefault(top, []).append(str(path.relative_to(ROOT)))
    assert not missing, f"imported by shipped files but not in slicer_requirements.txt: {missing}"


def test_a_forbidden_or_malformed_requirement_is_refused(tmp_path):
    bad = tmp_path / "req.txt"
    bad.write_text("scipy>=1.13\nvtk==9.6.0\n")
    with pytest.raises(FluoInputError, match="vtk must never be installed"):
        read_requirements(bad)
    bad.write_text("trame_slicer\n")
    with pytest.raises(FluoInputError, match="trame-slicer"):
        read_requirements(bad)
    bad.write_text("-e /path/to/FluoGuide\n")
    with pytest.raises(FluoInputError, match="not a requirement"):
        read_requirements(bad)


def test_missing_requirements_are_the_uninstalled_ones(tmp_path):
    req = tmp_path / "req.txt"
    req.write_text("# comment\nscipy>=1.13\nfluoguide-no-such-distribution>=1\n")
    assert missing_requirements(req) == ["fluoguide-no-such-distribution>=1"]
    assert missing_requirements() == []   # the development environment has them all


def test_readme_no_longer_installs_the_repository_into_slicer():
    text = (ROOT / "README.md").read_text()
    assert 'pip_install("-e' not in text


def test_sample_data_loads_each_phantom_with_its_truth():
    """What a Sample Data button calls (its registration needs Slicer's SampleData module)."""
    from fluoguide import mrml_io
    from fluoguide.phantoms import PHANTOMS
    from fluoguide.slicer_samples import SAMPLES, load_phantom

    assert {name for name, _ in SAMPLES.values()} == set(PHANTOMS)
    scene = mrml_io.new_scene()
    cbct, labels = load_phantom(scene, "slab", voxel_mm=2.0)
    truth = mrml_io.get_json_attribute(cbct, "FluoGuide.Truth")
    assert truth["phantom"] == "slab" and labels.IsA("vtkMRMLLabelMapVolumeNode")
    assert mrml_io.volume_array(labels).max() >= 1


def test_cmake_installs_every_data_file_the_libs_read(installed):
    """Every file pyproject.toml's package-data ships beside a Lib's code is
    installed by CMake too (the stored Monte Carlo sets were missing)."""
    import tomllib

    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    dirs = doc["tool"]["setuptools"]["package-dir"]
    data = doc["tool"]["setuptools"]["package-data"]
    wanted = set()
    for package, patterns in data.items():
        base = ROOT / dirs[package]
        for pattern in patterns:
            for f in base.glob(pattern):
                if f.is_file():
                    # a Lib installs relative to its module folder, fluoguide from the root
                    wanted.add(str(f.relative_to(base.parent if package.endswith("Lib")
                                                 else ROOT)))
    assert wanted, "package-data lists no file"
    assert not wanted - set(installed), sorted(wanted - set(installed))


def test_optional_and_platform_specific_requirements_are_marked():
    """mkl has no build for Apple silicon or ARM Linux: it is optional and marked
    for x86-64, so an install there goes on without it (SuperLU solves)."""
    from packaging.markers import Marker

    from fluoguide.slicer_deps import applies_here, requirements

    reqs = {r.name: r for r in requirements()}
    mkl = reqs["mkl"]
    assert mkl.optional and "SuperLU" in mkl.optional and mkl.marker
    for machine, expected in (("x86_64", True), ("AMD64", True), ("arm64", False),
                              ("aarch64", False)):
        assert Marker(mkl.marker).evaluate({"platform_machine": machine}) is expected
    assert reqs["pytetwild"].optional and reqs["embreex"].optional
    required = [r.name for r in reqs.values() if r.optional is None]
    assert "scipy" in required and "numba" in required
    assert all(applies_here(r) for r in reqs.values() if r.marker is None)


def test_packages_install_one_at_a_time_and_a_failure_stops_none(tmp_path):
    from fluoguide.slicer_deps import install_requirements, install_summary

    req = tmp_path / "req.txt"
    req.write_text("scipy>=1.13\nfluoguide-no-such-a>=1\n"
                   "fluoguide-no-such-b>=1  # optional: nothing real\n"
                   "fluoguide-not-here>=1 ; platform_machine == 'no-such-machine'\n")
    required, optional = install_summary(req)
    assert required == ["fluoguide-no-such-a>=1"]                # scipy is installed
    assert optional == [("fluoguide-no-such-b>=1", "nothing real")]
    calls = []

    def pip_install(line):       # what slicer.util.pip_install is given, one line each
        calls.append(line)
        if "no-such-a" in line:
            raise RuntimeError("pip failed\nERROR: No matching distribution found")

    out = install_requirements(["fluoguide-no-such-a>=1", "fluoguide-no-such-b>=1"], pip_install)
    assert calls == ["fluoguide-no-such-a>=1", "fluoguide-no-such-b>=1"]   # the second still ran
    assert out["fluoguide-no-such-a>=1"].endswith("No matching distribution found")
    assert out["fluoguide-no-such-b>=1"] is None


def test_the_panels_never_ask_in_a_modal_dialog_when_they_are_built():
    """The package offer is in the panel: nothing reachable from the widget's
    setup opens a modal dialog (it blocked Slicer's generic module tests)."""
    src = (ROOT / "fluoguide" / "slicer_module.py").read_text()
    tree = ast.parse(src)
    funcs = {n.name: n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    reach, todo = set(), ["setup"]
    while todo:
        name = todo.pop()
        if name in reach or name not in funcs:
            continue
        reach.add(name)
        for node in ast.walk(funcs[name]):
            if isinstance(node, ast.Attribute) and node.attr in funcs:
                todo.append(node.attr)
    called = {node.attr for name in reach for node in ast.walk(funcs[name])
              if isinstance(node, ast.Attribute)}
    called |= {node.id for name in reach for node in ast.walk(funcs[name])
               if isinstance(node, ast.Name)}
    assert "_packageOffer" in reach and "_buildPanel" in reach
    modal = {"confirmOkCancelDisplay", "confirmYesNoDisplay", "ensure_dependencies", "exec_",
             "exec"}
    assert not called & modal, called & modal


# Removed from Python by 3.12 (the Python of the supported Slicer releases,
# docs/slicer.md): modules and the unittest aliases the module tests could use
REMOVED_IN_312 = {"distutils", "imp", "asynchat", "asyncore", "smtpd"}
REMOVED_ATTRS_312 = {"assertEquals", "assertNotEquals", "assertAlmostEquals",
                     "assertNotAlmostEquals", "assertRegexpMatches", "assertRaisesRegexp",
                     "assertDictContainsSubset", "failUnless", "failIf", "failUnlessEqual",
                     "SafeConfigParser", "readfp", "getargspec", "formatargspec"}


def test_the_shipped_files_use_nothing_python_312_removed():
    found = []
    for path in _shipped_sources():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found += [(path, a.name) for a in node.names
                          if a.name.split(".")[0] in REMOVED_IN_312]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.split(".")[0] in REMOVED_IN_312:
                    found.append((path, node.module))
            elif isinstance(node, ast.Attribute) and node.attr in REMOVED_ATTRS_312:
                found.append((path, node.attr))
    assert not found, [(str(p.relative_to(ROOT)), n) for p, n in found]
    # and the oldest syntax they may rely on parses (Slicer's previous Python)
    for path in _shipped_sources():
        ast.parse(path.read_text(), filename=str(path), feature_version=(3, 9))


def test_sample_data_sources_are_scenes_in_the_cache_that_download_sample_loads(tmp_path):
    """``SampleData.downloadSample(name)`` goes through ``downloadFromSource``, which
    ignores a custom downloader: each phantom is a scene file already in Slicer's
    download cache (written once), found there under its file name and loaded as a
    scene, truth and all."""
    from fluoguide import mrml_io
    from fluoguide.slicer_samples import SAMPLES, sample_sources

    cache = tmp_path / "cache"
    sources = sample_sources(cache)
    assert [s["sampleName"] for s in sources] == list(SAMPLES)
    for s in sources:
        assert "customDownloader" not in s and s["loadFileTypes"] == "SceneFile"
        assert s["loadFiles"] is True
        # what downloadFileIntoCache finds (no checksum: an existing file is used)
        path = cache / s["fileNames"]
        assert path.is_file() and s["uris"] == path.as_uri()
        scene = mrml_io.load_scene(path)                 # what slicer.util.loadScene does
        phantom = SAMPLES[s["sampleName"]][0]
        for name in ("CBCT", "CBCTLabels"):
            truth = mrml_io.get_json_attribute(mrml_io.get_node(scene, name), "FluoGuide.Truth")
            assert truth["phantom"] == phantom, name
    mtime = (cache / sources[0]["fileNames"]).stat().st_mtime_ns
    sample_sources(cache)                                     # the next start: reused
    assert (cache / sources[0]["fileNames"]).stat().st_mtime_ns == mtime
