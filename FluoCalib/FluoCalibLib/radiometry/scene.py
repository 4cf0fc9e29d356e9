"""Radiometric, illumination and laser calibrations in the MRML scene and in a
JSON calibration file (docs/scene.md): attributes ``FluoCalib.Radiometry``,
``FluoCalib.Illumination`` and ``FluoCalib.Laser`` of the ``FluoCalibration``
node (plain JSON: numbers, lists, the cone as ``IlluminationCone.to_dict``)."""

from __future__ import annotations

import json
from pathlib import Path

from fluoguide import atomic, mrml_io
from fluoguide.jsonable import read_json, to_jsonable

from FluoCalibLib.geometry.scene import calibration_node

__all__ = ["RADIOMETRY_KEY", "ILLUMINATION_KEY", "LASER_KEY", "store_calibration",
           "load_calibration", "write_calibration_json"]

RADIOMETRY_KEY = "FluoCalib.Radiometry"
ILLUMINATION_KEY = "FluoCalib.Illumination"
LASER_KEY = "FluoCalib.Laser"


def store_calibration(scene, key, doc, node=None):
    """Put a JSON document under ``key`` on ``node`` (default: ``FluoCalibration``)."""
    mrml_io.set_json_attribute(calibration_node(scene, node), key, doc)


def load_calibration(scene, key, node=None):
    """The document under ``key`` of ``node`` (default: ``FluoCalibration``), or None."""
    if node is None:
        node = mrml_io.get_node(scene, "FluoCalibration", required=False)
    return None if node is None else mrml_io.get_json_attribute(node, key)


def write_calibration_json(path, key, doc):
    """Merge ``{key: doc}`` into a calibration JSON file (written atomically);
    ``FluoCalibLogic.loadCalibrationJson`` reads it back onto the scene.

    An existing file that is not a readable JSON object is refused, never
    overwritten: it holds the user's other calibrations.
    """
    path = Path(path)
    data = read_json(path, field="--calibration") if path.exists() else {}
    data[key.split(".", 1)[1]] = doc
    atomic.write_text(path, json.dumps(to_jsonable(data), indent=1, allow_nan=False))
    return path
