"""DICOM series written the way a scanner's export is, for the DICOM reader's tests
(``test_dicom.py``) and the CLI fuzz (``fuzz_cli.py``).

:func:`write_series` writes a volume given in the project's RAS convention as a
CT series, one slice per file, with SimpleITK's GDCM (the ``DicomSeriesFromArray``
recipe: per slice ``ImagePositionPatient``, ``ImageOrientationPatient``, the
series UID, modality CT), then sets each slice's rescale with pydicom, so the
HU a reader must return are ``stored * slope + intercept`` exactly. The
helpers below spoil a good series one way each.
"""

from __future__ import annotations

import locale
import shutil
from pathlib import Path

import numpy as np

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


def rotation(deg_x, deg_y, deg_z=0.0):
    """A rotation matrix: about z, then y, then x (degrees)."""
    ax, ay, az = np.radians([deg_x, deg_y, deg_z])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rx @ ry @ rz


def _ds(values):
    """A DICOM decimal string list (each value at most 16 characters)."""
    out = []
    for v in np.ravel(values):
        text = f"{float(v):.10g}"
        assert len(text) <= 16, text
        out.append(text)
    return "\\".join(out)


def write_series(folder, stored_kji, spacing_mm, origin_ras, direction_ras, slope=1.0,
                 intercept=0.0, uid="1.2.826.0.1.3680043.2.1125.77.1", description="CBCT",
                 prefix="IM", compress=False):
    """Write ``stored_kji`` (int16, the stored values) as a CT series in ``folder``.

    ``slope`` and ``intercept``: numbers, or one per slice; ``compress``: JPEG 2000
    (lossless). Returns the files in slice order (k = 0 first) and the HU a
    reader must return (float64).
    """
    import pydicom
    import SimpleITK as sitk

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stored = np.asarray(stored_kji, np.int16)
    nk = stored.shape[0]
    slopes = np.broadcast_to(np.asarray(slope, float), (nk,))
    intercepts = np.broadcast_to(np.asarray(intercept, float), (nk,))
    d_lps = LPS_TO_RAS @ np.asarray(direction_ras, float)
    o_lps = LPS_TO_RAS @ np.asarray(origin_ras, float)
    spacing = np.asarray(spacing_mm, float)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    if compress:
        writer.SetUseCompression(True)
        writer.SetCompressor("JPEG2000")
    files = []
    for k in range(nk):
        img = sitk.GetImageFromArray(stored[k])
        img.SetSpacing(spacing[:2].tolist())
        pos = o_lps + d_lps[:, 2] * spacing[2] * k
        for tag, value in (("0008|0060", "CT"), ("0020|000e", uid),
                           ("0020|000d", uid + ".0"), ("0008|103e", description),
                           ("0020|0013", str(k + 1)),
                           ("0020|0032", _ds(pos)),
                           ("0020|0037", _ds(np.concatenate([d_lps[:, 0], d_lps[:, 1]]))),
                           ("0018|0050", _ds([spacing[2]]))):
            img.SetMetaData(tag, value)
        f = folder / f"{prefix}{k:04d}.dcm"
        writer.SetFileName(str(f))
        saved = locale.setlocale(locale.LC_ALL)
        try:
            writer.Execute(img)
        finally:
            # SimpleITK 2.5's DICOM writer (GDCM) leaves the process in the C
            # locale: Python's text files would then read ASCII only
            locale.setlocale(locale.LC_ALL, saved)
        ds = pydicom.dcmread(f)
        ds.RescaleSlope = _ds([slopes[k]])
        ds.RescaleIntercept = _ds([intercepts[k]])
        ds.save_as(f)
        files.append(f)
    hu = stored.astype(np.float64) * slopes[:, None, None] + intercepts[:, None, None]
    return files, hu


def test_volume(shape_kji=(30, 36, 40), seed=0):
    """Stored values (about -500..700) that change along every axis, with noise,
    so a flipped, swapped or shifted axis shows."""
    rng = np.random.default_rng(seed)
    k, j, i = np.indices(shape_kji)
    return (k * 20 + j * 10 + i * 3 + rng.integers(0, 50, shape_kji) - 500).astype(np.int16)


def edit(files, **fields):
    """Set DICOM fields (keyword=value or keyword=callable(ds, k)) in ``files``."""
    import pydicom

    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        for key, value in fields.items():
            setattr(ds, key, value(ds, k) if callable(value) else value)
        ds.save_as(f)


def shift_positions(files, offsets_lps):
    """Move each slice's ImagePositionPatient by ``offsets_lps[k]`` (mm, LPS)."""
    edit(files, ImagePositionPatient=lambda ds, k: _ds(
        np.array([float(v) for v in ds.ImagePositionPatient]) + offsets_lps[k]).split("\\"))


def duplicate_slice(files, k):
    """A copy of slice ``k`` under another name (same position, another instance)."""
    import pydicom
    from pydicom.uid import generate_uid

    f = Path(files[k])
    dup = f.with_name(f.stem + "_copy.dcm")
    shutil.copy(f, dup)
    ds = pydicom.dcmread(dup)
    ds.SOPInstanceUID = generate_uid()
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.save_as(dup)
    return dup


def write_non_image(path, series_uid="1.2.826.0.1.3680043.2.1125.77.1"):
    """A DICOM object without pixel data (a Basic Text SR) at ``path``."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.88.11"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "SR"
    ds.SeriesInstanceUID = series_uid
    ds.StudyInstanceUID = series_uid + ".0"
    ds.save_as(path, enforce_file_format=True)
    return Path(path)
