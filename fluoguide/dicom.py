"""DICOM image series (a CBCT or CT exported one slice per file) read into RAS.

:func:`read_dicom_series` reads one series of a folder with its geometry kept
exactly and its values in Hounsfield units, and refuses, with one line that
names the folder or file, the DICOM keyword and the value, every series it
could not put together without guessing:

- several series in the folder and none chosen (the series are listed with
  their description and slice count; choose one by its SeriesInstanceUID);
- a file that is not DICOM, or a DICOM object that is not an image (no
  ``PixelData``: a structure set, a report, a presentation state);
- a multi-frame or colour image, a missing geometry field;
- slices of different size, pixel spacing or orientation
  (``ImageOrientationPatient`` differing between slices);
- two slices at one position, a missing slice (a gap of about twice the
  spacing or more), non-uniform slice spacing;
- gantry tilt: ``GantryDetectorTilt`` not 0, or slice positions that do not
  lie along the slice normal (sheared stacks).

Geometry. DICOM positions are in the patient's LPS frame, the project's
volumes in RAS (docs/scene.md): x and y change sign on the way in. Voxel
(i, j, k) is column i, row j of the k-th slice after sorting by the position's
projection on the slice normal n = r x c (r, c: the row and column direction
cosines of ``ImageOrientationPatient``): the I axis is r, the J axis c, the K
axis n; the spacing is (``PixelSpacing[1]``, ``PixelSpacing[0]``, the distance
between slice positions) [mm]: ``PixelSpacing`` is (row spacing, column
spacing), the distance between rows first; the origin is the first sorted
slice's ``ImagePositionPatient``.

Values. ``stored * RescaleSlope + RescaleIntercept`` per slice (each slice's
own values; slope 1 and intercept 0 when absent) [HU]. The volume is int16
when every slope and intercept is an integer and the values fit, else float32.

Tolerances. Positions and spacings agree when they differ by at most
:data:`POSITION_TOL_MM` or :data:`SPACING_TOL_FRACTION` of the slice spacing,
whichever is larger; direction cosines when they differ by at most
:data:`COSINE_TOL`.

Pixel data are decoded by pydicom (uncompressed and RLE transfer syntaxes);
a slice pydicom cannot decode (JPEG, JPEG 2000 without a plug-in) is read
through SimpleITK's GDCM instead, which applies the rescale itself.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["DicomVolume", "SeriesInfo", "list_series", "read_dicom_series", "POSITION_TOL_MM",
           "SPACING_TOL_FRACTION", "COSINE_TOL"]

#: positions and spacings agreeing within this [mm] (or the fraction below) are equal
POSITION_TOL_MM = 0.01
#: ... or within this fraction of the slice spacing, whichever is larger
SPACING_TOL_FRACTION = 0.01
#: direction cosines agreeing within this are equal; a cosine pair further than
#: this from orthonormal is refused
COSINE_TOL = 1e-5
#: the LPS-to-RAS flip (x and y change sign)
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])
#: bytes held per voxel at the peak of reading: the int32 (or float32) slice
#: stack and the int16 result (measured 6.1 B per voxel over the imports for
#: 512 x 512 x 300 voxels: 0.48 GB)
_BYTES_PER_VOXEL = 8


@dataclass
class SeriesInfo:
    """One series of a folder: its UID, description and files (unsorted)."""

    uid: str
    description: str
    files: list = field(default_factory=list)

    def summary(self):
        """``UID (description, N slices)``, as the refusals list it."""
        what = f"{self.description}, " if self.description else ""
        n = len(self.files)
        return f"{self.uid} ({what}{n} slice{'s' if n != 1 else ''})"


@dataclass
class DicomVolume:
    """A DICOM series read into the project's volume convention.

    Attributes
    ----------
    array_kji : ndarray (K, J, I)
        Values [HU]: int16, or float32 when the rescale is not integral.
    spacing_mm : ndarray (3,)
        Voxel size along I, J, K [mm].
    origin_mm : ndarray (3,)
        RAS position of voxel (0, 0, 0) [mm].
    direction : ndarray (3, 3)
        IJK-to-RAS direction cosines (columns: the I, J, K axes).
    series_uid, description : str
        ``SeriesInstanceUID`` and ``SeriesDescription``.
    modality : str
        ``Modality`` of the first slice ("CT", ...).
    files : list of Path
        The slice files in slice order (k = 0 first).
    """

    array_kji: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    series_uid: str
    description: str
    modality: str
    files: list

    def meta(self):
        """What the volume came from, as JSON-ready numbers and strings."""
        return {"format": "DICOM", "folder": str(self.files[0].parent),
                "series_uid": self.series_uid, "series_description": self.description,
                "modality": self.modality, "slices": len(self.files)}


def _dcmread(path, **kw):
    import pydicom

    with warnings.catch_warnings():
        # pydicom warns about values that break the standard's VR rules (a DS
        # longer than 16 characters); the checks below judge what matters
        warnings.simplefilter("ignore")
        return pydicom.dcmread(str(path), **kw)


def _headers(folder):
    """[(path, dataset)] of every file directly in ``folder`` (sorted by name),
    pixel data deferred (read when the series is chosen). Hidden files
    (a leading dot) are skipped; a file that is not DICOM is refused."""
    from pydicom.errors import InvalidDicomError

    folder = Path(folder)
    if not folder.is_dir():
        raise FluoInputError("DICOM folder not found", file=folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise FluoInputError("no files in the DICOM folder", file=folder)
    out = []
    for p in files:
        try:
            ds = _dcmread(p, defer_size=1024)
        except InvalidDicomError:
            raise FluoInputError("not a DICOM file (no DICM preamble); the folder must hold "
                                 "the series' files only", file=p) from None
        except OSError as exc:
            raise FluoInputError(f"cannot read ({exc.strerror or exc})", file=p) from None
        except Exception as exc:       # pydicom's parser on a damaged file: any error type
            raise FluoInputError(f"damaged DICOM file ({type(exc).__name__})", file=p) from None
        out.append((p, ds))
    return out


def _is_image(ds):
    return "PixelData" in ds or "FloatPixelData" in ds or "DoubleFloatPixelData" in ds


def _check_image_object(p, ds):
    """Refuse a DICOM object that is no single-frame grey-scale image."""
    if not _is_image(ds):
        sop = ds.get("SOPClassUID")
        name = getattr(sop, "name", None) or (str(sop) if sop else "unknown SOP class")
        raise FluoInputError(f"not an image ({name}); the folder must hold the series' image "
                             "files only", file=p, field="PixelData")
    frames = ds.get("NumberOfFrames")
    if frames is not None and int(frames) > 1:
        raise FluoInputError("multi-frame images are not read: export the series one slice "
                             "per file", file=p, field="NumberOfFrames", value=int(frames))
    spp = ds.get("SamplesPerPixel", 1)
    if int(spp) != 1:
        raise FluoInputError("not a grey-scale image", file=p, field="SamplesPerPixel",
                             value=int(spp))


def list_series(folder):
    """The image series of a DICOM folder.

    Parameters
    ----------
    folder : path
        A folder holding DICOM files (subfolders are not read).

    Returns
    -------
    list of SeriesInfo
        One per ``SeriesInstanceUID``, in order of their first file's name;
        ``files`` hold (path, dataset) pairs, pixel data not yet read.

    Raises
    ------
    FluoInputError
        A file that is not DICOM, a DICOM object that is not an image, an
        image without ``SeriesInstanceUID``.
    """
    series = {}
    for p, ds in _headers(folder):
        _check_image_object(p, ds)
        uid = str(ds.get("SeriesInstanceUID", "") or "").strip()
        if not uid:
            raise FluoInputError("image without a series", file=p, field="SeriesInstanceUID")
        info = series.get(uid)
        if info is None:
            desc = str(ds.get("SeriesDescription", "") or "").strip()
            info = series[uid] = SeriesInfo(uid, desc)
        info.files.append((p, ds))
    return list(series.values())


def _choose(folder, series, uid):
    if uid is not None:
        uid = str(uid).strip()
        for s in series:
            if s.uid == uid:
                return s
        listed = "; ".join(s.summary() for s in series)
        raise FluoInputError(f"no such series in the folder (it holds: {listed})", file=folder,
                             field="series", value=uid)
    if len(series) > 1:
        listed = "; ".join(s.summary() for s in series)
        raise FluoInputError(f"{len(series)} series in the folder, choose one by its "
                             f"SeriesInstanceUID: {listed}", file=folder, field="series")
    return series[0]


def _numbers(p, ds, keyword, n):
    """The ``n`` numbers of a multi-valued field, checked finite."""
    value = ds.get(keyword)
    if value is None:
        raise FluoInputError("missing", file=p, field=keyword)
    try:
        values = [float(v) for v in (value if n > 1 else [value])]
    except (TypeError, ValueError):
        raise FluoInputError(f"expected {n} numbers", file=p, field=keyword,
                             value=str(value)) from None
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise FluoInputError(f"expected {n} finite numbers", file=p, field=keyword,
                             value=values)
    return np.array(values)


def _rescale(p, ds):
    if "ModalityLUTSequence" in ds:
        raise FluoInputError("a modality look-up table is not applied: export the series with "
                             "RescaleSlope and RescaleIntercept", file=p,
                             field="ModalityLUTSequence")
    slope = _numbers(p, ds, "RescaleSlope", 1)[0] if "RescaleSlope" in ds else 1.0
    intercept = _numbers(p, ds, "RescaleIntercept", 1)[0] if "RescaleIntercept" in ds else 0.0
    if slope == 0:
        raise FluoInputError("must not be 0", file=p, field="RescaleSlope", value=slope)
    return slope, intercept


def _geometry(folder, files):
    """Sorted files and (spacing, origin, direction) in LPS, every check made."""
    first_p, first = files[0]
    iop = _numbers(first_p, first, "ImageOrientationPatient", 6)
    r, c = iop[:3], iop[3:]
    if (abs(np.linalg.norm(r) - 1) > COSINE_TOL or abs(np.linalg.norm(c) - 1) > COSINE_TOL
            or abs(r @ c) > COSINE_TOL):
        raise FluoInputError("row and column directions are not orthonormal", file=first_p,
                             field="ImageOrientationPatient", value=iop.tolist())
    normal = np.cross(r, c)
    normal /= np.linalg.norm(normal)
    pixel = _numbers(first_p, first, "PixelSpacing", 2)
    if np.any(pixel <= 0):
        raise FluoInputError("must be positive [mm]", file=first_p, field="PixelSpacing",
                             value=pixel.tolist())
    rows, cols = int(first.get("Rows", 0) or 0), int(first.get("Columns", 0) or 0)
    if rows < 1 or cols < 1:
        raise FluoInputError("image without rows or columns", file=first_p, field="Rows",
                             value=(rows, cols))
    positions = []
    for p, ds in files:
        tilt = ds.get("GantryDetectorTilt")
        if tilt is not None and str(tilt).strip() != "" and abs(float(tilt)) > 1e-6:
            raise FluoInputError("gantry tilt: slices are not perpendicular to their stacking "
                                 "axis; resample the series without tilt first", file=p,
                                 field="GantryDetectorTilt", value=float(tilt))
        if np.max(np.abs(_numbers(p, ds, "ImageOrientationPatient", 6) - iop)) > COSINE_TOL:
            raise FluoInputError(f"differs between slices (first slice {first_p.name}: "
                                 f"{iop.tolist()})", file=p, field="ImageOrientationPatient",
                                 value=_numbers(p, ds, "ImageOrientationPatient", 6).tolist())
        if np.max(np.abs(_numbers(p, ds, "PixelSpacing", 2) - pixel)) > 1e-6 * max(pixel):
            raise FluoInputError(f"differs between slices (first slice {first_p.name}: "
                                 f"{pixel.tolist()})", file=p, field="PixelSpacing",
                                 value=_numbers(p, ds, "PixelSpacing", 2).tolist())
        if (int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)) != (rows, cols):
            raise FluoInputError(f"image size differs between slices (first slice "
                                 f"{first_p.name}: {rows} x {cols})", file=p, field="Rows",
                                 value=(int(ds.get("Rows", 0) or 0),
                                        int(ds.get("Columns", 0) or 0)))
        positions.append(_numbers(p, ds, "ImagePositionPatient", 3))
    positions = np.array(positions)
    if len(files) < 2:
        raise FluoInputError("one slice is not a volume (a CBCT series has one file per "
                             "slice)", file=folder, field="ImagePositionPatient")
    along = positions @ normal
    order = np.argsort(along, kind="stable")
    files = [files[i] for i in order]
    positions, along = positions[order], along[order]
    steps = np.diff(along)
    spacing = float(np.median(steps))
    tol = max(POSITION_TOL_MM, SPACING_TOL_FRACTION * spacing)
    dup = np.flatnonzero(steps <= tol)
    if dup.size:
        i = int(dup[0])
        raise FluoInputError(f"two slices at one position ({files[i][0].name} and "
                             f"{files[i + 1][0].name}, {steps[i]:.4g} mm apart along the "
                             f"slice normal)", file=files[i + 1][0], field="ImagePositionPatient",
                             value=positions[i + 1].tolist())
    off = np.flatnonzero(np.abs(steps - spacing) > tol)
    if off.size:
        i = int(off[np.argmax(np.abs(steps[off] - spacing))])
        ratio = steps[i] / spacing
        if ratio > 1.5 and abs(ratio - round(ratio)) * spacing <= tol:
            problem = (f"missing slice: {steps[i]:.4g} mm between {files[i][0].name} and "
                       f"{files[i + 1][0].name}, {round(ratio) - 1} slice(s) of "
                       f"{spacing:.4g} mm missing")
        else:
            problem = (f"slice spacing is not uniform: {steps[i]:.4g} mm between "
                       f"{files[i][0].name} and {files[i + 1][0].name}, {spacing:.4g} mm "
                       f"elsewhere (tolerance {tol:.3g} mm)")
        raise FluoInputError(problem, file=folder, field="ImagePositionPatient",
                             value=positions[i + 1].tolist())
    # every position on the line through the first along the normal: a sheared
    # stack (gantry tilt written into the positions) has in-plane offsets
    rel = positions - positions[0]
    inplane = rel - np.outer(rel @ normal, normal)
    shift = np.linalg.norm(inplane, axis=1)
    ptol = max(POSITION_TOL_MM, SPACING_TOL_FRACTION * float(min(pixel)))
    if shift.max() > ptol:
        i = int(np.argmax(shift))
        raise FluoInputError(f"slice positions are not along the slice normal (gantry tilt or "
                             f"a sheared stack: {shift[i]:.4g} mm off in the slice plane at "
                             f"{files[i][0].name}); resample the series without tilt first",
                             file=folder, field="ImagePositionPatient",
                             value=positions[i].tolist())
    spacing_ijk = np.array([pixel[1], pixel[0], spacing])
    direction = np.column_stack([r, c, normal])
    return files, spacing_ijk, positions[0], direction, (rows, cols)


def _slice_values(p, ds):
    """One slice's values [HU] as float64: pydicom's decoding and the slice's
    rescale, else (a transfer syntax pydicom cannot decode) SimpleITK's GDCM,
    which applies the rescale itself."""
    try:
        # read afresh and let go: the header pass's dataset would keep the
        # pixel bytes and the decoded array of every slice (3x the volume)
        full = _dcmread(p)
    except OSError as exc:
        raise FluoInputError(f"cannot read ({exc.strerror or exc})", file=p) from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            stored = full.pixel_array
        except (NotImplementedError, RuntimeError, ValueError, AttributeError):
            stored = None
    del full
    if stored is not None:
        slope, intercept = _rescale(p, ds)
        return stored.astype(np.float64) * slope + intercept
    import SimpleITK as sitk

    from fluoguide.library_errors import image_read_problem, native_stderr_quiet

    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:
        with native_stderr_quiet():
            img = sitk.ReadImage(str(p), sitk.sitkFloat64)
    except RuntimeError as exc:
        problem, _ = image_read_problem(exc)
        raise FluoInputError(f"cannot decode the pixel data ({problem})", file=p,
                             field="TransferSyntaxUID",
                             value=getattr(ts, "name", None) or str(ts)) from None
    arr = sitk.GetArrayFromImage(img)
    return arr.reshape(arr.shape[-2:])


def read_dicom_series(folder, series=None):
    """Read one DICOM image series of a folder into RAS, values in HU.

    Parameters
    ----------
    folder : path
        A folder of DICOM files, one slice per file (subfolders are not read;
        hidden files are skipped).
    series : str, optional
        The ``SeriesInstanceUID`` to read; needed when the folder holds
        several series (they are listed in the refusal).

    Returns
    -------
    DicomVolume
        Values [HU], spacing [mm], RAS origin [mm] and direction cosines.

    Raises
    ------
    FluoInputError
        One line naming the folder or file, the DICOM keyword and the value:
        see the module's docstring for each refusal.
    """
    from fluoguide.memory import check_fits
    from fluoguide.volume_header import check_geometry

    folder = Path(folder)
    chosen = _choose(folder, list_series(folder), series)
    files, spacing, origin_lps, direction_lps, (rows, cols) = _geometry(folder, chosen.files)
    check_fits(_BYTES_PER_VOXEL * rows * cols * len(files),
               f"reading the DICOM series ({cols} x {rows} x {len(files)} voxels)",
               "crop or resample it first", file=folder)
    # integral rescales (the headers say) fill an int32 stack, made int16 at the
    # end when the values fit; any other goes to float32
    rescales = [_rescale(p, ds) for p, ds in files]
    integral = all(float(a).is_integer() and float(b).is_integer() for a, b in rescales)
    stack = np.empty((len(files), rows, cols), np.int32 if integral else np.float32)
    i32 = np.iinfo(np.int32)
    for k, (p, ds) in enumerate(files):
        values = _slice_values(p, ds)
        if values.shape != (rows, cols):
            raise FluoInputError(f"pixel data of {values.shape[0]} x {values.shape[1]} pixels, "
                                 f"the header says {rows} x {cols}", file=p, field="PixelData")
        if not np.all(np.isfinite(values)):
            raise FluoInputError("non-finite voxel values", file=p, field="PixelData")
        if stack.dtype == np.int32 and (values.min() < i32.min or values.max() > i32.max
                                        or not np.array_equal(values, np.round(values))):
            stack = stack.astype(np.float32)
        stack[k] = values
    i16 = np.iinfo(np.int16)
    if stack.dtype == np.int32 and stack.min() >= i16.min and stack.max() <= i16.max:
        arr = stack.astype(np.int16)
    else:
        arr = stack.astype(np.float32, copy=False)
    del stack
    origin = LPS_TO_RAS @ origin_lps
    direction = LPS_TO_RAS @ direction_lps
    check_geometry(spacing, origin, direction, file=folder)
    first = files[0][1]
    return DicomVolume(arr, spacing, origin, direction, chosen.uid, chosen.description,
                       str(first.get("Modality", "") or ""), [p for p, _ in files])
