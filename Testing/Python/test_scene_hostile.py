"""Scenes that a crash or a hostile author made: the loader refuses them with one
clear error, and a save or a phantom write killed at any moment leaves the old
state or the new one (issue #21)."""

import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from fluoguide import atomic, mrml_io
from fluoguide.errors import FluoInputError

ROOT = Path(__file__).resolve().parents[2]


def _scene_with(version):
    """A scene whose CBCT, labels and .mrml attribute all carry ``version``."""
    sc = mrml_io.new_scene()
    vol = mrml_io.add_volume(sc, "CBCT", np.full((4, 5, 6), version, np.int16), (1, 1, 1), (0, 0, 0))
    vol.SetAttribute("Version", str(version))
    mrml_io.add_volume(sc, "CBCTLabels", np.full((4, 5, 6), version, np.uint8), (1, 1, 1),
                       (0, 0, 0), labelmap=True)
    shift = np.eye(4)
    shift[0, 3] = version
    mrml_io.set_transform(sc, "CameraToCameraTool", shift)
    return sc


def _versions(path):
    sc = mrml_io.load_scene(path)
    attr = int(mrml_io.get_node(sc, "CBCT").GetAttribute("Version"))
    cbct = int(mrml_io.volume_array(mrml_io.get_node(sc, "CBCT")).max())
    lab = int(mrml_io.volume_array(mrml_io.get_node(sc, "CBCTLabels")).max())
    tf = int(round(mrml_io.get_transform(sc, "CameraToCameraTool")[0, 3]))
    return {attr, cbct, lab, tf}


def test_save_killed_between_any_two_renames_leaves_old_or_new(tmp_path):
    target = tmp_path / "s" / "scene.mrml"
    mrml_io.save_scene(_scene_with(1), target)
    assert _versions(target) == {1}
    # A child process saves version 2 and is killed (os._exit, no cleanup) right
    # before its k-th rename; for every k the folder must read as 1 or as 2.
    outcomes = set()
    for k in range(0, 8):
        code = textwrap.dedent(f"""
            import os, sys
            sys.path[:0] = {[str(ROOT)]!r}
            real = os.replace
            calls = [0]
            def replace(a, b):
                if calls[0] == {k}:
                    os._exit(9)
                calls[0] += 1
                real(a, b)
            os.replace = replace
            sys.path.insert(0, {str(Path(__file__).parent)!r})
            from test_scene_hostile import _scene_with
            from fluoguide import mrml_io
            mrml_io.save_scene(_scene_with(2 + {k} % 2), {str(target)!r})
        """)
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert r.returncode in (0, 9), r.stderr
        seen = _versions(target)
        assert len(seen) == 1, f"mixed scene after a kill before rename {k}: {seen}"
        outcomes |= seen
        assert not (target.parent / atomic.JOURNAL).exists()
    assert len(outcomes) >= 2  # some kills landed before the commit, some after


def test_phantom_write_killed_mid_commit_is_rolled_forward(tmp_path):
    from fluoguide.phantoms import make_phantom, write_phantom

    out = tmp_path / "ph"
    write_phantom(make_phantom("cylinder-tube", voxel_mm=2.0, depth_mm=3.0), out)
    code = textwrap.dedent(f"""
        import os, sys
        sys.path[:0] = {[str(ROOT)]!r}
        from fluoguide import atomic
        real = os.replace
        calls = [0]
        def replace(a, b):
            # the journal is replace no. 0 of the commit; die after two data files moved
            into_out = os.path.dirname(str(b)) == {str(out)!r}  # the outer commit's moves
            if into_out and calls[0] == 3:
                os._exit(9)
            calls[0] += into_out
            real(a, b)
        os.replace = replace
        from fluoguide.phantoms import make_phantom, write_phantom
        write_phantom(make_phantom("cylinder-tube", voxel_mm=2.0, depth_mm=6.0), {str(out)!r})
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 9, r.stderr
    assert (out / atomic.JOURNAL).exists()  # killed inside the transaction
    sc = mrml_io.load_scene(out / "scene.mrml")  # rolls it forward
    truth = mrml_io.get_json_attribute(mrml_io.get_node(sc, "CBCTLabels"), "FluoGuide.Truth")
    import json

    assert json.loads((out / "truth.json").read_text()) == truth
    assert not (out / atomic.JOURNAL).exists()


def test_atomic_path_keeps_the_old_file_on_error(tmp_path):
    p = tmp_path / "fig.png"
    p.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(p) as tmp:
            Path(tmp).write_bytes(b"half")
            raise RuntimeError("writer died")
    assert p.read_bytes() == b"old"
    assert [f.name for f in tmp_path.iterdir()] == ["fig.png"]


@pytest.fixture
def saved(tmp_path):
    sc = mrml_io.new_scene()
    mrml_io.set_transform(sc, "AToB", np.eye(4))
    mrml_io.set_transform(sc, "BToC", np.eye(4), parent="AToB")
    mrml_io.add_volume(sc, "V", np.zeros((3, 4, 5), np.int16), (1, 1, 1), (0, 0, 0))
    mrml_io.add_model(sc, "M", np.eye(3), np.array([[0, 1, 2]]))
    path = tmp_path / "scene" / "scene.mrml"
    mrml_io.save_scene(sc, path)
    return path


def _edit(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


@pytest.mark.parametrize("value", ["../outside.nrrd", "/etc/passwd", "sub/../../outside.nrrd"])
def test_storage_paths_outside_the_scene_folder_are_refused(saved, value):
    (saved.parent.parent / "outside.nrrd").write_bytes((saved.parent / "V.nrrd").read_bytes())
    _edit(saved, 'fileName="V.nrrd"', f'fileName="{value}"')
    with pytest.raises(FluoInputError, match="absolute path|outside its folder") as e:
        mrml_io.load_scene(saved)
    assert value in str(e.value)


def test_a_file_list_member_outside_the_folder_is_refused(saved):
    _edit(saved, 'fileName="V.nrrd"', 'fileName="V.nrrd" fileListMember0="../../../etc/passwd"')
    with pytest.raises(FluoInputError, match="outside its folder"):
        mrml_io.load_scene(saved)


def test_saved_scenes_name_their_files_only(saved):
    # no file list with paths into the staging folder, no absolute paths
    text = saved.read_text()
    assert "fluo-stage" not in text and "fileListMember" not in text
    assert str(saved.parent) not in text


def test_a_fifo_as_data_file_is_refused_without_blocking(saved):
    os.mkfifo(saved.parent / "pipe.nrrd")
    _edit(saved, 'fileName="V.nrrd"', 'fileName="pipe.nrrd"')
    result = {}

    def load():
        try:
            mrml_io.load_scene(saved)
        except FluoInputError as exc:
            result["error"] = str(exc)

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(30)
    if t.is_alive():  # unblock the reader so the test process can end
        with open(saved.parent / "pipe.nrrd", "wb"):
            pass
        pytest.fail("loading a scene with a FIFO data file blocked")
    assert "not a regular file" in result["error"]


def test_truncated_model_is_refused(saved):
    m = saved.parent / "M.vtk"
    m.write_bytes(m.read_bytes()[: len(m.read_bytes()) * 2 // 3])
    with pytest.raises(FluoInputError, match="corrupt model"):
        mrml_io.load_scene(saved)


def test_nan_transform_is_refused(saved):
    text = saved.read_text()
    # drop the storage reference so the inline matrix is the one read
    text = text.replace('references="storage:vtkMRMLTransformStorageNode1;"', 'references=""')
    text = text.replace('name="AToB" hideFromEditors="false" selectable="true" selected="false" references="" userTags="" matrixTransformToParent="1 0 0 0  0 1 0 0  0 0 1 0  0 0 0 1"',
                        'name="AToB" hideFromEditors="false" selectable="true" selected="false" references="" userTags="" matrixTransformToParent="nan 0 0 0  0 nan 0 0  0 0 nan 0  0 0 0 1"')
    saved.write_text(text)
    with pytest.raises(FluoInputError, match="corrupt transform"):
        mrml_io.load_scene(saved)


def test_transform_parent_cycle_is_refused(saved):
    _edit(saved, 'references="storage:vtkMRMLTransformStorageNode1;"',
          'references="storage:vtkMRMLTransformStorageNode1;transform:vtkMRMLLinearTransformNode2;"')
    with pytest.raises(FluoInputError, match="cycle"):
        mrml_io.load_scene(saved)


def test_deeply_nested_json_attribute_is_a_clear_error():
    sc = mrml_io.new_scene()
    node = mrml_io.set_transform(sc, "T", np.eye(4))
    node.SetAttribute("FluoGuide.Deep", "[" * 50000 + "]" * 50000)
    with pytest.raises(FluoInputError, match="nested too deeply"):
        mrml_io.get_json_attribute(node, "FluoGuide.Deep")


def test_scene_info_reads_a_thousand_transforms(tmp_path):
    sc = mrml_io.new_scene()
    for i in range(1000):
        mrml_io.set_transform(sc, f"T{i}", np.eye(4))
    path = mrml_io.save_scene(sc, tmp_path / "big" / "scene.mrml")
    from fluoapp.cli import main

    assert main(["scene", "info", str(path), "--json"]) == 0


def test_a_damaged_calibration_json_is_refused_not_overwritten(tmp_path):
    from FluoCalibLib.radiometry.scene import RADIOMETRY_KEY, write_calibration_json

    path = tmp_path / "calibration.json"
    damaged = '{"Intrinsics": {"fx": 800}, "HandEye": [1, 2],}'  # a trailing comma
    path.write_text(damaged)
    with pytest.raises(FluoInputError, match="not valid JSON .*line 1") as e:
        write_calibration_json(path, RADIOMETRY_KEY, {"gain": 1.0})
    assert "--calibration" in str(e.value)
    assert path.read_text() == damaged  # the user's other calibrations are still there
    path.write_text('{"Intrinsics": {"fx": 800}}')
    write_calibration_json(path, RADIOMETRY_KEY, {"gain": 1.0})
    import json

    assert json.loads(path.read_text()) == {"Intrinsics": {"fx": 800}, "Radiometry": {"gain": 1.0}}
    path.write_text("[1, 2]")
    with pytest.raises(FluoInputError, match="expected a JSON object"):
        write_calibration_json(path, RADIOMETRY_KEY, {"gain": 1.0})


def test_a_hostile_commit_journal_moves_and_deletes_nothing_outside(tmp_path):
    """A scene folder's journal names its staging folder; one that names a folder
    outside (../victim) must not move its files in, nor delete it afterwards."""
    import json

    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("keep me")
    target = tmp_path / "s" / "scene.mrml"
    mrml_io.save_scene(_scene_with(1), target)
    for stage in ("../victim", str(victim), ".fluo-stage-1/../../victim"):
        (target.parent / atomic.JOURNAL).write_text(
            json.dumps({"stage": stage, "files": ["precious.txt"]}))
        assert _versions(target) == {1}              # load_scene runs the recovery
        assert (victim / "precious.txt").read_text() == "keep me"
        assert not (target.parent / "precious.txt").exists()
        assert not (target.parent / atomic.JOURNAL).exists()
