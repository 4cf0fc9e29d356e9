"""FluoTomo's desktop panel driven headless: ``FluoTomoWidget.setupHeadless``
gives the widget its logic and parameter node without Qt, and its button
handlers run on what the parameter node holds, as the panel's buttons call
them in Slicer (what Qt itself does with the form: test_slicer_ui*.py).

The scene is small (an ellipsoidal body of 24 x 20 x 14 mm with a 6 mm
inclusion 2.5 mm under its top, 0.8 x 0.9 x 1.0 mm voxels, direction
diag(-1, -1, 1), origin far from zero) and the accuracy level "fast", so the
whole workflow takes about 10 s.
"""

import json

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.labelmap_io import write_volume_nrrd
from fluoguide.phantoms import ellipsoid_inclusion_labelmap

TRUE_YIELD = 2.6e-3  # 1/mm, the inclusion's (label 7)
OPTICS = {"n": 1.37,
          "excitation": {"3": {"mua_per_mm": 0.01, "musp_per_mm": 1.0},
                         "7": {"mua_per_mm": 0.012, "musp_per_mm": 1.1}},
          "emission": {"3": {"mua_per_mm": 0.008, "musp_per_mm": 0.9},
                       "7": {"mua_per_mm": 0.01, "musp_per_mm": 1.0}}}


@pytest.fixture
def panel(tmp_path):
    from FluoTomo import FluoTomoWidget

    sc = ellipsoid_inclusion_labelmap(spacing_mm=(0.8, 0.9, 1.0), semi_axes_mm=(12.0, 10.0, 7.0),
                                      inclusion_gap_mm=2.5, inclusion_offset_mm=(1.0, -1.0))
    write_volume_nrrd(tmp_path / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"],
                      sc["origin_mm"], sc["direction"])
    (tmp_path / "optics.json").write_text(json.dumps(OPTICS))
    import slicer

    scene = mrml_io.new_scene()
    colors = slicer.vtkMRMLColorLogic()  # the default colour tables, as Slicer's scene has them
    colors.SetMRMLScene(scene)
    widget = FluoTomoWidget()
    widget.setup()  # no Qt here: builds nothing
    logic = widget.setupHeadless(scene)
    widget.colorLogic = colors  # kept alive with the scene
    label = logic.loadLabelMap(tmp_path / "labels.nrrd")
    node = logic.getParameterNode()
    node.SetNodeReferenceID("LabelMap", label.GetID())
    for key, value in {"OpticsFile": str(tmp_path / "optics.json"),
                       "YieldByLabel": f"7:{TRUE_YIELD}", "Accuracy": "fast", "Seed": "3"}.items():
        node.SetParameter(key, value)
    return widget, logic, label, sc


@pytest.mark.slow      # simulate, mesh and reconstruct through the panel: 23 s beside a family run
def test_panel_workflow_simulate_mesh_reconstruct(panel, tmp_path):
    """Simulate -> build mesh -> HP into a chosen volume -> SP after a new
    acquisition. The simulation meshes the whole label map (0.8 mm near the
    optodes, graded), the reconstruction the region of interest at 1.0 mm
    (capped at 0.9 mm): different meshes, so the tolerance is the small
    end-to-end test's (test_own_scene.py): HP within 15 % of the true yield,
    peak inside the inclusion, within 3 mm of its centre."""
    widget, logic, label, sc = panel
    scene = logic.scene
    pnode = logic.getParameterNode()

    widget.onReconstruct()  # nothing simulated or loaded yet: refused, said why
    assert len(widget.errors) == 1 and "Acquisition" in widget.errors[0]
    assert scene.GetFirstNodeByName("FluoTomoYieldHP") is None

    widget.onSimulate()
    widget.onBuildMesh()
    mesh = pnode.GetNodeReference("Mesh")
    assert mesh is not None and mesh.GetName() == "FluoTomoMesh"
    vols = logic.meshRegionVolumes(mesh)
    assert set(vols) == {3, 7} and all(abs(err) < 1.0 for _, _, err in vols.values()), vols
    assert "label 7:" in widget.results[-1] and "region of interest" in widget.results[-1]

    chosen = mrml_io.add_volume(scene, "MyYield", np.zeros((2, 2, 2), np.float32),
                                (1, 1, 1), (0, 0, 0))  # as the selector's "create new" would
    pnode.SetNodeReferenceID("OutputVolume", chosen.GetID())
    widget.onReconstruct()
    assert widget.errors[1:] == []
    yield_node = scene.GetFirstNodeByName("MyYield")
    summary = mrml_io.get_json_attribute(yield_node, "FluoTomo.Reconstruction")
    assert summary["method"] == "HP" and summary["target"] == 7
    # the reconstruction ran on the mesh the panel built (and showed)
    assert summary["mesh"]["nodes"] == mrml_io.get_json_attribute(mesh, "FluoTomo.Mesh")["nodes"]
    assert "the mesh FluoTomoMesh" in widget.results[-1]
    err = summary["regions"]["7"]["yield_per_mm"] / TRUE_YIELD - 1
    assert abs(err) < 0.15, summary["regions"]
    assert summary["peak_label"] == 7
    assert np.linalg.norm(np.array(summary["peak_ras_mm"]) - sc["inclusion_centre_ras_mm"]) <= 3.0
    # on the label map's grid, coloured with the yield colour map, thresholded
    g, gl = mrml_io.volume_geometry(yield_node), mrml_io.volume_geometry(label)
    assert mrml_io.volume_array(yield_node).shape == mrml_io.volume_array(label).shape
    assert np.allclose(g["direction"], gl["direction"]) and np.allclose(g["origin"], gl["origin"])
    display = yield_node.GetDisplayNode()
    assert display.GetColorNodeID() == "vtkMRMLColorTableNodeIron" and display.GetApplyThreshold()

    # a new acquisition (another seed): the built mesh was not made for it, so the
    # reconstruction meshes the new one's region itself, into a new node (no output chosen)
    pnode.SetParameter("Seed", "4")
    pnode.SetNodeReferenceID("OutputVolume", None)
    pnode.SetParameter("Method", "SP")
    widget.onSimulate()
    widget.onReconstruct()
    assert widget.errors[1:] == []
    sp = scene.GetFirstNodeByName("FluoTomoYieldSP")
    assert sp is not None and scene.GetFirstNodeByName("MyYield") is yield_node
    assert "meshed for this acquisition" in widget.results[-1]
    s_sp = mrml_io.get_json_attribute(sp, "FluoTomo.Reconstruction")
    assert abs(s_sp["regions"]["7"]["yield_per_mm"] / TRUE_YIELD - 1) < 0.30  # SP: the 30 %

    # the acquisition written to a folder and loaded back gives the same measurements
    from FluoTomoLib.tomography import write_acquisition

    write_acquisition(tmp_path / "acq", widget.acquisition["acquisition"])
    pnode.SetParameter("AcquisitionFolder", str(tmp_path / "acq"))
    simulated = widget.acquisition["acquisition"]
    widget.onLoadAcquisition()
    assert widget.errors[1:] == []
    loaded = widget.acquisition["acquisition"]
    assert loaded is not simulated and np.array_equal(loaded.mask, simulated.mask)
    np.testing.assert_allclose(loaded.data, simulated.data, rtol=1e-6)


def test_panel_bad_input_is_shown_and_changes_nothing(panel, tmp_path):
    widget, logic, label, _ = panel
    pnode = logic.getParameterNode()
    pnode.SetParameter("YieldByLabel", "7:abc")
    widget.onSimulate()
    assert widget.acquisition is None
    assert widget.errors[-1].startswith("Simulate acquisition failed: Yield per label")
    pnode.SetParameter("YieldByLabel", "9:0.001")  # no label 9 in the map
    widget.onSimulate()
    assert widget.acquisition is None and "label is not in the label map" in widget.errors[-1]
    pnode.SetParameter("AcquisitionFolder", str(tmp_path / "missing"))
    widget.onLoadAcquisition()
    assert widget.acquisition is None and "missing" in widget.errors[-1]
    pnode.SetNodeReferenceID("LabelMap", None)
    widget.onBuildMesh()
    assert "Label map" in widget.errors[-1]
    assert widget.results == []
    assert logic.scene.GetNodesByClass("vtkMRMLModelNode").GetNumberOfItems() == 0


def test_load_phantom_and_segmentation_to_label_map(tmp_path, monkeypatch):
    """"Load phantom" selects CBCTLabels and CBCT and writes the phantom's own
    optical properties and yields as a user would give them; "Segmentation to
    label map" turns a segmentation back into the same label map."""
    import tempfile

    from fluoguide.phantoms import make_phantom
    from FluoTomo import FluoTomoWidget
    from FluoTomoLib.tomography import LabelMap, read_optics

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    widget = FluoTomoWidget()
    logic = widget.setupHeadless(mrml_io.new_scene())
    pnode = logic.getParameterNode()
    pnode.SetParameter("Phantom", "oral-cavity")
    widget.onLoadPhantom()
    assert widget.errors == []
    assert pnode.GetNodeReference("LabelMap").GetName() == "CBCTLabels"
    assert pnode.GetNodeReference("ReferenceVolume").GetName() == "CBCT"
    optics = read_optics(logic.parameter("OpticsFile"))
    assert str(tmp_path) in logic.parameter("OpticsFile")
    optics.check_labels(LabelMap.from_node(pnode.GetNodeReference("LabelMap")).labels)
    truth = make_phantom("oral-cavity").truth()["regions"]
    from fluoguide.parameters import parse_yields

    assert parse_yields(logic.parameter("YieldByLabel")) == pytest.approx(
        {int(k): r["optics"]["yield_per_mm"] for k, r in truth.items()
         if r["optics"]["yield_per_mm"] > 0})
    # the dye's absorption is the optics file's ICG slope, not in the background mua
    assert optics.fluorophore == "ICG"

    # a segmentation of the same regions (as the Segment Editor would hold it) back to
    # a label map on the CBCT's grid: the same voxels, the segments' names and volumes
    import slicer

    scene = logic.scene
    original = mrml_io.get_node(scene, "CBCTLabels")
    before = mrml_io.volume_array(original).copy()
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Regions")
    seg_logic = slicer.vtkSlicerSegmentationsModuleLogic()
    seg_logic.SetMRMLScene(scene)
    assert seg_logic.ImportLabelmapToSegmentationNode(original, seg)
    scene.RemoveNode(original)
    pnode.SetNodeReferenceID("Segmentation", seg.GetID())
    widget.onSegmentationToLabels()
    assert widget.errors == []
    made = pnode.GetNodeReference("LabelMap")
    assert made.GetName() == "CBCTLabels" and made.GetAttribute("FluoTomo.SourceSegmentation")
    np.testing.assert_array_equal(mrml_io.volume_array(made), before)
    for k, r in truth.items():
        assert f"label {k} = Label_{k}: {r['labelmap_volume_mm3']:.1f} mm^3" in widget.results[-1]
