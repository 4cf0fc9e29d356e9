"""Files that say one thing twice are refused (issue #34 item 3).

JSON and YAML readers keep one of two equal keys without a word (Python's json
and PyYAML the last, OpenCV's FileStorage the first), so ``"n": 2.9`` appended
to an optics.json changed the physics silently. Every reader of a user's JSON
or YAML refuses it, naming the file, the path of keys and the key: optics,
acquisition, calibration, batch and study files, a recording's log lines, MRML
attributes, Monte Carlo sets and OpenCV calibration YAML.
"""

import json
import shutil

import numpy as np
import pytest

from fluoguide.errors import FluoInputError


def _dup_first_key(text):
    """``text`` (a JSON object) with its first key given once more, first."""
    doc = json.loads(text)
    key = next(iter(doc))
    return "{" + json.dumps(key) + ": " + json.dumps(doc[key]) + ", " + text.lstrip()[1:]


@pytest.mark.parametrize("text, where, key", [
    ('{"n": 1.37, "x": 1, "n": 2.9}', "n", "n"),
    ('{"regions": {"3": {"mua": 0.01, "mua": 0.02}}}', "regions.3.mua", "mua"),
    ('{"cases": [{"labels": "a"}, {"labels": "a", "labels": "b"}]}', "cases[1].labels",
     "labels"),
    ('[{"a": {"b": 1}}, {"z": 1, "z": 1}]', "[1].z", "z"),
])
def test_read_json_names_the_file_the_path_of_keys_and_the_key(text, where, key, tmp_path):
    from fluoguide.jsonable import read_json

    p = tmp_path / "doc.json"
    p.write_text(text)
    with pytest.raises(FluoInputError) as e:
        read_json(p, expect=None, field="--optics")
    msg = str(e.value)
    assert msg.startswith(f"{p}: --optics: {where}: key given twice") and repr(key) in msg, msg


def test_json_without_duplicates_reads_as_before(tmp_path):
    from fluoguide.jsonable import loads, read_json

    text = '{"a": [1, {"b": 2, "c": {"d": null}}], "e": 1.5}'
    (tmp_path / "ok.json").write_text(text)
    assert read_json(tmp_path / "ok.json") == json.loads(text) == loads(text)
    assert type(loads(text)["a"][1]) is dict


def test_optics_json_with_n_twice_is_refused_by_the_cli(tmp_path, fluo):
    """The issue's case: ``"n": 2.9`` appended to optics.json."""
    from small_cases import write_own_scene

    write_own_scene(tmp_path)
    text = (tmp_path / "optics.json").read_text().rstrip()
    assert text.endswith("}")
    (tmp_path / "optics.json").write_text(text[:-1] + ', "n": 2.9}\n')
    r = fluo("tomo", "simulate", "--labels", tmp_path / "labels.nrrd", "--optics",
             tmp_path / "optics.json", "--yield", "7:0.0026", "--accuracy", "fast", "--out",
             tmp_path / "acq", "--json")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and r.stdout == "", r.stderr
    assert len(lines) == 1 and lines[0].startswith(f"fluo: error: {tmp_path / 'optics.json'}"), lines
    assert ": n: key given twice" in lines[0], lines
    assert not (tmp_path / "acq").exists()


def test_acquisition_json_with_a_key_twice_is_refused(own_scene, tmp_path):
    from FluoTomoLib.tomography import LabelMap, read_acquisition, read_optics

    acq = tmp_path / "acq"
    shutil.copytree(own_scene.acq, acq)
    f = acq / "acquisition.json"
    f.write_text(_dup_first_key(f.read_text()))
    key = next(iter(json.loads(f.read_text())))
    with pytest.raises(FluoInputError) as e:
        read_acquisition(acq, labelmap=LabelMap.from_file(own_scene.labels),
                         optics=read_optics(own_scene.optics))
    assert str(e.value).startswith(f"{f}: {key}: key given twice"), e.value


def test_calibration_json_with_a_key_twice_is_never_overwritten(tmp_path, capsys):
    from fluoapp import cli

    cal = tmp_path / "calibration.json"
    cal.write_text('{"Laser": {"error_3d_mm": 0.1}, "Laser": {"error_3d_mm": 0.2}}')
    before = cal.read_text()
    (tmp_path / "laser").mkdir()
    rc = cli.main(["calib", "laser", str(tmp_path / "laser"), "--calibration", str(cal), "--json"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"fluo: error: {cal}: --calibration: Laser: key given twice"), err
    assert cal.read_text() == before


def test_intrinsics_json_with_a_key_twice_is_refused(tmp_path):
    from FluoCalibLib.geometry.files import read_intrinsics

    p = tmp_path / "camera.json"
    p.write_text('{"camera": {"fx": 800, "fy": 800, "cx": 320, "cy": 240, "fx": 900}}')
    with pytest.raises(FluoInputError, match=r"--intrinsics: camera\.fx: key given twice"):
        read_intrinsics(p)


@pytest.mark.parametrize("name, text, needle", [
    ("dup.json", '{"cases": [{"labels": "labels.nrrd", "labels": "other.nrrd", '
                 '"optics": "optics.json", "acquisition": "acq"}]}', "cases[0].labels: key given"),
    ("dup.yaml", "cases:\n  - labels: labels.nrrd\n    optics: optics.json\n"
                 "    acquisition: acq\n    labels: other.nrrd\n",
     "cases[0].labels: key given twice in one YAML mapping (lines 2 and 5"),
    ("top.yaml", "methods: HP\ncases:\n  - {labels: a, optics: b, acquisition: c}\n"
                 "methods: NP\n", "methods: key given twice in one YAML mapping (lines 1 and 4"),
])
def test_batch_files_with_a_key_twice_are_refused(name, text, needle, tmp_path, fluo):
    p = tmp_path / name
    p.write_text(text)
    r = fluo("tomo", "batch", p, "--out", tmp_path / "out", "--json")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"fluo: error: {p}: ") and needle in lines[0], lines
    assert not (tmp_path / "out").exists()


def test_yaml_aliases_merges_and_cycles_are_not_duplicates():
    from fluoguide import strict_yaml

    # a merge may override what it brings in; an alias repeats a node; a cycle ends
    doc = strict_yaml.load("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\nd: *b\n")
    assert doc["c"] == {"x": 3, "y": 2} and doc["d"] == {"x": 1, "y": 2}
    assert strict_yaml.load("a: &x [1, *x]\n")["a"][0] == 1
    with pytest.raises(FluoInputError, match=r"f\.yaml: a\.b: key given twice"):
        strict_yaml.load("a: {b: 1, b: 2}\n", file="f.yaml")


def test_study_file_with_a_key_twice_is_refused(tmp_path):
    from fluoguide.runs.grid import load_study_file

    p = tmp_path / "study.yaml"
    p.write_text("mua: [0.01, 0.02]\nmusp: 1\nmua: 0.5\n")
    with pytest.raises(FluoInputError, match=r"study\.yaml: mua: key given twice"):
        load_study_file(p)


def test_recording_log_line_with_a_key_twice_is_refused(tmp_path, fluo):
    from FluoNavLib.devices.recorder import Recorder, read_recording

    rec = tmp_path / "rec"
    with Recorder(rec) as r:
        for k in range(3):
            r.add(np.zeros((4, 5), np.uint16), 0.1 * (k + 1), {"CameraToolToTracker": np.eye(4)})
    log = rec / "log.jsonl"
    lines = log.read_text().splitlines()
    lines[2] = lines[2][:-1] + ', "timestamp_s": 99.0}'       # line 3: the second frame
    log.write_text("\n".join(lines) + "\n")
    with pytest.raises(FluoInputError) as e:
        read_recording(rec)
    assert str(e.value).startswith(f"{log}: line 3: timestamp_s: key given twice"), e.value
    r = fluo("replay", rec, "--json")
    assert r.returncode == 2 and "line 3: timestamp_s: key given twice" in r.stderr, r.stderr


def test_mrml_json_attribute_with_a_key_twice_is_refused():
    from fluoguide import mrml_io

    scene = mrml_io.new_scene()
    node = mrml_io.add_volume(scene, "CBCTLabels", np.ones((2, 2, 2), np.uint8), (1, 1, 1),
                              (0, 0, 0), labelmap=True)
    node.SetAttribute("FluoGuide.Truth", '{"regions": {"1": {"n": 1.37, "n": 2.9}}}')
    with pytest.raises(FluoInputError,
                       match=r"CBCTLabels\.FluoGuide\.Truth: regions\.1\.n: key given twice"):
        mrml_io.get_json_attribute(node, "FluoGuide.Truth")


def test_monte_carlo_set_with_a_key_twice_is_refused(tmp_path):
    from FluoTomoLib.montecarlo import reference

    p = tmp_path / "set.json"
    p.write_text('{"kind": "halfspace", "photons": 1000, "kind": "fluorescence"}')
    with pytest.raises(FluoInputError, match=r"set\.json: kind: key given twice"):
        reference.read_set(p)


def test_opencv_yaml_with_a_key_twice_is_refused(tmp_path):
    import cv2

    from FluoCalibLib.geometry.opencv_yaml import read_calibration_yaml

    p = tmp_path / "camera.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_to_tool", np.eye(4))
    fs.write("avg_reprojection_error", 0.5)
    fs.release()
    assert read_calibration_yaml(p)["rms_px"] == 0.5
    # OpenCV keeps the first of the two silently
    p.write_text(p.read_text() + "avg_reprojection_error: 9.0\n")
    with pytest.raises(FluoInputError, match=r"camera\.yaml: avg_reprojection_error: key "
                                             r"given twice in one YAML mapping"):
        read_calibration_yaml(p)
