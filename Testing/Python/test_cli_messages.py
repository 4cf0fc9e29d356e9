"""What a hostile user reads (issue #34, item 8): one line ``fluo: error:
FILE: FIELD: what is wrong (got VALUE)`` on stderr, nothing before it but
progress lines, in the project's words:

- a damaged image file (a corrupt .nii.gz, a NRRD with a broken header, a
  .mha that is text) is said in words, never with ITK's build paths, and the
  readers' own lines (MetaIO, libpng) stay off stderr;
- files inside a folder the user named are shown as the user gave the folder
  (``acq/data.csv``), never as absolute paths;
- Python warnings go in the result's ``warnings`` (or the log when the
  command failed), never on stderr before the error;
- a newline or an escape sequence in a path or a value is escaped: the
  message stays one line.

Each command runs as a real process (the ``fluo`` fixture) where stderr is the
point: the C libraries write to file descriptor 2, not to ``sys.stderr``."""

from __future__ import annotations

import gzip
import json
import re
import shutil

import numpy as np
import pytest

# a progress line (fluoguide.progress): "calib camera:  20% detecting board 2/4 (3 s)"
PROGRESS = re.compile(r"^[\w .-]+: +\d+% .*\(\d+ s\)$")

# what a library's internals look like in a message
INTERNALS = re.compile(r"SimpleITK|itk::|ITK ERROR|\.(?:cxx|hxx|cpp|h):\d|0x[0-9a-f]{6}|/tmp/|"
                       r"OpenCV\(|libpng|MetaImage:|HDF5|Traceback")


def _error_line(r, rc=2):
    """The one error line of a refused command; every other line a progress line."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == rc, r.stderr
    assert lines and lines[-1].startswith("fluo: error: "), r.stderr
    assert all(PROGRESS.match(ln) for ln in lines[:-1]), r.stderr
    return lines[-1]


def _label_files(folder):
    """Damaged label maps of each kind ITK reads, beside a good one (returned by name)."""
    import SimpleITK as sitk

    lab = np.zeros((8, 10, 12), np.uint8)
    lab[2:6, 3:7, 3:9] = 1
    img = sitk.GetImageFromArray(lab)
    sitk.WriteImage(img, str(folder / "good.nii.gz"))
    sitk.WriteImage(img, str(folder / "good.nrrd"), True)
    nii = (folder / "good.nii.gz").read_bytes()
    # gzip whose content is not NIfTI, and a NIfTI cut in its header
    (folder / "corrupt.nii.gz").write_bytes(gzip.compress(np.random.default_rng(0).bytes(600)))
    (folder / "cut.nii.gz").write_bytes(gzip.compress(gzip.decompress(nii)[:200]))
    head, _, body = (folder / "good.nrrd").read_bytes().partition(b"\n\n")
    (folder / "sizes.nrrd").write_bytes(head.replace(b"sizes: 12 10 8", b"sizes: 12 x 8")
                                        + b"\n\n" + body)
    (folder / "cut.nrrd").write_bytes(head + b"\n\n" + body[: len(body) // 3])
    # header fields the header checks (fluoguide.volume_header) pass on to ITK
    (folder / "space.nrrd").write_bytes(head.replace(b"left-posterior-superior", b"nowhere")
                                        + b"\n\n" + body)
    text = head.replace(b"encoding: gzip", b"encoding: ascii") + b"\n\n"
    (folder / "ascii.nrrd").write_bytes(text + b"x " * 1000)
    # one "value" of 2,000 characters: ITK's reader crashed (SIGSEGV, no message)
    (folder / "long.nrrd").write_bytes(text + b"x" * 2000)
    (folder / "text.mha").write_text("this is a text file, not an image\n")
    # a MetaImage header without its data: MetaIO prints its own lines to stderr
    (folder / "nodata.mha").write_text("ObjectType = Image\nNDims = 3\nDimSize = 12 10 8\n"
                                       "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n")


# file -> what the message must say: the NRRD and NIfTI header checks' own words
# (fluoguide.volume_header) or ITK's error in words (fluoguide.library_errors), the
# field in the message's FIELD place
DAMAGED = {
    "corrupt.nii.gz": "sizeof_hdr: not a NIfTI header",
    "cut.nii.gz": "sizeof_hdr: NIfTI header cut short",
    "sizes.nrrd": "sizes: must be integers",
    "cut.nrrd": "cut short",
    "space.nrrd": 'space: cannot read label map (damaged NRRD header: couldn\'t parse space '
                  '"nowhere")',
    "ascii.nrrd": "cannot read label map (damaged NRRD data: couldn't parse element 1 of 960",
    "long.nrrd": "data: text data hold a value of more than 64 characters (not a number)",
    "text.mha": "cannot read label map (damaged file or an unknown image format)",
    "nodata.mha": "cannot read label map (damaged MetaImage file: its header or data cannot "
                  "be read)",
}


@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    d = tmp_path_factory.mktemp("damaged")
    _label_files(d)
    (d / "optics.json").write_text(json.dumps({
        "n": 1.37, "excitation": {"1": {"mua_per_mm": 0.01, "musp_per_mm": 1.0}},
        "emission": {"1": {"mua_per_mm": 0.008, "musp_per_mm": 0.9}}}))
    return d


@pytest.mark.parametrize("name", sorted(DAMAGED))
@pytest.mark.parametrize("command", ["mesh", "tomo simulate"])
def test_a_damaged_label_map_is_said_in_words(name, command, damaged, fluo):
    """ITK's text (``Exception thrown in SimpleITK ImageFileReader_Execute:
    /tmp/SimpleITK-build/ITK/Modules/IO/NRRD/src/itkNrrdImageIO.cxx:410``) was
    the message, and MetaIO's lines came before it."""
    if command == "mesh":
        argv = ["mesh", name, "--out", "out.vtu", "--fast", "--size", "3"]
    else:
        argv = ["tomo", "simulate", "--labels", name, "--optics", "optics.json", "--yield",
                "1:0.001", "--out", "acq"]
    r = fluo(*argv, cwd=damaged)
    line = _error_line(r)
    assert line.startswith(f"fluo: error: {name}: "), line     # the file as given
    assert DAMAGED[name] in line, line
    assert not INTERNALS.search(r.stderr), r.stderr
    assert not (damaged / "out.vtu").exists() and not (damaged / "acq").exists()


def test_library_error_texts_in_words():
    """The translation itself, on the texts SimpleITK 2 and OpenCV 4 raise."""
    from fluoguide.library_errors import image_read_problem, opencv_problem, scrub

    nrrd = ("Exception thrown in SimpleITK ImageFileReader_Execute: /tmp/SimpleITK-build/ITK/"
            "Modules/IO/NRRD/src/itkNrrdImageIO.cxx:410:\nitk::ERROR: NrrdImageIO(0x563936a37940)"
            ": ReadImageInformation: Error reading b.nrrd:\n[nrrd] nrrdLoad: trouble reading "
            "\"b.nrrd\"\n[nrrd] nrrdRead: trouble\n[nrrd] _nrrdFormatNRRD_read: trouble parsing "
            "type info |foo|\n[nrrd] _nrrdReadNrrdParse_type: couldn't parse type \"foo\"\n")
    assert image_read_problem(RuntimeError(nrrd)) == (
        "damaged NRRD header: couldn't parse type \"foo\"", "type")
    cut = ("Exception thrown in SimpleITK ImageFileReader_Execute: /x/itkNrrdImageIO.cxx:935:\n"
           "ITK ERROR: NrrdImageIO(0x55829b5cee70): Read: Error reading c.nrrd:\n[nrrd] "
           "_nrrdEncodingRaw_read: fread got only 23855 1-sized things, not 48000 (49.7% of "
           "expected)\n")
    assert image_read_problem(RuntimeError(cut)) == (
        "damaged NRRD data: data cut short: 23855 of 48000 values", None)
    cv = ("OpenCV(4.14.0) /io/opencv/modules/calib3d/src/calibration.cpp:2676: error: "
          "(-215:Assertion failed) nimages > 0 in function 'calibrateCameraRO'\n")
    assert opencv_problem(RuntimeError(cv)) == "OpenCV: assertion failed"
    yml = ("OpenCV(4.14.0) /io/opencv/modules/core/src/persistence_yml.cpp:681: error: "
           "(-212:Parsing error) parseValue in function 'c.yaml(5): Missing , between the "
           "elements'\n")
    assert opencv_problem(RuntimeError(yml)) == (
        "OpenCV: parsing error at line 5: Missing , between the elements")
    # anything else: the internals out, one line
    text = scrub("ITK ERROR: PNGImageIO(0x55829ad87d00): Error while reading file: "
                 "/home/u/data/x.png\nsecond line")
    assert text == "Error while reading file: x.png second line"


def test_a_damaged_opencv_yaml_is_one_line(tmp_path, fluo):
    """OpenCV's YAML parser error reached the user as ``fluo: internal error:
    SystemError: <class 'cv2.FileStorage'> returned a result with an exception
    set`` (its binding wraps the cv2.error), exit 1."""
    from FluoCalibLib.geometry.synthetic_boards import default_camera, make_dataset

    make_dataset(tmp_path / "boards", default_camera(320, 240), n_views=4)
    (tmp_path / "cam.yaml").write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n"
                                       "  rows: 3\n  cols: [\n")
    r = fluo("calib", "handeye", "--images", "boards/*.png", "--board", "chessboard:9x6:20",
             "--poses", "boards/truth.json", "--intrinsics", "cam.yaml", cwd=tmp_path)
    line = _error_line(r)
    assert line == ("fluo: error: cam.yaml: not an OpenCV FileStorage file (OpenCV: parsing "
                    "error at line 5: Missing , between the elements)"), line


# ------------------------------------------- warnings and the libraries' lines
def test_a_numpy_warning_does_not_precede_the_error(tmp_path, fluo):
    """A mesh with nodes no element uses: ``RuntimeWarning: invalid value
    encountered in divide`` and its source line came before the refusal."""
    from FluoTomoLib.meshing.mesh import Mesh
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured
    from FluoTomoLib.meshing.vtu_io import write_vtu

    m = mesh_labelmap_structured(np.ones((6, 6, 6), np.int32), np.ones(3),
                                 np.array([-2.5, -2.5, -5.5]), 1.5)
    write_vtu(Mesh(np.vstack([m.nodes_mm, m.nodes_mm[:3] + 100.0]), m.elements,
                   m.element_region), tmp_path / "unused.vtu")
    (tmp_path / "s.csv").write_text("0,0,0\n")
    (tmp_path / "d.csv").write_text("2,0,0\n")
    r = fluo("forward", "--mesh", "unused.vtu", "--mua", "0.01", "--musp", "1", "--sources",
             "s.csv", "--detectors", "d.csv", "--jacobian", cwd=tmp_path)
    assert "belong to no element" in _error_line(r), r.stderr
    assert "Warning" not in r.stderr, r.stderr


def test_damaged_pngs_print_no_libpng_lines(tmp_path, fluo):
    """``fluo calib camera --images`` on cut PNGs printed ``libpng error: ...``
    before the error, and on fuzz_cli's PNG claiming 20000 x 20000 pixels
    (over Pillow's own limit, so its header went unread) OpenCV decoded it."""
    import zlib

    import cv2

    ok, buf = cv2.imencode(".png", np.random.default_rng(1).integers(0, 255, (90, 120), np.uint8))
    (tmp_path / "cut").mkdir()
    for k in range(3):
        (tmp_path / "cut" / f"c{k}.png").write_bytes(buf.tobytes()[:300])
    bad = bytearray(buf.tobytes())
    bad[40] ^= 0xFF                     # a chunk's type: "libpng error: IDA[AB]: bad header"
    (tmp_path / "cut" / "c3.png").write_bytes(bytes(bad))

    def chunk(kind, body):
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    huge = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", (20000).to_bytes(4, "big") * 2
                                           + bytes([8, 0, 0, 0, 0]))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 1000)) + chunk(b"IEND", b""))
    (tmp_path / "huge").mkdir()
    for k in range(3):
        (tmp_path / "huge" / f"h{k}.png").write_bytes(huge)
    for folder, says in (("cut", "cannot read image"), ("huge", "image too large")):
        r = fluo("calib", "camera", "--images", f"{folder}/*.png", "--board", "chessboard:9x6:20",
                 "--yaml", "c.yaml", cwd=tmp_path)
        line = _error_line(r)
        assert says in line and f"{folder}/" in line, line
        assert "libpng" not in r.stderr, r.stderr


def test_opencv_camera_lines_stay_off_stderr(tmp_path, fluo):
    """OpenCV logged ``[ WARN:0@0.012] global cap_v4l.cpp:914 open
    VIDEOIO(V4L2:/dev/video0): can't open camera by index`` before the error."""
    from pathlib import Path

    if Path("/dev/video0").exists():
        pytest.skip("a camera is attached: index 0 would open and record")
    r = fluo("record", "--camera", "0", "--out", "rec", "--seconds", "0.5", cwd=tmp_path)
    assert _error_line(r) == ("fluo: error: camera: cannot open camera or video (OpenCV "
                              "VideoCapture) (got 0)"), r.stderr


def test_warnings_in_words():
    """What the CLI makes of Python warnings (``cli._warning_texts``): the
    project's by their message, numpy's with their category, deprecations
    left out, each once, one line each."""
    import warnings

    from fluoapp import cli
    from FluoTomoLib.optics import check_properties

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_properties(0.5, 1.0, where="excitation")       # musp/mua = 2: not diffusive
        check_properties(0.5, 1.0, where="excitation")
        np.array([1.0]) / np.array([0.0])
        warnings.warn("old API", DeprecationWarning)
        warnings.warn("a\nb", UserWarning)
    said = cli._warning_texts(caught)
    assert said == ["excitation: musp/mua = 2 < 10, diffusion theory is inaccurate",
                    "RuntimeWarning: divide by zero encountered in divide", "a\\nb"], said


# ------------------------------------------------------------- paths as given
@pytest.fixture
def own_copy(own_scene, tmp_path):
    """The own scene in a fresh folder (labels.nrrd, optics.json, acq/), to damage."""
    d = tmp_path / "own"
    d.mkdir()
    for f in ("labels.nrrd", "optics.json"):
        shutil.copy(own_scene.dir / f, d / f)
    shutil.copytree(own_scene.acq, d / "acq")
    return d


def test_acquisition_errors_name_files_as_given(own_copy, fluo):
    """``fluo tomo reconstruct --acquisition acq/`` with a bad acq/data.csv named
    ``/abs/path/acq/data.csv``."""
    data = own_copy / "acq" / "data.csv"
    rows = data.read_text().splitlines()
    k = next(i for i, ln in enumerate(rows) if ln and not ln.startswith("#"))
    rows[k] = "abc," + rows[k].split(",", 1)[1]
    data.write_text("\n".join(rows) + "\n")
    r = fluo("tomo", "reconstruct", "--labels", "labels.nrrd", "--optics", "optics.json",
             "--acquisition", "acq/", "--out", "rec", cwd=own_copy)
    line = _error_line(r)
    assert line.startswith("fluo: error: acq/data.csv: data: line "), line
    assert str(own_copy) not in r.stderr


def test_batch_and_scene_errors_name_files_as_given(own_copy, fluo):
    """A batch row's damaged label map and a scene's damaged data file were named by
    their absolute paths."""
    (own_copy / "bad.nrrd").write_text("NRRD0004\ntype: foo\n\n")
    (own_copy / "batch.csv").write_text("labels,optics,acquisition\nbad.nrrd,optics.json,acq\n")
    # run from the folder above: every path shown starts with the folder as typed
    r = fluo("tomo", "batch", f"{own_copy.name}/batch.csv", "--out", "runs", cwd=own_copy.parent)
    line = _error_line(r)
    assert line.startswith(f"fluo: error: {own_copy.name}/batch.csv: line 2, labels: "
                           f"{own_copy.name}/bad.nrrd: "), line
    assert str(own_copy) not in r.stderr
    from fluoguide import mrml_io

    scene = mrml_io.new_scene()
    mrml_io.add_volume(scene, "CBCTLabels", np.ones((4, 5, 6), np.uint8), (1, 1, 1), (0, 0, 0),
                       labelmap=True)
    mrml_io.save_scene(scene, own_copy / "sc" / "scene.mrml")
    nrrd = own_copy / "sc" / "CBCTLabels.nrrd"
    good = nrrd.read_bytes()
    nrrd.write_text("NRRD0004\ntype: foo\n\n")          # refused by the header checks
    r = fluo("scene", "info", "sc/scene.mrml", cwd=own_copy)
    assert _error_line(r) == ("fluo: error: sc/CBCTLabels.nrrd: dimension: required header "
                              "field missing")
    nrrd.write_bytes(good.replace(b"left-posterior-superior", b"nowhere"))   # by MRML's reader
    r = fluo("scene", "info", "sc/scene.mrml", cwd=own_copy)
    assert _error_line(r) == "fluo: error: sc/CBCTLabels.nrrd: CBCTLabels: corrupt volume file"
    (own_copy / "sc" / "CBCTLabels.nrrd").unlink()
    r = fluo("scene", "info", "sc/scene.mrml", cwd=own_copy)
    assert _error_line(r).startswith("fluo: error: sc/CBCTLabels.nrrd: "), r.stderr
    assert str(own_copy) not in r.stderr


# ------------------------------------------------------------------ one line
def test_a_newline_in_a_path_stays_one_line(tmp_path, fluo):
    """``fluo mesh $'bad\\nname.nrrd'`` split its message in two lines; so did an
    output path with a newline under a file."""
    r = fluo("mesh", "bad\nname.nrrd", "--out", "x.vtu", cwd=tmp_path)
    assert _error_line(r) == "fluo: error: bad\\nname.nrrd: label map file not found"
    _label_files(tmp_path)
    (tmp_path / "a_file").write_text("a file where a folder is expected\n")
    r = fluo("mesh", "good.nrrd", "--out", "a_file/x\n\x1b[31my.vtu", "--fast", cwd=tmp_path)
    line = _error_line(r)
    assert line.startswith("fluo: error: a_file/x\\n\\x1b[31my.vtu"), line
    assert "\x1b" not in r.stderr


def test_error_text_is_one_line_whatever_it_holds():
    """FluoInputError and FluoError (device) texts: every control character
    escaped, as Python writes it; escaping twice changes nothing."""
    from fluoguide.errors import FluoDeviceError, FluoInputError, one_line

    e = FluoInputError("not found", file="a\nb.nrrd", field="f\ri", value="v\x00")
    assert str(e) == "a\\nb.nrrd: f\\ri: not found (got 'v\\x00')"
    assert e.file == "a\nb.nrrd"                       # the attributes keep what was given
    assert str(FluoDeviceError("peer said:\nbye\u202e")) == "peer said:\\nbye\\u202e"
    wrapped = FluoInputError(str(e), file="batch.csv", field="row 1")
    assert str(wrapped) == "batch.csv: row 1: " + str(e)
    assert one_line(one_line("x\ny\\n")) == "x\\ny\\n"
    assert one_line("é ok 中") == "é ok 中"


def test_a_progress_line_is_one_line(capsys):
    """A progress message naming a file with a newline split its line in two."""
    from fluoguide.progress import TqdmProgress

    progress = TqdmProgress("mesh", after_s=0)
    progress(0.5, "reading bad\nname.nrrd")
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad\\nname.nrrd" in err, err


def test_the_last_resort_is_one_line_without_library_internals(capsys):
    """``fluo: internal error:`` kept the first line of a bug's message: ITK's
    build path, nothing of what followed a newline."""
    import argparse

    from fluoapp import cli

    exc = RuntimeError("Exception thrown in SimpleITK ImageFileReader_Execute: /tmp/SimpleITK-"
                       "build/ITK/Modules/IO/Meta/src/itkMetaImageIO.cxx:490:\nITK ERROR: "
                       "MetaImageIO(0x55829b823cf0): File cannot be read: x.mha\x1b[2J")
    assert cli._internal_error(exc, argparse.Namespace(debug=False)) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err == ("fluo: internal error: RuntimeError: File cannot be read: x.mha\\x1b[2J "
                   "(fluo --debug ... shows the traceback)\n"), err
