"""A CBCT turned into a label map by HU thresholds, without a person at the screen.

The web app's threshold tool makes one segment per HU range and
:meth:`FluoTomoLogic.segmentationToLabels` turns segment n into label n + 1,
a later segment winning where they overlap. :func:`threshold_labels` does the
same headless (``fluo segment``, ``FluoTomoLogic.segmentCbct``), and cleans
each label the way a person does by hand:

1. voxels with ``min_hu <= value <= max_hu`` (both ends included, as the
   threshold tool's);
2. the largest connected component only (voxels touching by a face:
   6-connectivity), so noise specks and detached objects (the table, a tube
   outside the tissue) are dropped;
3. its holes filled (enclosed background, in 3D), so an air bubble or a
   region of another label inside it belongs to it;
4. the labels painted in the order given, a later one over an earlier one
   (a bone or an inclusion inside the tissue stays itself).

Thresholds are written ``LABEL:MIN:MAX[,LABEL:MIN:MAX...]`` (HU; labels 1..255)
or as a JSON file ``{"LABEL": [MIN, MAX], ...}`` (:func:`parse_thresholds`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["parse_thresholds", "threshold_labels"]

#: bytes per CBCT voxel at the peak of :func:`threshold_labels` beside the CBCT:
#: the components' int32 labels, masks, the hole filling's temporaries and the
#: uint8 result (``fluo segment`` measured 16.7 B per voxel in all, reading
#: included, for 512 x 512 x 300 voxels: 1.3 GB over the imports)
BYTES_PER_VOXEL = 12

#: the syntax, as the refusals say it
SYNTAX = "LABEL:MIN:MAX[,...] (HU, labels 1..255) or a .json file {\"LABEL\": [MIN, MAX], ...}"


def _entry(label, lo, hi, field, file=None):
    try:
        lab = int(str(label).strip())
        if str(lab) != str(label).strip():
            raise ValueError
        lo, hi = float(lo), float(hi)
    except (TypeError, ValueError):
        raise FluoInputError(f"expected {SYNTAX}", file=file, field=field,
                             value=f"{label}:{lo}:{hi}") from None
    if not 1 <= lab <= 255:
        raise FluoInputError("label must be within 1..255 (0 is air)", file=file, field=field,
                             value=lab)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise FluoInputError("thresholds must be finite numbers [HU]", file=file,
                             field=f"{field}[{lab}]", value=(lo, hi))
    if not lo < hi:
        raise FluoInputError("the minimum must be below the maximum [HU]", file=file,
                             field=f"{field}[{lab}]", value=(lo, hi))
    return lab, lo, hi


def parse_thresholds(spec, field="thresholds"):
    """The thresholds of each label, in the order they are painted.

    Parameters
    ----------
    spec : str, path, dict or sequence
        ``"1:-500:3000,2:60:3000"`` (LABEL:MIN:MAX, HU), the path of a JSON
        file ``{"1": [-500, 3000], "2": [60, 3000]}``, such a dict, or a
        sequence of (label, min, max).
    field : str
        The option named in refusals.

    Returns
    -------
    list of (int, float, float)
        (label, min [HU], max [HU]); each label once.
    """
    from fluoguide.jsonable import read_json

    file = None
    entries = []
    if isinstance(spec, (str, Path)) and (isinstance(spec, Path) or spec.strip().lower()
                                          .endswith(".json")):
        file = Path(spec)
        spec = read_json(file, dict, field=field)
    if isinstance(spec, dict):
        for label, rng in spec.items():
            if not isinstance(rng, (list, tuple)) or len(rng) != 2 or any(
                    isinstance(v, bool) or not isinstance(v, (int, float)) for v in rng):
                raise FluoInputError(f"expected {SYNTAX}", file=file, field=f"{field}[{label}]",
                                     value=rng)
            entries.append(_entry(label, rng[0], rng[1], field, file))
    elif isinstance(spec, str):
        text = spec.strip()
        if not text:
            raise FluoInputError(f"expected {SYNTAX}", field=field, value=spec)
        for part in text.split(","):
            bits = part.strip().split(":")
            if len(bits) != 3:
                raise FluoInputError(f"expected {SYNTAX}", field=field, value=part.strip())
            entries.append(_entry(*bits, field))
    else:
        try:
            entries = [_entry(lab, lo, hi, field) for lab, lo, hi in spec]
        except (TypeError, ValueError):
            raise FluoInputError(f"expected {SYNTAX}", field=field, value=repr(spec)) from None
    if not entries:
        raise FluoInputError(f"no threshold given: expected {SYNTAX}", file=file, field=field)
    seen = set()
    for lab, _, _ in entries:
        if lab in seen:
            raise FluoInputError("label given twice", file=file, field=field, value=lab)
        seen.add(lab)
    return entries


def _largest_component(mask):
    """(the largest 6-connected component of ``mask``, number of components)."""
    from scipy import ndimage

    lab, n = ndimage.label(mask)
    if n <= 1:
        return mask, n
    counts = np.bincount(lab.ravel())
    counts[0] = 0
    return lab == int(np.argmax(counts)), n


def clean_mask(mask):
    """One segment the way :func:`threshold_labels` keeps each label: the
    largest 6-connected component of ``mask`` (K, J, I) bool, its holes filled.

    Returns
    -------
    mask : ndarray (K, J, I) bool
    info : dict
        ``components`` (before keeping the largest), ``dropped_voxels``
        (outside the largest), ``filled_voxels`` (holes filled).
    """
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    found = int(mask.sum())
    kept_mask, components = _largest_component(mask)
    kept = int(kept_mask.sum())
    filled = ndimage.binary_fill_holes(kept_mask)
    return filled, {"components": int(components), "dropped_voxels": found - kept,
                    "filled_voxels": int(filled.sum()) - kept}


def threshold_labels(hu_kji, thresholds, spacing_mm=(1.0, 1.0, 1.0), field="thresholds",
                     progress=None, cancel=None):
    """Label map of a CBCT: per label its HU range, its largest connected
    component, its holes filled; later labels painted over earlier ones.

    Parameters
    ----------
    hu_kji : ndarray (K, J, I)
        CBCT values [HU].
    thresholds : as :func:`parse_thresholds` takes
        Each label's range [HU], both ends included.
    spacing_mm : (3,) float
        Voxel size (I, J, K) [mm], for the volumes reported.
    field : str
        The option named in refusals.
    progress, cancel : optional
        ``fluoguide.progress`` callbacks (a fraction per label).

    Returns
    -------
    labels : ndarray (K, J, I) uint8
        0 air (no label), else the label.
    report : dict
        Per label (``"1"``, ...): ``min_hu``, ``max_hu``, ``in_range_voxels``
        (before cleaning), ``components`` (6-connected, before keeping the
        largest), ``dropped_voxels`` (outside the largest), ``filled_voxels``
        (holes filled), ``voxels`` and ``volume_mm3`` (the final map's, after
        later labels were painted over it).

    Raises
    ------
    FluoInputError
        A label whose range holds no voxel of the CBCT (naming the label and
        the range), a malformed threshold (:func:`parse_thresholds`).
    """

    from fluoguide.memory import check_fits
    from fluoguide.progress import check_cancel, report

    entries = parse_thresholds(thresholds, field)
    hu = np.asarray(hu_kji)
    if hu.ndim != 3:
        raise FluoInputError("CBCT must be 3D (K, J, I)", field="CBCT", value=hu.shape)
    check_fits(BYTES_PER_VOXEL * hu.size, f"segmenting the CBCT ({hu.size} voxels)",
               "crop or resample it first", field="CBCT")
    labels = np.zeros(hu.shape, np.uint8)
    out = {}
    for n, (lab, lo, hi) in enumerate(entries):
        check_cancel(cancel)
        report(progress, n / len(entries), f"label {lab}")
        mask = (hu >= lo) & (hu <= hi)
        found = int(mask.sum())
        if found == 0:
            raise FluoInputError(f"no voxel of the CBCT in this HU range (the CBCT holds "
                                 f"{float(hu.min()):g}..{float(hu.max()):g})",
                                 field=f"{field}[{lab}]", value=(lo, hi))
        mask, info = clean_mask(mask)
        labels[mask] = lab
        out[str(lab)] = {"min_hu": lo, "max_hu": hi, "in_range_voxels": found, **info}
    vox = float(np.prod(np.asarray(spacing_mm, float)))
    for lab, row in out.items():
        row["voxels"] = int(np.count_nonzero(labels == int(lab)))
        row["volume_mm3"] = row["voxels"] * vox
    report(progress, 1.0, "labels")
    return labels, out
