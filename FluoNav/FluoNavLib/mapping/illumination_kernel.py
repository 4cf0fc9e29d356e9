"""The illumination cone evaluated per pixel in one compiled pass (video rate).

Same formulas as ``IlluminationCone.factors`` (docs/physics.md section 6.1), read
straight from the ray cast (pixel ray, distance, face) instead of from
(H, W, 3) point and normal arrays, so a full frame costs one pass over the
pixels.  The tests check it against ``IlluminationCone.factors`` to 1e-12, so
the two cannot drift apart silently.  Neutral terms cost nothing: gamma = 0
skips the distance factor, alpha = 0 the power, an axisymmetric cone the
crescent.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["cone_factors_from_cast"]


@njit(cache=True, parallel=True)
def _cone_kernel(rays, R, c, face, t, visible, normals, Lr, Lt, origin, axis, phi_max, alpha,
                 gamma, asym, e1, e2, asym_amp, asym_phase, ang_out, fore_out, dist_out, lit_out):
    for p in prange(rays.shape[0]):
        ang_out[p] = 0.0
        fore_out[p] = 0.0
        dist_out[p] = 0.0
        lit_out[p] = False
        if not visible[p]:
            continue
        f = face[p]
        # hit point and normal in the world, then in the light frame
        wx = c[0] + t[p] * (R[0, 0] * rays[p, 0] + R[0, 1] * rays[p, 1] + R[0, 2] * rays[p, 2]) - Lt[0]
        wy = c[1] + t[p] * (R[1, 0] * rays[p, 0] + R[1, 1] * rays[p, 1] + R[1, 2] * rays[p, 2]) - Lt[1]
        wz = c[2] + t[p] * (R[2, 0] * rays[p, 0] + R[2, 1] * rays[p, 1] + R[2, 2] * rays[p, 2]) - Lt[2]
        rx = Lr[0, 0] * wx + Lr[1, 0] * wy + Lr[2, 0] * wz - origin[0]
        ry = Lr[0, 1] * wx + Lr[1, 1] * wy + Lr[2, 1] * wz - origin[1]
        rz = Lr[0, 2] * wx + Lr[1, 2] * wy + Lr[2, 2] * wz - origin[2]
        nx = Lr[0, 0] * normals[f, 0] + Lr[1, 0] * normals[f, 1] + Lr[2, 0] * normals[f, 2]
        ny = Lr[0, 1] * normals[f, 0] + Lr[1, 1] * normals[f, 1] + Lr[2, 1] * normals[f, 2]
        nz = Lr[0, 2] * normals[f, 0] + Lr[1, 2] * normals[f, 1] + Lr[2, 2] * normals[f, 2]
        d = np.sqrt(rx * rx + ry * ry + rz * rz)
        if d <= 1e-12:
            continue
        ux, uy, uz = rx / d, ry / d, rz / d
        cos_t = min(max(ux * axis[0] + uy * axis[1] + uz * axis[2], -1.0), 1.0)
        theta = np.arccos(cos_t)
        if theta > phi_max:
            continue
        cos_b = -(nx * ux + ny * uy + nz * uz)
        if cos_b <= 0.0:
            continue
        a = max(cos_t, 0.0)
        if alpha != 0.0:
            a = a ** alpha
        else:
            a = 1.0
        if asym:
            phi = np.arctan2(ux * e2[0] + uy * e2[1] + uz * e2[2], ux * e1[0] + uy * e1[1] + uz * e1[2])
            a *= 1.0 + asym_amp * (theta / phi_max) ** 2 * np.cos(phi - asym_phase)
        ang_out[p] = a
        fore_out[p] = min(cos_b, 1.0)
        if gamma != 0.0:
            g = 1.0 + gamma * d
            dist_out[p] = 1.0 / (g * g)
        else:
            dist_out[p] = 1.0
        lit_out[p] = True


def cone_factors_from_cast(rays_cam, camera_to_world, face, distance_mm, visible, face_normals,
                           cone, light_to_world):
    """(angular, foreshortening, distance factor, lit) maps of the image shape.

    ``rays_cam``: (H, W, 3) unit pixel rays in the camera frame; the hit point
    is camera centre + distance x ray (world); the normal is the face's.
    """
    shape = face.shape
    M = np.ascontiguousarray(np.asarray(camera_to_world, float))
    L = np.ascontiguousarray(np.asarray(light_to_world, float))
    n = face.size
    out = [np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_)]
    asym = not cone.is_axisymmetric
    e1, e2 = cone.azimuth_basis() if asym else (np.zeros(3), np.zeros(3))
    # alpha = 0 means (cos theta)^0 = 1, also at theta = 90 deg
    _cone_kernel(np.ascontiguousarray(rays_cam, float).reshape(-1, 3), M[:3, :3].copy(), M[:3, 3].copy(),
                 np.ascontiguousarray(face).reshape(-1), np.ascontiguousarray(distance_mm, float).reshape(-1),
                 np.ascontiguousarray(visible).reshape(-1), np.ascontiguousarray(face_normals, float),
                 L[:3, :3].copy(), L[:3, 3].copy(), np.asarray(cone.origin_mm, float).reshape(3),
                 cone.unit_axis, float(np.deg2rad(cone.half_angle_deg)), float(cone.alpha),
                 float(cone.gamma_per_mm), asym, np.asarray(e1, float), np.asarray(e2, float),
                 float(cone.asym_amplitude), float(cone.asym_phase_rad), *out)
    return tuple(o.reshape(shape) for o in out)
