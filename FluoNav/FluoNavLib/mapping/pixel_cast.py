"""Every camera pixel's ray cast onto the tissue surface.

Two paths give the same per-pixel result: z-buffer rasterisation in
undistorted normalised coordinates followed by an exact float64 intersection
of each pixel's own ray (``rasterize.py``, numba; the video-rate default),
and an Embree BVH (embreex, float32) for cameras whose rays reach 90 deg.
Both are built once per mesh (and per camera/binning for the raster grid);
moving the camera only changes the pose.  :func:`reference_cast` is the slow
exact brute force the fast paths are checked against.

Per pixel the result is the hit face, point, outward normal, distance along
the ray, and a mask of usable pixels: missed rays, hits on the inside of the
surface (camera inside the tissue, or a fold seen from behind), and grazing
hits (viewing angle beyond ``max_view_deg``, default 89 deg) are masked,
never NaN.  Degenerate triangles (zero area) are skipped; their ids still
index the full triangle list so cell data stays aligned with the model node.
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["SurfaceCaster", "PixelHits", "cast_camera", "reference_cast"]


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
        # own C-ordered copies: the BVH is built from them (a caller's array changed
        # later must not change the raster path alone), and they are the argument
        # types the compiled kernels are prepared for (``kernels.py``): a column
        # slice or a read-only buffer would be compiled again at the first cast
        P = np.array(points_mm, float, order="C")
        T = np.array(triangles, np.int64, order="C")
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

    def ray_grid(self, camera, binning=1):
        """The rasterisation grid of a camera at a binning, built once and kept
        (the pixel rays and z-buffer are per camera, not per pose)."""
        from FluoNavLib.mapping.rasterize import RayGrid

        key = (id(camera), int(binning))
        cache = self.__dict__.setdefault("_grids", {})
        hit = cache.get(key)
        if hit is None or hit[0] is not camera:
            if len(cache) >= 8:                 # a full-res grid holds ~60 MB: keep few
                cache.pop(next(iter(cache)))
            cache[key] = (camera, RayGrid(camera, binning))
        return cache[key][1]

    @property
    def normal_spread_rad(self):
        """Per face, the largest angle [rad] between the normals of the faces that
        share one of its vertices (its one-ring), computed once per mesh.

        It is how well the mesh knows the surface's orientation there: a few
        degrees on smooth tissue, tens of degrees on creases narrower than the
        CBCT resolves (a cavity rim), where the illumination model, which
        depends on the normal, cannot be trusted (``flux_map.model_error``)."""
        if getattr(self, "_spread", None) is None:
            T, N = self.triangles, self.face_normals
            mean = np.zeros((len(self.points_mm), 3))
            for j in range(3):
                np.add.at(mean, T[:, j], N)
            mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-30)
            cos_min = np.ones(len(self.points_mm))
            for j in range(3):
                np.minimum.at(cos_min, T[:, j], np.sum(N * mean[T[:, j]], axis=1))
            # half-cone angle at each vertex; a face's one-ring spans up to twice it
            half = np.arccos(np.clip(cos_min, -1.0, 1.0))
            self._spread = np.where(self.valid_face, 2.0 * np.max(half[T], axis=1), np.pi)
        return self._spread

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
        if len(self._face_index) == 0:          # nothing but degenerate triangles
            return np.full(len(d), -1, np.int64), np.full(len(d), np.inf)
        res = self._scene.run(o, d, output=1)
        prim = np.asarray(res["primID"])
        hit = np.asarray(res["geomID"]) >= 0
        face = np.where(hit, self._face_index[np.where(hit, prim, 0)], -1)
        dist = np.where(hit, np.asarray(res["tfar"], float), np.inf)
        return face, dist


class PixelHits:
    """Per-pixel geometry of one camera view (arrays of the image shape).

    ``face`` (int, -1 where masked), ``distance_mm`` (along the ray, inf where
    masked), ``cos_view`` (cosine between the outward normal and the ray back
    to the camera, 0 where masked), ``visible`` (usable pixel), ``reason``
    (uint8: 0 ok, 1 miss, 2 back face / inside, 3 grazing) are computed by the
    cast.  ``point_mm`` (world hit point, 0 where masked) and ``normal``
    (outward unit face normal, 0 where masked) are either given or derived on
    first use from the rays and the face normals, so a video-rate cast does
    not pay for arrays nobody reads.
    """

    def __init__(self, face, distance_mm, cos_view, visible, reason, camera_center_mm,
                 point_mm=None, normal=None, rays_cam=None, rotation=None, face_normals=None):
        self.face = face
        self.distance_mm = distance_mm
        self.cos_view = cos_view
        self.visible = visible
        self.reason = reason
        self.camera_center_mm = np.asarray(camera_center_mm, float)
        self._point = point_mm
        self._normal = normal
        self.rays_cam = rays_cam                # (H, W, 3) camera-frame unit rays (shared, read-only)
        self.rotation = rotation                # camera-to-world rotation of the cast
        self.face_normals = face_normals        # (F, 3) world normals the face ids index

    @property
    def shape(self):
        return self.face.shape

    @property
    def point_mm(self):
        if self._point is None:
            d = self.rays_cam @ self.rotation.T
            t = np.where(self.visible, self.distance_mm, 0.0)
            self._point = np.where(self.visible[..., None],
                                   self.camera_center_mm + d * t[..., None], 0.0)
        return self._point

    @property
    def normal(self):
        if self._normal is None:
            n = self.face_normals[np.where(self.visible, self.face, 0)]
            self._normal = np.where(self.visible[..., None], n, 0.0)
        return self._normal


def cast_camera(caster, camera, camera_to_world, binning=1, max_view_deg=89.0, method="auto",
                progress=None, cancel=None):
    """Cast every (binned) pixel of a calibrated camera at a pose onto the surface.

    Parameters
    ----------
    caster : SurfaceCaster
    camera : CameraModel (distortion included through its pixel rays)
    camera_to_world : (4, 4) camera frame (OpenCV: x right, y down, z forward)
        to the surface's frame, mm.
    binning : int
    max_view_deg : pixels seen at a larger angle to the normal are masked (grazing)
    method : "auto" (z-buffer rasterisation for pinhole cameras, with or without
        distortion; the BVH for fisheye lenses), "raster" (forced; approximate
        for a fisheye where triangles are smaller than a pixel) or "embree".
    progress : ``progress(fraction, message)`` or None: reports the compilation of
        the ray-casting kernels when this process has not compiled them yet (a
        first run: seconds; ``FluoNavLib.mapping.kernels``), at fraction 0
    cancel : CancelToken or None, checked while they compile

    Returns
    -------
    PixelHits
    """
    M = np.asarray(camera_to_world, float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise FluoInputError("camera pose must be a finite 4x4 matrix", field="camera_to_world")
    if method not in ("auto", "raster", "embree"):
        raise FluoInputError("cast method must be auto, raster or embree", field="method",
                             value=method)
    if method != "embree":
        grid = caster.ray_grid(camera, binning)
        # "auto" rasterises where pixel centres are sampled exactly: without
        # distortion (normalised grid = pixels) or with pinhole distortion
        # (pixel-space raster).  A fisheye keeps the BVH: on a normalised grid
        # a triangle smaller than a cell can hide between cell centres
        # ("raster" forces that approximation).
        if grid.usable and (grid.exact or grid.pixel_space or method == "raster"):
            # a caller that did not prepare the kernels (a direct call, a script)
            # still hears why its first cast takes seconds; prepared: a no-op
            from FluoNavLib.mapping.kernels import prepare_kernels

            prepare_kernels(progress, 0.0, cancel)
            return _cast_raster(caster, grid, M, max_view_deg)
        if method == "raster":
            raise FluoInputError("camera rays reach 90 deg or beyond: rasterisation impossible",
                                 field="method", value=method)
    return _cast_embree(caster, camera, M, binning, max_view_deg)


def _cast_raster(caster, grid, M, max_view_deg):
    from FluoNavLib.mapping.rasterize import raster_cast

    face, t, cos, reason, visible = raster_cast(grid, caster.points_mm, caster.triangles,
                                                caster.valid_face, caster.face_normals, M,
                                                max_view_deg)
    return PixelHits(face=face, distance_mm=t, cos_view=cos, visible=visible, reason=reason,
                     camera_center_mm=M[:3, 3], rays_cam=grid.rays_cam, rotation=M[:3, :3].copy(),
                     face_normals=caster.face_normals)


def _cast_embree(caster, camera, M, binning, max_view_deg):
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


def reference_cast(points_mm, triangles, origin_mm, directions, chunk=None):
    """Slow exact reference: every ray against every triangle, float64.

    Returns (face id or -1, distance [mm] or inf) of the nearest hit per ray,
    degenerate triangles skipped.  Cost is rays x triangles: for checking the
    fast paths on small meshes or on a sample of pixels.
    """
    P = np.asarray(points_mm, float)
    T = np.asarray(triangles, np.int64)
    o = np.asarray(origin_mm, float).reshape(3)
    D = np.asarray(directions, float).reshape(-1, 3)
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    a = P[T[:, 0]]
    e1 = P[T[:, 1]] - a
    e2 = P[T[:, 2]] - a
    good = np.linalg.norm(np.cross(e1, e2), axis=1) > 0
    tv = o - a
    qv = np.cross(tv, e1)                                          # (F, 3), ray independent
    face = np.full(len(D), -1, np.int64)
    dist = np.full(len(D), np.inf)
    chunk = chunk or max(1, int(2e6 // max(len(T), 1)))      # ~50 MB of temporaries
    for s in range(0, len(D), chunk):
        d = D[s:s + chunk]
        pv = np.cross(d[:, None, :], e2[None])                     # (n, F, 3)
        det = np.einsum("nfi,fi->nf", pv, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = np.einsum("nfi,fi->nf", pv, tv) * inv
            v = (d @ qv.T) * inv
            t = (qv * e2).sum(1)[None] * inv
        hit = good[None] & (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(hit, t, np.inf)
        k = np.argmin(t, axis=1)
        tk = t[np.arange(len(d)), k]
        face[s:s + chunk] = np.where(np.isfinite(tk), k, -1)
        dist[s:s + chunk] = tk
    return face, dist
