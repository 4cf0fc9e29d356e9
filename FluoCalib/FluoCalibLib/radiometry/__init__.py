"""Radiometric calibration: camera response (EMVA 1288), the radiometric camera model, the
illumination cone and its fit, the laser beam line, synthetic light data and plots.

Modules
-------
- ``camera_response``: Camera response characterisation from image stacks, reported as EMVA 1288 does.
- ``datasets``: Reading the illumination and laser calibration folders, checked.
- ``illumination_fit``: Calibration of a broad-beam light (cone model of ``illumination_model``) from images of a flat phantom of known reflectance, as in docs/physics.md section 6.2.
- ``illumination_model``: Broad-beam illumination model: a right circular cone with angular, obliquity and distance roll-off (docs/physics.md section 6.1).
- ``laser_line``: Laser beam-line calibration (docs/physics.md section 7).
- ``plots``: PNG plots of the radiometric calibrations (photon transfer, linearity, dark signal, ratio images) that a person can read.
- ``radiometric_model``: Radiometric camera model: counts [ADU] <-> radiance [W/mm^2/sr], and noise.
- ``scene``: Radiometric, illumination and laser calibrations in the MRML scene and in a JSON calibration file (docs/scene.md): attributes ``FluoCalib.Radiometry``, ``FluoCalib.Illumination`` and ``FluoCalib.Laser`` of the ``FluoCalibration`` node (plain JSON: numbers, lists, the cone as ``IlluminationCone.to_dict``).
- ``synthetic``: Synthetic radiometric data with known truth: camera stacks, images of a flat phantom under a broad-beam cone, and laser spots.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "camera_response": ["Frame", "load_stack", "write_stack", "characterize"],
    "datasets": ["ILLUMINATION_KEYS", "LASER_KEYS", "read_dataset"],
    "illumination_fit": ["segment_active", "calibrate_illumination"],
    "illumination_model": ["IlluminationCone", "IlluminationFactors"],
    "laser_line": ["spot_centroid", "fit_line", "calibrate_laser"],
    "plots": ["plot_radiometry", "plot_ratio_images"],
    "radiometric_model": ["PLANCK_J_S", "LIGHT_SPEED_M_PER_S", "RadiometricCamera", "photon_energy_j"],
    "scene": ["RADIOMETRY_KEY", "ILLUMINATION_KEY", "LASER_KEY", "store_calibration", "load_calibration", "write_calibration_json"],
    "synthetic": ["synthetic_stack", "synthetic_lens_spectral_frames", "endoscope_camera", "endoscope_cone", "plane_poses", "synthetic_illumination", "synthetic_laser", "ray_plane_points", "write_illumination_set", "write_laser_set"],
})
