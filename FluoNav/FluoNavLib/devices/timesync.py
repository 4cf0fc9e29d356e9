"""Time synchronisation of tracker poses to camera frames.

Each source stamps its samples with its own clock; a fixed latency [s] per
source (measured, e.g. with :func:`estimate_latency`) maps them to one time
base.  :class:`PoseBuffer` keeps a tool's recent poses and gives the pose at a
frame time by SLERP (rotation) and linear interpolation (translation), with a
status: ``OK``, ``STALE`` (the nearest samples are too far apart or too old:
the watchdog), ``MISSING`` (the tool was not seen around that time) or
``EXTRAPOLATION`` refused (the frame is newer than the last pose).  A frame
without an ``OK`` pose is flagged and must not be mapped.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from FluoCalibLib.geometry.transforms import matrix_to_quaternion, quaternion_to_matrix, slerp

__all__ = ["PoseBuffer", "estimate_latency"]


class PoseBuffer:
    """Recent poses of one tool, interpolated to arbitrary times."""

    def __init__(self, latency_s=0.0, max_gap_s=0.05, max_age_s=0.1, capacity=4096):
        self.latency_s = float(latency_s)
        self.max_gap_s = float(max_gap_s)
        self.max_age_s = float(max_age_s)
        self._t = deque(maxlen=capacity)
        self._m = deque(maxlen=capacity)

    def add(self, t_source_s, matrix):
        """A sample at the source's time; ``matrix`` None = tool missing then."""
        t = float(t_source_s) - self.latency_s
        if self._t and t <= self._t[-1]:
            return False             # out of order or duplicate: ignored
        self._t.append(t)
        self._m.append(None if matrix is None else np.asarray(matrix, float))
        return True

    def latest_time(self):
        return self._t[-1] if self._t else None

    def at(self, t_s):
        """(4x4 or None, status) at time ``t_s`` (common time base)."""
        if not self._t:
            return None, "MISSING"
        ts = list(self._t)
        k = bisect.bisect_left(ts, t_s)
        if k == len(ts):
            age = t_s - ts[-1]
            if age <= 1e-9 and self._m[-1] is not None:
                return self._m[-1].copy(), "OK"
            return None, ("STALE" if age > self.max_age_s else "EXTRAPOLATION")
        if ts[k] == t_s:
            m = self._m[k]
            return (None, "MISSING") if m is None else (m.copy(), "OK")
        if k == 0:
            return None, "MISSING"
        t0, t1 = ts[k - 1], ts[k]
        m0, m1 = self._m[k - 1], self._m[k]
        if m0 is None or m1 is None:
            return None, "MISSING"
        if t1 - t0 > self.max_gap_s:
            return None, "STALE"
        a = (t_s - t0) / (t1 - t0)
        q = slerp(matrix_to_quaternion(m0[:3, :3]), matrix_to_quaternion(m1[:3, :3]), a)
        out = np.eye(4)
        out[:3, :3] = quaternion_to_matrix(q)
        out[:3, 3] = (1 - a) * m0[:3, 3] + a * m1[:3, 3]
        return out, "OK"


def estimate_latency(t_a, signal_a, t_b, signal_b, max_lag_s=0.5, step_s=0.001):
    """Delay [s] of signal b relative to signal a (b(t) ~ a(t - lag)), by the peak
    of the normalised cross-correlation of the two motion signals (e.g. the
    speed of a tool seen by the tracker and by the camera), resampled on a
    common grid."""
    t_a, t_b = np.asarray(t_a, float), np.asarray(t_b, float)
    lo, hi = max(t_a[0], t_b[0]) + max_lag_s, min(t_a[-1], t_b[-1]) - max_lag_s
    if hi - lo < 4 * max_lag_s:
        from fluoguide.errors import FluoInputError

        raise FluoInputError("signals overlap too little for the lag range", field="signals",
                             value=(lo, hi))
    grid = np.arange(lo, hi, step_s)
    a = np.interp(grid, t_a, signal_a)
    a = (a - a.mean()) / (a.std() + 1e-12)
    best, best_lag = -np.inf, 0.0
    for lag in np.arange(-max_lag_s, max_lag_s + step_s / 2, step_s):
        b = np.interp(grid + lag, t_b, signal_b)
        b = (b - b.mean()) / (b.std() + 1e-12)
        c = float(np.mean(a * b))
        if c > best:
            best, best_lag = c, float(lag)
    return best_lag
