"""OpenIGTLink input (from PLUS or any server) into the MRML scene, as
SlicerOpenIGTLink maps it: a TRANSFORM message named ``CameraToTracker``
updates (or creates) the linear transform node of that name, an IMAGE message
updates the scalar volume node of its device name, and each node carries the
message time in the attribute ``FluoNav.IGTLTimestamp``.

pyigtl keeps only the latest message per device between polls, so a slow
poller silently loses messages.  :class:`IGTLReceiver` counts what it got and
what it must have missed: from a ``seq`` metadata field when the sender puts
one (FluoGuide's own senders do; metadata needs OpenIGTLink header version 2,
``msg.header_version = 2``, else pyigtl silently drops it), otherwise from
timestamp gaps larger than 1.5 nominal periods.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError

__all__ = ["IGTLReceiver", "TIMESTAMP_ATTRIBUTE"]

TIMESTAMP_ATTRIBUTE = "FluoNav.IGTLTimestamp"


class IGTLReceiver:
    """Poll an OpenIGTLink server and write what arrives into ``scene``."""

    def __init__(self, scene, host="127.0.0.1", port=18944, nominal_rate_hz=None):
        self.scene = scene
        self.host, self.port = host, int(port)
        self.nominal_rate_hz = nominal_rate_hz
        self.client = None
        self.received = {}       # device -> messages applied
        self.lost = {}           # device -> messages known to be lost
        self.first_seq = {}      # device -> first sequence number seen (senders count from 0)
        self._last_seq = {}
        self._last_ts = {}

    def connect(self, timeout_s=5.0):
        import pyigtl

        self.client = pyigtl.OpenIGTLinkClient(host=self.host, port=self.port)
        t0 = time.monotonic()
        while not self.client.is_connected():
            if time.monotonic() - t0 > timeout_s:
                self.client.stop()
                raise FluoInputError("no OpenIGTLink server answered", field="--igtl",
                                     value=f"{self.host}:{self.port}")
            time.sleep(0.02)
        return self

    def close(self):
        if self.client is not None:
            self.client.stop()
            self.client = None

    def __enter__(self):
        return self.connect()

    def __exit__(self, *exc):
        self.close()

    def poll(self):
        """Apply the latest message of every device; returns the device names updated."""
        updated = []
        for msg in self.client.get_latest_messages():
            name = msg.device_name
            self._account(name, msg)
            if msg.message_type == "TRANSFORM":
                node = mrml_io.set_transform(self.scene, name, np.asarray(msg.matrix, float))
            elif msg.message_type == "IMAGE":
                node = self._image(name, msg)
            else:
                continue
            node.SetAttribute(TIMESTAMP_ATTRIBUTE, repr(float(msg.timestamp)))
            self.received[name] = self.received.get(name, 0) + 1
            updated.append(name)
        return updated

    def _account(self, name, msg):
        seq = (msg.metadata or {}).get("seq")
        if seq is not None:
            seq = int(seq)
            last = self._last_seq.get(name)
            self.first_seq.setdefault(name, seq)
            if last is not None and seq > last + 1:
                self.lost[name] = self.lost.get(name, 0) + seq - last - 1
            self._last_seq[name] = seq
        elif self.nominal_rate_hz:
            last = self._last_ts.get(name)
            period = 1.0 / self.nominal_rate_hz
            if last is not None and msg.timestamp - last > 1.5 * period:
                self.lost[name] = self.lost.get(name, 0) + int(round((msg.timestamp - last) / period)) - 1
            self._last_ts[name] = msg.timestamp

    def _image(self, name, msg):
        img = np.asarray(msg.image)
        if img.ndim == 2:
            img = img[None]
        if img.ndim != 3:
            raise FluoInputError("IMAGE message must be 2D or 3D scalar", field=name,
                                 value=img.shape)
        m = np.asarray(msg.ijk_to_world_matrix, float)
        spacing = np.linalg.norm(m[:3, :3], axis=0)
        direction = m[:3, :3] / np.where(spacing > 0, spacing, 1.0)
        return mrml_io.add_volume(self.scene, name, img, spacing, m[:3, 3], direction=direction)

    def receive(self, seconds, poll_hz=200.0):
        """Poll for ``seconds``; returns {received, lost} per device."""
        t_end = time.monotonic() + float(seconds)
        while time.monotonic() < t_end:
            self.poll()
            time.sleep(1.0 / poll_hz)
        return {"received": dict(self.received), "lost": dict(self.lost)}
