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

__all__ = ["Recorder", "read_recording", "replay", "to_scene"]


class Recorder:
    """Append tracked frames to ``folder`` (created; must be empty or new)."""

    def __init__(self, folder, tools=("CameraToolToTracker",)):
        self.folder = Path(folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            raise FluoInputError("recording folder exists and is not empty", file=self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.tools = list(tools)
        self.n = 0
        self._last_t = None
        self._log = open(self.folder / "log.jsonl", "a", encoding="utf-8")
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


def read_recording(folder):
    """(tools, list of frame dicts with ``image`` loaded lazily via ``load()``).

    A last log line cut by a crash is ignored; a frame file missing for a
    complete line is an error naming it.
    """
    folder = Path(folder)
    log = folder / "log.jsonl"
    if not log.is_file():
        raise FluoInputError("not a recording (no log.jsonl)", file=folder)
    lines = log.read_text(encoding="utf-8").splitlines()
    if not lines:
        raise FluoInputError("empty recording log", file=log)
    try:
        header = json.loads(lines[0])
    except json.JSONDecodeError:
        raise FluoInputError("corrupt recording header", file=log, field="line 1") from None
    frames = []
    for k, line in enumerate(lines[1:], start=2):
        try:
            doc = json.loads(line)
        except json.JSONDecodeError:
            if k == len(lines):
                break             # the frame in flight when the recorder died
            raise FluoInputError("corrupt log line", file=log, field=f"line {k}") from None
        path = folder / doc["file"]
        if not path.is_file():
            raise FluoInputError("frame file of the log is missing", file=path)
        doc["path"] = path
        frames.append(doc)
    return header.get("tools", []), frames


def _poses(doc):
    return {tool: None if v is None else np.array(v, float).reshape(4, 4)
            for tool, v in doc["poses"].items()}


def replay(folder, speed="recorded"):
    """Yield (image, info, poses) in order; ``speed`` "recorded" keeps the
    recorded intervals, "max" goes as fast as the disk allows."""
    _, frames = read_recording(folder)
    t_wall0 = time.monotonic()
    t_rec0 = frames[0]["timestamp_s"] if frames else 0.0
    for doc in frames:
        if speed == "recorded":
            wait = (doc["timestamp_s"] - t_rec0) - (time.monotonic() - t_wall0)
            if wait > 0:
                time.sleep(wait)
        info = {k: doc[k] for k in ("frame", "timestamp_s", "exposure_s", "pose_valid", "pose_status")}
        yield np.load(doc["path"]), info, _poses(doc)


def to_scene(folder, scene=None):
    """The recording as ``frame_store`` nodes in a (new) MRML scene."""
    from fluoguide import mrml_io

    from FluoNavLib.devices import frame_store

    tools, frames = read_recording(folder)
    scene = scene or mrml_io.new_scene()
    frame_store.new_recording(scene, tools=tools)
    for doc in frames:
        frame_store.append_tracked_frame(scene, np.load(doc["path"]), doc["timestamp_s"],
                                         _poses(doc), doc["exposure_s"], doc["pose_valid"],
                                         doc["pose_status"])
    return scene
