"""FluoNav's library: tracked devices and surface-flux mapping.

Subpackages: ``devices`` (trackers, camera frames, live loop, recording) and
``mapping`` (per-pixel ray casting, the navigated illumination model, flux maps,
contours).
"""
