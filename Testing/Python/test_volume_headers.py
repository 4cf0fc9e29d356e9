"""Volume headers that lie are refused with the file and the header field (issue
#34 items 4 and 7).

ITK (SimpleITK 2.4 / ITK 5.4, under the label-map readers and MRML) reads a
NIfTI with a NaN, zero or negative ``pixdim`` as spacing 1 (or a flipped axis),
ignores a NaN quaternion or a skewed ``sform`` (a warning on stderr, exit 0), reads
an NRRD ``spacings: nan`` as 1, keeps a skewed ``space directions`` as a
non-orthonormal direction, and cuts off data beyond what the header declares.
Each file here is written correctly by SimpleITK or by hand, then one header
field is edited; each must be refused by ``fluo mesh``, ``fluo tomo simulate
--labels``, the logic's ``loadLabelMap`` and a scene that refers to it.
"""

import gzip
import struct

import numpy as np
import pytest

from fluoguide.errors import FluoInputError

LABELS = np.zeros((6, 7, 8), np.uint8)
LABELS[1:5, 2:6, 2:7] = 1
LABELS[2:4, 3:5, 3:5] = 7


def _nifti(path, edit=None, tail=b""):
    """A NIfTI-1 label map written by SimpleITK (LPS 1 mm voxels, qform and sform
    both set), then ``edit(header bytearray)`` and ``tail`` appended."""
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(LABELS)
    img.SetSpacing((1.0, 1.0, 1.0))
    sitk.WriteImage(img, str(path.with_suffix(".tmp.nii")))
    data = bytearray(path.with_suffix(".tmp.nii").read_bytes())
    path.with_suffix(".tmp.nii").unlink()
    assert struct.unpack_from("<hh", data, 252) == (1, 1)      # qform_code, sform_code
    if edit:
        edit(data)
    data += tail
    if path.name.endswith(".gz"):
        path.write_bytes(gzip.compress(bytes(data)))
    else:
        path.write_bytes(bytes(data))
    return path


def _pack(fmt, offset, *values):
    return lambda b: struct.pack_into("<" + fmt, b, offset, *values)


def _nrrd(path, directions="(1,0,0) (0,1,0) (0,0,1)", origin="(0,0,0)", spacings=None,
          extra=b"", encoding="raw"):
    """A NRRD written by hand: ``space directions`` (or ``spacings``), origin,
    raw or gzip data with ``extra`` bytes after the declared ones."""
    k, j, i = LABELS.shape
    geometry = (f"spacings: {spacings}\n" if spacings is not None else
                f"space: left-posterior-superior\nspace directions: {directions}\n"
                f"space origin: {origin}\n")
    head = (f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {i} {j} {k}\n{geometry}"
            f"kinds: domain domain domain\nendian: little\nencoding: {encoding}\n\n").encode()
    data = LABELS.tobytes() + extra
    path.write_bytes(head + (gzip.compress(data) if encoding == "gzip" else data))
    return path


BAD = {
    # NIfTI-1: pixdim at byte 76, quatern_b/c/d at 256, qoffset at 268, srow_x at 280
    "pixdim_nan.nii": (lambda p: _nifti(p, _pack("f", 80, float("nan"))), "pixdim[1]"),
    "pixdim_zero.nii": (lambda p: _nifti(p, _pack("f", 84, 0.0)), "pixdim[2]"),
    "pixdim_neg.nii.gz": (lambda p: _nifti(p, _pack("f", 88, -1.0)), "pixdim[3]"),
    "pixdim_vs_sform.nii": (lambda p: _nifti(p, _pack("f", 80, 2.0)), "pixdim"),
    "quatern_nan.nii": (lambda p: _nifti(p, _pack("f", 256, float("nan"))), "quatern_b/c/d"),
    "qoffset_inf.nii": (lambda p: _nifti(p, _pack("f", 272, float("inf"))), "qoffset_x/y/z"),
    "srow_nan.nii": (lambda p: _nifti(p, _pack("f", 280, float("nan"))), "srow_x/y/z"),
    "srow_skew.nii": (lambda p: _nifti(p, _pack("f", 284, 0.5)), "srow_x/y/z"),
    "extra.nii": (lambda p: _nifti(p, tail=b"\x07" * 100), "data"),
    "extra.nii.gz": (lambda p: _nifti(p, tail=b"\x07" * 100), "data"),
    "cut.nii": (lambda p: (_nifti(p), p.write_bytes(p.read_bytes()[:-10]))[0], "data"),
    # NRRD
    "spacing_zero.nrrd": (lambda p: _nrrd(p, spacings="0 1 1"), "spacings"),
    "spacing_neg.nrrd": (lambda p: _nrrd(p, spacings="1 -1 1"), "spacings"),
    "spacing_nan.nrrd": (lambda p: _nrrd(p, spacings="1 1 nan"), "spacings"),
    "direction_zero.nrrd": (lambda p: _nrrd(p, "(0,0,0) (0,1,0) (0,0,1)"), "space directions"),
    "direction_nan.nrrd": (lambda p: _nrrd(p, "(1,0,0) (0,nan,0) (0,0,1)"), "space directions"),
    "direction_skew.nrrd": (lambda p: _nrrd(p, "(1,0,0) (0.5,1,0) (0,0,1)"), "space directions"),
    "origin_inf.nrrd": (lambda p: _nrrd(p, origin="(0,inf,0)"), "space origin"),
    "extra.nrrd": (lambda p: _nrrd(p, extra=b"\x01" * 50), "data"),
    "extra_gzip.nrrd": (lambda p: _nrrd(p, extra=b"\x01" * 50, encoding="gzip"), "data"),
    "spacings_twice.nrrd": (lambda p: _nrrd(p, spacings="1 1 1\nspacings: 2 2 2"), "spacings"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_lying_header_is_refused_with_file_and_field(name, tmp_path):
    from fluoguide.labelmap_io import read_labelmap

    make, field = BAD[name]
    p = make(tmp_path / name)
    with pytest.raises(FluoInputError) as e:
        read_labelmap(p)
    assert str(e.value).startswith(f"{p}: {field}: "), e.value


@pytest.mark.parametrize("name", ["good.nii", "good.nii.gz"])
def test_itk_written_nifti_and_hand_written_nrrd_still_read(name, tmp_path):
    from fluoguide.labelmap_io import read_labelmap, write_volume_nrrd

    arr, spacing, origin, direction = read_labelmap(_nifti(tmp_path / name))
    np.testing.assert_array_equal(arr, LABELS)
    np.testing.assert_allclose(spacing, 1.0)
    for f in (_nrrd(tmp_path / "raw.nrrd", "(-1,0,0) (0,-1,0) (0,0,1)"),
              _nrrd(tmp_path / "gz.nrrd", encoding="gzip"),
              _nrrd(tmp_path / "spacings.nrrd", spacings="0.5 0.6 0.7")):
        np.testing.assert_array_equal(read_labelmap(f)[0], LABELS)
    write_volume_nrrd(tmp_path / "w.nrrd", LABELS, (0.5, 0.6, 0.7), (1, 2, 3),
                      np.diag([-1.0, -1.0, 1.0]))
    _, spacing, origin, direction = read_labelmap(tmp_path / "w.nrrd")
    np.testing.assert_allclose(spacing, (0.5, 0.6, 0.7))
    np.testing.assert_allclose(origin, (1, 2, 3))


def test_segmentation_layout_passes_the_header_check(tmp_path):
    """A 4D .seg.nrrd as Slicer writes it: a list axis with 'none' direction."""
    from fluoguide.volume_header import check_volume_file

    k, j, i = LABELS.shape
    two = np.stack([LABELS, LABELS], axis=-1)           # (k, j, i, 2): 2 layers fastest
    head = (f"NRRD0004\ntype: uint8\ndimension: 4\nspace: left-posterior-superior\n"
            f"sizes: 2 {i} {j} {k}\nspace directions: none (1,0,0) (0,1,0) (0,0,1)\n"
            f"kinds: list domain domain domain\nencoding: gzip\nspace origin: (0,0,0)\n"
            f"Segment0_ID:=s0\n\n").encode()
    p = tmp_path / "s.seg.nrrd"
    p.write_bytes(head + gzip.compress(two.tobytes()))
    assert check_volume_file(p)["shape"] == [2, i, j, k]


def test_a_header_declaring_more_than_memory_holds_is_refused_before_reading(tmp_path):
    from fluoguide.volume_header import check_volume_file

    p = tmp_path / "huge.nrrd"
    p.write_bytes(b"NRRD0004\ntype: uint16\ndimension: 3\nsizes: 100000 100000 100000\n"
                  b"encoding: gzip\n\n" + gzip.compress(b"\x00" * 100))
    with pytest.raises(FluoInputError, match=r"huge\.nrrd: reading the volume \(100000 x "
                                             r"100000 x 100000 voxels\) needs about "
                                             r"6000000\.0 GB of memory"):
        check_volume_file(p, copies=3.0)


@pytest.mark.parametrize("name", ["pixdim_nan.nii", "extra.nrrd", "direction_skew.nrrd"])
def test_mesh_and_tomo_simulate_refuse_the_file_and_write_nothing(name, tmp_path, fluo):
    """``fluo mesh FILE``: the issue's NaN voxel size was meshed, exit 0."""
    from small_cases import write_own_scene

    make, field = BAD[name]
    p = make(tmp_path / name)
    r = fluo("mesh", p, "--out", tmp_path / "m.vtu", "--size", "2", "--fast", "--json")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"fluo: error: {p}: {field}: "), lines
    write_own_scene(tmp_path / "own")
    r = fluo("tomo", "simulate", "--labels", p, "--optics", tmp_path / "own" / "optics.json",
             "--yield", "7:0.0026", "--accuracy", "fast", "--out", tmp_path / "acq", "--json")
    assert r.returncode == 2 and f"{p}: {field}: " in r.stderr, r.stderr
    assert not (tmp_path / "m.vtu").exists() and not (tmp_path / "acq").exists()


def test_logic_load_label_map_and_a_scene_refuse_the_file(tmp_path):
    import FluoTomo

    from fluoguide import mrml_io

    bad = BAD["spacing_nan.nrrd"][0](tmp_path / "spacing_nan.nrrd")
    with pytest.raises(FluoInputError, match="spacings: voxel spacing of axis 2"):
        FluoTomo.FluoTomoLogic(mrml_io.new_scene()).loadLabelMap(bad)
    # a scene whose label map file lies: MRML reads it through ITK too
    scene = mrml_io.new_scene()
    mrml_io.add_volume(scene, "CBCTLabels", LABELS, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                       labelmap=True)
    mrml_io.save_scene(scene, tmp_path / "s" / "scene.mrml")
    (tmp_path / "s" / "CBCTLabels.nrrd").write_bytes(bad.read_bytes())
    with pytest.raises(FluoInputError) as e:
        mrml_io.load_scene(tmp_path / "s" / "scene.mrml")
    assert str(e.value).startswith(f"{(tmp_path / 's' / 'CBCTLabels.nrrd').resolve()}: "
                                   "spacings: "), e.value


def test_nifti2_headers_are_checked_too(tmp_path):
    """NIfTI-2 (540-byte header, 64-bit sizes, double transforms), written by hand
    (the field offsets agree with nibabel 5.4's NIfTI-2 writer; ITK 5.4 reads no
    NIfTI-2, so the check guards the readers that will)."""
    from fluoguide.volume_header import check_volume_file

    def nifti2(pixdim1):
        h = bytearray(544)
        struct.pack_into("<i", h, 0, 540)
        h[4:12] = b"n+2\0\r\n\x1a\n"
        struct.pack_into("<hh", h, 12, 2, 8)                          # uint8, 8 bits
        k, j, i = LABELS.shape
        struct.pack_into("<8q", h, 16, 3, i, j, k, 1, 1, 1, 1)
        struct.pack_into("<8d", h, 104, 1.0, pixdim1, 1.0, 1.0, 0, 0, 0, 0)
        struct.pack_into("<q", h, 168, 544)                           # vox_offset
        struct.pack_into("<ii", h, 344, 1, 1)                         # qform, sform codes
        struct.pack_into("<12d", h, 400, pixdim1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0)
        p = tmp_path / f"v2_{pixdim1}.nii"
        p.write_bytes(bytes(h) + LABELS.tobytes())
        return p

    good = nifti2(1.0)
    assert check_volume_file(good) == {"shape": [8, 7, 6], "bytes": LABELS.size}
    with pytest.raises(FluoInputError, match=r"pixdim\[1\]: voxel size must be positive"):
        check_volume_file(nifti2(float("nan")))
    bad = good.read_bytes() + b"\x00" * 8
    good.write_bytes(bad)
    with pytest.raises(FluoInputError, match=r"data: more data than the header declares"):
        check_volume_file(good)
