"""Label-map files: NRRD / NIfTI volumes, 3D Slicer segmentations (``.seg.nrrd``)
and an MRML scene's ``CBCTLabels``, read into RAS geometry; NRRD written; a
CBCT from a DICOM folder, a scene or a volume file (:func:`read_cbct`).

A label map is ``(labels_kji, spacing_mm, origin_mm, direction)``: the array
indexed [k, j, i] as Slicer's ``arrayFromVolume``, voxel size (I, J, K), the
RAS position of voxel (0, 0, 0) and the IJK-to-RAS direction cosines (columns
= I, J, K axes).  ITK files are LPS; their origin and directions are flipped
in x and y on the way in and out.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.library_errors import image_read_problem, image_write_problem, native_stderr_quiet

_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


def read_labelmap(path, node_name="CBCTLabels"):
    """(labels_kji, spacing_mm, origin_mm, direction) of a label-map file.

    ``path``: ``.nrrd`` / ``.nii`` / ``.nii.gz`` (integer voxels), ``.seg.nrrd``
    (segment n -> label n + 1) or ``.mrml`` (the node ``node_name``).
    """
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("label map file not found", file=p)
    if p.suffix == ".mrml":
        from fluoguide import mrml_io

        node = mrml_io.get_node(mrml_io.load_scene(p), node_name, "vtkMRMLLabelMapVolumeNode")
        geo = mrml_io.volume_geometry(node)
        return mrml_io.volume_array(node).copy(), geo["spacing"], geo["origin"], geo["direction"]
    import SimpleITK as sitk

    img = _read_image(p, "label map")
    arr = sitk.GetArrayFromImage(img)
    if "Segment0_ID" in img.GetMetaDataKeys():
        arr = _segments_to_labels(img, arr, p)
    if arr.ndim != 3 or not np.issubdtype(arr.dtype, np.integer):
        raise FluoInputError("label map must be a 3D integer image", file=p,
                             value=(arr.shape, str(arr.dtype)))
    return (arr,) + _geometry(img, p)


#: what reading a volume holds at its peak per byte of voxel data: ITK's image
#: and numpy's copy of it (GetArrayFromImage), measured 2.0x for a 134 MB
#: uint8 map; 3 leaves room for a segmentation's label conversion
READ_COPIES = 3.0


def _read_image(p, what):
    """The ITK image of ``p`` after its header is checked (fluoguide.volume_header:
    NaN or non-positive voxel sizes, non-finite origins, skewed directions, data
    longer or shorter than declared), and its size against the memory left."""
    import SimpleITK as sitk

    from fluoguide.volume_header import check_volume_file

    check_volume_file(p, copies=READ_COPIES)
    try:
        with native_stderr_quiet():     # the readers' own lines (MetaIO, NIfTI, HDF5)
            return sitk.ReadImage(str(p))
    except RuntimeError as exc:         # ITK's text names its build's files: say it in words
        problem, field = image_read_problem(exc)
        raise FluoInputError(f"cannot read {what} ({problem})", file=p, field=field) from None


def _geometry(img, p):
    """(spacing, origin, direction) of an ITK image in RAS, checked: finite,
    positive and orthonormal (whatever the format: the header checks know NRRD
    and NIfTI only)."""
    from fluoguide.volume_header import check_geometry

    spacing = np.array(img.GetSpacing(), float)
    origin = np.array(img.GetOrigin(), float)
    direction = np.array(img.GetDirection(), float)
    if len(spacing) != 3 or direction.size != 9:
        raise FluoInputError("volume must be 3D", file=p, value=len(spacing))
    check_geometry(spacing, origin, direction.reshape(3, 3), file=p)
    return spacing, _LPS_TO_RAS @ origin, _LPS_TO_RAS @ direction.reshape(3, 3)


def read_volume_nrrd(path):
    """(array_kji, spacing_mm, origin_mm, direction) of any 3D volume file that
    ITK reads (NRRD, NIfTI), in RAS: e.g. a ``yield.nrrd`` written by
    :func:`write_volume_nrrd`."""
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("volume file not found", file=p)
    import SimpleITK as sitk

    img = _read_image(p, "volume")
    arr = sitk.GetArrayFromImage(img)
    if arr.ndim != 3:
        raise FluoInputError("volume must be 3D", file=p, value=arr.shape)
    return (arr,) + _geometry(img, p)


def read_cbct(path, series=None, node_name="CBCT"):
    """A CBCT (or CT) volume in RAS, whatever it comes as: the one reader every
    command, panel and logic method that takes a CBCT calls.

    Parameters
    ----------
    path : path
        A folder of DICOM files (one series, or several and ``series``:
        :func:`fluoguide.dicom.read_dicom_series`), an MRML scene (``.mrml``:
        its scalar volume ``node_name``), or a volume file ITK reads (NRRD,
        NIfTI, MetaImage), its header checked (:mod:`fluoguide.volume_header`).
    series : str, optional
        The DICOM ``SeriesInstanceUID`` to read (a folder only).
    node_name : str
        The scene's CBCT node (``.mrml`` only).

    Returns
    -------
    tuple
        ``(array_kji, spacing_mm, origin_mm, direction, source)``: the values
        [HU] indexed [k, j, i], voxel size (I, J, K) [mm], the RAS position of
        voxel (0, 0, 0) [mm], the IJK-to-RAS direction cosines (columns) and
        a dict saying what was read (format, file or folder, series).
    """
    p = Path(path)
    if p.is_dir():
        from fluoguide.dicom import read_dicom_series

        vol = read_dicom_series(p, series=series)
        return vol.array_kji, vol.spacing_mm, vol.origin_mm, vol.direction, vol.meta()
    if series is not None:
        raise FluoInputError("a series is chosen in a DICOM folder only; this is a file",
                             file=p, field="series", value=str(series))
    if not p.exists():
        raise FluoInputError("CBCT not found (give a DICOM folder or a volume file)", file=p)
    if not p.is_file():
        raise FluoInputError("not a regular file or folder", file=p)
    if p.suffix == ".mrml":
        from fluoguide import mrml_io

        node = mrml_io.get_node(mrml_io.load_scene(p), node_name, "vtkMRMLScalarVolumeNode")
        geo = mrml_io.volume_geometry(node)
        return (mrml_io.volume_array(node), geo["spacing"], geo["origin"], geo["direction"],
                {"format": "MRML", "file": str(p), "node": node_name})
    try:
        with open(p, "rb") as fh:
            head = fh.read(132)
    except OSError as exc:
        raise FluoInputError(f"cannot read ({exc.strerror or exc})", file=p) from None
    if head[128:132] == b"DICM":
        raise FluoInputError("one DICOM file is one slice: give the folder that holds the "
                             "series", file=p)
    arr, spacing, origin, direction = read_volume_nrrd(p)
    if arr.dtype.kind not in "iuf":
        raise FluoInputError("CBCT voxels must be numbers", file=p, value=str(arr.dtype))
    return arr, spacing, origin, direction, {"format": p.name.partition(".")[2].upper() or "volume",
                                             "file": str(p)}


def _segments_to_labels(img, arr, path):
    """Label map from a 3D Slicer segmentation (.seg.nrrd): segment n -> label n+1.

    Slicer stores segments as label values in one or more layers (a 3D image,
    or a 4D one read as a multi-component image: one component per layer);
    ``Segment<n>_LabelValue`` and ``Segment<n>_Layer`` say where segment n
    lives.  Where segments of different layers overlap, the later one wins.
    """
    keys = set(img.GetMetaDataKeys())
    layers = arr if arr.ndim == 4 else arr[..., None]
    if arr.ndim not in (3, 4) or not np.issubdtype(arr.dtype, np.integer):
        raise FluoInputError("segmentation must be a 3D or 4D integer image", file=path,
                             value=(arr.shape, str(arr.dtype)))
    out = np.zeros(layers.shape[:3], dtype=np.int32)
    n = 0
    while f"Segment{n}_ID" in keys:
        try:
            value = int(img.GetMetaData(f"Segment{n}_LabelValue")) if \
                f"Segment{n}_LabelValue" in keys else 1
            layer = int(img.GetMetaData(f"Segment{n}_Layer")) if f"Segment{n}_Layer" in keys else 0
        except ValueError:
            raise FluoInputError("non-integer label value or layer", file=path,
                                 field=f"Segment{n}") from None
        if not 0 <= layer < layers.shape[3]:
            raise FluoInputError(f"layer does not exist ({layers.shape[3]} layers)", file=path,
                                 field=f"Segment{n}_Layer", value=layer)
        out[layers[..., layer] == value] = n + 1
        n += 1
    return out


def write_volume_nrrd(path, array_kji, spacing_mm, origin_mm, direction=None):
    """Write a 3D volume as NRRD (gzip) with its RAS geometry, atomically (a
    temporary name, then one rename)."""
    import SimpleITK as sitk

    p = Path(path)
    arr = np.ascontiguousarray(array_kji)
    if arr.ndim != 3:
        raise FluoInputError("volume must be 3D (K, J, I)", file=p, value=arr.shape)
    d = np.eye(3) if direction is None else np.asarray(direction, float)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in spacing_mm])
    img.SetOrigin((_LPS_TO_RAS @ np.asarray(origin_mm, float)).tolist())
    img.SetDirection((_LPS_TO_RAS @ d).ravel().tolist())
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}.nrrd")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        sitk.WriteImage(img, str(tmp), True)
        os.replace(tmp, p)
    except (OSError, RuntimeError) as exc:
        tmp.unlink(missing_ok=True)
        problem = (image_write_problem(exc) if isinstance(exc, RuntimeError)
                   else f"cannot write ({exc.strerror or exc})")
        raise FluoInputError(problem, file=p) from None
    return p
