"""Reading the illumination and laser calibration folders, checked.

A folder holds a JSON description (``illumination.json``: ``camera``,
``phantom_to_camera``, ``rd``, ``images``; ``laser.json``: ``camera``,
``camera_to_tracker``, ``laser_to_tracker``, ``phantom_to_tracker``,
``images``; either may add ``truth`` for a synthetic set) and the images it
lists. ``synth-light`` writes such folders (``synthetic.write_*_set``).
"""

from __future__ import annotations

from pathlib import Path

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import read_json

__all__ = ["ILLUMINATION_KEYS", "LASER_KEYS", "read_dataset"]

ILLUMINATION_KEYS = ("camera", "phantom_to_camera", "rd")
LASER_KEYS = ("camera", "camera_to_tracker", "laser_to_tracker", "phantom_to_tracker")


def read_dataset(folder, name, required=()):
    """(images as float arrays, description dict) of ``folder/name``.

    Raises FluoInputError for a missing folder or file, bad JSON, a missing key
    or an unreadable image.
    """
    from FluoCalibLib.radiometry.camera_response import _read_image
    from fluoguide import atomic
    from fluoguide.paths import inside

    folder = Path(folder)
    if not folder.is_dir():
        raise FluoInputError("folder not found", field="folder", value=str(folder))
    atomic.recover(folder)   # finish a write a crash interrupted: the new set, whole
    p = folder / name
    if not p.is_file():
        raise FluoInputError(f"folder needs {name}", file=p)
    doc = read_json(p)
    for key in required:
        if key not in doc:
            raise FluoInputError("missing key", file=p, field=key)
    if not isinstance(doc.get("images"), list) or not doc["images"]:
        raise FluoInputError("needs a non-empty 'images' list", file=p, field="images")
    # a manifest names files in its own folder, never ../ or absolute paths
    images = [_read_image(inside(folder, f, file=p, field=f"images[{i}]", given=True))
              .astype(float)
              for i, f in enumerate(doc["images"])]
    return images, doc
