"""Simulated acquisitions: the tracked laser raster scan, non-contact sources and detectors
(tracked laser beam and tracked camera onto the tissue surface), rendered camera frames.

Modules
-------
- ``camera_frames``: Camera frames of the emission light on the tissue surface, rendered from the FEM field: what the tracked fluorescence camera records during a laser scan.
- ``noncontact_optodes``: Non-contact sources and detectors from a tracked laser and a tracked camera.
- ``tracked_scan``: A tracked laser raster scan and a tracked camera, with realistic tracking error.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "camera_frames": ["tomography_camera", "camera_pose_above", "surface_caster", "cast", "surface_values", "frame_radiance", "exposure_gain", "expose", "detector_counts"],
    "noncontact_optodes": ["ray_triangle_intersect", "virtual_detectors", "detector_mask", "roi_mean_counts", "counts_to_boundary_fluence", "boundary_fluence_to_counts"],
    "tracked_scan": ["rotation_between", "TrackingError", "laser_tool_pose_for_target", "beam_in_world", "raster_scan", "camera_pose_looking_at", "world_to_camera"],
})
