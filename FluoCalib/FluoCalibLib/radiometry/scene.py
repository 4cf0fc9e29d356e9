"""Radiometric, illumination and laser calibrations in the MRML scene and in a
JSON calibration file (docs/scene.md): attributes ``FluoCalib.Radiometry``,
``FluoCalib.Illumination`` and ``FluoCalib.Laser`` of the ``FluoCalibration``
node (plain JSON: numbers, lists, the cone as ``IlluminationCone.to_dict``)."""

from __future__ import annotations

import json
from pathlib import Path

from fluoguide import mrml_io

from FluoCalibLib.geometry.scene import calibration_node

__all__ = ["RADIOMETRY_KEY", "ILLUMINATION_KEY", "LASER_KEY", "store_calibration",
           "load_calibration", "write_calibration_json"]

RADIOMETRY_KEY = "FluoCalib.Radiometry"
ILLUMINATION_KEY = "FluoCalib.Illumination"
LASER_KEY = "FluoCalib.Laser"


def store_calibration(scene, key, doc):
    """Put a JSON document on the ``FluoCalibration`` node under ``key``."""
    mrml_io.set_json_attribute(calibration_node(scene), key, doc)


def load_calibration(scene, key):
    node = mrml_io.get_node(scene, "FluoCalibration", required=False)
    return None if node is None else mrml_io.get_json_attribute(node, key)


def write_calibration_json(path, key, doc):
    """Merge ``{key: doc}`` into a calibration JSON file (written atomically);
    ``FluoCalibLogic.loadCalibrationJson`` reads it back onto the scene."""
    path = Path(path)
    data = {}
    if path.is_file():
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError:
            data = {}
    data[key.split(".", 1)[1]] = doc
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
    return path
