"""The headless threshold segmentation of a CBCT (issue #35): per label its HU
range, its largest connected component, its holes filled, later labels over
earlier ones (``FluoTomoLib.tomography.threshold_labels``,
``FluoTomoLogic.segmentCbct``, ``fluo segment``), and the command-line route
from the scanner's files to a label map: DICOM folder -> ``fluo scene import``
-> ``fluo segment --cbct scene.mrml``."""

import json

import numpy as np
import pytest

import dicom_cases as dc
from fluoguide import mrml_io
from fluoguide.errors import FluoInputError
from fluoguide.labelmap_io import read_labelmap
from FluoTomoLib.tomography import parse_thresholds, threshold_labels

SPACING = (0.5, 0.6, 0.8)
ORIGIN = (-10.0, 20.0, -5.5)
DIRECTION = dc.rotation(15.0, 0.0, -30.0)
THRESHOLDS = "1:-500:3000,2:300:3000"


def _phantom():
    """(CBCT [HU] int16, expected labels): a tissue ellipsoid (40 HU) with an
    enclosed air bubble and a bone ball (1000 HU) inside it, a tissue speck in
    the air away from it, a bone speck in the air too."""
    k, j, i = np.indices((30, 36, 40))
    body = ((i - 20) / 15.0) ** 2 + ((j - 18) / 13.0) ** 2 + ((k - 15) / 11.0) ** 2 <= 1
    bubble = (i - 14) ** 2 + (j - 18) ** 2 + (k - 15) ** 2 <= 9
    bone = (i - 25) ** 2 + (j - 18) ** 2 + (k - 15) ** 2 <= 16
    cbct = np.full(body.shape, -1000, np.int16)
    cbct[body] = 40
    cbct[bubble] = -1000
    cbct[bone] = 1000
    cbct[1:3, 1:3, 1:3] = 40                    # a tissue speck in a corner
    cbct[27:29, 33:35, 37:39] = 1000            # a bone speck in the opposite one
    expected = np.zeros(body.shape, np.uint8)
    expected[body] = 1                          # the bubble filled
    expected[bone] = 2
    return cbct, expected


def test_largest_component_holes_filled_later_labels_win():
    cbct, expected = _phantom()
    labels, report = threshold_labels(cbct, THRESHOLDS, SPACING)
    assert labels.dtype == np.uint8 and np.array_equal(labels, expected)
    t, b = report["1"], report["2"]
    assert t["components"] == 3 and t["dropped_voxels"] == 8 + 8     # both specks
    assert t["filled_voxels"] == int(((np.indices(cbct.shape)[2] - 14) ** 2 + (
        np.indices(cbct.shape)[1] - 18) ** 2 + (np.indices(cbct.shape)[0] - 15) ** 2 <= 9).sum())
    assert b["components"] == 2 and b["dropped_voxels"] == 8 and b["filled_voxels"] == 0
    assert b["voxels"] == int((expected == 2).sum())
    assert t["volume_mm3"] == pytest.approx((expected == 1).sum() * 0.5 * 0.6 * 0.8)
    # the same from a JSON file, a dict and triples
    assert parse_thresholds({"1": [-500, 3000], "2": [300, 3000]}) == parse_thresholds(
        THRESHOLDS) == parse_thresholds([(1, -500, 3000), (2, 300, 3000)])


@pytest.mark.parametrize("spec, needle", [
    ("1:-500", "LABEL:MIN:MAX"), ("0:1:2", "1..255"), ("256:1:2", "1..255"),
    ("1:5:2", "below the maximum"), ("1:nan:2", "finite"), ("1:-500:3000,1:0:10", "twice"),
    ("", "LABEL:MIN:MAX"), ("x:1:2", "LABEL:MIN:MAX"), ({"1": [1]}, "LABEL:MIN:MAX"),
    ("1:5000:6000", "no voxel of the CBCT"),
])
def test_bad_thresholds_refused(spec, needle):
    cbct, _ = _phantom()
    with pytest.raises(FluoInputError, match="thresholds") as e:
        threshold_labels(cbct, spec)
    assert needle in str(e.value)


def test_logic_segments_a_cbct_node():
    from FluoTomo import FluoTomoLogic

    cbct, expected = _phantom()
    scene = mrml_io.new_scene()
    mrml_io.add_volume(scene, "CBCT", cbct, SPACING, ORIGIN, direction=DIRECTION)
    node, report = FluoTomoLogic(scene).segmentCbct(THRESHOLDS)
    assert node.GetName() == "CBCTLabels" and node.IsA("vtkMRMLLabelMapVolumeNode")
    assert np.array_equal(mrml_io.volume_array(node), expected)
    geo = mrml_io.volume_geometry(node)
    np.testing.assert_allclose(geo["direction"], DIRECTION, atol=1e-12)
    np.testing.assert_allclose(geo["origin"], ORIGIN)
    assert mrml_io.get_json_attribute(node, "FluoTomo.Thresholds")["2"]["voxels"] == report[
        "2"]["voxels"]


def test_dicom_to_scene_to_label_map(tmp_path, fluo):
    cbct, expected = _phantom()
    # stored = HU + 1024 with slope 1, intercept -1024, as scanners write CT
    dc.write_series(tmp_path / "dcm", (cbct.astype(np.int32) + 1024).astype(np.int16), SPACING,
                    ORIGIN, DIRECTION, slope=1.0, intercept=-1024.0)
    r = fluo("scene", "import", "--cbct", tmp_path / "dcm", "--out", tmp_path / "scene")
    assert r.returncode == 0, r.stderr
    r = fluo("segment", "--cbct", tmp_path / "scene" / "scene.mrml", "--thresholds", THRESHOLDS,
             "--out", tmp_path / "labels.nrrd", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["labels"]["1"]["dropped_voxels"] == 16 and out["cbct"]["format"] == "MRML"
    labels, spacing, origin, direction = read_labelmap(tmp_path / "labels.nrrd")
    assert np.array_equal(labels, expected)
    np.testing.assert_allclose(spacing, SPACING, atol=1e-6)
    np.testing.assert_allclose(origin, ORIGIN, atol=1e-6)
    np.testing.assert_allclose(direction, DIRECTION, atol=1e-6)
    # straight from the DICOM folder, thresholds from a JSON file, readable output
    (tmp_path / "t.json").write_text(json.dumps({"1": [-500, 3000], "2": [300, 3000]}))
    r = fluo("segment", "--cbct", tmp_path / "dcm", "--thresholds", tmp_path / "t.json",
             "--out", tmp_path / "labels2.nrrd")
    assert r.returncode == 0, r.stderr
    assert np.array_equal(read_labelmap(tmp_path / "labels2.nrrd")[0], expected)
    # a command that takes the label map takes it
    r = fluo("mesh", tmp_path / "labels.nrrd", "--out", tmp_path / "m.vtu", "--size", "2",
             "--fast", "--json")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("args, needle", [
    (["--thresholds", "1:5:2"], "--thresholds[1]: the minimum must be below"),
    (["--thresholds", "1:5000:6000"], "--thresholds[1]: no voxel of the CBCT"),
    (["--thresholds", "{t_dup}"], "key given twice"),
    (["--thresholds", "1:-500:3000", "--series", "9.9.9"], "--series: no such series"),
    (["--thresholds", "1:-500:3000", "--out-name", "labels.vtk"], "name it .nrrd"),
])
def test_segment_refusals_one_line_nothing_written(tmp_path, fluo, args, needle):
    cbct, _ = _phantom()
    dc.write_series(tmp_path / "dcm", cbct, SPACING, ORIGIN, DIRECTION)
    (tmp_path / "dup.json").write_text('{"1": [-500, 3000], "1": [0, 10]}')
    out = tmp_path / "labels.nrrd"
    if "--out-name" in args:
        out = tmp_path / args[-1]
        args = args[:-2]
    args = [a.replace("{t_dup}", str(tmp_path / "dup.json")) for a in args]
    r = fluo("segment", "--cbct", tmp_path / "dcm", *args, "--out", out)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["dcm", "dup.json"]
