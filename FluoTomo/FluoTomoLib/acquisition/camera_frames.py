"""Camera frames of the emission light on the tissue surface, rendered from the
FEM field: what the tracked fluorescence camera records during a laser scan.

Every pixel is cast onto the surface (FluoNav's rasteriser, one cast per
camera pose: the camera stays put while the laser moves); its radiance is the
Lambertian radiance of the boundary exitance at the hit point,

    Phi (P1 on the surface facet) -> J = Phi / (2A) -> L = J / pi,

scaled by the laser power and the camera's radiometric gain G [ADU per
W/mm^2/sr] (docs/physics.md sections 5.1 and 8.2), with shot noise (gain 1 e-/ADU),
read noise and the 14-bit range; saturated pixels are flagged.  The
software side then maps pixels to the surface with the *reported* camera pose
and averages the pixels of a ~1 mm^2 ROI around each virtual detector
(``noncontact_optodes.roi_mean_counts``).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

ADC_MAX_ADU = 16383


def tomography_camera(binning=4):
    """The open-field fluorescence camera (1392 x 1040, f ~ 1860 px), binned:
    from 150 mm a 4x4-binned pixel covers about 0.32 mm of the surface, so a
    1 mm^2 ROI averages ~10 pixels."""
    from FluoNavLib.mapping.synthetic import open_field_camera

    return open_field_camera(binning)


def camera_pose_above(centre_mm, distance_mm=150.0, tilt_deg=0.0):
    """CameraToWorld of a camera ``distance_mm`` above ``centre_mm`` looking down
    (optionally tilted about x), image up = +y."""
    from FluoCalibLib.geometry import transforms as tf

    c = np.asarray(centre_mm, float)
    t = np.deg2rad(tilt_deg)
    eye = c + distance_mm * np.array([0.0, -np.sin(t), np.cos(t)])
    return tf.look_at(eye, c, up=(0.0, 1.0, 0.0))


def surface_caster(mesh, facet_mask=None):
    """SurfaceCaster of a tet mesh's boundary (optionally some facets only) and
    the facet -> node table used to interpolate nodal fields at hits."""
    from FluoNavLib.mapping.pixel_cast import SurfaceCaster

    facets = mesh.boundary_facets if facet_mask is None else mesh.boundary_facets[facet_mask]
    return SurfaceCaster(mesh.nodes_mm, facets), facets


def cast(caster, camera, camera_to_world, progress=None, cancel=None):
    """The camera's pixels cast onto the surface (``FluoNavLib``'s cast_camera;
    ``progress`` hears its kernels compile on a first run)."""
    from FluoNavLib.mapping.pixel_cast import cast_camera

    return cast_camera(caster, camera, camera_to_world, progress=progress, cancel=cancel)


def surface_values(hits, facets, nodes_mm, nodal):
    """P1 interpolation of nodal fields (N, k) at the pixels' hit points:
    (H, W, k), zero where a pixel sees no surface."""
    vis = hits.visible
    out = np.zeros(hits.shape + (nodal.shape[1],))
    if not np.any(vis):
        return out
    f = facets[hits.face[vis]]                         # (P, 3) nodes of the hit facets
    p = hits.point_mm[vis]
    a, b, c = nodes_mm[f[:, 0]], nodes_mm[f[:, 1]], nodes_mm[f[:, 2]]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    w = np.clip(np.stack([1 - w1 - w2, w1, w2], axis=1), 0.0, 1.0)
    w /= w.sum(axis=1, keepdims=True)
    out[vis] = np.einsum("pk,pkj->pj", w, nodal[f])
    return out


def frame_radiance(hits, facets, nodes_mm, fluence_per_w, robin_A, laser_power_w):
    """(S, H, W) noise-free radiance [W/mm^2/sr] each pixel sees, one frame per
    source: nodal emission fluence per watt (N, S) -> boundary exitance ->
    Lambertian radiance at the laser power."""
    phi = surface_values(hits, facets, nodes_mm, np.asarray(fluence_per_w, float))
    return np.moveaxis(np.maximum(phi, 0.0) * laser_power_w / (2.0 * robin_A) / np.pi, -1, 0)


def exposure_gain(hits, radiance, sources_mm, exclude_mm=3.0, field="camera"):
    """The gain G [ADU per W/mm^2/sr] a user sets with the exposure time: the
    brightest pixel farther than ``exclude_mm`` from its frame's source (the
    laser spot itself saturates) at 60 % of the 14-bit range.  ``radiance``:
    (S, H, W) as :func:`frame_radiance` gives it; ``sources_mm`` (S, 3)."""
    far = np.linalg.norm(hits.point_mm[None] - np.asarray(sources_mm, float)[:, None, None, :],
                         axis=-1) > exclude_mm
    peak = float(np.max(np.where(far & hits.visible[None], radiance, 0.0)))
    if not peak > 0:
        raise FluoInputError("the camera sees no fluorescence away from the sources",
                             field=field)
    return 0.6 * ADC_MAX_ADU / peak


def expose(radiance, gain_adu_per_radiance, offset_adu, read_noise_adu, rng):
    """Noisy 14-bit frames [ADU] and their saturation mask: G L signal with
    shot noise (gain 1 e-/ADU), offset and Gaussian read noise."""
    signal = np.asarray(radiance, float) * gain_adu_per_radiance
    noisy = (rng.poisson(signal).astype(float) + offset_adu
             + rng.normal(0.0, read_noise_adu, signal.shape))
    saturated = noisy >= ADC_MAX_ADU
    return np.clip(np.round(noisy), 0, ADC_MAX_ADU), saturated


def detector_counts(frames, saturated, hits_reported, detectors_mm, roi_area_mm2=1.0,
                    min_pixels=4, with_se=False):
    """(S, D) mean ROI counts of every frame at the virtual detectors, from the
    pixel-to-surface map of the *reported* camera pose; NaN where the ROI has
    fewer than ``min_pixels`` unsaturated pixels.  Also returns the (S, D)
    number of pixels averaged, and with ``with_se`` the (S, D) standard
    errors of the means [ADU] (``noncontact_optodes.roi_mean_counts``)."""
    from FluoTomoLib.acquisition.noncontact_optodes import roi_mean_counts

    S = len(frames)
    counts = np.full((S, len(detectors_mm)), np.nan)
    se = np.full((S, len(detectors_mm)), np.nan)
    n_pix = np.zeros((S, len(detectors_mm)), dtype=np.int64)
    pts = hits_reported.point_mm
    for s in range(S):
        valid = hits_reported.visible & ~saturated[s]
        if not np.any(valid):
            raise FluoInputError("every pixel of a frame is saturated or off the surface",
                                 field="frame", value=s)
        out = roi_mean_counts(frames[s], pts, valid, detectors_mm, roi_area_mm2, min_pixels,
                              with_se=with_se)
        counts[s], n_pix[s] = out[0], out[1]
        if with_se:
            se[s] = out[2]
    return (counts, n_pix, se) if with_se else (counts, n_pix)
