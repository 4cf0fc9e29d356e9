"""docs/examples run as a user would run them."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from fluoguide import mrml_io

ROOT = Path(__file__).resolve().parents[2]


def test_reconstruct_own_labelmap_example(tmp_path):
    """docs/examples/reconstruct_own_labelmap.py: its own example inputs (a
    label map file, optics.json, a simulated acquisition folder) in, a saved
    scene out whose yield volumes peak in the inclusion."""
    r = subprocess.run([sys.executable, str(ROOT / "docs" / "examples" /
                                            "reconstruct_own_labelmap.py"),
                        "--make-example", str(tmp_path), "--accuracy", "fast", "--methods", "HP"],
                       capture_output=True, text=True, timeout=900, cwd=tmp_path)
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
    bad = subprocess.run([sys.executable, str(ROOT / "docs" / "examples" /
                                              "reconstruct_own_labelmap.py"),
                          str(tmp_path / "nope.nrrd"), str(tmp_path / "inputs" / "optics.json"),
                          str(tmp_path / "inputs" / "acquisition"), str(tmp_path / "o2")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "nope.nrrd" in bad.stderr and "Traceback" not in bad.stderr
