"""Camera frame sources: a UVC camera or video file (OpenCV ``VideoCapture``),
a folder of images, a FluoGuide recording, or synthetic frames.

Every source has ``read()`` -> :class:`Frame` or ``None`` at the end, and
``close()``.  A frame carries its own sequence number and timestamp [s]:
live sources stamp the host's ``time.monotonic()`` when the frame arrives
(the camera latency is subtracted later, see ``timesync``); file sources
carry the recorded or nominal times.  Images are 2D arrays (colour frames
are converted to grey: the fluorescence camera is monochrome, a colour
UVC camera is only a stand-in).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError, check_number, seeded_rng

__all__ = ["Frame", "OpenCVSource", "ImageSequenceSource", "RecordingSource", "SyntheticSource",
           "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm", ".bmp", ".jpg", ".jpeg", ".npy")


@dataclass
class Frame:
    image: np.ndarray               # 2D counts [ADU]
    timestamp_s: float              # arrival (live) or recorded time [s]
    sequence: int                   # source frame number: gaps = frames lost upstream
    exposure_s: float = None
    poses: dict = None              # recorded poses (RecordingSource only)
    info: dict = field(default_factory=dict)


def _grey(img, what):
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        import cv2

        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or img.size == 0:
        raise FluoInputError("not a 2D (or colour) image", file=what, value=img.shape)
    return img


class _Source:
    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __iter__(self):
        while (f := self.read()) is not None:
            yield f


class OpenCVSource(_Source):
    """A camera (device index, e.g. 0 for /dev/video0) or a video file.

    Live cameras are stamped with the host clock at ``read()``; video files
    with their own position (``CAP_PROP_POS_MSEC``) so a file replays with its
    recorded times.
    """

    def __init__(self, device=0, width=None, height=None, fps=None):
        import cv2

        self._cv2 = cv2
        self.device = device
        self.is_file = not isinstance(device, int)
        if not self.is_file:
            # OpenCV crashes (SIGSEGV) on a negative index
            check_number("camera", device, 0, 1023, integer=True)
        for name, v in (("width", width), ("height", height)):
            if v is not None:
                check_number(name, v, 1, 20000, integer=True)
        if fps is not None:
            check_number("fps", fps, 0.0, 1000.0, lo_open=True)
        from fluoguide.library_errors import native_stderr_quiet

        # OpenCV logs "[ WARN:0@...] global cap_v4l.cpp:914 open VIDEOIO(...)" on
        # stderr for a camera it cannot open: the one-line error below says it
        with native_stderr_quiet():
            self.cap = cv2.VideoCapture(str(device) if self.is_file else device)
        if not self.cap.isOpened():
            self.cap.release()
            raise FluoInputError("cannot open camera or video (OpenCV VideoCapture)",
                                 field="camera", value=device)
        for prop, v in ((cv2.CAP_PROP_FRAME_WIDTH, width), (cv2.CAP_PROP_FRAME_HEIGHT, height),
                        (cv2.CAP_PROP_FPS, fps)):
            if v:
                self.cap.set(prop, float(v))
        self.n = 0

    def read(self):
        ok, img = self.cap.read()
        t_host = time.monotonic()
        if not ok:
            return None
        t = self.cap.get(self._cv2.CAP_PROP_POS_MSEC) / 1000.0 if self.is_file else t_host
        self.n += 1
        return Frame(_grey(img, self.device), float(t), self.n - 1)

    def close(self):
        self.cap.release()


class ImageSequenceSource(_Source):
    """The images of a folder in name order, at ``fps`` (nominal times k / fps;
    ``realtime`` paces them at ``fps`` and stamps the host clock, as a camera).

    16-bit PNG/TIFF keep their depth (``IMREAD_UNCHANGED``); ``.npy`` files are
    loaded as arrays.
    """

    def __init__(self, folder, fps=20.0, realtime=False):
        self.realtime = bool(realtime)
        self._t0 = None
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FluoInputError("image folder not found", file=self.folder)
        if not fps > 0:
            raise FluoInputError("must be > 0", field="fps", value=fps)
        self.fps = float(fps)
        self.files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise FluoInputError(f"no images ({', '.join(IMAGE_SUFFIXES)})", file=self.folder)
        self.n = 0

    def read(self):
        if self.n >= len(self.files):
            return None
        path = self.files[self.n]
        from fluoguide.images import read_image

        img = read_image(path)
        self.n += 1
        t = (self.n - 1) / self.fps
        if self.realtime:         # played as a live camera: paced, stamped with the host clock
            self._t0 = self._t0 if self._t0 is not None else time.monotonic()
            time.sleep(max(0.0, self._t0 + t - time.monotonic()))
            t = time.monotonic()
        return Frame(_grey(img, path), t, self.n - 1, info={"file": path.name})


class RecordingSource(_Source):
    """The frames of a ``recorder`` folder with their recorded poses and times."""

    def __init__(self, folder):
        from FluoNavLib.devices.recorder import read_recording

        self.tools, self._docs = read_recording(folder)
        self.n = 0

    def read(self):
        if self.n >= len(self._docs):
            return None
        doc = self._docs[self.n]
        self.n += 1
        from fluoguide.images import read_image

        # read_recording checked the poses (16 finite numbers) and the file name
        return Frame(read_image(doc["path"]), doc["timestamp_s"], doc["frame"], doc["exposure_s"],
                     doc["poses"], {"pose_valid": doc["pose_valid"],
                                    "pose_status": doc["pose_status"]})


class SyntheticSource(_Source):
    """Poisson frames at ``fps`` paced in real time (a camera stand-in for the
    simulator): the mean level varies slowly so frames differ."""

    def __init__(self, fps=20.0, width=348, height=260, n_frames=None, seed=0):
        from fluoguide.images import MAX_IMAGE_PIXELS

        check_number("fps", fps, 0.0, 1000.0, lo_open=True)
        check_number("width", width, 1, 20000, integer=True)
        check_number("height", height, 1, 20000, integer=True)
        if width * height > MAX_IMAGE_PIXELS:
            raise FluoInputError(f"frame larger than {MAX_IMAGE_PIXELS} pixels",
                                 field="width x height", value=(width, height))
        self.period_s = 1.0 / float(fps)
        self.shape = (int(height), int(width))
        self.n_frames = n_frames
        self.rng = seeded_rng(seed)
        self.n = 0
        self._next = None

    def read(self):
        if self.n_frames is not None and self.n >= self.n_frames:
            return None
        now = time.monotonic()
        if self._next is None:
            self._next = now
        late = int((now - self._next) / self.period_s)
        if late > 0:              # like a camera, slots missed by a slow reader are gone
            self.n += late
            self._next += late * self.period_s
        if self._next > now:                       # pace like a camera
            time.sleep(self._next - now)
        t = time.monotonic()
        self._next += self.period_s
        img = self.rng.poisson(200.0 + 50.0 * np.sin(t) ** 2, size=self.shape).astype(np.uint16)
        self.n += 1
        return Frame(img, t, self.n - 1, exposure_s=0.5 * self.period_s)
