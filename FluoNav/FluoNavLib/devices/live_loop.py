"""The live loop: tracker poses + camera frames -> one callback per frame.

A tracker thread polls the NDI client and feeds one :class:`PoseBuffer` per
tool; the frames of a ``frame_sources`` source are matched to the poses
interpolated at their time and handed to ``callback(image, info, poses)``
(the FluoNav mapping, a :class:`Recorder`, a display: any callable).  A frame
whose pose is not ``OK`` for every tool is still delivered, with
``info["pose_valid"]`` False and ``info["pose_status"]``, and its poses None:
the callback must not map it.

With ``drop_policy="latest"`` a grabber thread keeps only the newest frame
while the callback is busy (bounded latency for live use); each frame it
replaces is counted in ``dropped_slow``.  With ``"none"`` every frame is
processed (files, recording).  Frame accounting is exact: over the source's
sequence numbers, ``delivered + dropped_slow + dropped_upstream`` equals the
frames expected, and ``lost_unreported`` reports the difference (must be 0).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from fluoguide.errors import FluoInputError

from FluoNavLib.devices.timesync import PoseBuffer

__all__ = ["LiveLoop"]


class _Tracker(threading.Thread):
    """Polls ``client`` in short chunks until stopped, feeding the buffers."""

    def __init__(self, client, tools, buffers, lock):
        super().__init__(daemon=True, name="fluo-tracker")
        self.client, self.tools, self.buffers, self.lock = client, tools, buffers, lock
        self.stop_event = threading.Event()
        self.error = None

    def _on_frame(self, reply, t_host):
        with self.lock:
            for name, handle in self.tools.items():
                p = reply.tools.get(handle)
                ok = p is not None and p.state == "OK"
                self.buffers[name].add(t_host, p.matrix() if ok else None)

    def run(self):
        try:
            while not self.stop_event.is_set():
                self.client.track(0.05, on_frame=self._on_frame)
        except Exception as exc:  # recovery failed: reported by the loop, never swallowed
            self.error = exc


class LiveLoop:
    """Run ``callback(image, info, poses)`` for every frame of ``frames``.

    Parameters
    ----------
    frames : a ``frame_sources`` source (``read()`` -> Frame or None)
    callback : callable(image, info, poses)
    tracker : NDIClient, initialised and started, or None (poses recorded in
        the frames are used, e.g. a ``RecordingSource``)
    tools : dict tool name -> port handle of the tracker
    camera_latency_s, tracker_latency_s : fixed delays [s] of each source
        (measured, e.g. with ``timesync.estimate_latency``)
    pose_wait_s : how long a frame waits for a pose newer than itself [s]
    drop_policy : "latest" (live) or "none" (process every frame)
    """

    def __init__(self, frames, callback, tracker=None, tools=None, camera_latency_s=0.0,
                 tracker_latency_s=0.0, pose_wait_s=0.1, drop_policy="latest",
                 max_gap_s=0.05, max_age_s=0.1):
        if not callable(callback):
            raise FluoInputError("callback must be callable", field="callback", value=callback)
        if drop_policy not in ("latest", "none"):
            raise FluoInputError("drop_policy must be 'latest' or 'none'", field="drop_policy",
                                 value=drop_policy)
        self.frames, self.callback, self.tracker = frames, callback, tracker
        self.tools = dict(tools or {"CameraToolToTracker": 1})
        self.camera_latency_s = float(camera_latency_s)
        self.pose_wait_s = float(pose_wait_s)
        self.drop_policy = drop_policy
        self.lock = threading.Lock()
        self.buffers = {name: PoseBuffer(tracker_latency_s, max_gap_s, max_age_s)
                        for name in self.tools}
        self.counters = {"frames_in": 0, "delivered": 0, "dropped_slow": 0, "dropped_upstream": 0,
                         "pose_invalid": 0, "pose_status": {}}
        self.latency_ms = []      # callback start - frame time (live sources)
        self._first_seq = self._last_seq = None

    # -- frames ----------------------------------------------------------------
    def _count_in(self, frame):
        c = self.counters
        c["frames_in"] += 1
        if self._last_seq is not None and frame.sequence > self._last_seq + 1:
            c["dropped_upstream"] += frame.sequence - self._last_seq - 1
        if self._first_seq is None:
            self._first_seq = frame.sequence
        self._last_seq = frame.sequence

    def _grabber(self, box, cond, stop):
        """Keep the newest frame in ``box`` (drop_policy "latest")."""
        try:
            while not stop.is_set():
                f = self.frames.read()
                with cond:
                    if f is None:             # end of source: after the frame still waiting
                        box.append(None)
                    else:
                        self._count_in(f)
                        if box:               # the callback is behind: replace, counted
                            self.counters["dropped_slow"] += 1
                        box[:] = [f]
                    cond.notify()
                if f is None:
                    return
        except Exception as exc:
            with cond:
                box.append(exc)
                cond.notify()

    # -- poses -----------------------------------------------------------------
    def _poses_at(self, t):
        """({tool: 4x4 or None}, status) at frame time ``t`` (waits for a newer pose)."""
        deadline = time.monotonic() + self.pose_wait_s
        while True:
            with self.lock:
                newest = min((b.latest_time() or -np.inf) for b in self.buffers.values())
            if newest >= t or time.monotonic() >= deadline:
                break
            time.sleep(0.002)
        poses, status = {}, "OK"
        with self.lock:
            for name, buf in self.buffers.items():
                m, s = buf.at(t)
                poses[name] = m
                if s != "OK" and status == "OK":
                    status = s
        return poses, status

    def _deliver(self, frame, live):
        t = frame.timestamp_s - self.camera_latency_s
        if self.tracker is not None:
            poses, status = self._poses_at(t)
        else:
            poses = dict(frame.poses or {})
            status = frame.info.get("pose_status", "OK" if poses else "MISSING")
            if not frame.info.get("pose_valid", bool(poses)) and status == "OK":
                status = "MISSING"
        valid = status == "OK" and all(m is not None for m in poses.values())
        if not valid:
            poses = {name: None for name in poses}   # never hand out a pose that is not OK
            self.counters["pose_invalid"] += 1
            self.counters["pose_status"][status] = self.counters["pose_status"].get(status, 0) + 1
        info = {"frame": self.counters["delivered"], "sequence": frame.sequence, "timestamp_s": t,
                "exposure_s": frame.exposure_s, "pose_valid": valid,
                "pose_status": "OK" if valid else status}
        if live:
            self.latency_ms.append(1000.0 * (time.monotonic() - frame.timestamp_s))
        self.counters["delivered"] += 1
        self.callback(frame.image, info, poses)

    # -- run -------------------------------------------------------------------
    def run(self, seconds=None, max_frames=None, live=True):
        """Process frames until the source ends, ``seconds`` pass or ``max_frames``
        are delivered; returns the counters (and the tracker's, if any).

        ``live``: frame timestamps are host ``time.monotonic()`` (latency measured).
        """
        t_end = None if seconds is None else time.monotonic() + float(seconds)
        tracker = None
        if self.tracker is not None:
            tracker = _Tracker(self.tracker, self.tools, self.buffers, self.lock)
            tracker.start()
        stop, cond, box, grab = threading.Event(), threading.Condition(), [], None
        if self.drop_policy == "latest":
            grab = threading.Thread(target=self._grabber, args=(box, cond, stop), daemon=True,
                                    name="fluo-grabber")
            grab.start()
        try:
            while (t_end is None or time.monotonic() < t_end) and \
                    (max_frames is None or self.counters["delivered"] < max_frames):
                if tracker is not None and tracker.error is not None:
                    raise tracker.error
                if grab is None:
                    frame = self.frames.read()
                    if frame is None:
                        break
                    self._count_in(frame)
                else:
                    with cond:
                        cond.wait_for(lambda: bool(box), timeout=0.1)
                        if not box:
                            continue
                        frame = box.pop(0)
                    if isinstance(frame, Exception):
                        raise frame
                    if frame is None:
                        break
                self._deliver(frame, live)
        finally:
            stop.set()
            if grab is not None:
                grab.join(timeout=5.0)
                with cond:        # a frame grabbed after the end is counted, not lost
                    self.counters["dropped_slow"] += sum(
                        x is not None and not isinstance(x, Exception) for x in box)
                    box.clear()
            if tracker is not None:
                tracker.stop_event.set()
                tracker.join(timeout=5.0)
        return self.report()

    def report(self):
        c = dict(self.counters)
        expected = 0 if self._first_seq is None else self._last_seq - self._first_seq + 1
        c["lost_unreported"] = expected - c["delivered"] - c["dropped_slow"] - c["dropped_upstream"]
        lat = np.array(self.latency_ms)
        c["latency_ms"] = None if lat.size == 0 else {
            "median": float(np.median(lat)), "p95": float(np.percentile(lat, 95)),
            "max": float(lat.max())}
        if self.tracker is not None:
            s = self.tracker.stats
            c["tracker"] = {"frames": s.frames, "missing": s.missing, "crc_errors": s.crc_errors,
                            "timeouts": s.timeouts, "recovered": s.recovered,
                            "lost_unreported": s.lost_unreported()}
        return c
