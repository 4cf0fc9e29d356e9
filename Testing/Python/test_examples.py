"""docs/examples run as a user would run them: with the virtual environment's
``python`` after ``make venv``, from a folder of their own, no ``PYTHONPATH``."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fluoguide import mrml_io
from test_installed import installed_origins, installed_root

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "docs" / "examples" / "reconstruct_own_labelmap.py"


def _as_documented(args, cwd, timeout):
    """``python EXAMPLE ARGS`` in ``cwd`` with this process's environment less
    ``PYTHONPATH`` (which the test suite sets to the tree under test)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, str(EXAMPLE), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=cwd, env=env)


def test_reconstruct_own_labelmap_help_as_documented(tmp_path):
    r = _as_documented(["--help"], tmp_path, 60)
    assert r.returncode == 0, r.stderr
    assert "--make-example" in r.stdout and "LABELS optics.json ACQUISITION OUT" in r.stdout


@pytest.mark.slow
def test_reconstruct_own_labelmap_example(tmp_path):
    """docs/examples/reconstruct_own_labelmap.py as its docstring runs it (no
    ``PYTHONPATH``: ``FluoTomo`` comes from the installation): its own example
    inputs (a label map file, optics.json, a simulated acquisition folder) in,
    a saved scene out whose yield volumes peak in the inclusion (25-80 s)."""
    if installed_root(installed_origins(tmp_path)) != ROOT:
        # a git worktree sharing the main checkout's .venv: the example would run
        # that checkout's code, not this one's
        pytest.skip(f"{sys.prefix} has another checkout installed, not {ROOT}")
    r = _as_documented(["--make-example", tmp_path, "--accuracy", "fast", "--methods", "HP"],
                       tmp_path, 900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "saved" in r.stdout
    scene = mrml_io.load_scene(tmp_path / "scene.mrml")
    names = {n["name"] for n in mrml_io.node_summary(scene)}
    assert {"labels", "FluoTomoMesh", "FluoTomoYieldHP"} <= names, names
    lab = mrml_io.volume_array(mrml_io.get_node(scene, "labels"))
    vol = mrml_io.volume_array(mrml_io.get_node(scene, "FluoTomoYieldHP"))
    assert vol.shape == lab.shape
    k, j, i = np.unravel_index(int(np.argmax(vol)), vol.shape)
    assert lab[k, j, i] == 7
    info = mrml_io.get_json_attribute(mrml_io.get_node(scene, "FluoTomoYieldHP"),
                                      "FluoTomo.Reconstruction")
    assert abs(info["regions"]["7"]["yield_per_mm"] - 2.6e-3) / 2.6e-3 < 0.3, info["regions"]
    bad = _as_documented([tmp_path / "nope.nrrd", tmp_path / "inputs" / "optics.json",
                          tmp_path / "inputs" / "acquisition", tmp_path / "o2"], tmp_path, 300)
    assert bad.returncode == 2 and "nope.nrrd" in bad.stderr and "Traceback" not in bad.stderr
