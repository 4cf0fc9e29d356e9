"""Each module writes only the scene nodes docs/scene.md documents for it."""

import fnmatch
import re
from pathlib import Path

import numpy as np
import pytest

from fluoguide import mrml_io

DOC = Path(__file__).resolve().parents[2] / "docs" / "scene.md"


def documented_nodes():
    """(name pattern, class, module) of every row of the Nodes table."""
    rows = []
    in_nodes = False
    for line in DOC.read_text().splitlines():
        if line.startswith("## "):
            in_nodes = line.strip() == "## Nodes"
            continue
        m = re.match(r"\|\s*`([^`]+)`\s*\|\s*(vtkMRML\w+)\s*\|\s*(\w+)\s*\|", line)
        if in_nodes and m:
            rows.append(m.groups())
    return rows


def _data_nodes(scene):
    return {(n["name"], n["class"]) for n in mrml_io.node_summary(scene)}


def _check(module, before, after):
    allowed = [(pat, cls) for pat, cls, mod in documented_nodes() if mod == module]
    for name, cls in sorted(after - before):
        ok = any(fnmatch.fnmatchcase(name, pat) and cls == c for pat, c in allowed)
        assert ok, f"{module} wrote {name} ({cls}), which docs/scene.md does not list for it"


def test_doc_table_parses():
    rows = documented_nodes()
    assert ("CBCT", "vtkMRMLScalarVolumeNode", "FluoGuide") in rows
    assert {mod for _, _, mod in rows} >= {"FluoGuide", "FluoCalib", "FluoNav"}


def _scenario_fluoguide(scene):
    from fluoguide.phantoms import add_phantom_to_scene, make_phantom

    add_phantom_to_scene(scene, make_phantom("slab", voxel_mm=2.0))


def _scenario_fluocalib(scene, tmp_path):
    import json

    from FluoCalib import FluoCalibLogic

    logic = FluoCalibLogic(scene)
    logic.setHandEye(np.eye(4))
    p = tmp_path / "calib.json"
    p.write_text(json.dumps({"fx": 1000.0}))
    logic.loadCalibrationJson(p)
    pts = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    logic.registerTrackerToReference(pts, pts + 1.0)
    logic.getParameterNode()


def _scenario_fluonav(scene):
    from FluoNav import FluoNavLogic

    logic = FluoNavLogic(scene)
    logic.buildSurface()
    logic.getParameterNode()
    logic.connectTracker("ndi-sim")
    try:
        while not logic.updateTracker():
            pass
    finally:
        logic.disconnect()
    logic.showTrackedCamera()


def _scenario_fluotomo(scene):
    from FluoTomo import FluoTomoLogic

    logic = FluoTomoLogic(scene)
    logic.labelVolumes()
    logic.buildMesh(mrml_io.get_node(scene, "CBCTLabels"), sizeMm=6.0)


@pytest.mark.parametrize("module", ["FluoGuide", "FluoCalib", "FluoNav", "FluoTomo"])
def test_module_writes_only_documented_nodes(module, tmp_path):
    scene = mrml_io.new_scene()
    if module != "FluoGuide":
        _scenario_fluoguide(scene)
    before = _data_nodes(scene)
    if module == "FluoGuide":
        _scenario_fluoguide(scene)
    elif module == "FluoCalib":
        _scenario_fluocalib(scene, tmp_path)
    elif module == "FluoNav":
        _scenario_fluonav(scene)
    else:
        _scenario_fluotomo(scene)
    after = _data_nodes(scene)
    assert after >= before
    _check(module, before, after)


def test_frame_correction_and_mapping_write_documented_nodes():
    """FluoNav's results (transport, flux and raw images, the mapped surface) are
    the nodes docs/scene.md lists; the synthetic acquisition they start from is
    FluoGuide's and FluoCalib's (surface, calibration, recording)."""
    from FluoNav import FluoNavLogic

    scene = mrml_io.new_scene()
    logic = FluoNavLogic(scene)
    logic.makeSyntheticAcquisition(views=2, binning=8, triangles=8000)
    before = _data_nodes(scene)
    for name, cls in before:
        assert any(fnmatch.fnmatchcase(name, pat) and cls == c
                   for pat, c, _ in documented_nodes()), (name, cls)
    logic.correctFrame(0)
    logic.mapFrames()
    after = _data_nodes(scene)
    assert {("FluoNavTransport", "vtkMRMLScalarVolumeNode"),
            ("FluoNavFlux", "vtkMRMLScalarVolumeNode"),
            ("FluoNavSurfaceFlux", "vtkMRMLModelNode")} <= after - before
    _check("FluoNav", before, after)


@pytest.mark.slow      # NP, SP and HP of the own scene: 22 s at load 2.3
def test_tomography_results_are_documented_and_saved(tmp_path, own_scene):
    """A reconstruction through the logic API (the shared own scene at the fast
    level; it was a full balanced tube case, ~20 GB, to check node names)."""
    from FluoTomo import FluoTomoLogic
    from small_cases import TRUE_YIELD

    scene = mrml_io.new_scene()
    logic = FluoTomoLogic(scene)
    lab = logic.loadLabelMap(own_scene.labels, name="CBCTLabels")   # as the app names it
    before = _data_nodes(scene)
    summary, node = logic.reconstruct(lab, own_scene.optics, own_scene.acq, method="HP",
                                      accuracy="fast")
    after = _data_nodes(scene)
    new = after - before
    assert ("FluoTomoYieldHP", "vtkMRMLScalarVolumeNode") in new
    _check("FluoTomo", before, after)
    path = mrml_io.save_scene(scene, tmp_path / "scene.mrml")
    loaded = mrml_io.load_scene(path)
    vol = mrml_io.volume_array(mrml_io.get_node(loaded, "FluoTomoYieldHP"))
    assert vol.max() > 0.3 * TRUE_YIELD
    info = mrml_io.get_json_attribute(mrml_io.get_node(loaded, "FluoTomoYieldHP"),
                                      "FluoTomo.Reconstruction")
    assert info["method"] == "HP" and info["solver"]["iterations"] >= 1
    assert info["method"] == summary["method"] and node.GetName() == "FluoTomoYieldHP"
    # a second run gets its own output node (the first is kept)
    _, node2 = logic.reconstruct(lab, own_scene.optics, own_scene.acq, method="HP",
                                 accuracy="fast")
    assert node2.GetID() != node.GetID() and node2.GetName() == "FluoTomoYieldHP_1"
    assert mrml_io.get_node(scene, "FluoTomoYieldHP").GetID() == node.GetID()
