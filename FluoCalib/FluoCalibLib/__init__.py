"""FluoCalib's library: device calibration.

Subpackages: ``geometry`` (camera intrinsics, hand-eye, transforms, registration)
and ``radiometry`` (camera response, radiometric model, illumination cone, laser line).
"""
