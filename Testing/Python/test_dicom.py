"""DICOM CBCT in (issue #35): a series written by SimpleITK from a volume in RAS,
LPS and oblique orientations comes back with identical geometry and values
(``fluoguide.dicom``, ``fluoguide.labelmap_io.read_cbct``); each series that
cannot be read without guessing is refused by ``fluo scene import`` with one
line naming the field, exit 2, nothing written."""

import json

import numpy as np
import pytest

import dicom_cases as dc
from fluoguide import mrml_io
from fluoguide.dicom import list_series, read_dicom_series
from fluoguide.errors import FluoInputError
from fluoguide.labelmap_io import read_cbct

SPACING = (0.5, 0.6, 0.8)
ORIGIN = (120.5, -80.25, 340.0)
DIRECTIONS = {"RAS": np.eye(3), "LPS": np.diag([-1.0, -1.0, 1.0]),
              "oblique": dc.rotation(20.0, -25.0, 10.0)}


def _good(folder, direction="oblique", **kw):
    kw.setdefault("slope", 2.0)
    kw.setdefault("intercept", -1024.0)
    return dc.write_series(folder, dc.test_volume(), SPACING, ORIGIN, DIRECTIONS[direction], **kw)


@pytest.mark.parametrize("name", list(DIRECTIONS))
def test_series_comes_back_with_its_geometry_and_hu(tmp_path, name):
    files, hu = _good(tmp_path / name, name)
    vol = read_dicom_series(tmp_path / name)
    assert vol.array_kji.shape == (30, 36, 40)
    assert vol.array_kji.dtype == np.int16            # slope 2, intercept -1024: integral
    assert np.array_equal(vol.array_kji, hu)
    np.testing.assert_allclose(vol.spacing_mm, SPACING, atol=1e-6)
    np.testing.assert_allclose(vol.origin_mm, ORIGIN, atol=1e-6)
    np.testing.assert_allclose(vol.direction, DIRECTIONS[name], atol=1e-6)
    assert vol.files == files and vol.modality == "CT" and vol.description == "CBCT"
    # the one reader every command calls: the same
    arr, spacing, origin, direction, source = read_cbct(tmp_path / name)
    assert np.array_equal(arr, hu) and source["slices"] == 30 and source["format"] == "DICOM"


def test_files_in_any_order_and_a_rescale_per_slice(tmp_path):
    # slopes and intercepts that differ per slice and are not integers: float32
    # HU; file names that do not follow the slice order
    slopes = np.linspace(0.5, 1.5, 30)
    files, hu = _good(tmp_path / "s", slope=slopes, intercept=-1000.25)
    for k, f in enumerate(files):
        f.rename(f.with_name(f"X{(k * 7) % 30:03d}_{k}.dcm"))
    vol = read_dicom_series(tmp_path / "s")
    assert vol.array_kji.dtype == np.float32
    np.testing.assert_allclose(vol.array_kji, hu, rtol=0, atol=1e-3)
    np.testing.assert_allclose(vol.origin_mm, ORIGIN, atol=1e-6)


def test_compressed_slices_and_the_gdcm_fallback(tmp_path, monkeypatch):
    # JPEG 2000 slices: pydicom decodes them (Pillow); where it cannot (no
    # plug-in for the transfer syntax), GDCM does, with the rescale applied
    import pydicom

    files, hu = _good(tmp_path / "s", compress=True)
    assert pydicom.dcmread(files[0]).file_meta.TransferSyntaxUID.is_compressed
    assert np.array_equal(read_dicom_series(tmp_path / "s").array_kji, hu)

    def no_decoder(self):
        raise NotImplementedError("no plug-in")

    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(no_decoder))
    vol = read_dicom_series(tmp_path / "s")
    assert vol.array_kji.dtype == np.int16 and np.array_equal(vol.array_kji, hu)


def test_geometry_agrees_with_simpleitk_own_series_reader(tmp_path):
    import SimpleITK as sitk

    _good(tmp_path / "s")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    img = reader.Execute()
    vol = read_dicom_series(tmp_path / "s")
    flip = np.diag([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(vol.origin_mm, flip @ np.array(img.GetOrigin()), atol=1e-6)
    np.testing.assert_allclose(vol.direction, flip @ np.reshape(img.GetDirection(), (3, 3)),
                               atol=1e-6)
    np.testing.assert_allclose(vol.spacing_mm, img.GetSpacing(), atol=1e-6)
    assert np.array_equal(vol.array_kji, sitk.GetArrayFromImage(img))


def test_two_series_listed_and_one_chosen(tmp_path):
    _good(tmp_path / "d", uid="1.2.3.4.1", description="head CBCT")
    files, hu2 = dc.write_series(tmp_path / "d", dc.test_volume((4, 36, 40), seed=1), SPACING,
                                 ORIGIN, np.eye(3), uid="1.2.3.4.2", description="scout",
                                 prefix="SC")
    assert [(s.uid, len(s.files)) for s in list_series(tmp_path / "d")] == [
        ("1.2.3.4.1", 30), ("1.2.3.4.2", 4)]
    with pytest.raises(FluoInputError) as e:
        read_dicom_series(tmp_path / "d")
    assert "1.2.3.4.1 (head CBCT, 30 slices); 1.2.3.4.2 (scout, 4 slices)" in str(e.value)
    assert np.array_equal(read_dicom_series(tmp_path / "d", series="1.2.3.4.2").array_kji, hu2)


def _one_line_exit_2(r, *needles):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _spoil(case, d):
    """A good series in ``d`` spoiled one way; returns the needles of its refusal
    and the extra arguments."""
    files, _ = _good(d)
    n = np.cross(*(dc.LPS_TO_RAS @ DIRECTIONS["oblique"])[:, :2].T)
    if case == "two-series":
        dc.write_series(d, dc.test_volume((4, 36, 40)), SPACING, ORIGIN, np.eye(3),
                        uid="1.2.3.9", description="scout", prefix="SC")
        return ["--series", "2 series", "1.2.826.0.1.3680043.2.1125.77.1 (CBCT, 30 slices)",
                "1.2.3.9 (scout, 4 slices)"], []
    if case == "unknown-series":
        return ["--series", "no such series", "1.2.3.999"], ["--series", "1.2.3.999"]
    if case == "missing-slice":
        files[15].unlink()
        return ["ImagePositionPatient", "missing slice", "1 slice(s) of 0.8 mm"], []
    if case == "duplicated-slice":
        dc.duplicate_slice(files, 12)
        return ["ImagePositionPatient", "two slices at one position", "IM0012"], []
    if case == "non-uniform-spacing":
        dc.shift_positions(files, [n * (0.3 if k >= 10 else 0.0) for k in range(30)])
        return ["ImagePositionPatient", "not uniform", "1.1 mm"], []
    if case == "sheared-tilt":
        r = (dc.LPS_TO_RAS @ DIRECTIONS["oblique"])[:, 1]
        dc.shift_positions(files, [r * 0.2 * k for k in range(30)])
        return ["ImagePositionPatient", "not along the slice normal"], []
    if case == "gantry-tilt":
        dc.edit(files, GantryDetectorTilt="12.5")
        return ["GantryDetectorTilt", "12.5"], []
    if case == "orientation-differs":
        dc.edit(files[7:8], ImageOrientationPatient=["1", "0", "0", "0", "1", "0"])
        return ["ImageOrientationPatient", "differs between slices", "IM0007"], []
    if case == "non-image":
        dc.write_non_image(d / "report.dcm")
        return ["report.dcm", "PixelData", "not an image", "Basic Text SR"], []
    if case == "not-dicom":
        (d / "notes.txt").write_text("scanned on Tuesday\n")
        return ["notes.txt", "not a DICOM file"], []
    if case == "one-file":
        return ["IM0003.dcm", "give the folder"], ["--cbct", str(files[3])]
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["two-series", "unknown-series", "missing-slice",
                                  "duplicated-slice", "non-uniform-spacing", "sheared-tilt",
                                  "gantry-tilt", "orientation-differs", "non-image", "not-dicom",
                                  "one-file"])
def test_bad_series_refused_with_one_line(tmp_path, case, fluo):
    d = tmp_path / "dcm"
    needles, extra = _spoil(case, d)
    args = ["scene", "import", "--cbct", str(d), "--out", str(tmp_path / "scene")]
    if extra and extra[0] == "--cbct":
        args[3] = extra[1]
    else:
        args += extra
    r = fluo(*args)
    _one_line_exit_2(r, *needles)
    assert not (tmp_path / "scene").exists()          # nothing written


def test_scene_import_writes_a_scene_the_commands_take(tmp_path, fluo):
    files, hu = _good(tmp_path / "dcm")
    r = fluo("scene", "import", "--cbct", tmp_path / "dcm", "--out", tmp_path / "scene",
             "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["source"]["series_uid"] == "1.2.826.0.1.3680043.2.1125.77.1"
    assert out["dimensions_ijk"] == [40, 36, 30] and out["voxel_type"] == "int16"
    scene = mrml_io.load_scene(tmp_path / "scene" / "scene.mrml")
    node = mrml_io.get_node(scene, "CBCT", "vtkMRMLScalarVolumeNode")
    geo = mrml_io.volume_geometry(node)
    assert np.array_equal(mrml_io.volume_array(node), hu)
    np.testing.assert_allclose(geo["spacing"], SPACING, atol=1e-6)
    np.testing.assert_allclose(geo["origin"], ORIGIN, atol=1e-6)
    np.testing.assert_allclose(geo["direction"], DIRECTIONS["oblique"], atol=1e-6)
    assert mrml_io.get_json_attribute(node, "FluoGuide.Source")["slices"] == 30
    # scene info reads it; the readable form names the volume
    r = fluo("scene", "info", tmp_path / "scene" / "scene.mrml", "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["nodes"][0]["name"] == "CBCT"
    r = fluo("scene", "import", "--cbct", tmp_path / "dcm", "--out", tmp_path / "scene2")
    assert r.returncode == 0 and "CBCT" in r.stdout, r.stderr


def test_a_volume_file_is_taken_too_and_series_refused_for_it(tmp_path, fluo):
    from fluoguide.labelmap_io import write_volume_nrrd

    arr = dc.test_volume((6, 8, 10))
    write_volume_nrrd(tmp_path / "cbct.nrrd", arr, SPACING, ORIGIN, DIRECTIONS["oblique"])
    got, spacing, origin, direction, source = read_cbct(tmp_path / "cbct.nrrd")
    assert np.array_equal(got, arr) and source["format"] == "NRRD"
    np.testing.assert_allclose(direction, DIRECTIONS["oblique"], atol=1e-6)
    r = fluo("scene", "import", "--cbct", tmp_path / "cbct.nrrd", "--series", "1.2",
             "--out", tmp_path / "scene")
    _one_line_exit_2(r, "--series", "DICOM folder only")
    assert not (tmp_path / "scene").exists()
