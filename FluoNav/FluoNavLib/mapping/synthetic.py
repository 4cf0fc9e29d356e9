"""A synthetic navigated acquisition on the oral-cavity phantom: homogeneous
fluorescence (uniform transport T), a light coupled to the camera, tracked
views looking into the cavity, camera noise — the data with known truth that
the surface-flux mapping is tested and benchmarked on."""

from __future__ import annotations

import numpy as np

from fluoguide.errors import check_number, seeded_rng

from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

from FluoNavLib.mapping.flux_map import forward_image, view_model
from FluoNavLib.mapping.pixel_cast import SurfaceCaster, cast_camera

__all__ = ["oral_cavity_surface", "open_field_camera", "coupled_light", "view_poses",
           "render_view"]


# The largest optical transport a synthetic view renders (dimensionless): far
# above tissue's (< 1), below where the photon counts' Poisson draws overflow
MAX_TRANSPORT = 100.0


def oral_cavity_surface(target_triangles=62000, seed=0):
    """SurfaceCaster of the oral-cavity phantom's air-tissue surface (RAS mm)."""
    from fluoguide.phantoms import make_phantom

    from FluoNavLib.mapping.surface import surface_from_labelmap

    check_number("target_triangles", target_triangles, 0, 10_000_000, integer=True,
                 what="must be 0 (keep all) .. 10,000,000")
    p = make_phantom("oral-cavity", seed=seed)
    ijk = np.diag([*p.spacing_mm, 1.0])
    ijk[:3, 3] = p.origin_mm
    poly = surface_from_labelmap(p.labels, ijk, target_triangles=target_triangles)
    return SurfaceCaster.from_polydata(poly), poly


def open_field_camera(binning=1):
    """1392 x 1040 sensor, 6.45 um pixels, a 12 mm lens (f ~ 1860 px): the whole
    oral cavity from 120 mm."""
    check_number("binning", binning, 1, 64, integer=True)
    cam = CameraModel(1860.0, 1860.0, 695.5, 519.5, (0.0, 0.0, 0.0, 0.0, 0.0), 1392, 1040)
    return cam.binned(binning) if binning > 1 else cam


def coupled_light():
    """A ring-light-like source beside the lens, wide enough to light the view."""
    axis = tf.rotation_matrix([1.0, 0.0, 0.0], np.deg2rad(3.0)) @ np.array([0.0, 0.0, 1.0])
    return IlluminationCone(origin_mm=(12.0, 0.0, 0.0), axis=tuple(axis), half_angle_deg=40.0,
                            alpha=2.0, gamma_per_mm=0.01, system_gain_adu=1.5e5, frame="Camera")


def view_poses(n=4, distance_mm=120.0, centre=(0.0, 0.0, -20.0)):
    """CameraToWorld poses looking into the cavity from above at several angles."""
    check_number("views", n, 1, 360, integer=True)
    check_number("distance_mm", distance_mm, 0.0, 10_000.0, lo_open=True)
    poses = []
    for k in range(n):
        az = 2 * np.pi * k / max(n, 1)
        tilt = 0.0 if k == 0 else np.deg2rad(15.0)
        eye = np.asarray(centre) + distance_mm * np.array([np.sin(tilt) * np.cos(az),
                                                           np.sin(tilt) * np.sin(az), np.cos(tilt)])
        poses.append(tf.look_at(eye, centre, up=(0.0, 1.0, 0.0)))
    return poses


def render_view(caster, camera, camera_to_world, cone, transport=0.3, radiometric=None, seed=0):
    """(noisy counts [ADU], hits, view model) of one view of homogeneous tissue.

    ``transport`` is the optical transport T (dimensionless, 0..100; tissue's is
    below 1, larger values only saturate the sensor).
    """
    check_number("transport", transport, 0.0, MAX_TRANSPORT)
    rcam = radiometric or RadiometricCamera(gain_adu_per_e=1.0)
    rng = seeded_rng(seed)
    hits = cast_camera(caster, camera, camera_to_world)
    vm = view_model(hits, cone, camera_to_world)
    S = forward_image(vm, cone, transport)                      # ADU above offset
    e = np.maximum(S / rcam.gain_adu_per_e, 0.0)
    el = rng.poisson(e) + rng.poisson(rcam.dark_current_e_per_s * rcam.exposure_s, e.shape)
    el = np.minimum(el, rcam.full_well_e) + rcam.bias_e + rng.normal(0, rcam.read_noise_e, e.shape)
    counts = np.clip(np.round(el * rcam.gain_adu_per_e), 0, rcam.adc_max_adu)
    return counts, hits, vm
