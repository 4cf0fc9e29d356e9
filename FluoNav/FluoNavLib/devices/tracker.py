"""One interface over the pose sources: an NDI tracker on a serial port (or
the simulator on a pseudo-terminal), an OpenIGTLink server, a recording.

A :class:`TrackerSession` is opened by :func:`open_tracker`; ``poll()`` gives
the newest poses ``{tool: 4x4 or None}`` (None: the tool is missing),
``track(seconds)`` runs for a while and returns the session's account of every
frame (the numbers ``fluo track`` prints), ``close()`` ends it. ``track`` is the
one live-tracking loop: ``fluo track`` runs it for a fixed time, the web app's
stream (``FluoNavLogic.streamPhantomFrames``) with a callback per frame until it
stops it. The FluoNav logic writes polled poses into transform nodes
(``CameraToolToTracker``); the Slicer widget polls on a timer.

Bad input (no port, a malformed address, a duration that is not finite) is a
FluoInputError; a device that answers nothing usable is a FluoDeviceError.
"""

from __future__ import annotations

import abc
import math
import time

import numpy as np

from fluoguide.errors import FluoDeviceError, FluoInputError

__all__ = ["SOURCES", "TrackerSession", "NDITracker", "IGTLTracker", "ReplayTracker",
           "open_tracker", "check_seconds", "parse_host_port", "finite_pose"]

#: Pose sources :func:`open_tracker` knows.
SOURCES = ("ndi", "ndi-sim", "igtl", "replay")


def check_seconds(value, field="--seconds"):
    """A tracking duration: finite, positive, at most a day (inf never ends, NaN never starts)."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise FluoInputError("must be a number of seconds", field=field, value=value) from None
    if not math.isfinite(value) or value <= 0 or value > 86400:
        raise FluoInputError("must be a number of seconds in (0, 86400]", field=field, value=value)
    return value


def parse_host_port(address, field="--igtl"):
    """``HOST:PORT`` -> (host, port)."""
    host, _, port = str(address or "").rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise FluoInputError("expected HOST:PORT", field=field, value=address)
    return host, int(port)


class TrackerSession(abc.ABC):
    """A connected pose source (see the module docstring)."""

    source = ""

    @abc.abstractmethod
    def poll(self):
        """The latest poses {tool name: 4x4 or None}, or None when nothing new."""

    @abc.abstractmethod
    def track(self, seconds, on_poses=None, stop=None):
        """Track for ``seconds`` [s] or until ``stop()`` is true (asked before each
        read); ``on_poses(poses, t_host)`` per frame; returns the statistics."""

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class NDITracker(TrackerSession):
    """An NDI tracker (serial port) or the protocol-faithful simulator.

    Parameters
    ----------
    port : str, optional
        Serial port of a real tracker; None with ``simulate``.
    simulate : bool
        Start an ``NDISimulator`` on a pseudo-terminal (``sim_tools`` moving
        tools, the faults ``inject_faults`` names: True for the typical ones, or
        a comma-separated list of ``ndi_simulator.FAULT_KINDS``).
    tools : int
        Passive tools to request from a real tracker (the simulator has two).
    tool_names : sequence of str
        Transform-node name of each port handle in order (handle 1 first).
    """

    def __init__(self, port=None, simulate=False, inject_faults=False, seed=0, tools=1,
                 tool_names=("CameraToolToTracker",), sim_tools=None, roms=None):
        from FluoNavLib.devices import ndi_simulator
        from FluoNavLib.devices.ndi_client import NDIClient
        from FluoNavLib.devices.ndi_protocol import NDIProtocolError

        self.source = "ndi-sim" if simulate else "ndi"
        self.sim = None
        if simulate:
            faults = ndi_simulator.Faults.named(inject_faults)
            kw = {"faults": faults, "seed": seed}
            if sim_tools is not None:
                kw["tools"] = list(sim_tools)
            self.sim = ndi_simulator.NDISimulator(**kw)
            port = self.sim.start()
        elif not port:
            raise FluoInputError("choose a simulated tracker or a serial port", field="source")
        self.port = port
        self.tool_names = tuple(tool_names)
        self.last_frame = None   # the device's frame number of the last new frame
        try:
            try:
                self.client = NDIClient(port).open()
            except Exception as exc:
                raise FluoInputError(f"cannot open serial port ({exc})", field="--serial",
                                     value=port) from None
            if roms is None:
                n = (2 if sim_tools is None else len(sim_tools)) if simulate else int(tools)
                roms = [b"FluoGuide sim tool " * 4] * n
            try:
                self.client.initialize(roms)
                self.client.start()
            except NDIProtocolError as exc:
                raise FluoDeviceError(f"tracker on {port} could not be set up: {exc} "
                                      f"({self._faults()})") from None
        except BaseException:
            self.close()
            raise
        self._failures = 0

    def _faults(self):
        """The client's fault counts, in words (for an error message)."""
        st = self.client.stats
        return (f"CRC errors {st.crc_errors}, time-outs {st.timeouts}, malformed "
                f"{st.malformed}, device errors {st.device_errors}, unrequested replies "
                f"{st.duplicate_replies}, recoveries {st.recovered}")

    def _poses(self, reply):
        """``{tool: 4x4 or None}`` of a new frame; notes its device frame number."""
        frames = [p.frame for p in reply.tools.values() if p.frame is not None]
        self.last_frame = max(frames) if frames else self.last_frame
        poses = {}
        for k, name in enumerate(self.tool_names):
            p = reply.tools.get(k + 1)
            poses[name] = p.matrix() if p is not None and p.state == "OK" else None
        return poses

    def poll(self):
        """One TX request: ``{tool: 4x4 or None}``, or None when no new frame came
        (a duplicate, or a fault that was counted and, after repeated faults,
        recovered from)."""
        from FluoNavLib.devices.ndi_protocol import NDIProtocolError

        try:
            reply = self.client.poll()
            self._failures = 0
        except NDIProtocolError as exc:
            if exc.kind == "duplicate":    # resynchronised (a device that keeps it up is refused)
                return None
            self._failures += 1
            if self._failures >= self.client.max_failures:
                if not self.client.recover():
                    raise FluoDeviceError(f"tracker on {self.port}: {exc}, and it did not "
                                          f"recover ({self._faults()})") from None
                self._failures = 0
            return None
        if reply is None:
            return None
        return self._poses(reply)

    def track(self, seconds, on_poses=None, stop=None):
        """Track for ``seconds`` [s] or until ``stop()`` is true (asked before each
        poll); ``on_poses(poses, t_host)`` per new frame (``last_frame`` is its
        device frame number meanwhile).

        Returns the account of ``fluo track``: frames, rate, reported gaps and
        faults, ``lost_unreported`` (computed, must be 0), simulator counters.
        Raises FluoDeviceError when the tracker delivered no frame at all (unless
        ``stop`` ended the run).
        """
        from FluoNavLib.devices.ndi_protocol import NDIProtocolError

        seconds = check_seconds(seconds)
        callback = None if on_poses is None else (lambda reply, t: on_poses(self._poses(reply), t))
        stopped = []

        def halt():
            if stop is not None and stop():
                stopped.append(True)
                return True
            return False

        t0 = time.monotonic()
        try:
            stats = self.client.track(seconds, on_frame=callback, stop=halt)
        except NDIProtocolError as exc:
            # failures in a row and every recovery attempt failed: one device error
            raise FluoDeviceError(f"tracker on {self.port}: {exc}, and it did not recover "
                                  f"({self._faults()})") from None
        elapsed = time.monotonic() - t0
        if stats.frames == 0 and not stopped:
            # a tracker that answered nothing usable is a failed run, not an empty success
            raise FluoDeviceError(
                f"tracker on {self.port} delivered no frames in {elapsed:.1f} s "
                f"({self._faults()})")
        return {"frames": stats.frames, "rate_hz": stats.frames / elapsed, "seconds": elapsed,
                "missing": stats.missing, "tool_missing": stats.tool_missing,
                "out_of_volume": stats.out_of_volume, "crc_errors": stats.crc_errors,
                "timeouts": stats.timeouts, "malformed": stats.malformed,
                "device_errors": stats.device_errors, "recovered": stats.recovered,
                "duplicate_replies": stats.duplicate_replies,
                "late_replies": stats.late_replies, "stale_replies": stats.stale_replies,
                "counter_jumps": stats.counter_jumps,
                "lost_unreported": stats.lost_unreported(), "segments": stats.segments,
                "simulator": self.sim.counters if self.sim is not None else None}

    def close(self):
        client, self.client = getattr(self, "client", None), None
        try:
            if client is not None and client.serial is not None:
                try:
                    client.stop()
                except Exception:  # the device may be gone already; closing must still happen
                    pass
                client.close()
        finally:
            sim, self.sim = self.sim, None
            if sim is not None:
                sim.stop()


class IGTLTracker(TrackerSession):
    """An OpenIGTLink server (PLUS or any other): TRANSFORM messages update the
    transform nodes of their device names in ``scene`` as they arrive."""

    source = "igtl"

    def __init__(self, scene, address, rate_hz=None):
        from FluoNavLib.devices.igtl_client import IGTLReceiver

        host, port = parse_host_port(address)
        self.receiver = IGTLReceiver(scene, host, port, nominal_rate_hz=rate_hz).connect()

    def poll(self):
        from fluoguide import mrml_io

        updated = self.receiver.poll(budget_s=0.02)
        poses = {}
        for name in updated:
            node = mrml_io.get_node(self.receiver.scene, name, required=False)
            if node is not None and node.IsA("vtkMRMLLinearTransformNode"):
                poses[name] = mrml_io.transform_matrix(node)
        return poses or None

    def track(self, seconds, on_poses=None, stop=None):
        """Apply messages for ``seconds`` [s] or until ``stop()`` is true; the
        messages update their nodes themselves (``on_poses`` is not called)."""
        seconds = check_seconds(seconds)
        out = self.receiver.receive(seconds, stop=stop)
        out["seconds"] = seconds
        return out

    def close(self):
        self.receiver.close()


class ReplayTracker(TrackerSession):
    """A recording (``fluo record``) played back: poses bit-exact, at the
    recorded pace or as fast as possible (``speed="max"``)."""

    source = "replay"

    def __init__(self, folder, speed="recorded"):
        from FluoNavLib.devices.recorder import read_recording, replay

        read_recording(folder)  # refuses a folder that is not a recording, now
        self.folder = folder
        self._frames = replay(folder, speed)
        self.last_image = None
        self.last_info = None

    @staticmethod
    def _valid(info, poses):
        # a frame recorded without a valid pose keeps the tracker's last numbers
        # in its log line; they must never reach a transform node
        return {k: (v if info["pose_valid"] else None) for k, v in poses.items()}

    def poll(self):
        """The next recorded frame's poses (None for every tool of a frame without a
        valid pose), or None at the end of the recording."""
        try:
            image, info, poses = next(self._frames)
        except StopIteration:
            return None
        self.last_image, self.last_info = image, info
        return self._valid(info, poses)

    def track(self, seconds=None, on_poses=None, stop=None):
        """Play to the end (or for ``seconds`` [s], or until ``stop()`` is true):
        frames and frames with a valid pose."""
        t_end = None if seconds is None else time.monotonic() + check_seconds(seconds)
        n = valid = 0
        t0 = time.monotonic()
        while not (stop is not None and stop()):    # asked before a frame is taken
            item = next(self._frames, None)
            if item is None:
                break
            _, info, poses = item
            n += 1
            valid += bool(info["pose_valid"])
            if on_poses is not None:
                on_poses(self._valid(info, poses), time.monotonic())
            if t_end is not None and time.monotonic() >= t_end:
                break
        return {"frames": n, "frames_with_pose": valid, "seconds": time.monotonic() - t0}


def open_tracker(source, address=None, scene=None, **options):
    """A :class:`TrackerSession` of ``source`` (one of :data:`SOURCES`).

    ``address``: the serial port (``ndi``), ``HOST:PORT`` (``igtl``), the
    recording folder (``replay``); unused for ``ndi-sim``. ``options`` go to
    the session class (``inject_faults``, ``seed``, ``tools``, ``rate_hz``,
    ``speed`` ...). ``igtl`` needs the ``scene`` its messages update.
    """
    if source == "ndi":
        return NDITracker(port=address, **options)
    if source == "ndi-sim":
        return NDITracker(simulate=True, **options)
    if source == "igtl":
        if scene is None:
            raise ValueError("an OpenIGTLink session writes into a scene: pass scene=")
        return IGTLTracker(scene, address, **options)
    if source == "replay":
        if not address:
            raise FluoInputError("choose a recording folder", field="recording")
        return ReplayTracker(address, **options)
    raise FluoInputError(f"unknown tracker source (one of {', '.join(SOURCES)})", field="source",
                         value=source)


def finite_pose(matrix):
    """True for a finite 4x4 pose (guards what reaches a transform node)."""
    m = np.asarray(matrix, float)
    return m.shape == (4, 4) and bool(np.all(np.isfinite(m)))
