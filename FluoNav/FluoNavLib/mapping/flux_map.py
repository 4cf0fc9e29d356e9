"""The navigated illumination model on ray-cast pixels (docs/physics.md section 6.1).

For a light coupled to the camera (cone in the camera frame) or tracked on its
own (``light_to_world``):

    S(u, v) = Dsys T(p_s) I(theta, beta, d)        forward camera image [ADU above offset]
    T_hat   = S / (Dsys I)                          optical transport image
    J       = pi L,  L = (S_counts - offset) / G    surface flux (exitance) [W/mm^2]

Pixels where I is below ``min_intensity`` of its maximum (cone edge, grazing
light), saturated or under-range counts, and pixels the ray cast masked are
flagged and left NaN-free (value 0, mask False).  Only what the scene needs
is modelled: a neutral term (alpha = 0, gamma = 0) costs nothing, and a flat,
homogeneous scene can skip ray casting (:func:`plane_hits`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError

from FluoNavLib.mapping.pixel_cast import PixelHits

__all__ = ["ViewModel", "view_model", "forward_image", "transport_image", "surface_flux",
           "accumulate_on_faces", "plane_hits", "model_error", "DEFAULT_MAX_MODEL_ERROR"]

#: pixels whose predicted model error (:func:`model_error`) exceeds this are not
#: corrected.  Measured on the oral-cavity phantom with an independent surface
#: and tracked poses (docs/surface-mapping.md): without the guard 99 % of the
#: visible pixels are corrected but only 83 % of those within 5 %, and the few
#: pixels at the cavity rim, off by up to 7x, set the contour's peak (miss rate
#: 99 %); with it 81 % are corrected, 93 % of those within 5 %, miss rate 0.1 %.
DEFAULT_MAX_MODEL_ERROR = 0.10


@dataclass
class ViewModel:
    """Factor maps of one view (image shape); ``intensity`` = their product."""

    angular: np.ndarray
    foreshortening: np.ndarray
    distance: np.ndarray
    intensity: np.ndarray
    lit: np.ndarray


def _to_light(hits, camera_to_world, light_to_world):
    W = np.asarray(camera_to_world if light_to_world is None else light_to_world, float)
    Rt = W[:3, :3].T
    p = (hits.point_mm - W[:3, 3]) @ Rt.T
    n = hits.normal @ Rt.T
    return p, n


def view_model(hits, cone, camera_to_world, light_to_world=None):
    """Illumination factors at every visible pixel (0 elsewhere)."""
    if not isinstance(hits, PixelHits):
        raise FluoInputError("needs the PixelHits of a cast", field="hits")
    if hits.rays_cam is not None and hits.face_normals is not None:
        # the ray cast kept rays + distances + faces: one compiled pass
        from FluoNavLib.mapping.illumination_kernel import cone_factors_from_cast

        ang, fore, dist, lit = cone_factors_from_cast(
            hits.rays_cam, camera_to_world, hits.face, hits.distance_mm, hits.visible,
            hits.face_normals, cone, camera_to_world if light_to_world is None else light_to_world)
        return ViewModel(angular=ang, foreshortening=fore, distance=dist,
                         intensity=ang * fore * dist, lit=lit)
    p, n = _to_light(hits, camera_to_world, light_to_world)
    f = cone.factors(p, n)
    lit = f.lit & hits.visible
    z = np.zeros(hits.shape)
    return ViewModel(angular=np.where(lit, f.angular, z), foreshortening=np.where(lit, f.foreshortening, z),
                     distance=np.where(lit, f.distance, z), intensity=np.where(lit, f.intensity, z),
                     lit=lit)


def model_error(hits, vm, caster=None, position_uncertainty_mm=0.5, depth_jump_mm=2.0):
    """Predicted relative error of the illumination model at every pixel.

    The light's foreshortening cos(beta) depends on the surface normal; a
    normal off by delta changes it by about tan(beta) * delta.  Two things make
    the normal at a pixel uncertain:

    - where the pixel really lands: the pose (tracking, hand-eye) and the
      surface are known to ``position_uncertainty_mm`` (0.5 mm: the median
      mapping error measured with 0.25 mm / 0.1 deg tracking and a 0.3 mm /
      0.15 deg hand-eye error), so the true normal may be any normal within
      that distance: the spread of the normals over an image window of that
      size (in pixels, from the pixels' own footprint on the surface);
    - how well the mesh knows its orientation: the spread of the normals
      around the hit face (``SurfaceCaster.normal_spread_rad``; ``caster``
      None for an exact surface).

    The error is tan(beta) times half the larger spread.  A pixel whose window
    holds a depth discontinuity (a surface more than ``depth_jump_mm`` nearer
    or farther, or a masked pixel: an occluding rim or the silhouette) may see
    another surface altogether: its error is unbounded (inf), as is that of
    masked pixels.
    """
    from scipy import ndimage

    if hits.shape != vm.intensity.shape:
        raise FluoInputError("cast and view model differ in shape", field="hits",
                             value=(hits.shape, vm.intensity.shape))
    vis = hits.visible
    if not vis.any():
        return np.full(hits.shape, np.inf)
    P = hits.point_mm
    step = np.linalg.norm(P[:, 1:] - P[:, :-1], axis=-1)[vis[:, 1:] & vis[:, :-1]]
    footprint = float(np.median(step)) if step.size else 1.0
    r = int(np.clip(np.ceil(position_uncertainty_mm / max(footprint, 1e-6)), 1, 50))
    size = 2 * r + 1
    N = np.where(vis[..., None], hits.normal, 0.0)
    chord2 = np.zeros(hits.shape)
    for c in range(3):
        hi = ndimage.maximum_filter(N[..., c], size=size, mode="nearest")
        lo = ndimage.minimum_filter(N[..., c], size=size, mode="nearest")
        chord2 += (hi - lo) ** 2
    # the normals' component ranges bound the largest chord between two of them
    spread = 2.0 * np.arcsin(np.clip(0.5 * np.sqrt(chord2), 0.0, 1.0))
    if caster is not None:
        spread = np.maximum(spread, caster.normal_spread_rad[np.where(vis, hits.face, 0)])
    d = np.where(vis, hits.distance_mm, np.nan)
    big = np.where(vis, d, 1e12)             # a masked pixel in the window: a jump
    small = np.where(vis, d, -1e12)
    jump = ((ndimage.maximum_filter(big, size=size, mode="nearest") - d > depth_jump_mm)
            | (d - ndimage.minimum_filter(small, size=size, mode="nearest") > depth_jump_mm))
    cos_b = np.clip(vm.foreshortening, 1e-6, 1.0)
    tan_b = np.sqrt(1.0 - cos_b * cos_b) / cos_b
    err = tan_b * 0.5 * spread
    return np.where(vis & vm.lit & ~jump, err, np.inf)


def forward_image(vm, cone, transport):
    """S = Dsys T I [ADU above offset]; ``transport`` scalar or per-pixel."""
    T = np.broadcast_to(np.asarray(transport, float), vm.intensity.shape)
    return np.where(vm.lit, cone.system_gain_adu * T * vm.intensity, 0.0)


def transport_image(counts_above_offset, vm, cone, min_intensity=0.05, valid=None):
    """T_hat = S / (Dsys I) and its mask (lit, I >= min_intensity * max I, valid counts,
    and ``valid``: e.g. ``model_error(...) <= DEFAULT_MAX_MODEL_ERROR``)."""
    S = np.asarray(counts_above_offset, float)
    if S.shape != vm.intensity.shape:
        raise FluoInputError("image and cast differ in shape (binning?)", field="image",
                             value=(S.shape, vm.intensity.shape))
    imax = float(vm.intensity.max()) if vm.lit.any() else 0.0
    ok = vm.lit & (vm.intensity >= min_intensity * imax) & np.isfinite(S)
    if valid is not None:
        ok &= valid
    denom = cone.system_gain_adu * np.where(ok, vm.intensity, 1.0)
    return np.where(ok, S / denom, 0.0), ok


def surface_flux(counts_adu, radiometric):
    """(exitance J [W/mm^2], valid mask) from raw counts through the camera model."""
    L, valid, _, _ = radiometric.radiance_from_counts(counts_adu, min_snr=3.0)
    return np.where(valid, radiometric.exitance_from_radiance(np.where(valid, L, 0.0)), 0.0), valid


def view_weights(hits, vm, snr=None):
    """Quality weight of each pixel for accumulation: viewing and lighting
    obliquity, distance (1/d^2 of the pixel footprint) and SNR."""
    w = hits.cos_view * np.where(vm.lit, vm.foreshortening, 0.0)
    d = np.where(hits.visible, hits.distance_mm, np.inf)
    w = w / (1.0 + (d / 100.0) ** 2)
    if snr is not None:
        w = w * np.clip(np.asarray(snr, float) / 100.0, 0.0, 1.0)
    return np.where(hits.visible & vm.lit, w, 0.0)


def accumulate_on_faces(n_faces, views):
    """Weighted mean per face over views: ``views`` = [(face ids, values, weights, mask)].

    Returns (mean (n_faces,), total weight (n_faces,)); faces never seen have
    weight 0 and mean 0."""
    num = np.zeros(n_faces)
    den = np.zeros(n_faces)
    for face, val, w, mask in views:
        m = mask & (face >= 0) & (w > 0)
        np.add.at(num, face[m], (w * val)[m])
        np.add.at(den, face[m], w[m])
    mean = np.divide(num, den, out=np.zeros(n_faces), where=den > 0)
    return mean, den


def plane_hits(camera, camera_to_world, plane_point_mm, plane_normal, binning=1):
    """Closed-form PixelHits for a flat scene (no ray casting): every ray meets
    the plane; masked like cast_camera (behind, grazing)."""
    M = np.asarray(camera_to_world, float)
    rays = camera.pixel_grid_rays(binning) @ M[:3, :3].T
    n = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
    c = M[:3, 3]
    den = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((np.asarray(plane_point_mm, float) - c) @ n) / den
    cos_view = -den
    visible = np.isfinite(s) & (s > 0) & (cos_view > np.cos(np.deg2rad(89.0)))
    reason = np.where(visible, 0, np.where(np.isfinite(s) & (s > 0), 3, 1)).astype(np.uint8)
    pts = np.where(visible[..., None], c + rays * np.where(visible, s, 0)[..., None], 0.0)
    return PixelHits(face=np.where(visible, 0, -1), point_mm=pts,
                     normal=np.where(visible[..., None], n, 0.0),
                     distance_mm=np.where(visible, s, np.inf), cos_view=np.where(visible, cos_view, 0.0),
                     visible=visible, reason=reason, camera_center_mm=c)
