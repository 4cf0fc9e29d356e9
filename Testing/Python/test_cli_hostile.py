"""The CLI's promises on hostile input, fast and in process (issue #21; the
fuzz run, ``fuzz_cli.py``, covers every option of every subcommand, slowly):
exit 2 with one line naming the field, exit 1 and one line for a bug, the
traceback only under ``--debug``, nothing written by a refused run."""

import json
import sys
import textwrap

import numpy as np
import pytest

from fluoapp import cli


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    lines = [ln for ln in out.err.splitlines() if ln.strip()]
    return rc, out.out, lines


@pytest.mark.parametrize("argv, field", [
    (["analytic", "--mua", "0.01", "--musp", "1", "--yield", "nan"], "yield_per_mm"),
    (["analytic", "--mua", "0.01", "--musp", "1e300"], "musp_per_mm"),
    (["bench", "mapping", "--repeats", "0"], "repeats"),
    (["demo", "--only", "bogus", "--out", "{tmp}/demo"], "--only"),
    (["demo", "--only", "", "--out", "{tmp}/demo"], "--only"),
    (["nav", "synth", "--views", "0", "--out", "{tmp}/nav"], "views"),
    (["nav", "synth", "--binning", "0", "--out", "{tmp}/nav"], "binning"),
    (["calib", "synth-boards", "--noise", "nan", "--out", "{tmp}/b"], "noise_sigma"),
    (["calib", "synth-boards", "--seed", "-1", "--out", "{tmp}/b"], "seed"),
    (["calib", "synth-boards", "--height", "1000000000", "--out", "{tmp}/b"], "height"),
    (["track", "--sim", "--rate", "60", "--seconds", "1"], "--rate"),
    (["track", "--sim", "--seconds", "inf"], "--seconds"),
    (["record", "--camera", "-1", "--out", "{tmp}/rec", "--seconds", "1"], "camera"),
    (["calib", "pivot", "--poses", "{tmp}/wrongtype.json"], "tool_to_tracker"),
    (["calib", "pivot", "--poses", "{tmp}/latin1.json"], "--poses"),
])
def test_garbage_is_one_line_exit_2_and_writes_nothing(argv, field, tmp_path, capsys):
    (tmp_path / "wrongtype.json").write_text('{"tool_to_tracker": {"foo": 1}}')
    (tmp_path / "latin1.json").write_bytes('{"a": "\xe9"}'.encode("latin-1"))
    before = sorted(p.name for p in tmp_path.iterdir())
    rc, out, lines = _run([a.format(tmp=tmp_path) for a in argv] + ["--json"], capsys)
    assert rc == 2 and out == "", lines
    assert len(lines) == 1 and lines[0].startswith("fluo: error:") and field in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_jacobian_out_writes_exactly_the_path_reported(tmp_path, capsys):
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    lab = np.ones((10, 10, 10), np.int32)
    write_vtu(mesh_labelmap_structured(lab, np.ones(3), np.array([-4.5, -4.5, -9.5]), 2.0),
              tmp_path / "m.vtu")
    (tmp_path / "s.csv").write_text("0,0,0\n")
    (tmp_path / "d.csv").write_text("3,0,0\n")
    base = ["forward", "--mesh", str(tmp_path / "m.vtu"), "--mua", "0.01", "--musp", "1",
            "--sources", str(tmp_path / "s.csv"), "--detectors", str(tmp_path / "d.csv"), "--json"]
    rc, out, lines = _run(base + ["--jacobian-out", str(tmp_path / "J")], capsys)
    assert rc == 0, lines
    doc = json.loads(out)
    assert doc["jacobian_file"] == str(tmp_path / "J")            # not J.npy
    assert np.load(tmp_path / "J").shape == tuple(doc["jacobian_shape"])
    (tmp_path / "adir").mkdir()
    rc, out, lines = _run(base + ["--jacobian-out", str(tmp_path / "adir")], capsys)
    assert rc == 2 and "is a folder" in lines[0] and list((tmp_path / "adir").iterdir()) == []


def test_a_refused_calibration_writes_no_plot_and_no_yaml(tmp_path, capsys):
    """--scene is checked before the work: plots and YAML were left behind."""
    from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

    make_dataset(tmp_path / "boards", default_camera(320, 240), n_views=4)
    (tmp_path / "bad.mrml").write_text("not a scene")
    rc, out, lines = _run(["calib", "camera", "--images", str(tmp_path / "boards" / "*.png"),
                           "--board", "chessboard:9x6:20", "--yaml", str(tmp_path / "c.yaml"),
                           "--scene", str(tmp_path / "bad.mrml"), "--json"], capsys)
    assert rc == 2 and "bad.mrml" in lines[0]
    assert not (tmp_path / "c.yaml").exists()


def test_last_resort_one_line_exit_1_and_the_traceback_under_debug(tmp_path, capsys,
                                                                   monkeypatch):
    """A bug in a handler: one line and exit 1; ``fluo --debug`` adds the traceback."""
    # a module written here, not a file of the tree (test_physics_doc checks names)
    (tmp_path / "fluo_boom").with_suffix(".py").write_text(textwrap.dedent("""
        def _boom(args):
            return {"ratio": 1 / 0}

        def register(sub):
            p = sub.add_parser("boom", help="a subcommand with a bug")
            p.set_defaults(func=_boom)
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cli, "CLI_MODULES", cli.CLI_MODULES + ["fluo_boom"])
    rc, out, lines = _run(["boom"], capsys)
    assert rc == 1 and out == "" and len(lines) == 1, lines
    assert lines[0].startswith("fluo: internal error: ZeroDivisionError: division by zero")
    assert "--debug" in lines[0]
    rc, out, lines = _run(["--debug", "boom"], capsys)
    assert rc == 1 and lines[0].startswith("Traceback") and "1 / 0" in "\n".join(lines)
    assert lines[-1].startswith("fluo: internal error: ZeroDivisionError")
    sys.modules.pop("fluo_boom", None)


# ----------------------------------------------------------------- issue #34
def _small_mesh(tmp_path):
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    lab = np.ones((10, 10, 10), np.int32)
    write_vtu(mesh_labelmap_structured(lab, np.ones(3), np.array([-4.5, -4.5, -9.5]), 2.0),
              tmp_path / "m.vtu")
    (tmp_path / "s.csv").write_text("0,0,0\n")
    (tmp_path / "d.csv").write_text("3,0,0\n")
    return ["forward", "--mesh", str(tmp_path / "m.vtu"), "--mua", "0.01", "--musp", "1",
            "--sources", str(tmp_path / "s.csv"), "--detectors", str(tmp_path / "d.csv"), "--json"]


def test_forward_refuses_an_unknown_solver_naming_the_valid_ones(tmp_path, capsys):
    """Issue #34 item 7: the analytic path never used --solver, so ``bogus`` ran, exit 0."""
    base = _small_mesh(tmp_path)
    for model in ("auto", "analytic", "fem"):
        rc, out, lines = _run(base + ["--solver", "bogus", "--model", model], capsys)
        assert rc == 2 and out == "" and len(lines) == 1, lines
        assert lines[0] == ("fluo: error: --solver: unknown solver; use auto, pardiso, splu, "
                            "amg (got 'bogus')"), lines
    rc, out, lines = _run(base + ["--solver", "splu", "--model", "fem"], capsys)
    assert rc == 0 and json.loads(out)["solver"] == "superlu", lines


def test_analytic_refuses_distances_beyond_10_m_without_a_numpy_warning(capsys):
    """Issue #34 item 7: ``--rho 1e300`` printed nulls after numpy's overflow warnings."""
    import warnings

    base = ["analytic", "--mua", "0.01", "--musp", "1", "--json"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")           # a RuntimeWarning fails the test
        for rho in ("1e300", "3,1e5", "inf"):
            rc, out, lines = _run(base + ["--rho", rho], capsys)
            assert rc == 2 and out == "" and len(lines) == 1, lines
            assert lines[0].startswith("fluo: error: --rho: distances must be finite, within "
                                       "0..10000 mm"), lines
        rc, out, lines = _run(base + ["--rho", "0,3,10000"], capsys)
    assert rc == 0 and lines == [], lines
    doc = json.loads(out)
    assert doc["R_rho"][-1] == 0.0 and np.isfinite(doc["ln_robin_surface_fluence"][-1])


@pytest.mark.parametrize("row, value", [("1e300,0,0", "1e+300"), ("0,nan,0", "nan"),
                                        ("0,0,-2e5", "-200000.0")])
def test_calib_register_refuses_absurd_coordinates_with_file_and_row(row, value, tmp_path,
                                                                     capsys):
    """Issue #34 item 5: coordinates of 1e300 went into the SVD (a null FRE, exit 0)."""
    pts = np.array([[0, 0, 0], [50, 0, 0], [0, 40, 0], [0, 0, 30], [20, 20, 20.0]])
    np.savetxt(tmp_path / "fixed.csv", pts, delimiter=",")
    lines_csv = [",".join(f"{v:g}" for v in p) for p in pts]
    lines_csv[2] = row
    (tmp_path / "moving.csv").write_text("\n".join(lines_csv) + "\n")
    rc, out, lines = _run(["calib", "register", "--moving", str(tmp_path / "moving.csv"),
                           "--fixed", str(tmp_path / "fixed.csv"), "--json"], capsys)
    assert rc == 2 and out == "" and len(lines) == 1, lines
    assert lines[0].startswith(f"fluo: error: {tmp_path / 'moving.csv'}: --moving row 3: "), lines
    assert lines[0].endswith(f"(got {value})"), lines
    from FluoCalibLib.geometry.registration import register_points

    from fluoguide.errors import FluoInputError

    bad = pts.copy()
    bad[4, 1] = 1e300
    with pytest.raises(FluoInputError, match=r"moving_mm row 5: coordinates must be within "
                                             r"\+-100000 mm"):
        register_points(bad, pts)


@pytest.mark.parametrize("argv", [["mesh", "{long}", "--out", "{tmp}/m.vtu", "--fast"],
                                  ["phantom", "cylinder-tube", "--voxel-mm", "4", "--out",
                                   "{tmp}/{name300}"]])
def test_a_path_too_long_for_the_file_system_is_one_line_exit_2(argv, tmp_path, capsys):
    """ENAMETOOLONG from any reader's ``is_file`` was ``fluo: internal error: OSError``."""
    subs = {"long": "a" * 5000, "tmp": tmp_path, "name300": "b" * 300}
    rc, out, lines = _run([a.format(**subs) for a in argv] + ["--json"], capsys)
    assert rc == 2 and out == "" and len(lines) == 1, lines
    assert lines[0].startswith("fluo: error: ") and lines[0].endswith(
        "characters): name too long for the file system"), lines
    assert len(lines[0]) < 200 and list(tmp_path.iterdir()) == []
