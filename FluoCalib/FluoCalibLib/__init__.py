"""Calibration: camera geometry, radiometry, illumination, laser."""
