"""Tracked camera frames recorded to a folder through the live loop (``fluo
record``, ``FluoNavLogic.recordFrames``): the simulated NDI tracker, and
synthetic, image-sequence or camera frames."""

from __future__ import annotations

from pathlib import Path

from fluoguide.errors import FluoInputError


def frame_source(frames=None, camera=None, fps=20.0, width=348, height=260, seed=0):
    """The camera: images of the folder ``frames`` played at ``fps`` [1/s],
    the OpenCV/UVC camera of index ``camera``, else synthetic frames of
    ``width`` x ``height`` px."""
    from FluoNavLib.devices import frame_sources as fs

    if frames:
        return fs.ImageSequenceSource(frames, fps=fps, realtime=True)
    if camera is not None:
        return fs.OpenCVSource(camera, fps=fps)
    return fs.SyntheticSource(fps=fps, width=width, height=height, seed=seed)


def record_simulated(out, seconds, fps=20.0, frames=None, camera=None, width=348, height=260,
                     inject_faults=None, seed=0):
    """Record ``seconds`` [s] of frames with the simulated tracker's poses into
    the new or empty folder ``out``; every frame the camera gives is kept (a
    slow disk shows as latency, or as camera-side gaps).

    Returns
    -------
    dict
        Frames delivered, without pose, dropped, latency [ms], the tracker's
        frames, missing, CRC errors, recoveries and unreported losses, the folder.
    """
    from FluoNavLib.devices.live_loop import LiveLoop
    from FluoNavLib.devices.recorder import Recorder
    from FluoNavLib.devices.tracker import check_seconds, open_tracker

    check_seconds(seconds)
    if not (fps > 0 and fps <= 1000):
        raise FluoInputError("must be a frame rate in (0, 1000] Hz", field="fps", value=fps)
    session = open_tracker("ndi-sim", inject_faults=inject_faults, seed=seed,
                           roms=[b"camera tool rom " * 4])
    try:
        # the camera before the folder: a refused source must not leave a recording behind
        with frame_source(frames, camera, fps, width, height, seed) as cam, \
                Recorder(out) as rec:
            def write(image, info, poses):
                rec.add(image, info["timestamp_s"], poses, exposure_s=info["exposure_s"],
                        pose_valid=info["pose_valid"], pose_status=info["pose_status"])

            # a recording keeps every frame the camera gave (no "latest" dropping)
            loop = LiveLoop(cam, write, tracker=session.client,
                            tools={"CameraToolToTracker": 1}, camera_latency_s=0.5 / fps,
                            drop_policy="none")
            res = loop.run(seconds=seconds)
        stats = session.client.stats
    finally:
        session.close()
    return {"frames": res["delivered"], "frames_without_pose": res["pose_invalid"],
            "pose_status": res["pose_status"], "dropped_slow": res["dropped_slow"],
            "dropped_upstream": res["dropped_upstream"],
            "frames_lost_unreported": res["lost_unreported"], "latency_ms": res["latency_ms"],
            "tracker_frames": stats.frames, "tracker_missing": stats.missing,
            "crc_errors": stats.crc_errors, "recovered": stats.recovered,
            "lost_unreported": stats.lost_unreported(), "folder": str(Path(out).resolve())}
