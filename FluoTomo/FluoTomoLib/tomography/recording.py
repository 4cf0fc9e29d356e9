"""A recorded tracked laser scan turned into an acquisition, and a recording
rendered from a label map's truth to check that path against.

The recording layout (docs/recording.md; all text files UTF-8)::

    REC/recording.json   {"format": "fluoguide-scan-recording", "version": 1,
                          "frames": "frames.csv", "poses": "poses.csv",
                          "laser_tool": "LaserToolToTracker",
                          "camera_tool": "CameraToolToTracker",
                          "laser_power_w": 0.01, "exposure_s": 0.1,
                          "time_sync_tolerance_s": 0.05,
                          "calibration": "calibration.json"}
    REC/frames.csv       frame,file,timestamp_s[,exposure_s][,laser_power_w]
    REC/poses.csv        timestamp_s,tool,status,m00,m01,...,m33   (ToolToTracker, mm)
    REC/frame_0000.png   16-bit grey images [ADU] (.png, .tif or .npy)
    REC/calibration.json the calibrations (FluoCalib's calibration JSON file)

or FluoNav's recorder folder (``log.jsonl`` and ``frame_NNNNNN.npy``, the tool
poses already at each frame's time) with the same ``recording.json`` beside it
saying ``"log": "log.jsonl"`` instead of ``frames``/``poses``.  Both are read
by :func:`read_scan_recording` into one form (frames, pose samples per tool),
so :func:`acquire_recording` has one path.

The calibrations (a FluoCalib calibration JSON file, or a scene's
``FluoCalibration`` node and transforms, docs/scene.md): ``CameraIntrinsics``,
``HandEye.camera_to_tool`` (CameraToCameraTool), ``Registration.
tracker_to_reference`` (TrackerToReference; the ``TrackerToReference``
transform in a scene), ``Laser`` (``origin_mm``, ``direction`` in laser-tool
coordinates) and ``Radiometry`` (``gain_adu_per_radiance`` G [ADU per
W/mm^2/sr] at ``reference_exposure_s``, ``offset_adu``, ``saturation_adu``;
docs/physics.md section 5.1).
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

FORMAT = "fluoguide-scan-recording"
TIME_SYNC_TOLERANCE_S = 0.05
#: how far the laser spot seen by the camera may lie from the tracked beam's
#: surface point [mm]: about three times the two chains' combined error at a
#: 0.5 mm tracker and a 0.3 mm hand-eye calibration (each spot point carries the
#: camera tool's, the hand-eye's and the laser tool's error, ~0.7 mm together),
#: and below the 3 mm pitch of a raster, so a spot of another position or a
#: tracker glitch is caught
SPOT_TOLERANCE_MM = 2.0
#: the beam's surface point must be seen by the camera within this [mm]
VISIBLE_TOLERANCE_MM = 1.0
REASONS = ("pose missing", "pose stale", "surface not visible", "spot not found",
           "spot far from the beam", "saturated")
_REC_KEYS = {"format", "version", "frames", "poses", "log", "laser_tool", "camera_tool",
             "laser_power_w", "exposure_s", "time_sync_tolerance_s", "calibration", "comment",
             "simulation"}


def _num(v, file, field, positive=True):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or (
            positive and v <= 0):
        raise FluoInputError("must be a positive number" if positive else "must be a number",
                             file=file, field=field, value=v)
    return float(v)


def _csv_rows(path, field):
    """(header, [(line number, {column: stripped string})]) of a CSV file with ``#``
    comments; a row with another number of values than the header is refused."""
    from FluoTomoLib.tomography.acquisition_file import read_text_file

    p, text = read_text_file(path, field)
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].lstrip().startswith("#")]
    if len(rows) < 2:
        raise FluoInputError("needs a header line and at least one row", file=p, field=field)
    head = [h.strip() for h in rows[0]]
    out = []
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(head):
            raise FluoInputError(f"{len(row)} values for {len(head)} columns", file=p,
                                 field=f"line {n}")
        out.append((n, dict(zip(head, (v.strip() for v in row)))))
    return head, out


def _float(text, file, field):
    try:
        v = float(text)
    except ValueError:
        raise FluoInputError("must be a number", file=file, field=field, value=text) from None
    if not np.isfinite(v):
        raise FluoInputError("must be a finite number", file=file, field=field, value=text)
    return v


def read_scan_recording(folder):
    """Read and check a recording folder (the documented layout or FluoNav's
    recorder folder with its ``recording.json``).

    Returns a dict: ``frames`` (list of {frame, file, path, time_s, exposure_s,
    laser_power_w}), ``samples`` ({tool: list of (time_s, 4x4 or None, status)}),
    ``laser_tool``, ``camera_tool``, ``tolerance_s``, ``calibration`` (path or
    None), ``doc`` (recording.json).  Refusals name the file, the field and the
    value (FluoInputError).
    """
    from fluoguide.paths import inside

    base = Path(folder)
    jpath, doc = _read_recording_json(base)
    laser_tool = str(doc.get("laser_tool", "LaserToolToTracker"))
    camera_tool = str(doc.get("camera_tool", "CameraToolToTracker"))
    power = _num(doc.get("laser_power_w"), jpath, "laser_power_w")
    exposure = (_num(doc["exposure_s"], jpath, "exposure_s") if doc.get("exposure_s")
                is not None else None)
    tol = _num(doc.get("time_sync_tolerance_s", TIME_SYNC_TOLERANCE_S), jpath,
               "time_sync_tolerance_s")
    calib = doc.get("calibration")
    calib = None if calib is None else inside(base, str(calib), file=jpath, field="calibration",
                                              given=True)
    if "log" in doc:                     # FluoNav's recorder folder
        frames, samples = _read_recorder_folder(base, jpath, doc, exposure, power)
    else:
        for key in ("frames", "poses"):
            if key not in doc:
                raise FluoInputError("missing (or 'log' for a recorder folder)", file=jpath,
                                     field=key)
        frames = _read_frames_csv(base, jpath, doc, exposure, power)
        samples = _read_poses_csv(base, jpath, doc)
    if not frames:
        raise FluoInputError("the recording has no frame", file=base)
    for tool in (laser_tool, camera_tool):
        if tool not in samples:
            raise FluoInputError("no pose of this tool in the recording", file=base,
                                 field=tool)
    return {"frames": frames, "samples": samples, "laser_tool": laser_tool,
            "camera_tool": camera_tool, "tolerance_s": tol, "calibration": calib, "doc": doc,
            "folder": base}


def _read_recording_json(base):
    """(path, dict) of the folder ``base``'s recording.json, its format, version
    and keys checked."""
    from fluoguide.jsonable import read_json

    if not base.is_dir():
        raise FluoInputError("recording folder not found", file=base)
    jpath = base / "recording.json"
    if not jpath.is_file():
        raise FluoInputError("not a scan recording (no recording.json)", file=base)
    doc = read_json(jpath)
    if not isinstance(doc, dict):
        raise FluoInputError("must be a JSON object", file=jpath)
    if doc.get("format", FORMAT) != FORMAT:
        raise FluoInputError(f"format must be {FORMAT!r}", file=jpath, field="format",
                             value=doc.get("format"))
    if doc.get("version", 1) != 1:
        raise FluoInputError("unsupported version (this reader knows 1)", file=jpath,
                             field="version", value=doc.get("version"))
    extra = set(doc) - _REC_KEYS
    if extra:
        raise FluoInputError("unknown key", file=jpath, field=sorted(extra)[0])
    return jpath, doc


def _read_recorder_folder(base, jpath, doc, exposure, power):
    """(frames, samples) of FluoNav's recorder folder (its log.jsonl); ``exposure``
    [s] where a frame names none, ``power`` [W] every frame's laser power."""
    from fluoguide.paths import inside

    from FluoNavLib.devices.recorder import read_recording

    if inside(base, str(doc["log"]), file=jpath, field="log", given=True).name != "log.jsonl":
        raise FluoInputError("the recorder's log is log.jsonl", file=jpath, field="log",
                             value=doc["log"])
    frames, samples = [], {}
    _, recs = read_recording(base)
    for r in recs:
        t = r["timestamp_s"]
        frames.append({"frame": int(r["frame"]), "file": r["file"], "path": r["path"],
                       "time_s": t, "exposure_s": r["exposure_s"] or exposure,
                       "laser_power_w": power})
        status = r["pose_status"] if r["pose_valid"] else (
            r["pose_status"] if r["pose_status"] != "OK" else "MISSING")
        for tool, m in r["poses"].items():
            st = "OK" if (m is not None and status == "OK") else (
                "MISSING" if m is None else status)
            samples.setdefault(tool, []).append((t, m if st == "OK" else None, st))
    return frames, samples


def _read_frames_csv(base, jpath, doc, exposure, power):
    """The frames of the documented layout's frames CSV: list of {frame, file, path,
    time_s, exposure_s [s], laser_power_w [W]}, ``exposure`` and ``power`` where a
    row names none."""
    from fluoguide.paths import inside

    frames = []
    fpath = inside(base, str(doc["frames"]), file=jpath, field="frames", given=True)
    head, rows = _csv_rows(fpath, "frames")
    for col in ("frame", "file", "timestamp_s"):
        if col not in head:
            raise FluoInputError("missing column", file=fpath, field=col)
    last = -np.inf
    for n, r in rows:
        t = _float(r["timestamp_s"], fpath, f"line {n} timestamp_s")
        if not t > last:
            raise FluoInputError("timestamps must increase", file=fpath,
                                 field=f"line {n} timestamp_s", value=r["timestamp_s"])
        last = t
        e = (_float(r["exposure_s"], fpath, f"line {n} exposure_s")
             if r.get("exposure_s") else exposure)
        if e is None or not e > 0:
            raise FluoInputError("needs a positive exposure (column exposure_s or "
                                 "recording.json exposure_s)", file=fpath,
                                 field=f"line {n} exposure_s", value=e)
        pw = (_float(r["laser_power_w"], fpath, f"line {n} laser_power_w")
              if r.get("laser_power_w") else power)
        if not pw > 0:
            raise FluoInputError("must be positive", file=fpath,
                                 field=f"line {n} laser_power_w", value=pw)
        try:
            frame_no = int(r["frame"])
        except ValueError:
            raise FluoInputError("must be an integer", file=fpath, field=f"line {n} frame",
                                 value=r["frame"]) from None
        path = inside(base, r["file"], file=fpath, field=f"line {n} file", given=True)
        if not path.is_file():
            raise FluoInputError("frame file not found", file=path,
                                 field=f"{fpath.name} line {n} file")
        frames.append({"frame": frame_no, "file": r["file"], "path": path, "time_s": t,
                       "exposure_s": e, "laser_power_w": pw})
    return frames


_MATRIX_COLS = [f"m{i}{j}" for i in range(4) for j in range(4)]
_QUATERNION_COLS = ["qw", "qx", "qy", "qz", "tx_mm", "ty_mm", "tz_mm"]


def _read_poses_csv(base, jpath, doc):
    """The tool poses of the documented layout's poses CSV: {tool: list of
    (time_s [s], 4x4 [mm] or None, status)}."""
    from fluoguide.paths import inside

    samples = {}
    ppath = inside(base, str(doc["poses"]), file=jpath, field="poses", given=True)
    head, rows = _csv_rows(ppath, "poses")
    for col in ("timestamp_s", "tool"):
        if col not in head:
            raise FluoInputError("missing column", file=ppath, field=col)
    if all(c in head for c in _MATRIX_COLS):
        form = "matrix"
    elif all(c in head for c in _QUATERNION_COLS):
        form = "quaternion"
    else:
        raise FluoInputError("needs the columns m00..m33 (4x4, row-major) or qw,qx,qy,qz,"
                             "tx_mm,ty_mm,tz_mm", file=ppath, field="header")
    for n, r in rows:
        t = _float(r["timestamp_s"], ppath, f"line {n} timestamp_s")
        status = (r.get("status") or "OK").upper()
        m = _pose_of_row(r, n, ppath, form) if status == "OK" else None
        samples.setdefault(r["tool"], []).append((t, m, status))
    return samples


def _pose_of_row(r, n, ppath, form):
    """The 4x4 rigid pose [mm] of poses CSV row ``r`` (line ``n``), from its matrix
    or quaternion columns (``form``)."""
    if form == "matrix":
        m = np.array([_float(r[c], ppath, f"line {n} {c}") for c in _MATRIX_COLS]
                     ).reshape(4, 4)
        R = m[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or not np.allclose(
                m[3], [0, 0, 0, 1], atol=1e-9):
            raise FluoInputError("not a rigid transform (rotation + translation)",
                                 file=ppath, field=f"line {n} {r['tool']}")
        return m
    from FluoCalibLib.geometry.transforms import quaternion_to_matrix

    qcols = _QUATERNION_COLS
    q = np.array([_float(r[c], ppath, f"line {n} {c}") for c in qcols[:4]])
    if not abs(np.linalg.norm(q) - 1.0) < 1e-3:
        raise FluoInputError("quaternion must have unit length", file=ppath,
                             field=f"line {n} qw..qz",
                             value=round(float(np.linalg.norm(q)), 6))
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(q / np.linalg.norm(q))
    m[:3, 3] = [_float(r[c], ppath, f"line {n} {c}") for c in qcols[4:]]
    return m


def pose_at(samples, t, tolerance_s):
    """(4x4 or None, status) of one tool at frame time ``t``: the samples of
    the tool interpolated (FluoNavLib.devices.timesync.PoseBuffer: SLERP and
    linear), ``"missing"`` where the tracker reported the tool missing then,
    ``"stale"`` where the nearest samples are farther apart than
    ``tolerance_s`` or the frame is past the last sample."""
    from FluoNavLib.devices.timesync import PoseBuffer

    buf = PoseBuffer(max_gap_s=tolerance_s, max_age_s=tolerance_s, capacity=len(samples) + 1)
    bad = None
    for ts, m, st in sorted(samples, key=lambda s: s[0]):
        if abs(ts - t) <= 1e-9 and st not in ("OK", "MISSING"):
            bad = st
        buf.add(ts, m)
    if bad is not None:                       # the recorder said so at this frame
        return None, "stale" if bad in ("STALE", "EXTRAPOLATION") else "missing"
    m, status = buf.at(t)
    if status == "OK":
        return m, "ok"
    if status == "STALE" or status == "EXTRAPOLATION":
        # an isolated sample exactly at t is OK; too far from any sample is stale
        near = [s for s in samples if abs(s[0] - t) <= tolerance_s and s[1] is not None]
        if near:
            return min(near, key=lambda s: abs(s[0] - t))[1].copy(), "ok"
        return None, "stale"
    return None, "missing"


def read_calibration(path):
    """The calibrations an acquisition needs, from a FluoCalib calibration JSON
    file or a scene (``.mrml``: its ``FluoCalibration`` node and transforms).

    Returns a dict: ``camera`` (CameraModel), ``camera_to_tool`` (hand-eye),
    ``tracker_to_reference``, ``beam_origin_tool_mm``, ``beam_dir_tool``,
    ``gain``, ``offset_adu``, ``saturation_adu``, ``reference_exposure_s``.
    """
    from FluoCalibLib.geometry.camera_model import CameraModel

    p = Path(path)
    if not p.is_file():
        raise FluoInputError("calibration not found", file=p)
    if p.suffix.lower() == ".mrml":
        from fluoguide import mrml_io

        scene = mrml_io.load_scene(p)
        node = mrml_io.get_node(scene, "FluoCalibration", required=False)
        if node is None:
            raise FluoInputError("the scene has no FluoCalibration node", file=p,
                                 field="FluoCalibration")
        doc = {}
        for key in ("CameraIntrinsics", "Laser", "Radiometry", "HandEye", "Registration"):
            v = mrml_io.get_json_attribute(node, f"FluoCalib.{key}")
            if v is not None:
                doc[key] = v
        from FluoCalibLib.geometry.scene import handeye_node

        if handeye_node(scene, required=False) is not None:
            from FluoCalibLib.geometry.scene import load_handeye

            doc.setdefault("HandEye", {})["camera_to_tool"] = load_handeye(scene).tolist()
        if mrml_io.get_node(scene, "TrackerToReference", required=False) is not None:
            doc.setdefault("Registration", {})["tracker_to_reference"] = mrml_io.get_transform(
                scene, "TrackerToReference").tolist()
    else:
        from fluoguide.jsonable import read_json

        doc = read_json(p)
        if not isinstance(doc, dict):
            raise FluoInputError("must be a JSON object", file=p)

    def need(key, sub=None):
        v = doc.get(key)
        if not isinstance(v, dict) or (sub is not None and v.get(sub) is None):
            raise FluoInputError("missing (see docs/recording.md, Calibrations)", file=p,
                                 field=key if sub is None else f"{key}.{sub}")
        return v if sub is None else v[sub]

    def matrix(key, sub):
        try:
            m = np.asarray(need(key, sub), float)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)) or not np.allclose(
                m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-4) or not np.allclose(
                m[3], [0, 0, 0, 1]):
            raise FluoInputError("must be a rigid 4x4 transform", file=p, field=f"{key}.{sub}")
        return m

    try:
        camera = CameraModel.from_dict(need("CameraIntrinsics"))
    except FluoInputError as exc:
        raise FluoInputError(exc.problem, file=p,
                             field=f"CameraIntrinsics.{exc.field or ''}") from None
    laser = need("Laser")
    o = np.asarray(laser.get("origin_mm", [np.nan] * 3), float)
    d = np.asarray(laser.get("direction", [np.nan] * 3), float)
    if o.shape != (3,) or d.shape != (3,) or not np.all(np.isfinite(np.r_[o, d])) or not \
            np.linalg.norm(d) > 0:
        raise FluoInputError("needs origin_mm and a non-zero direction (3 numbers each)",
                             file=p, field="Laser")
    rad = need("Radiometry")
    out = {"camera": camera, "camera_to_tool": matrix("HandEye", "camera_to_tool"),
           "tracker_to_reference": matrix("Registration", "tracker_to_reference"),
           "beam_origin_tool_mm": o, "beam_dir_tool": d / np.linalg.norm(d)}
    for key, name, default, positive in (("gain", "gain_adu_per_radiance", None, True),
                                         ("offset_adu", "offset_adu", 0.0, False),
                                         ("saturation_adu", "saturation_adu", 16383.0, True),
                                         ("reference_exposure_s", "reference_exposure_s", None,
                                          True)):
        v = rad.get(name, default)
        if v is None:
            raise FluoInputError("missing (see docs/recording.md, Calibrations)", file=p,
                                 field=f"Radiometry.{name}")
        out[key] = _num(v, p, f"Radiometry.{name}", positive)
    return out


def detect_spot(image, min_contrast_adu=200.0, max_area_fraction=0.01, fraction=0.9):
    """(u, v) [px] of the laser spot: in the frame median-filtered over 3 x 3
    pixels (a hot pixel is not a spot), the blob of pixels above ``fraction``
    of the brightest level (over the frame's median) that holds the brightest
    pixel, its intensity-weighted centroid (the core of the spot, as
    FluoCalibLib.radiometry.laser_line.spot_centroid takes it: a lower level
    takes in the fluorescence around the spot, brightest toward the target,
    and pulls the centroid to it); None when the frame has no distinct spot
    (its brightest pixel less than ``min_contrast_adu`` above the frame's
    median, or a blob larger than ``max_area_fraction`` of the frame: not a
    spot)."""
    from scipy import ndimage

    img = np.asarray(image, float)
    sm = ndimage.median_filter(img, 3)             # a hot pixel is not a spot
    med = float(np.median(sm))
    hi = float(sm.max())
    if not hi - med >= min_contrast_adu:
        return None
    mask = sm >= med + fraction * (hi - med)
    lab, n = ndimage.label(mask)
    k = lab[np.unravel_index(int(np.argmax(sm)), sm.shape)]
    if k == 0:
        return None
    blob = lab == k
    if blob.sum() > max_area_fraction * blob.size:
        return None
    w = sm[blob] - med
    ys, xs = np.nonzero(blob)
    return float(np.sum(xs * w) / w.sum()), float(np.sum(ys * w) / w.sum())


def _surface_point_at_pixel(hits, uv):
    """The surface point a (sub-)pixel position sees, from its nearest pixel."""
    H, W = hits.visible.shape
    u, v = int(round(uv[0])), int(round(uv[1]))
    if not (0 <= u < W and 0 <= v < H) or not hits.visible[v, u]:
        return None
    return np.asarray(hits.point_mm[v, u], float)


#: Where a source's surface point comes from: the laser spot the camera sees
#: (the same camera pose as the frame's detector readings, so a tracking or
#: hand-eye error moves source and readings together) or the tracked beam.
SOURCE_FROM = ("spot", "beam")


def acquire_recording(labelmap, optics, recording, calibration=None,
                      spot_tolerance_mm=SPOT_TOLERANCE_MM, detector_factor=2, exclude_mm=3.0,
                      roi_area_mm2=1.0, source_from="spot", progress=None, cancel=None):
    """A recorded tracked laser scan -> (Acquisition, per-frame report, info).

    For each frame: the laser and camera tool poses at the frame's time (the
    time-sync tolerance of recording.json), the tracked beam cast onto the
    label map's surface, the camera pose TrackerToReference @
    CameraToolToTracker @ CameraToCameraTool and every pixel cast onto the
    surface, the laser spot found in the frame and cast onto the surface,
    checked against the beam's point (``spot_tolerance_mm``), and the frame's
    pixels at saturation farther than ``exclude_mm`` from the source (nearer,
    they are expected and no pair there is used; a frame washed out so that
    no spot shows is reported saturated, not spotless).  A frame that fails one of
    these is reported with its reason and not used; the others give the
    acquisition through ``acquisition_from_tracked_frames`` (counts scaled to
    the calibration's reference exposure and the first used frame's laser
    power, docs/physics.md section 8.2).  The source is the spot's surface
    point (``source_from="spot"``: seen with the frame's own camera pose, as
    its readings are, so a tracking or hand-eye error moves both together
    and the pairs' distances hold) or the beam's (``"beam"``).  The
    acquisition states the readings' noise as the frames show it
    (``meta["noise_pct"]``, ``acquisition_file.frames_noise_pct``).

    ``recording``: a folder (:func:`read_scan_recording`) or its dict;
    ``calibration``: a calibration JSON file or a scene (.mrml), or None for
    the one recording.json names.  Report rows: {frame, time_s, used, reason,
    detail}.
    """
    from fluoguide.progress import check_cancel, report

    from FluoNavLib.mapping.pixel_cast import SurfaceCaster
    from FluoTomoLib.tomography.acquisition_file import acquisition_from_tracked_frames

    t0 = time.perf_counter()
    rec = recording if isinstance(recording, dict) else read_scan_recording(recording)
    cal = _recording_calibration(rec, calibration)
    if not (np.isfinite(spot_tolerance_mm) and 0 < spot_tolerance_mm <= 50):
        raise FluoInputError("must be a distance within (0, 50] mm", field="spot_tolerance_mm",
                             value=spot_tolerance_mm)
    if source_from not in SOURCE_FROM:
        raise FluoInputError(f"must be one of {', '.join(SOURCE_FROM)}", field="source_from",
                             value=source_from)
    camera = cal["camera"]
    surf = labelmap.surface()
    pts_ras = labelmap.to_ras(surf.points)
    tris = surf.triangles if np.linalg.det(labelmap.direction) > 0 else surf.triangles[:, ::-1]
    caster = SurfaceCaster(pts_ras, tris)
    rows, keep = [], []
    images, sat, cams, lasers, hits_used, scale, spots = [], [], [], [], [], [], []
    n = len(rec["frames"])
    for k, fr in enumerate(rec["frames"]):
        check_cancel(cancel)
        report(progress, 0.9 * k / n, f"frame {k + 1} of {n}")
        row = {"frame": fr["frame"], "time_s": fr["time_s"], "used": False, "reason": None,
               "detail": ""}
        rows.append(row)
        kept = _examine_frame(fr, row, rec, cal, caster, pts_ras, tris, spot_tolerance_mm,
                              exclude_mm, source_from)
        if kept is None:
            continue
        row["used"] = True
        keep.append(k)
        images.append(kept["image"])
        sat.append(kept["saturated"])
        cams.append(kept["camera_ras"])
        lasers.append(kept["laser_ras"])
        hits_used.append(kept["hits"])
        spots.append(kept["spot_ras"])
        scale.append((cal["reference_exposure_s"] / fr["exposure_s"]))
        row["laser_power_w"] = fr["laser_power_w"]
    used = [r for r in rows if r["used"]]
    if len(used) < 2:
        reasons = sorted({r["reason"] for r in rows if not r["used"]})
        raise FluoInputError(f"only {len(used)} of {n} frames usable ({', '.join(reasons)}): "
                             "nothing to reconstruct", file=rec["folder"], field="frames")
    power = used[0]["laser_power_w"]
    off = cal["offset_adu"]
    frames = np.array([off + (im - off) * sc * power / r["laser_power_w"]
                       for im, sc, r in zip(images, scale, used)])
    report(progress, 0.9, "detector readings")
    acq = acquisition_from_tracked_frames(
        labelmap, frames, np.array(sat), camera, np.array(cams), np.array(lasers),
        cal["beam_origin_tool_mm"], cal["beam_dir_tool"], cal["gain"], off, power,
        n_tissue=optics.n, boundary=optics.boundary, detector_factor=detector_factor,
        exclude_mm=exclude_mm, roi_area_mm2=roi_area_mm2, source=str(rec["folder"]),
        hits=hits_used, sources_ras=np.array(spots) if source_from == "spot" else None)
    # the readings' noise as the frames show it: stated, the reconstruction
    # grades its fit against it and bounds the model's error in its intervals
    # (a recording has no simulation to say it)
    acq.meta["noise_pct"] = acq.meta.get("noise_from_frames_pct")
    info = _recording_info(rows, used, n, power, spot_tolerance_mm, rec, acq, t0)
    acq.meta.update({"recording": {k: v for k, v in info.items() if k != "seconds"}})
    report(progress, 1.0, "done")
    return acq, rows, info


def _recording_calibration(rec, calibration):
    """The calibrations (:func:`read_calibration`) of ``calibration`` (a file, a
    scene or its dict), or of the one the recording ``rec`` names."""
    if calibration is None:
        if rec["calibration"] is None:
            raise FluoInputError("no calibration: give one (a calibration JSON file or a "
                                 "scene) or name it in recording.json", field="calibration",
                                 file=rec["folder"] / "recording.json")
        calibration = rec["calibration"]
    return calibration if isinstance(calibration, dict) else read_calibration(calibration)


def _pose_failure(rec, st_l, st_c):
    """(reason, detail) of a frame whose laser or camera tool pose status is not
    ``"ok"``."""
    bad = [(t, s) for t, s in ((rec["laser_tool"], st_l), (rec["camera_tool"], st_c))
           if s != "ok"]
    reason = "pose missing" if any(s == "missing" for _, s in bad) else "pose stale"
    detail = ", ".join(
        f"{t} {s}" + (f" (no sample within {rec['tolerance_s']:g} s)" if s == "stale"
                      else "") for t, s in bad)
    return reason, detail


def _examine_frame(fr, row, rec, cal, caster, pts_ras, tris, spot_tolerance_mm, exclude_mm,
                   source_from="spot"):
    """Check one frame: its tool poses, the tracked beam's surface point (RAS
    mm) seen by the camera, the laser spot within ``spot_tolerance_mm`` [mm] of
    it, no saturation farther than ``exclude_mm`` [mm] from the source (the
    spot, or with ``source_from="beam"`` the beam's point).

    A frame that fails gets its ``row``'s reason and detail and gives None; a
    used one gives {image (ADU, float), saturated, camera_ras, laser_ras, hits,
    spot_ras (the spot's surface point, RAS mm)}.
    ``row`` also gets ``spot_to_beam_mm`` once the spot is found.
    """
    from fluoguide.images import read_image

    from FluoTomoLib.acquisition.camera_frames import cast
    from FluoTomoLib.acquisition.noncontact_optodes import ray_triangle_intersect
    from FluoTomoLib.acquisition.tracked_scan import beam_in_world

    camera, TtR = cal["camera"], cal["tracker_to_reference"]
    L, st_l = pose_at(rec["samples"][rec["laser_tool"]], fr["time_s"], rec["tolerance_s"])
    C, st_c = pose_at(rec["samples"][rec["camera_tool"]], fr["time_s"], rec["tolerance_s"])
    if st_l != "ok" or st_c != "ok":
        row["reason"], row["detail"] = _pose_failure(rec, st_l, st_c)
        return None
    laser_ras = TtR @ L
    cam_ras = TtR @ C @ cal["camera_to_tool"]
    o, d = beam_in_world(laser_ras, cal["beam_origin_tool_mm"], cal["beam_dir_tool"])
    src, _, face = ray_triangle_intersect(o[None], d[None], pts_ras, tris)
    if face[0] < 0:
        row["reason"], row["detail"] = "surface not visible", "the tracked beam misses the surface"
        return None
    src = src[0]
    hits = cast(caster, camera, cam_ras)
    uv_src = camera.project((np.linalg.inv(cam_ras) @ np.append(src, 1.0))[:3][None])[0]
    seen = None if not np.all(np.isfinite(uv_src)) else _surface_point_at_pixel(hits, uv_src)
    if seen is None or np.linalg.norm(seen - src) > VISIBLE_TOLERANCE_MM:
        row["reason"] = "surface not visible"
        row["detail"] = "the camera does not see the beam's surface point"
        return None
    img = read_image(fr["path"], field=f"frame {fr['frame']}")
    if img.ndim != 2 or img.shape != (camera.height, camera.width):
        raise FluoInputError("frame is not the camera's size (a grey image of "
                             f"{camera.width} x {camera.height} px)", file=fr["path"],
                             value=list(img.shape))
    img = img.astype(float)
    saturated = img >= cal["saturation_adu"]
    uv = detect_spot(img)
    spot = None if uv is None else _surface_point_at_pixel(hits, uv)
    # saturation is expected near the source: measured from where the source
    # will be (the spot, seen with this frame's own camera pose: the beam's
    # point carries both tools' tracking errors and a pixel of the spot's own
    # glare could fall beyond exclude_mm from it)
    centre = spot if (source_from == "spot" and spot is not None) else src
    far = hits.visible & (np.linalg.norm(hits.point_mm - centre, axis=-1) > exclude_mm)
    n_sat = int(np.sum(saturated & far))
    sat_detail = f"{n_sat} pixels at saturation farther than {exclude_mm:g} mm from the source"
    if spot is None:         # a frame washed out by saturation has no spot either
        row["reason"], row["detail"] = (("saturated", sat_detail) if n_sat else
                                        ("spot not found",
                                         "no distinct bright spot on the surface"))
        return None
    miss = float(np.linalg.norm(spot - src))
    row["spot_to_beam_mm"] = round(miss, 3)
    if miss > spot_tolerance_mm:
        row["reason"] = "spot far from the beam"
        row["detail"] = f"{miss:.2f} mm > {spot_tolerance_mm:g} mm"
        return None
    if n_sat:
        row["reason"], row["detail"] = "saturated", sat_detail
        return None
    return {"image": img, "saturated": saturated, "camera_ras": cam_ras,
            "laser_ras": laser_ras, "hits": hits, "spot_ras": spot}


def _recording_info(rows, used, n, power, spot_tolerance_mm, rec, acq, t0):
    """The acquisition's summary of the recording: frames used and rejected (by
    reason), the laser power [W], the tolerances [mm, s], the time [s] since
    ``t0``.  Drops the rows' working ``laser_power_w``."""
    for r in rows:
        r.pop("laser_power_w", None)
    rejected = {}
    for r in rows:
        if not r["used"]:
            rejected.setdefault(r["reason"], []).append(r["frame"])
    return {"frames": n, "frames_used": len(used), "frames_rejected": rejected,
            "used_frames": [r["frame"] for r in used], "laser_power_w": power,
            "spot_tolerance_mm": spot_tolerance_mm, "time_sync_tolerance_s": rec["tolerance_s"],
            "measurements": acq.n_measurements, "noise_pct": acq.meta.get("noise_pct"),
            "seconds": time.perf_counter() - t0,
            "warnings": ([f"{n - len(used)} of {n} frames not used (frames.json says why)"]
                         if len(used) < n else [])}


def write_recorded_acquisition(folder, acq, rows, info):
    """The acquisition folder with its per-frame report ``frames.json``, as one
    transaction (fluoguide.atomic)."""
    from fluoguide.jsonable import dumps

    from FluoTomoLib.tomography.acquisition_file import write_acquisition

    rec = {k: info[k] for k in ("frames", "frames_used", "frames_rejected", "laser_power_w",
                                "spot_tolerance_mm", "time_sync_tolerance_s", "noise_pct")}
    extra = {"comment": "from a recorded scan: boundary fluence per watt; noise_pct is the "
                        "frames' own (each ROI mean's scatter about a plane over the ROI); "
                        "frames.json lists every frame, used or not and why"}
    if info.get("noise_pct") is not None:
        extra["noise_pct"] = info["noise_pct"]
    return write_acquisition(folder, acq, extra_files={"frames.json": dumps(
        {"frames": rows, "summary": rec})}, extra=extra)


# ------------------------------------------------------------------ rendering a recording

def _perturb(pose, trans_sd_mm, rot_sd_deg, rng):
    """A tool pose as the tracker reports it: rotated about the tool's own
    origin and moved (Gaussian, per axis)."""
    from FluoCalibLib.geometry.transforms import make_rigid, rotvec_to_matrix

    dr = rng.normal(0.0, np.deg2rad(rot_sd_deg), 3)
    dt = rng.normal(0.0, trans_sd_mm, 3)
    return pose @ make_rigid(rotvec_to_matrix(dr), np.zeros(3)) + np.pad(
        dt[:, None], ((0, 1), (3, 0)))


def record_scan(labelmap, optics, yield_by_label, out, tracking_error_mm=0.5,
                tracking_error_deg=0.1, hand_eye_error_mm=0.3, seed=0, accuracy="fast",
                laser_power_w=0.01, exposure_s=0.1, camera_distance_mm=150.0,
                missing_pose=(), saturated=(), spot_off=(), spot_off_mm=5.0, scan=None,
                progress=None, cancel=None):
    """Render a recording (the documented layout) of a tracked laser raster
    scan over the label map's inclusions, from the truth.

    The scan is ``default_scan``'s source grid; the emission light of each
    source is the FEM field on a mesh of the whole label map (the true
    optics, the fluorophore's absorption where it is), rendered into 16-bit
    frames from the camera's *true* pose, with the laser spot leaking through
    the emission filter at the true entry point, shot and read noise.  The
    written tool poses carry the tracking error (``tracking_error_mm``: the
    3D RMS of each reported tool position, ``tracking_error_deg`` per axis
    about the tool's origin, drawn anew for each pose), the written hand-eye
    calibration a ``hand_eye_error_mm`` displacement of the camera (a random
    direction), TrackerToReference the true registration.  Faults for tests,
    by frame number: ``missing_pose`` (the laser tool reported missing),
    ``saturated`` (20 times the exposure), ``spot_off`` (the laser tool's
    reported pose ``spot_off_mm`` away from where the light went).

    Returns a dict: ``folder``, ``truth`` (true sources, camera pose,
    yields), ``frames``, ``camera_gain``, ``seconds``.
    """
    from fluoguide.jsonable import dumps
    from fluoguide.progress import check_cancel, report

    from FluoTomoLib.fem.kernels import prepare_kernels
    from FluoTomoLib.tomography.accuracy import accuracy_settings
    from FluoTomoLib.tomography.simulate import MAX_SCAN_PATCHES, default_scan, whole_map_model

    t0 = time.perf_counter()
    _check_record_inputs(labelmap, optics, yield_by_label, out, tracking_error_mm,
                         tracking_error_deg, hand_eye_error_mm, seed)
    rng = np.random.default_rng(seed)
    lm = labelmap
    targets = lm.inclusion_labels()[:MAX_SCAN_PATCHES] or lm.default_target()
    src_ras, _, cfg = default_scan(lm, targets, **(scan or {}))
    S = len(src_ras)
    for name, frames_given in (("missing_pose", missing_pose), ("saturated", saturated),
                               ("spot_off", spot_off)):
        for f in frames_given:
            if not 0 <= int(f) < S:
                raise FluoInputError(f"no such frame (the scan has {S})", field=name, value=f)
    # --- the truth: FEM emission fields on the whole label map
    prepare_kernels(progress, 0.0, cancel)
    settings = accuracy_settings(accuracy)
    src_l = lm.to_local(src_ras)
    fm, mesh, y_nodes, _, _ = whole_map_model(lm, optics, yield_by_label, src_l, src_l,
                                              settings, lm.default_target(), progress, cancel)
    fields = fm.emission_fields(y_nodes)                # (N, S) per W
    fm.release()
    del fm
    check_cancel(cancel)
    # --- the camera above the scan, looking down its mean normal, true pose
    report(progress, 0.7, "camera frames")
    nrm, up, cam_true = _true_camera_pose(lm, src_ras, camera_distance_mm)
    camera, frames, gain, offset = _render_frames(lm, mesh, fields, optics, src_ras, cam_true,
                                                  camera_distance_mm, laser_power_w,
                                                  saturated, rng)
    # --- the tracked tools: true poses and what the tracker reports
    rig = _tracking_rig(cam_true, hand_eye_error_mm, rng)
    files = _frame_and_pose_files(frames, src_ras, rig, nrm, up, tracking_error_mm,
                                  tracking_error_deg, exposure_s, laser_power_w,
                                  missing_pose, spot_off, spot_off_mm, rng)
    files["calibration.json"] = json.dumps(
        _rendered_calibration(camera, rig, hand_eye_error_mm, gain, offset, exposure_s),
        indent=1)
    truth = {"yield_by_label": {str(int(k)): float(v) for k, v in yield_by_label.items()},
             "sources_ras_mm": src_ras.round(4).tolist(), "camera_to_ras": cam_true.tolist(),
             "hand_eye_true": rig.hand_eye_true.tolist(), "tracking_error_mm": tracking_error_mm,
             "tracking_error_deg": tracking_error_deg, "hand_eye_error_mm": hand_eye_error_mm,
             "seed": int(seed), "accuracy": settings["level"], "mesh_nodes": mesh.n_nodes,
             "faults": {"missing_pose": sorted(int(f) for f in missing_pose),
                        "saturated": sorted(int(f) for f in saturated),
                        "spot_off": sorted(int(f) for f in spot_off)},
             "scan": {"patches": cfg["patches"]}}
    files["recording.json"] = dumps({
        "format": FORMAT, "version": 1, "frames": "frames.csv", "poses": "poses.csv",
        "laser_tool": "LaserToolToTracker", "camera_tool": "CameraToolToTracker",
        "laser_power_w": float(laser_power_w), "exposure_s": float(exposure_s),
        "time_sync_tolerance_s": TIME_SYNC_TOLERANCE_S, "calibration": "calibration.json",
        "simulation": truth})
    _write_recording_folder(out, files)
    report(progress, 1.0, "done")
    return {"folder": str(out), "frames": S, "camera_gain": float(gain), "truth": truth,
            "seconds": time.perf_counter() - t0}


def _check_record_inputs(labelmap, optics, yield_by_label, out, tracking_error_mm,
                         tracking_error_deg, hand_eye_error_mm, seed):
    """Refuse (FluoInputError) errors [mm, deg] outside 0..10, a bad seed, yields of
    labels not in the map or none > 0 [1/mm], an output folder not writable."""
    from fluoguide import atomic

    for name, v in (("tracking_error_mm", tracking_error_mm),
                    ("tracking_error_deg", tracking_error_deg),
                    ("hand_eye_error_mm", hand_eye_error_mm)):
        if not (np.isfinite(v) and 0 <= v <= 10):
            raise FluoInputError("must be within 0..10", field=name, value=v)
    if not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2 ** 32:
        raise FluoInputError("seed must be an integer within 0..2**32-1", field="seed",
                             value=seed)
    optics.check_labels(labelmap.labels)
    for lab, v in yield_by_label.items():
        if int(lab) not in labelmap.labels:
            raise FluoInputError("label is not in the label map", field="yield", value=int(lab))
    if not any(v > 0 for v in yield_by_label.values()):
        raise FluoInputError("no label fluoresces: give a yield > 0 to at least one",
                             field="yield")
    atomic.check_writable(Path(out), folder=True)


def _true_camera_pose(lm, src_ras, camera_distance_mm):
    """The camera's true pose, ``camera_distance_mm`` [mm] above the sources' centre
    along the skin's outward normal there, looking down it.

    Returns
    -------
    nrm : (3,) the outward unit normal (RAS)
    up : (3,) the camera's up direction (RAS, not normalised)
    cam_true : 4x4 camera-to-RAS pose [mm]
    """
    from FluoCalibLib.geometry.transforms import look_at

    centre = src_ras.mean(axis=0)
    nrm = lm.vector_to_ras(lm.surface().closest(lm.to_local(centre[None]))[1])[0]
    nrm /= np.linalg.norm(nrm)
    up = np.cross(nrm, [1.0, 0.0, 0.0])
    up = up if np.linalg.norm(up) > 0.1 else np.cross(nrm, [0.0, 1.0, 0.0])
    cam_true = look_at(centre + camera_distance_mm * nrm, centre, up / np.linalg.norm(up))
    return nrm, up, cam_true


def _render_frames(lm, mesh, fields, optics, src_ras, cam_true, camera_distance_mm,
                   laser_power_w, saturated, rng):
    """The camera's 16-bit frames of each source's emission ``fields`` (per W) at
    ``laser_power_w`` [W], with the laser spot, shot and read noise; the frames
    in ``saturated`` exposed 20 times too long.

    Returns
    -------
    camera : the tomography camera
    frames : (S, H, W) counts [ADU]
    gain : float [ADU per W/mm^2/sr], 0.6 of full scale at the brightest pixel
        away from the sources
    offset : float, the frames' dark offset [ADU]
    """
    from FluoCalibLib.geometry.transforms import invert_rigid
    from FluoTomoLib.acquisition.camera_frames import (ADC_MAX_ADU, cast, expose,
                                                       exposure_gain, frame_radiance,
                                                       tomography_camera)
    from FluoTomoLib.optics import robin_A
    from FluoNavLib.mapping.pixel_cast import SurfaceCaster

    S = len(src_ras)
    mesh_ras = lm.mesh_to_ras(mesh)
    facets = mesh_ras.boundary_facets
    caster = SurfaceCaster(mesh_ras.nodes_mm, facets)
    camera = tomography_camera()
    hits = cast(caster, camera, cam_true)
    A = float(robin_A(optics.n, optics.boundary))
    radiance = frame_radiance(hits, facets, mesh_ras.nodes_mm, fields, A, laser_power_w)
    gain = exposure_gain(hits, radiance, src_ras, 3.0, field="yield")   # G at exposure_s
    # the laser's spot through the emission filter: a 0.4 mm (1 sd) Gaussian
    # at the true entry point, 50 times saturation at its centre
    uv = camera.project((invert_rigid(cam_true) @ np.c_[src_ras, np.ones(S)].T).T[:, :3])
    vv, uu = np.mgrid[0:camera.height, 0:camera.width]
    px_mm = camera_distance_mm / camera.fx
    sd_px = 0.4 / px_mm
    for s in range(S):
        spot = np.exp(-((uu - uv[s, 0]) ** 2 + (vv - uv[s, 1]) ** 2) / (2 * sd_px ** 2))
        radiance[s] += 50.0 * ADC_MAX_ADU / gain * spot
        if s in set(int(f) for f in saturated):
            radiance[s] *= 20.0
    offset = 100.0
    frames, _ = expose(radiance, gain, offset, 2.0, rng)
    return camera, frames, gain, offset


@dataclass
class _Rig:
    """The rendered tracking set-up (4x4 rigid transforms [mm]): TrackerToReference
    ``TtR`` and its inverse ``RtT``, the true and the written hand-eye
    calibrations, the camera tool's true pose in the tracker, the laser beam's
    origin [mm] and direction in the laser tool."""

    TtR: np.ndarray
    RtT: np.ndarray
    hand_eye_true: np.ndarray
    hand_eye_written: np.ndarray
    cam_tool_true: np.ndarray
    beam_o: np.ndarray
    beam_d: np.ndarray


def _tracking_rig(cam_true, hand_eye_error_mm, rng):
    """The tracking set-up (:class:`_Rig`) of a camera at ``cam_true``, the written
    hand-eye calibration ``hand_eye_error_mm`` [mm] off in a random direction."""
    from FluoCalibLib.geometry.transforms import invert_rigid, make_rigid, rotvec_to_matrix

    TtR = make_rigid(rotvec_to_matrix(np.deg2rad([3.0, -2.0, 10.0])), [40.0, -25.0, -900.0])
    RtT = invert_rigid(TtR)
    hand_eye_true = make_rigid(rotvec_to_matrix(np.deg2rad([1.0, 2.0, -3.0])), [35.0, 5.0, -20.0])
    cam_tool_true = RtT @ cam_true @ invert_rigid(hand_eye_true)
    dirn = rng.normal(size=3)
    hand_eye_written = hand_eye_true.copy()
    hand_eye_written[:3, 3] += hand_eye_error_mm * dirn / np.linalg.norm(dirn)
    beam_o, beam_d = np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, 1.0])
    return _Rig(TtR, RtT, hand_eye_true, hand_eye_written, cam_tool_true, beam_o, beam_d)


def _frame_and_pose_files(frames, src_ras, rig, nrm, up, tracking_error_mm,
                          tracking_error_deg, exposure_s, laser_power_w, missing_pose,
                          spot_off, spot_off_mm, rng):
    """The recording's frame PNGs, ``frames.csv`` and ``poses.csv`` ({name: content}):
    one frame every 0.2 s, the tools' reported poses (errors ``tracking_error_mm``
    3D RMS [mm], ``tracking_error_deg`` per axis [deg]) just before and after it,
    with the faults ``missing_pose`` and ``spot_off`` (``spot_off_mm`` [mm])."""
    import cv2

    from FluoTomoLib.acquisition.tracked_scan import laser_tool_pose_for_target

    RtT = rig.RtT
    sd_t = tracking_error_mm / np.sqrt(3.0)
    frame_rows, pose_rows = [], []
    files = {}
    dt = 0.2
    for s in range(len(src_ras)):
        t = 1.0 + dt * s
        L_true = RtT @ laser_tool_pose_for_target(src_ras[s], rig.beam_o, rig.beam_d, -nrm)
        L_rep = _perturb(L_true, sd_t, tracking_error_deg, rng)
        if s in set(int(f) for f in spot_off):
            side = np.cross(nrm, up)
            L_rep[:3, 3] += RtT[:3, :3] @ (spot_off_mm * side / np.linalg.norm(side))
        # the tracker's samples around the frame (60 Hz), tools held still
        for ts in (t - 0.008, t + 0.009):
            C_rep = _perturb(rig.cam_tool_true, sd_t, tracking_error_deg, rng)
            missing = s in set(int(f) for f in missing_pose)
            for tool, m, st in (("LaserToolToTracker", L_rep, "MISSING" if missing else "OK"),
                                ("CameraToolToTracker", C_rep, "OK")):
                vals = ([f"{v!r}" for v in m.ravel().tolist()] if st == "OK" else [""] * 16)
                pose_rows.append(",".join([f"{ts:.6f}", tool, st] + vals))
        name = f"frame_{s:04d}.png"
        ok, buf = cv2.imencode(".png", np.asarray(frames[s], np.uint16))
        files[name] = buf.tobytes()
        frame_rows.append(f"{s},{name},{t:.6f},{exposure_s!r},{laser_power_w!r}")
    mcols = ",".join(f"m{i}{j}" for i in range(4) for j in range(4))
    files["frames.csv"] = "frame,file,timestamp_s,exposure_s,laser_power_w\n" + "\n".join(
        frame_rows) + "\n"
    files["poses.csv"] = f"timestamp_s,tool,status,{mcols}\n" + "\n".join(pose_rows) + "\n"
    return files


def _rendered_calibration(camera, rig, hand_eye_error_mm, gain, offset, exposure_s):
    """The recording's calibration.json document: the camera, the written hand-eye
    calibration, TrackerToReference, the laser beam, the radiometry (``gain``
    [ADU per W/mm^2/sr], ``offset`` [ADU] at ``exposure_s`` [s])."""
    from FluoTomoLib.acquisition.camera_frames import ADC_MAX_ADU

    return {"CameraIntrinsics": camera.to_dict(),
            "HandEye": {"camera_to_tool": rig.hand_eye_written.tolist(),
                        "simulated_error_mm": float(hand_eye_error_mm)},
            "Registration": {"tracker_to_reference": rig.TtR.tolist()},
            "Laser": {"origin_mm": rig.beam_o.tolist(), "direction": rig.beam_d.tolist()},
            "Radiometry": {"gain_adu_per_radiance": float(gain), "offset_adu": offset,
                           "saturation_adu": float(ADC_MAX_ADU),
                           "reference_exposure_s": float(exposure_s)}}


def _write_recording_folder(out, files):
    """Write ``files`` ({name: bytes or str}) into the folder ``out`` as one
    transaction (fluoguide.atomic), recording.json last."""
    from fluoguide import atomic

    try:
        with atomic.staged_folder(Path(out), last=("recording.json",)) as stage:
            for name, content in files.items():
                if isinstance(content, bytes):
                    (stage / name).write_bytes(content)
                else:
                    (stage / name).write_text(content, encoding="utf-8")
    except OSError as exc:
        raise atomic.output_error(exc, Path(out)) from None
