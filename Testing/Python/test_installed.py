"""The tree as ``make venv`` installs it (``pip install -e``): every top-level
name a user, a script or 3D Slicer imports resolves from any folder, the module
files (``FluoTomo/FluoTomo.py``, ...) included, without ``PYTHONPATH``.

The test suite itself puts the module folders on ``sys.path`` (pyproject.toml's
``pythonpath``, conftest.py), so only a child process with ``PYTHONPATH``
cleared sees what the installation alone provides.
"""

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# Slicer's layout: a module file sits in the folder of its own name, next to its Lib
MODULE_FILES = sorted(p.stem for p in ROOT.glob("*/*.py") if p.stem == p.parent.name)
PACKAGES = {"fluoguide": "fluoguide", "fluoapp": "fluoapp",
            **{f"{m}Lib": f"{m}/{m}Lib" for m in MODULE_FILES}}
# top-level name -> the file it must import from, relative to the installed tree
EXPECTED = {**{m: f"{m}/{m}.py" for m in MODULE_FILES},
            **{p: f"{folder}/__init__.py" for p, folder in PACKAGES.items()}}


def _clean_env():
    """This process's environment without PYTHONPATH: imports come from the
    virtual environment's installation only."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def installed_origins(cwd):
    """Top-level name -> the file a fresh interpreter (this one's virtual
    environment, ``PYTHONPATH`` cleared, started in ``cwd``) imports it from;
    None where nothing is found (or only a folder, a namespace package)."""
    code = ("import importlib.util, json, sys\n"
            "names = json.loads(sys.argv[1])\n"
            "specs = {n: importlib.util.find_spec(n) for n in names}\n"
            "print(json.dumps({n: s and s.origin for n, s in specs.items()}))\n")
    r = subprocess.run([sys.executable, "-c", code, json.dumps(sorted(EXPECTED))],
                       capture_output=True, text=True, timeout=60, cwd=cwd, env=_clean_env())
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def installed_root(origins):
    """The checkout the installation points at (``fluoguide``'s parent folder)."""
    return Path(origins["fluoguide"]).parents[1] if origins.get("fluoguide") else None


def test_the_module_files_are_found():
    # the discovery above must see Slicer's three modules, or the tests below check nothing
    assert MODULE_FILES == ["FluoCalib", "FluoNav", "FluoTomo"]


def test_pyproject_maps_every_top_level_name_to_its_file():
    """The editable install's finder (setuptools' ``__editable__`` finder) maps a
    top-level name to ``package-dir[name]``: a package when that folder holds
    ``__init__.py``, else the module file ``package-dir[name] + ".py"``; a
    module is installed only when ``py-modules`` lists it."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    package_dir = cfg.get("package-dir", {})
    for name, rel in EXPECTED.items():
        target = ROOT / package_dir.get(name, name)
        found = target / "__init__.py" if (target / "__init__.py").is_file() \
            else target.with_suffix(".py")
        assert found == ROOT / rel, f"pyproject.toml maps {name} to {found}, not {rel}"
        listed = cfg["packages"] if rel.endswith("__init__.py") else cfg.get("py-modules", [])
        assert name in listed, f"{name} is not in pyproject.toml's list"


def test_every_top_level_name_imports_as_installed_from_any_folder(tmp_path):
    """``python -c "import FluoTomo"`` in a folder outside the checkout, with no
    ``PYTHONPATH``: each name resolves to its file in the installed checkout
    (in a git worktree that shares the main checkout's ``.venv``, that checkout)."""
    origins = installed_origins(tmp_path)
    root = installed_root(origins)
    wrong = {n: o for n, o in origins.items()
             if root is None or o is None or Path(o) != root / EXPECTED[n]}
    assert not wrong, (f"not importable as installed (run `make venv`: pyproject.toml "
                       f"changed since {sys.prefix} was installed): {wrong}")
