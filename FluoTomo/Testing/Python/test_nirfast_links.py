"""NIRFAST optode files (.source, .meas, .link): exact round trip, NIRFAST layout, errors."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from FluoTomoLib.meshing.nirfast_io import read_optodes, write_optodes


def _optodes():
    rng = np.random.default_rng(3)
    src = rng.uniform(-30, 30, (4, 3))
    det = rng.uniform(-30, 30, (5, 3))
    link = np.array([[0, 0, 1], [0, 4, 0], [3, 2, 1], [2, 1, 1]])
    return src, det, link


def test_round_trip_is_exact(tmp_path):
    src, det, link = _optodes()
    fwhm = np.array([0.0, 1.5, 2.25, 1e-3])
    stem = write_optodes(tmp_path / "m", src, det, link, fwhm_mm=fwhm, fixed=True)
    back = read_optodes(stem)
    assert np.array_equal(back["sources_mm"], src) and np.array_equal(back["detectors_mm"], det)
    assert np.array_equal(back["source_fwhm_mm"], fwhm)
    assert np.array_equal(back["link"], link)
    assert back["source_fixed"] and back["meas_fixed"]
    # NIRFAST's layout: 'fixed', a column header, 1-based numbers
    lines = (tmp_path / "m.source").read_text().splitlines()
    assert lines[0] == "fixed" and lines[1].split() == ["num", "x", "y", "z", "fwhm"]
    assert lines[2].split()[0] == "1"
    assert (tmp_path / "m.meas").read_text().splitlines()[1].split() == ["num", "x", "y", "z"]
    link_lines = (tmp_path / "m.link").read_text().splitlines()
    assert link_lines[0] == "source detector active" and link_lines[2] == "1 5 0"
    # reading through any of the three file names works too
    assert np.array_equal(read_optodes(tmp_path / "m.link")["link"], link)


def test_defaults_2d_and_nirfast_extras(tmp_path):
    src = np.array([[0.0, 1.0], [2.0, 3.0]])
    det = np.array([[5.0, 5.0]])
    write_optodes(tmp_path / "a", src, det, fixed=False)
    back = read_optodes(tmp_path / "a")
    assert not back["source_fixed"]
    assert back["link"].tolist() == [[0, 0, 1], [1, 0, 1]]
    assert np.array_equal(back["sources_mm"], src)
    # a file as NIRFAST writes it after moving sources: extra columns, rows out of order
    (tmp_path / "b.source").write_text("num x y z fwhm ele ip1 ip2 ip3 ip4\n"
                                       "2 1 2 3 0 7 0.1 0.2 0.3 0.4\n1 4 5 6 0 8 1 0 0 0\n")
    (tmp_path / "b.meas").write_text("num x y z\n1 0 0 0\n")
    back = read_optodes(tmp_path / "b")
    assert back["sources_mm"].tolist() == [[4, 5, 6], [1, 2, 3]]
    assert back["source_int_func"].shape == (2, 5)
    assert back["link"].tolist() == [[0, 0, 1], [1, 0, 1]]   # no .link: all pairs


def test_corrupt_files_are_named(tmp_path):
    src, det, link = _optodes()
    write_optodes(tmp_path / "m", src, det, link)
    (tmp_path / "m.link").write_text("source detector active\n1 9 1\n")
    with pytest.raises(FluoInputError, match="m.link.*does not exist"):
        read_optodes(tmp_path / "m")
    (tmp_path / "m.link").write_text("1 2 1\n")
    with pytest.raises(FluoInputError, match="header"):
        read_optodes(tmp_path / "m")
    write_optodes(tmp_path / "m", src, det, link)
    (tmp_path / "m.meas").write_text("num x y z\n1 0 0\n")
    with pytest.raises(FluoInputError, match="m.meas.*line 2"):
        read_optodes(tmp_path / "m")
    (tmp_path / "m.meas").write_text("num x y z\n1 0 0 nan\n")
    with pytest.raises(FluoInputError, match="non-finite"):
        read_optodes(tmp_path / "m")
    (tmp_path / "m.meas").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(FluoInputError, match="m.meas"):
        read_optodes(tmp_path / "m")
    with pytest.raises(FluoInputError, match="not found"):
        read_optodes(tmp_path / "missing")
    with pytest.raises(FluoInputError, match="link"):
        write_optodes(tmp_path / "w", src, det, [[0, 7]])
    with pytest.raises(FluoInputError, match="fwhm"):
        write_optodes(tmp_path / "w", src, det, fwhm_mm=-1)
    with pytest.raises(FluoInputError, match="same dimension"):
        write_optodes(tmp_path / "w", src, det[:, :2])
