"""The ``fluo`` command: JSON output, one-line errors with exit code 2.

Commands run through the ``fluo`` fixture (conftest.py): a child forked from a
process that imported the stack, with a real process's exit code and streams;
the fuzz runs every subcommand once as ``python -m fluoapp`` besides."""

import json

import pytest

from fluoapp.cli import build_parser, main


def test_help_lists_every_subcommand():
    text = build_parser().format_help()
    for cmd in ("phantom", "scene"):
        assert cmd in text


def test_phantom_json_and_scene_info(tmp_path, fluo):
    r = fluo("phantom", "cylinder-tube", "--out", str(tmp_path / "p"), "--depth-mm", "2.7",
                 "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["phantom"] == "cylinder-tube"
    for region in out["regions"].values():
        assert abs(region["volume_error_pct"]) < 2
    r = fluo("scene", "info", str(tmp_path / "p" / "scene.mrml"), "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert {n["name"] for n in info["nodes"]} == {"CBCT", "CBCTLabels"}


@pytest.mark.parametrize("args, needle", [
    (["phantom", "liver", "--out", "X"], "unknown phantom"),
    (["phantom", "slab", "--out", "/proc/forbidden/x"], "/proc/forbidden"),
    (["scene", "info", "/nonexistent/scene.mrml"], "scene file not found"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, args, needle, fluo):
    args = [a.replace("X", str(tmp_path / "x")) for a in args]
    r = fluo(*args)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert r.stdout == ""


def test_corrupt_scene_exit_2(tmp_path, capsys):
    bad = tmp_path / "scene.mrml"
    bad.write_text("<MRML> <Volume id='x' name='CBCT' storageNodeRef='s'/> <broken")
    assert main(["scene", "info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "scene.mrml" in err


def test_a_reader_that_stops_early_gets_no_traceback(tmp_path):
    """``fluo ... | head``: the reader closed the pipe before the result was
    printed (here before the command started); the command ends with exit 1
    and nothing but its own lines on stderr."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", "fluoapp", "phantom", "slab", "--voxel-mm", "2",
                          "--out", str(tmp_path / "p"), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 1, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err
