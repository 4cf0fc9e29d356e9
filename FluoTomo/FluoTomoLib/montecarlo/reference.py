"""Stored Monte Carlo reference sets: what they are, how to read and write them, and
the fluorescence case.

The sets live in ``FluoTomoLib/montecarlo/data/`` (data/README.md: provenance).
Each is one JSON file: the medium, the volume and voxel size, the engine and its
version, photons, seeds, the command that regenerates it, and the tallies with their
standard errors.  ``independent_reflectance_n137.csv`` is not ours: it is an MCX-CL
run made outside this code (the README says by whom and how) against which our own
driver is checked.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import loads

DATA_DIR = Path(__file__).resolve().parent / "data"
INDEPENDENT_N137 = DATA_DIR / "independent_reflectance_n137.csv"

HALFSPACE_SETS = {
    # name: (mua, musp, n); the files hold their own regeneration commands
    "halfspace_n137": (0.01, 1.0, 1.37),
    "halfspace_n100": (0.01, 1.0, 1.0),
}
FLUORESCENCE_SET = "fluorescence_inclusion"


def set_path(name):
    return DATA_DIR / f"{name}.json"


def read_set(path):
    """A stored set (JSON) as a dict; one-line FluoInputError when it is not one."""
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("file not found", file=p)
    try:
        data = loads(p.read_text(), file=p)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise FluoInputError(f"not a JSON Monte Carlo set ({exc})", file=p) from None
    if not isinstance(data, dict) or data.get("kind") not in ("halfspace", "fluorescence"):
        raise FluoInputError("not a Monte Carlo set (needs kind 'halfspace' or 'fluorescence')",
                             file=p, field="kind",
                             value=data.get("kind") if isinstance(data, dict) else None)
    return data


def write_json_atomic(path, data):
    from fluoguide import atomic
    from fluoguide.jsonable import dumps

    return atomic.write_text(path, dumps(data, indent=1) + "\n", field="--out")


def halfspace_set(medium, merged, command):
    """The stored form of a merged half-space simulation."""
    return {
        "kind": "halfspace",
        "created": datetime.date.today().isoformat(),
        "command": command,
        **medium.metadata(),
        "rho_mm": medium.rho_mm.tolist(),
        "fluence_depths_mm": medium.fluence_depths_mm.tolist(),
        "fluence_rho_mm": medium.fluence_rho_mm.tolist(),
        "engine": merged["engine"], "engine_version": merged["engine_version"],
        "device": merged["device"], "photons": merged["photons"], "runs": merged["runs"],
        "seeds": merged["seeds"], "seconds": round(merged["seconds"], 1),
        "energy": merged["energy"], "R": merged["R"], "fluence": merged["fluence"],
    }


def medium_of_set(data):
    """The HalfSpace a stored half-space set was made with."""
    from FluoTomoLib.montecarlo.halfspace import HalfSpace

    med = data["medium"]
    return HalfSpace(med["mua_per_mm"], med["musp_per_mm"], med["n_inside"], g=med["g"],
                     size_mm=data["volume_mm"], voxel_mm=data["voxel_mm"], rho_mm=data["rho_mm"],
                     fluence_depths_mm=data["fluence_depths_mm"],
                     fluence_rho_mm=data["fluence_rho_mm"])


def merged_of_set(data):
    """A stored set in the form merge_halfspace returns."""
    return {k: data[k] for k in ("R", "fluence", "energy", "photons", "runs", "seeds", "seconds",
                                 "engine", "engine_version", "device")} | \
        {"exit_records_truncated": False}


def read_independent_reflectance(path=INDEPENDENT_N137):
    """The independent MCX-CL R(rho) (not made by this code): dict of arrays rho_mm,
    width_mm, R, se, se_cp, n_inside; from the CSV's header and rows."""
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("file not found", file=p)
    lines = [ln for ln in p.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    head = lines[0].split(",")
    try:
        rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    except ValueError as exc:
        raise FluoInputError(f"not numeric ({exc})", file=p) from None
    col = {h: rows[:, i] for i, h in enumerate(head)}
    return {"rho_mm": col["rho_mm"], "width_mm": col["annulus_width_mm"],
            "R": col["R_per_mm2"], "se": col["se_per_mm2"], "se_cp": col["se_cp_per_mm2"],
            "n_inside": float(col["n_inside"][0]), "photons": int(col["photons_total"][0])}


# ---------------------------------------------------------------- the fluorescence case

def fluorescence_case():
    """A buried fluorescent sphere under three optodes (each a source and a detector).

    Box 60 x 40 x 30 mm of tissue (1 mm voxels), top face z = 0 (RAS, tissue below);
    sphere of radius 4 mm centred 7 mm deep under the middle optode; optodes at
    x = -10, 0, 10 mm on the top face.  Excitation: mua 0.02 /mm background, 0.03 /mm
    in the sphere (the fluorophore absorbs), musp 1.0 /mm; emission: mua 0.01 /mm,
    musp 0.8 /mm everywhere; n 1.37; yield 0.005 /mm in the sphere, 0 elsewhere.
    """
    nx, ny, nz = 60, 40, 30
    h = 1.0
    M = np.eye(4)
    M[:3, 3] = [-(nx - 1) / 2 * h, -(ny - 1) / 2 * h, -(nz - 0.5) * h]   # k up, top face z=0
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ras = np.stack([i, j, k], -1) @ M[:3, :3].T * h + M[:3, 3]
    labels = np.ones((nz, ny, nx), np.uint8)
    centre = np.array([0.0, 0.0, -7.0])
    labels[np.linalg.norm(ras - centre, axis=-1) <= 4.0] = 2
    optodes = np.array([[-10.0, 0.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    return {
        "labels_kji": labels, "ijk_to_ras": M,
        "optics_x": {1: (0.02, 1.0, 1.37), 2: (0.03, 1.0, 1.37)},
        "optics_m": {1: (0.01, 0.8, 1.37), 2: (0.01, 0.8, 1.37)},
        "yield_per_label": {2: 0.005},
        "sources_ras": optodes, "detectors_ras": optodes,
        "inclusion_centre_mm": centre.tolist(), "inclusion_radius_mm": 4.0,
    }


def fluorescence_set(case, result, command):
    """The stored form of simulate_acquisition's result for the fluorescence case."""
    return {
        "kind": "fluorescence",
        "created": datetime.date.today().isoformat(),
        "command": command,
        "description": fluorescence_case.__doc__.strip().split("\n\n")[1].replace("\n", " "),
        "volume_mm": [float(s) for s in np.array(case["labels_kji"].shape[::-1])],
        "voxel_mm": 1.0, "g": result["g"],
        "optics_x": {str(k): list(v) for k, v in case["optics_x"].items()},
        "optics_m": {str(k): list(v) for k, v in case["optics_m"].items()},
        "yield_per_label": {str(k): v for k, v in case["yield_per_label"].items()},
        "sources_ras": np.asarray(case["sources_ras"]).tolist(),
        "detectors_ras": np.asarray(case["detectors_ras"]).tolist(),
        "detector_radius_mm": result["detector_radius_mm"],
        "engine": result["engine"], "engine_version": result["engine_version"],
        "device": result["device"], "photons_per_run": result["photons_per_run"],
        "runs": result["runs"], "seeds": result["seeds"], "seconds": round(result["seconds"], 1),
        "units": result["units"],
        "excitation": np.asarray(result["excitation"]).tolist(),
        "excitation_se": np.asarray(result["excitation_se"]).tolist(),
        "emission": np.asarray(result["emission"]).tolist(),
        "emission_se": np.asarray(result["emission_se"]).tolist(),
    }
