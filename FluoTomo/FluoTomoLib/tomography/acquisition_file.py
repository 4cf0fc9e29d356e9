"""An acquisition folder a person can write by hand, and the tracked-frames route.

``ACQ/acquisition.json`` (all coordinates RAS mm, the label map's space)::

    {
      "format": "fluoguide-acquisition", "version": 1,
      "units": "1/mm^2",
      "sources_ras_mm": "sources.csv",
      "detectors_ras_mm": "detectors.csv",
      "data": "data.csv",
      "laser_power_w": 0.01
    }

- ``sources_ras_mm`` / ``detectors_ras_mm``: a CSV file (one ``x,y,z`` per line, a
  header line allowed) or an inline list of ``[x, y, z]``: points on the tissue
  surface where the laser enters and where the camera reads.
- ``data``: one row per source, one column per detector (CSV, or an inline list of
  lists); an unused pair is ``-`` in the CSV or ``null`` inline.  NaN and
  infinity are refused, never read as "unused".
- ``units``: ``"1/mm^2"`` boundary fluence per watt of laser power (what the model
  predicts; the default); ``"W/mm^2"`` boundary fluence, divided by
  ``laser_power_w`` (one number, or one per source); ``"counts"`` camera ROI
  means [ADU], turned into fluence per watt with ``camera_gain_adu_per_radiance``
  (G, ADU per W/mm^2/sr at ``reference_exposure_s``), ``camera_offset_adu``,
  ``laser_power_w`` and optionally ``exposure_s`` (one number or one per source:
  counts above the offset scale with exposure).
- ``exclude_mm`` (optional): pairs closer than this to their source are left out
  (diffusion is not valid there), on top of those marked unused.
- ``noise_pct`` (optional): the data's relative noise, one standard deviation
  per measurement [%] (shot and read noise of the ROI means, laser power
  jitter): the reconstruction tests its fit against it and widens its intervals
  when the model explains the data worse than this noise would allow. A
  simulated acquisition states its own (``simulation.noise_pct``).

The raw route, ``"kind": "tracked-frames"`` (what the cylinder-tube demo
records): camera frames of the emission light, one per laser position, the
tracked laser tool poses and camera pose, and the calibration::

    {
      "format": "fluoguide-acquisition", "version": 1, "kind": "tracked-frames",
      "frames": "frames.npy",                    (S, H, W) counts [ADU]
      "laser_poses": "laser_poses.json",         S 4x4 LaserToolToRAS (tracked)
      "laser_beam": {"origin_tool_mm": [0, 0, 0], "direction_tool": [0, 0, 1]},
      "camera": {"fx": .., "fy": .., "cx": .., "cy": .., "dist": [..], "width": .., "height": ..},
      "camera_to_ras": [[..4x4..]],
      "camera_gain_adu_per_radiance": 1.2e7, "camera_offset_adu": 100,
      "laser_power_w": 0.01,
      "detector_factor": 2, "exclude_mm": 3.0, "roi_area_mm2": 1.0
    }

Sources are where the tracked beams meet the label map's tissue surface;
detectors are the sources plus ``detector_factor - 1`` points between
neighbours (dropped onto the surface along the beams); every pixel is cast
onto the surface from the tracked camera pose and the unsaturated pixels in a
``roi_area_mm2`` disc around each detector are averaged; counts become fluence
per watt as above (docs/physics.md section 8.2).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

FORMAT = "fluoguide-acquisition"
UNITS = ("1/mm^2", "W/mm^2", "counts")
_FLUENCE_KEYS = {"format", "version", "kind", "units", "sources_ras_mm", "detectors_ras_mm",
                 "data", "laser_power_w", "exposure_s", "reference_exposure_s",
                 "camera_gain_adu_per_radiance", "camera_offset_adu", "exclude_mm", "comment",
                 "simulation", "noise_pct"}
_RAW_KEYS = {"format", "version", "kind", "frames", "laser_poses", "laser_beam", "camera",
             "camera_to_ras", "camera_gain_adu_per_radiance", "camera_offset_adu",
             "laser_power_w", "detector_factor", "exclude_mm", "roi_area_mm2", "saturation_adu",
             "comment", "simulation"}


@dataclass
class Acquisition:
    """Sources, detectors and data, ready for a reconstruction.

    Attributes
    ----------
    sources_ras_mm : (S, 3) surface points where the light enters [RAS mm]
    detectors_ras_mm : (D, 3) surface points read by the camera [RAS mm]
    data : (S, D) boundary fluence per watt of laser power [1/mm^2]; 0 where unused
    mask : (S, D) bool, the pairs measured and used
    units : the units the data were given in (converted to 1/mm^2 here)
    meta : anything else the file said (``simulation``: how it was simulated)
    source : the file the data came from (named in messages about the data)
    files : the files the points came from, ``{"sources": .., "detectors": ..}``,
        as the user gave them (a message about a point names its CSV, not the data's)
    """

    sources_ras_mm: np.ndarray
    detectors_ras_mm: np.ndarray
    data: np.ndarray
    mask: np.ndarray
    units: str = "1/mm^2"
    meta: dict = field(default_factory=dict)
    source: str | None = None
    files: dict = field(default_factory=dict)

    def file_of(self, what):
        """The file to name in a message about ``what`` ("sources", "detectors",
        "data"): its own CSV when it had one, else the acquisition's file."""
        return self.files.get(what, self.source)

    def __post_init__(self):
        f = self.source
        self.sources_ras_mm = _points(self.sources_ras_mm, f, "sources_ras_mm")
        self.detectors_ras_mm = _points(self.detectors_ras_mm, f, "detectors_ras_mm")
        S, D = len(self.sources_ras_mm), len(self.detectors_ras_mm)
        data = np.asarray(self.data, float)
        mask = np.asarray(self.mask, bool)
        if data.shape != (S, D):
            raise FluoInputError(f"data must be one row per source and one column per detector "
                                 f"({S} x {D})", file=f, field="data", value=list(data.shape))
        if mask.shape != (S, D):
            raise FluoInputError("mask must match the data", file=f, field="mask",
                                 value=list(mask.shape))
        bad = mask & ~np.isfinite(data)
        if np.any(bad):
            s, d = np.argwhere(bad)[0]
            raise FluoInputError("must be a finite number (mark an unused pair with '-' or null)",
                                 file=f, field=f"data[{s}][{d}]", value=float(data[s, d]))
        if not mask.any():
            raise FluoInputError("no source-detector pair is used", file=f, field="data")
        if not np.any(data[mask] != 0):
            raise FluoInputError("every used measurement is zero: nothing to reconstruct",
                                 file=f, field="data")
        self.data = np.where(mask, data, 0.0)
        self.mask = mask

    def noise_pct(self):
        """The data's stated relative noise [%] (one SD per measurement): the
        acquisition file's ``noise_pct``, else its simulation's; None when neither
        says, or says 0 (the reconstruction then judges its fit from the residual
        alone)."""
        for v in (self.meta.get("noise_pct"), (self.meta.get("simulation") or {}).get("noise_pct")):
            if v is not None:
                # 0: noise-free data (a simulation without noise): no noise model
                return float(v) if float(v) > 0 else None
        return None

    @property
    def n_measurements(self):
        return int(self.mask.sum())

    def y(self):
        """The used measurements, source-major (row s*D + d of the model's data)."""
        return self.data[self.mask]

    def check_for_log(self):
        """A log data model needs every used measurement > 0."""
        bad = self.mask & (self.data <= 0)
        if np.any(bad):
            s, d = np.argwhere(bad)[0]
            raise FluoInputError(f"{int(bad.sum())} measurements are <= 0: a log data model "
                                 "needs positive data (mark those pairs unused, or use the "
                                 "linear data model)", file=self.source, field=f"data[{s}][{d}]",
                                 value=float(self.data[s, d]))


def _points(value, file, field):
    p = np.asarray(value, float) if not isinstance(value, np.ndarray) else value.astype(float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise FluoInputError("needs a list of [x, y, z] points (RAS mm)", file=file, field=field,
                             value=list(np.shape(p)))
    if not np.all(np.isfinite(p)):
        i = int(np.flatnonzero(~np.all(np.isfinite(p), axis=1))[0])
        raise FluoInputError("coordinates must be finite", file=file, field=f"{field}[{i}]",
                             value=p[i].tolist())
    return p


def _is_number(text):
    try:
        float(text)
        return True
    except ValueError:
        return False


def read_text_file(path, field):
    """(Path, text) of a UTF-8 text file; a missing or unreadable one refused in one
    line naming it and ``field`` (FluoInputError)."""
    p = Path(path)
    if not p.is_file():
        raise FluoInputError("file not found", file=p, field=field)
    try:
        return p, p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FluoInputError(f"cannot read ({getattr(exc, 'strerror', None) or exc})", file=p,
                             field=field) from None


def _read_csv_rows(path, field, allow_unused=False):
    """Rows of numbers from a CSV file (commas, semicolons or spaces; ``#``
    comments and one header line allowed).  ``-`` is an unused value (NaN in
    the result, with the mask) when ``allow_unused``."""
    p, text = read_text_file(path, field)
    rows, used = [], []
    header_seen = False
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [v for v in line.replace(";", ",").replace("\t", ",").replace(" ", ",").split(",")
                 if v.strip()]
        vals, ok = [], []
        try:
            for v in parts:
                if allow_unused and v.strip() == "-":
                    vals.append(np.nan)
                    ok.append(False)
                else:
                    vals.append(float(v))
                    ok.append(True)
        except FluoInputError:
            raise
        except ValueError:
            if not rows and not header_seen and not any(_is_number(v) for v in parts):
                header_seen = True                        # a header line (no number in it)
                continue
            raise FluoInputError(f"line {n} is not numeric", file=p, field=field,
                                 value=line[:80]) from None
        bad = [v for v, x, u in zip(parts, vals, ok) if u and not np.isfinite(x)]
        if bad:         # NaN is refused, never read as "unused"
            raise FluoInputError("must be a finite number" + (
                " (mark an unused pair with '-')" if allow_unused else ""),
                file=p, field=f"{field} line {n}", value=bad[0].strip())
        rows.append(vals)
        used.append(ok)
    if not rows:
        raise FluoInputError("no rows", file=p, field=field)
    if len({len(r) for r in rows}) != 1:
        lens = [len(r) for r in rows]
        n_bad = next(k for k, v in enumerate(lens) if v != lens[0])
        raise FluoInputError(f"rows of different lengths ({lens[0]} and {lens[n_bad]} values)",
                             file=p, field=field, value=f"row {n_bad + 1}")
    return np.array(rows, float), np.array(used, bool)


def read_points_csv(path, field):
    """Points (N, 3) [RAS mm] from a CSV file of ``x,y,z`` rows (one header line
    and ``#`` comments allowed), refused naming ``path`` and ``field`` when a
    row is not three finite numbers."""
    rows, _ = _read_csv_rows(path, field)
    return _points(rows, path, field)


def _number(doc, key, file, positive=True, default=None):
    v = doc.get(key, default)
    if v is None:
        raise FluoInputError("missing", file=file, field=key)
    try:
        arr = np.asarray(v, float) if not isinstance(v, bool) else None
    except (TypeError, ValueError):      # a string, a dict, ragged lists
        arr = None
    if arr is None or arr.ndim > 1 or not np.all(np.isfinite(arr)) or (
            positive and np.any(arr <= 0)) or (not positive and np.any(arr < 0)):
        raise FluoInputError(f"must be a {'positive' if positive else 'non-negative'} number "
                             "(or one per source)", file=file, field=key, value=v)
    return arr


def _per_source(arr, S, file, key):
    if arr.ndim == 0:
        return np.full(S, float(arr))
    if arr.shape != (S,):
        raise FluoInputError(f"needs one number or one per source ({S})", file=file, field=key,
                             value=len(arr))
    return arr


def read_acquisition(folder, labelmap=None, optics=None):
    """Read and validate an acquisition folder (or its ``acquisition.json``).

    A tracked-frames acquisition needs the ``labelmap`` (its tissue surface)
    to place sources, detectors and pixels; camera counts need the ``optics``
    (the tissue's refractive index sets the boundary factor 2A).  Returns an
    :class:`Acquisition`.
    """
    from fluoguide import atomic
    from fluoguide.jsonable import read_json

    p = Path(folder)
    jpath = p if p.suffix == ".json" else p / "acquisition.json"
    if not p.exists():
        raise FluoInputError("acquisition folder not found", file=p)
    if jpath.parent.is_dir():
        atomic.recover(jpath.parent)   # finish a write a crash interrupted: the new set, whole
    doc = read_json(jpath)
    base = jpath.parent
    if doc.get("format", FORMAT) != FORMAT:
        raise FluoInputError(f"not an acquisition file (format must be {FORMAT!r})", file=jpath,
                             field="format", value=doc.get("format"))
    if doc.get("version", 1) != 1:
        raise FluoInputError("unsupported version (this reader knows 1)", file=jpath,
                             field="version", value=doc.get("version"))
    kind = doc.get("kind", "fluence")
    if kind == "tracked-frames":
        if labelmap is None:
            raise FluoInputError("a tracked-frames acquisition needs the label map (its "
                                 "surface places sources and pixels)", file=jpath, field="kind")
        if optics is None:
            raise FluoInputError("camera counts need the tissue's refractive index (the "
                                 "optics)", file=jpath, field="kind")
        return _read_tracked_frames(doc, base, jpath, labelmap, optics)
    if kind != "fluence":
        raise FluoInputError("kind must be 'fluence' or 'tracked-frames'", file=jpath,
                             field="kind", value=kind)
    extra = set(doc) - _FLUENCE_KEYS
    if extra:
        raise FluoInputError("unknown key", file=jpath, field=sorted(extra)[0])
    pts = {}
    files = {}
    for key in ("sources_ras_mm", "detectors_ras_mm"):
        v = doc.get(key)
        if v is None:
            raise FluoInputError("missing (a CSV file name or a list of [x, y, z])", file=jpath,
                                 field=key)
        if isinstance(v, str):
            given = _inside(base, v, jpath, key)
            rows, _ = _read_csv_rows(given, key)
            pts[key] = _points(rows, given, key)
            files[key.split("_")[0]] = str(given)
        else:
            try:
                pts[key] = _points(v, jpath, key)
            except (TypeError, ValueError):
                raise FluoInputError("needs a list of [x, y, z] points (RAS mm)", file=jpath,
                                     field=key) from None
    S, D = len(pts["sources_ras_mm"]), len(pts["detectors_ras_mm"])
    dv = doc.get("data")
    if dv is None:
        raise FluoInputError("missing (a CSV file name or a list of lists)", file=jpath,
                             field="data")
    if isinstance(dv, str):
        data_file = _inside(base, dv, jpath, "data")
        data, used = _read_csv_rows(data_file, "data", allow_unused=True)
        where = data_file
    else:
        where = jpath
        if not isinstance(dv, list) or not all(isinstance(r, list) for r in dv):
            raise FluoInputError("needs one list per source (null for an unused pair)",
                                 file=jpath, field="data")
        if len({len(r) for r in dv}) > 1:
            raise FluoInputError("rows of different lengths", file=jpath, field="data")
        used = np.array([[v is not None for v in r] for r in dv], bool)
        try:
            data = np.array([[np.nan if v is None else float(v) for v in r] for r in dv], float)
        except (TypeError, ValueError):
            raise FluoInputError("data must be numbers or null", file=jpath,
                                 field="data") from None
        if np.any(used & ~np.isfinite(data)):
            s, d = np.argwhere(used & ~np.isfinite(data))[0]
            raise FluoInputError("must be a finite number (null marks an unused pair)",
                                 file=jpath, field=f"data[{s}][{d}]")
    if data.shape != (S, D):
        raise FluoInputError(f"data must have one row per source and one column per detector "
                             f"({S} x {D})", file=where, field="data", value=list(data.shape))
    units = doc.get("units", "1/mm^2")
    if units not in UNITS:
        raise FluoInputError(f"units must be one of {', '.join(UNITS)}", file=jpath,
                             field="units", value=units)
    if units == "counts" and optics is None:
        raise FluoInputError("camera counts need the tissue's refractive index (the optics)",
                             file=jpath, field="units", value=units)
    y = _to_fluence_per_watt(data, units, doc, S, jpath, optics)
    mask = used.copy()
    if doc.get("exclude_mm") is not None:
        ex = float(_number(doc, "exclude_mm", jpath, positive=False))
        dist = np.linalg.norm(pts["sources_ras_mm"][:, None] - pts["detectors_ras_mm"][None],
                              axis=2)
        mask &= dist > ex
    if doc.get("noise_pct") is not None:
        nz = _number(doc, "noise_pct", jpath, positive=False)
        if nz.ndim != 0 or not float(nz) < 100.0:
            raise FluoInputError("must be a relative noise within 0..100 %", file=jpath,
                                 field="noise_pct", value=doc["noise_pct"])
    meta = {k: doc[k] for k in ("simulation", "comment", "exclude_mm", "noise_pct") if k in doc}
    files.setdefault("sources", str(jpath))
    files.setdefault("detectors", str(jpath))
    return Acquisition(pts["sources_ras_mm"], pts["detectors_ras_mm"], np.where(mask, y, 0.0),
                       mask, units, meta, source=str(where if where != jpath else jpath),
                       files=files)


def _inside(base, name, jpath, field):
    """A data file named in acquisition.json: inside the acquisition folder
    (checked on the resolved paths); returned as given (``acq/data.csv``), the
    name its reader's messages show."""
    q = (base / name).resolve()
    if base.resolve() not in q.parents:
        raise FluoInputError("files must lie in the acquisition folder", file=jpath, field=field,
                             value=name)
    return base / name


def _to_fluence_per_watt(data, units, doc, S, file, optics=None):
    if units == "1/mm^2":
        return data
    power = _per_source(_number(doc, "laser_power_w", file), S, file, "laser_power_w")
    if units == "W/mm^2":
        return data / power[:, None]
    from FluoTomoLib.acquisition.noncontact_optodes import counts_to_boundary_fluence
    from FluoTomoLib.optics import robin_A

    gain = float(_number(doc, "camera_gain_adu_per_radiance", file))
    offset = float(_number(doc, "camera_offset_adu", file, positive=False, default=0.0))
    counts = data
    if "exposure_s" in doc:
        exp = _per_source(_number(doc, "exposure_s", file), S, file, "exposure_s")
        ref = float(_number(doc, "reference_exposure_s", file))
        counts = offset + (data - offset) * (ref / exp)[:, None]
    return counts_to_boundary_fluence(counts, offset, gain,
                                      robin_A(optics.n, optics.boundary), 1.0) / power[:, None]


def _atomic_folder_write(folder, files):
    """Write {name: bytes or str} into ``folder`` as one transaction: a new
    folder appears whole with one rename, an existing one gets the new files as
    a journaled commit, ``acquisition.json`` last (fluoguide.atomic)."""
    from fluoguide import atomic

    out = Path(folder)
    try:
        with atomic.staged_folder(out, last=("acquisition.json",)) as stage:
            for name, content in files.items():
                target = stage / name
                if isinstance(content, bytes):
                    target.write_bytes(content)
                else:
                    target.write_text(content, encoding="utf-8")
    except OSError as exc:
        raise atomic.output_error(exc, out) from None
    return out


def write_acquisition(folder, acq, simulation=None, extra_files=None, extra=None):
    """Write an :class:`Acquisition` as a folder (``acquisition.json``,
    ``sources.csv``, ``detectors.csv``, ``data.csv`` in 1/mm^2), as one
    transaction: a reader sees the old folder or the new one.  ``extra_files``
    ({name: text}) are written in the same transaction (e.g. the per-frame
    report ``frames.json`` of a recording); ``extra`` ({key: value}) goes into
    ``acquisition.json`` (keys the reader knows: ``comment``, ``noise_pct``)."""
    from fluoguide.jsonable import dumps

    def pts_csv(p):
        return "x_mm,y_mm,z_mm\n" + "".join(f"{a:.9g},{b:.9g},{c:.9g}\n" for a, b, c in p)

    rows = []
    for s in range(len(acq.sources_ras_mm)):
        rows.append(",".join(f"{v:.9g}" if m else "-" for v, m in zip(acq.data[s], acq.mask[s])))
    doc = {"format": FORMAT, "version": 1, "kind": "fluence", "units": "1/mm^2",
           "sources_ras_mm": "sources.csv", "detectors_ras_mm": "detectors.csv",
           "data": "data.csv",
           "comment": "boundary fluence per watt of laser power; '-' marks an unused pair"}
    if simulation is not None:
        doc["simulation"] = simulation
    doc.update(extra or {})
    return _atomic_folder_write(folder, {
        **(extra_files or {}),
        "sources.csv": pts_csv(acq.sources_ras_mm), "detectors.csv": pts_csv(acq.detectors_ras_mm),
        "data.csv": "\n".join(rows) + "\n", "acquisition.json": dumps(doc)})


# ----------------------------------------------------------------- tracked frames

def _matrix(v, file, field, shape):
    try:
        m = np.asarray(v, float)
    except (TypeError, ValueError):
        raise FluoInputError("must be numbers", file=file, field=field) from None
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise FluoInputError(f"must be a finite {'x'.join(map(str, shape))} array", file=file,
                             field=field, value=list(m.shape))
    return m


def _rigid(m, file, field):
    R = m[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise FluoInputError("must be a rigid transform (rotation + translation)", file=file,
                             field=field)
    return m


def _read_tracked_frames(doc, base, jpath, labelmap, optics):
    from FluoCalibLib.geometry.camera_model import CameraModel

    extra = set(doc) - _RAW_KEYS
    if extra:
        raise FluoInputError("unknown key", file=jpath, field=sorted(extra)[0])
    for key in ("frames", "laser_poses", "laser_beam", "camera", "camera_to_ras",
                "camera_gain_adu_per_radiance", "laser_power_w"):
        if key not in doc:
            raise FluoInputError("missing", file=jpath, field=key)
    fpath = _inside(base, str(doc["frames"]), jpath, "frames")
    try:
        frames = np.load(fpath, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FluoInputError(f"cannot read frames ({str(exc)[:100]})", file=fpath) from None
    if frames.ndim != 3 or not np.all(np.isfinite(frames)):
        raise FluoInputError("frames must be a finite (S, H, W) array of counts", file=fpath,
                             value=list(frames.shape))
    lp = doc["laser_poses"]
    if isinstance(lp, str):
        from fluoguide.jsonable import read_json

        lp = read_json(_inside(base, lp, jpath, "laser_poses"), expect=list)
    poses = _matrix(lp, jpath, "laser_poses", (len(frames), 4, 4))
    for s in range(len(poses)):
        _rigid(poses[s], jpath, f"laser_poses[{s}]")
    beam = doc["laser_beam"]
    if not isinstance(beam, dict):
        raise FluoInputError("needs origin_tool_mm and direction_tool", file=jpath,
                             field="laser_beam")
    b_o = _matrix(beam.get("origin_tool_mm"), jpath, "laser_beam.origin_tool_mm", (3,))
    b_d = _matrix(beam.get("direction_tool"), jpath, "laser_beam.direction_tool", (3,))
    if np.linalg.norm(b_d) == 0:
        raise FluoInputError("must not be zero", file=jpath, field="laser_beam.direction_tool")
    try:
        camera = CameraModel.from_dict(doc["camera"])
    except FluoInputError as exc:
        raise FluoInputError(exc.problem, file=jpath, field=f"camera.{exc.field or ''}") from None
    if (camera.height, camera.width) != frames.shape[1:]:
        raise FluoInputError("frames are not the camera's size", file=fpath,
                             value=[list(frames.shape[1:]), [camera.height, camera.width]])
    cam_pose = _rigid(_matrix(doc["camera_to_ras"], jpath, "camera_to_ras", (4, 4)), jpath,
                      "camera_to_ras")
    gain = float(_number(doc, "camera_gain_adu_per_radiance", jpath))
    offset = float(_number(doc, "camera_offset_adu", jpath, positive=False, default=0.0))
    power = float(_number(doc, "laser_power_w", jpath))
    factor = doc.get("detector_factor", 2)
    if not isinstance(factor, int) or isinstance(factor, bool) or not 1 <= factor <= 8:
        raise FluoInputError("must be an integer 1..8", file=jpath, field="detector_factor",
                             value=factor)
    exclude = float(_number(doc, "exclude_mm", jpath, positive=False, default=3.0))
    roi_area = float(_number(doc, "roi_area_mm2", jpath, default=1.0))
    saturation = float(_number(doc, "saturation_adu", jpath, default=16383.0))
    acq = acquisition_from_tracked_frames(
        labelmap, frames, frames >= saturation, camera, cam_pose, poses, b_o, b_d, gain, offset,
        power, n_tissue=optics.n, boundary=optics.boundary, detector_factor=factor,
        exclude_mm=exclude,
        roi_area_mm2=roi_area, source=str(jpath))
    acq.meta.update({k: doc[k] for k in ("simulation", "comment") if k in doc})
    acq.units = "counts (tracked frames)"
    return acq


def acquisition_from_tracked_frames(labelmap, frames, saturated, camera, camera_to_ras,
                                    laser_poses, beam_origin_tool_mm, beam_dir_tool, gain,
                                    offset_adu, laser_power_w, n_tissue=None, detector_factor=2,
                                    exclude_mm=3.0, roi_area_mm2=1.0, source=None,
                                    boundary=None, hits=None, sources_ras=None):
    """What the software makes of a tracked laser scan seen by a tracked camera.

    Sources: each tracked beam cast onto the label map's tissue surface.
    Detectors: the sources plus ``detector_factor - 1`` points between
    neighbours, dropped onto the surface along the beams; those within
    ``exclude_mm`` of the active source are left out.  Data: every pixel cast
    onto the surface from the tracked camera pose, the unsaturated pixels of a
    ``roi_area_mm2`` disc around each detector averaged, counts -> boundary
    fluence per watt (docs/physics.md section 8.2; ``n_tissue``, the tissue's
    refractive index, sets the Robin factor 2A with ``boundary``'s method,
    ``optics.robin_A``; None: its default).

    Parameters are RAS (poses LaserToolToRAS and CameraToRAS, mm); returns an
    :class:`Acquisition`.  ``camera_to_ras`` is one 4x4 (a camera that stays
    put) or one per frame (S, 4, 4) (a tracked camera read at each frame's
    time: each frame is mapped with its own pose); ``hits``: the frames'
    pixel casts when the caller has them already (one PixelHits, or one per
    frame), so they are not cast twice; ``sources_ras`` (S, 3): the sources'
    surface points when the caller located them otherwise (the laser spot
    seen in each frame), None for the beams' surface points.
    """
    from FluoTomoLib.acquisition.camera_frames import cast, detector_counts
    from FluoTomoLib.acquisition.noncontact_optodes import (counts_to_boundary_fluence,
                                                            detector_mask, virtual_detectors)
    from FluoTomoLib.acquisition.tracked_scan import beam_in_world
    from FluoTomoLib.optics import robin_A

    surf = labelmap.surface()
    pts_ras = labelmap.to_ras(surf.points)
    tris = surf.triangles if np.linalg.det(labelmap.direction) > 0 else surf.triangles[:, ::-1]
    from FluoTomoLib.acquisition.noncontact_optodes import ray_triangle_intersect

    o, d = zip(*(beam_in_world(T, beam_origin_tool_mm, beam_dir_tool) for T in laser_poses))
    o, d = np.asarray(o), np.asarray(d)
    src, _, face = ray_triangle_intersect(o, d, pts_ras, tris)
    if np.any(face < 0):
        s = int(np.flatnonzero(face < 0)[0])
        raise FluoInputError("the tracked laser beam misses the tissue surface", file=source,
                             field=f"laser_poses[{s}]")
    if sources_ras is not None:
        src = np.asarray(sources_ras, float).reshape(len(src), 3)
    det = virtual_detectors(src, factor=detector_factor)
    # points between sources: onto the surface along the mean beam direction
    mean_dir = d.mean(axis=0)
    mean_dir /= np.linalg.norm(mean_dir)
    between = np.ones(len(det), bool)
    between[::detector_factor] = False
    if np.any(between):
        hit, _, f2 = ray_triangle_intersect(det[between] - 50.0 * mean_dir,
                                            np.tile(mean_dir, (int(between.sum()), 1)), pts_ras,
                                            tris)
        if np.any(f2 < 0):
            raise FluoInputError("a detector between two sources has no surface under it",
                                 file=source, field="laser_poses")
        det[between] = hit
    mask = detector_mask(src, det, exclude_mm)
    from FluoNavLib.mapping.pixel_cast import SurfaceCaster

    frames = np.asarray(frames, float)
    saturated = np.asarray(saturated, bool)
    poses = np.asarray(camera_to_ras, float)
    if hits is None:
        caster = SurfaceCaster(pts_ras, tris)
        hits = ([cast(caster, camera, P) for P in poses] if poses.ndim == 3
                else cast(caster, camera, poses))
    if isinstance(hits, (list, tuple)):          # one cast per frame
        counts = np.full((len(frames), len(det)), np.nan)
        se = np.full((len(frames), len(det)), np.nan)
        n_pix = np.zeros((len(frames), len(det)), dtype=np.int64)
        for s, h in enumerate(hits):
            counts[s:s + 1], n_pix[s:s + 1], se[s:s + 1] = detector_counts(
                frames[s:s + 1], saturated[s:s + 1], h, det, roi_area_mm2, with_se=True)
    else:
        counts, n_pix, se = detector_counts(frames, saturated, hits, det, roi_area_mm2,
                                            with_se=True)
    lost = mask & ~np.isfinite(counts)
    if np.any(lost):
        s, dd = np.argwhere(lost)[0]
        raise FluoInputError(f"{int(lost.sum())} detector ROIs have too few unsaturated pixels "
                             "(saturated, or not seen by the camera)", file=source,
                             field=f"frames[{s}] detector {dd}")
    if n_tissue is None:
        raise FluoInputError("the tissue's refractive index is needed", field="n_tissue")
    y = counts_to_boundary_fluence(np.nan_to_num(counts), offset_adu, gain,
                                   robin_A(n_tissue, boundary), laser_power_w)
    return Acquisition(src, det, np.where(mask, y, 0.0), mask, "counts (tracked frames)",
                       {"roi_counts": counts, "roi_pixels": n_pix, "roi_se": se,
                        "noise_from_frames_pct": frames_noise_pct(counts, se, offset_adu, mask)},
                       source=source)


def frames_noise_pct(counts_adu, se_adu, offset_adu, mask):
    """The readings' relative noise as the frames show it [%]: the root mean
    square over the used pairs of each ROI mean's standard error over its
    signal above the offset (``roi_se``: the pixels' scatter about a plane
    over the ROI, shot and read noise); None when no used pair has one."""
    signal = np.asarray(counts_adu, float) - offset_adu
    ok = np.asarray(mask, bool) & np.isfinite(se_adu) & (signal > 0)
    if not np.any(ok):
        return None
    return float(100.0 * np.sqrt(np.mean((np.asarray(se_adu)[ok] / signal[ok]) ** 2)))


def write_tracked_frames(folder, frames, laser_poses, beam_origin_tool_mm, beam_dir_tool, camera,
                         camera_to_ras, gain, offset_adu, laser_power_w, detector_factor=2,
                         exclude_mm=3.0, simulation=None):
    """Write a tracked-frames acquisition folder (the raw route) atomically."""
    import io

    from fluoguide.jsonable import dumps

    buf = io.BytesIO()
    np.save(buf, np.asarray(frames, np.float32))
    doc = {"format": FORMAT, "version": 1, "kind": "tracked-frames", "frames": "frames.npy",
           "laser_poses": "laser_poses.json",
           "laser_beam": {"origin_tool_mm": list(map(float, beam_origin_tool_mm)),
                          "direction_tool": list(map(float, beam_dir_tool))},
           "camera": camera.to_dict(), "camera_to_ras": np.asarray(camera_to_ras).tolist(),
           "camera_gain_adu_per_radiance": float(gain), "camera_offset_adu": float(offset_adu),
           "laser_power_w": float(laser_power_w), "detector_factor": int(detector_factor),
           "exclude_mm": float(exclude_mm)}
    if simulation is not None:
        doc["simulation"] = simulation
    return _atomic_folder_write(folder, {
        "frames.npy": buf.getvalue(),
        "laser_poses.json": json.dumps(np.asarray(laser_poses).tolist()),
        "acquisition.json": dumps(doc)})
