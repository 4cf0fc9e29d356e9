"""Recording tracked frames to disk incrementally, and replaying them.

A recording folder holds one ``frame_NNNNNN.npy`` per camera frame and an
append-only ``log.jsonl`` with one line per frame (time, exposure, pose
validity and status, and each tool's 4x4 pose).  Each frame is written to a
temporary name, fsynced and renamed before its log line is appended and
fsynced, so a crash loses at most the frame in flight and never leaves a log
line without its image.  JSON writes floats with Python's shortest round-trip
repr, so replayed poses equal the recorded ones bit for bit.

``to_scene`` turns a folder into the MRML form of ``frame_store`` (for 3D
Slicer and the app); ``replay`` yields the frames at the recorded pace or as
fast as possible.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.jsonable import loads

__all__ = ["Recorder", "read_recording", "replay", "to_scene"]


class Recorder:
    """Append tracked frames to ``folder`` (created; must be empty or new)."""

    def __init__(self, folder, tools=("CameraToolToTracker",)):
        from fluoguide import atomic

        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise FluoInputError("output exists and is not a folder", file=self.folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            raise FluoInputError("recording folder exists and is not empty", file=self.folder)
        atomic.check_writable(self.folder, folder=True)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            # an existing folder that refuses files (EACCES/EPERM, root too, where
            # os.access said yes): one line naming it, not a traceback
            self._log = open(self.folder / "log.jsonl", "a", encoding="utf-8")
        except OSError as exc:
            raise atomic.output_error(exc, self.folder) from None
        self.tools = list(tools)
        self.n = 0
        self._last_t = None
        header = {"format": "fluoguide-recording/1", "tools": self.tools}
        self._append(header)

    def _append(self, doc):
        self._log.write(json.dumps(doc) + "\n")
        self._log.flush()
        os.fsync(self._log.fileno())

    def add(self, image, timestamp_s, poses, exposure_s=None, pose_valid=True, pose_status="OK"):
        """Write one frame; returns its number."""
        img = np.asarray(image)
        if img.ndim != 2 or img.size == 0:
            raise FluoInputError("camera frame must be a non-empty 2D array", field="image",
                                 value=getattr(img, "shape", None))
        t = float(timestamp_s)
        if not np.isfinite(t) or (self._last_t is not None and t <= self._last_t):
            raise FluoInputError("frame timestamps must be finite and increase",
                                 field="timestamp_s", value=timestamp_s)
        name = f"frame_{self.n:06d}.npy"
        tmp = self.folder / (name + ".tmp")
        with open(tmp, "wb") as f:
            np.save(f, img)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.folder / name)
        doc = {"frame": self.n, "file": name, "timestamp_s": t,
               "exposure_s": None if exposure_s is None else float(exposure_s),
               "pose_valid": bool(pose_valid), "pose_status": str(pose_status), "poses": {}}
        for tool in self.tools:
            m = (poses or {}).get(tool)
            doc["poses"][tool] = None if m is None else [float(v) for v in np.asarray(m, float).ravel()]
        self._append(doc)
        self._last_t = t
        self.n += 1
        return self.n - 1

    def close(self):
        if not self._log.closed:
            self._log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _frame_doc(doc, folder, log, line, tools):
    """Check one log line's frame record (a damaged log is named, never half used)."""
    from fluoguide.paths import inside

    where = f"line {line}"
    if not isinstance(doc, dict):
        raise FluoInputError("log line is not a JSON object", file=log, field=where)
    for key in ("file", "timestamp_s", "poses"):
        if key not in doc:
            raise FluoInputError(f"log line lacks '{key}'", file=log, field=where)
    t = doc["timestamp_s"]
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not np.isfinite(t):
        raise FluoInputError("timestamp must be a finite number [s]", file=log,
                             field=f"{where}.timestamp_s", value=t)
    e = doc.get("exposure_s")
    if e is not None and (isinstance(e, bool) or not isinstance(e, (int, float))
                          or not np.isfinite(e) or e < 0):
        raise FluoInputError("exposure must be a non-negative number [s]", file=log,
                             field=f"{where}.exposure_s", value=e)
    if not isinstance(doc["poses"], dict):
        raise FluoInputError("poses must be an object of tool -> 16 numbers", file=log,
                             field=f"{where}.poses")
    poses = {}
    for tool, v in doc["poses"].items():
        if v is None:
            poses[tool] = None
            continue
        try:
            m = np.array(v, dtype=float)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.size != 16 or not np.all(np.isfinite(m)):
            raise FluoInputError("a pose must be 16 finite numbers (4x4, row-major)", file=log,
                                 field=f"{where}.poses.{tool}")
        poses[tool] = m.reshape(4, 4)
    path = inside(folder, doc["file"], file=log, field=f"{where}.file", given=True)
    if not path.is_file():
        raise FluoInputError("frame file of the log is missing", file=path)
    return {"frame": doc.get("frame", line - 2), "file": doc["file"], "path": path,
            "timestamp_s": float(t), "exposure_s": None if e is None else float(e),
            "pose_valid": bool(doc.get("pose_valid", True)),
            "pose_status": str(doc.get("pose_status", "OK")), "poses": poses}


def read_recording(folder):
    """(tools, list of frame dicts with their ``path``, checked).

    A last log line cut by a crash is ignored; a frame file missing for a
    complete line, a file name outside the folder, a damaged pose or a
    timestamp that is not finite or does not increase is an error naming the
    line.
    """
    folder = Path(folder)
    log = folder / "log.jsonl"
    if not folder.is_dir():
        raise FluoInputError("recording folder not found", file=folder)
    if not log.is_file():
        raise FluoInputError("not a recording (no log.jsonl)", file=folder)
    try:
        lines = log.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise FluoInputError("recording log is not UTF-8 text", file=log) from None
    if not lines:
        raise FluoInputError("empty recording log", file=log)
    try:
        header = loads(lines[0], file=log, field="line 1")
    except (json.JSONDecodeError, RecursionError):
        raise FluoInputError("corrupt recording header", file=log, field="line 1") from None
    if not isinstance(header, dict) or not isinstance(header.get("tools", []), list):
        raise FluoInputError("recording header must be an object with a 'tools' list", file=log,
                             field="line 1")
    frames = []
    for k, line in enumerate(lines[1:], start=2):
        try:
            doc = loads(line, file=log, field=f"line {k}")
        except (json.JSONDecodeError, RecursionError):
            if k == len(lines):
                break             # the frame in flight when the recorder died
            raise FluoInputError("corrupt log line", file=log, field=f"line {k}") from None
        frame = _frame_doc(doc, folder, log, k, header.get("tools", []))
        if frames and not frame["timestamp_s"] > frames[-1]["timestamp_s"]:
            raise FluoInputError("timestamps must increase", file=log,
                                 field=f"line {k}.timestamp_s", value=frame["timestamp_s"])
        frames.append(frame)
    return [str(t) for t in header.get("tools", [])], frames


def _load_frame(doc):
    from fluoguide.images import read_image

    return read_image(doc["path"])


# a longer pause between two recorded frames is replayed as this long (it is
# counted): a damaged timestamp must not make a replay wait for days
MAX_REPLAY_GAP_S = 5.0


def replay(folder, speed="recorded", stats=None):
    """Yield (image, info, poses) in order; ``speed`` "recorded" keeps the
    recorded intervals (a pause longer than ``MAX_REPLAY_GAP_S`` is shortened
    to it and counted in ``stats["gaps_shortened"]``), "max" goes as fast as
    the disk allows."""
    _, frames = read_recording(folder)
    stats = {} if stats is None else stats
    stats["gaps_shortened"] = 0
    t_wall0 = time.monotonic()
    shift = 0.0                       # recorded time skipped by shortened gaps
    prev = frames[0]["timestamp_s"] if frames else 0.0
    t_rec0 = prev
    for doc in frames:
        if speed == "recorded":
            gap = doc["timestamp_s"] - prev
            if gap > MAX_REPLAY_GAP_S:
                shift += gap - MAX_REPLAY_GAP_S
                stats["gaps_shortened"] += 1
            wait = (doc["timestamp_s"] - t_rec0 - shift) - (time.monotonic() - t_wall0)
            if wait > 0:
                time.sleep(wait)
        prev = doc["timestamp_s"]
        info = {k: doc[k] for k in ("frame", "timestamp_s", "exposure_s", "pose_valid", "pose_status")}
        yield _load_frame(doc), info, doc["poses"]


def to_scene(folder, scene=None):
    """The recording as ``frame_store`` nodes in a (new) MRML scene."""
    from fluoguide import mrml_io

    from FluoNavLib.devices import frame_store

    tools, frames = read_recording(folder)
    scene = scene or mrml_io.new_scene()
    frame_store.new_recording(scene, tools=tools)
    for doc in frames:
        frame_store.append_tracked_frame(scene, _load_frame(doc), doc["timestamp_s"],
                                         doc["poses"], doc["exposure_s"], doc["pose_valid"],
                                         doc["pose_status"])
    return scene
