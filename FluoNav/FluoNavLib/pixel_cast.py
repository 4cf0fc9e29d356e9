"""Every camera pixel's ray cast onto the tissue surface.

The surface (triangles, RAS mm) goes into an Embree BVH once; moving the
camera only changes the rays, so the acceleration structure is rebuilt only
when the mesh changes (``SurfaceCaster.mesh_version``).  Per pixel the result
is the hit face, point, outward normal, distance along the ray, and a mask of
usable pixels: missed rays, hits on the inside of the surface (camera inside
the tissue, or a fold seen from behind), and grazing hits (viewing angle
beyond ``max_view_deg``, default 89 deg) are masked, never NaN.

Degenerate triangles (zero area) are dropped from the BVH; their ids still
index the full triangle list so cell data stays aligned with the model node.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["SurfaceCaster", "PixelHits", "cast_camera"]


def _embree():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:  # pragma: no cover - embreex is a dependency
        raise FluoInputError(f"embreex is not installed ({exc})", field="ray caster") from None
    return rtcore_scene, TriangleMesh


class SurfaceCaster:
    """Ray casting onto one triangle surface (RAS mm)."""

    def __init__(self, points_mm, triangles):
        P = np.asarray(points_mm, float)
        T = np.asarray(triangles, np.int64)
        if P.ndim != 2 or P.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 3 or len(T) == 0:
            raise FluoInputError("surface needs (N, 3) points and (M, 3) triangles",
                                 field="surface", value=(P.shape, T.shape))
        if T.min() < 0 or T.max() >= len(P) or not np.all(np.isfinite(P)):
            raise FluoInputError("triangle indices out of range or non-finite points",
                                 field="surface")
        self.points_mm = P
        self.triangles = T
        e1 = P[T[:, 1]] - P[T[:, 0]]
        e2 = P[T[:, 2]] - P[T[:, 0]]
        n = np.cross(e1, e2)
        area2 = np.linalg.norm(n, axis=1)
        self.face_area_mm2 = 0.5 * area2
        scale = max(float(np.median(area2)), 1e-30)
        self.valid_face = area2 > 1e-9 * scale
        self.face_normals = np.where(self.valid_face[:, None], n / np.where(area2 > 0, area2, 1)[:, None], 0.0)
        self._face_index = np.flatnonzero(self.valid_face)   # BVH primitive -> face id
        rs, TriangleMesh = _embree()
        self._scene = rs.EmbreeScene()
        TriangleMesh(self._scene, P[T[self._face_index]].astype(np.float32))
        self.mesh_version = 0

    @classmethod
    def from_polydata(cls, poly):
        from vtk.util import numpy_support as ns

        pts = ns.vtk_to_numpy(poly.GetPoints().GetData())
        conn = ns.vtk_to_numpy(poly.GetPolys().GetConnectivityArray())
        off = ns.vtk_to_numpy(poly.GetPolys().GetOffsetsArray())
        if not np.all(np.diff(off) == 3):
            raise FluoInputError("surface must be triangles only", field="surface")
        return cls(pts, conn.reshape(-1, 3))

    @property
    def n_faces(self):
        return len(self.triangles)

    def cast(self, origins, directions):
        """(face id or -1, distance along the unit direction [mm]) per ray."""
        o = np.ascontiguousarray(origins, np.float32).reshape(-1, 3)
        d = np.asarray(directions, float).reshape(-1, 3)
        d = np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True), np.float32)
        if len(o) == 1 and len(d) > 1:
            o = np.ascontiguousarray(np.broadcast_to(o, d.shape))
        res = self._scene.run(o, d, output=1)
        prim = np.asarray(res["primID"])
        hit = np.asarray(res["geomID"]) >= 0
        face = np.where(hit, self._face_index[np.where(hit, prim, 0)], -1)
        dist = np.where(hit, np.asarray(res["tfar"], float), np.inf)
        return face, dist


@dataclass
class PixelHits:
    """Per-pixel geometry of one camera view (arrays of the image shape)."""

    face: np.ndarray            # int, -1 where masked
    point_mm: np.ndarray        # (H, W, 3) world (RAS) hit point, 0 where masked
    normal: np.ndarray          # (H, W, 3) outward unit normal, 0 where masked
    distance_mm: np.ndarray     # along the ray, inf where masked
    cos_view: np.ndarray        # cos of the angle between normal and the ray back to the camera
    visible: np.ndarray         # bool: usable pixel
    reason: np.ndarray          # uint8: 0 ok, 1 miss, 2 back face (inside), 3 grazing
    camera_center_mm: np.ndarray

    @property
    def shape(self):
        return self.face.shape


def cast_camera(caster, camera, camera_to_world, binning=1, max_view_deg=89.0):
    """Cast every (binned) pixel of a calibrated camera at a pose onto the surface.

    ``camera_to_world``: 4x4 camera frame (OpenCV: x right, y down, z forward)
    to the surface's frame, mm.
    """
    M = np.asarray(camera_to_world, float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise FluoInputError("camera pose must be a finite 4x4 matrix", field="camera_to_world")
    rays_cam = camera.pixel_grid_rays(binning)                    # (h, w, 3) unit, cached
    shape = rays_cam.shape[:2]
    ok_ray = np.all(np.isfinite(rays_cam), axis=-1)
    dirs = np.where(ok_ray[..., None], rays_cam, [0.0, 0.0, 1.0]) @ M[:3, :3].T
    center = M[:3, 3]
    face, dist = caster.cast(center[None], dirs.reshape(-1, 3))
    face = face.reshape(shape)
    dist = dist.reshape(shape)
    hit = (face >= 0) & ok_ray
    n = caster.face_normals[np.where(hit, face, 0)]
    cos_view = -np.einsum("hwi,hwi->hw", n, dirs)
    reason = np.zeros(shape, np.uint8)
    reason[~hit] = 1
    reason[hit & (cos_view <= 0)] = 2
    grazing = hit & (cos_view > 0) & (cos_view < np.cos(np.deg2rad(max_view_deg)))
    reason[grazing] = 3
    visible = reason == 0
    point = np.where(visible[..., None], center + dirs * np.where(visible, dist, 0.0)[..., None], 0.0)
    return PixelHits(face=np.where(visible, face, -1), point_mm=point,
                     normal=np.where(visible[..., None], n, 0.0),
                     distance_mm=np.where(visible, dist, np.inf),
                     cos_view=np.where(visible, cos_view, 0.0), visible=visible, reason=reason,
                     camera_center_mm=center)
