"""Primary-ray casting by z-buffer rasterisation (the video-rate path).

For a central camera every pixel ray leaves the camera centre, so casting
all of them equals rasterising the triangles with a depth test and then
intersecting each pixel's own exact ray (float64 Moller-Trumbore or the face
plane) with the face found at that pixel.  Everything per camera and binning
(pixel rays, grids, buffers) is built once (:class:`RayGrid`); per frame the
mesh is moved into the camera frame, projected and rasterised (numba, row
bands in parallel), then resolved per pixel (numba, parallel).

Two samplings, both exact at the pixel centres:

- no distortion: the grid in undistorted normalised coordinates (x/z, y/z)
  *is* the pixel grid (cell centre = pixel ray); 1/z is affine there, so the
  depth test is exact;
- pinhole distortion: vertices are projected through the distortion into
  pixel space and triangles are rasterised there; triangles larger than
  ``_MAX_PIX_EXTENT`` pixels are tessellated into planar sub-triangles (their
  edges curve in pixel space); a pixel whose own face misses (sub-pixel chord
  sag) tries its neighbours' faces.  Triangles reaching behind the near plane
  or outside the disc where the distortion is invertible go to a sparse
  normalised grid, searched in a 3 x 3 neighbourhood.

Triangles crossing the camera plane are clipped at ``znear_mm``, so a camera
inside the cavity (or inside the tissue) still sees what is in front of it.
A fisheye lens has no pixel-space path: :func:`pixel_cast.cast_camera` uses
the BVH there (forcing "raster" gives the normalised grid, approximate where
triangles are smaller than a pixel).  Rays at 90 deg or more from the axis
have no normalised coordinates (:attr:`RayGrid.usable` False).
"""

from __future__ import annotations

import numpy as np
from numba import get_num_threads, njit, prange

__all__ = ["RayGrid", "raster_cast"]

_EPS_BARY = 1e-9        # closes cracks along shared edges in the exact intersection
_EPS_RASTER = 1e-6      # inclusive coverage test in grid units (no cracks between triangles)
_MAX_PIX_EXTENT = 24.0  # px: larger triangles are tessellated (their edges curve in pixel space)


class RayGrid:
    """The normalised-coordinate grid of one camera at one binning.

    Attributes
    ----------
    rays_cam : (h, w, 3) unit rays of the pixels (camera frame)
    cell : (h*w,) int32 grid cell of each pixel ray, -1 for undefined rays
    x0, y0, sx, sy : grid origin (centre of cell 0) and pitch in normalised units
    gw, gh : grid size in cells
    exact : True when every pixel ray passes through its cell centre (no distortion)
    """

    def __init__(self, camera, binning=1, max_cells_factor=4.0):
        rays = camera.pixel_grid_rays(binning)
        self.rays_cam = rays
        h, w = rays.shape[:2]
        self.shape = (h, w)
        flat = np.ascontiguousarray(rays.reshape(-1, 3), dtype=np.float64)
        self._rays_flat = flat
        ok = np.all(np.isfinite(flat), axis=1) & (flat[:, 2] > 1e-3)
        self.usable = bool(ok.any())
        if not self.usable:
            return
        xn = np.where(ok, flat[:, 0] / np.where(ok, flat[:, 2], 1.0), 0.0)
        yn = np.where(ok, flat[:, 1] / np.where(ok, flat[:, 2], 1.0), 0.0)
        # pitch: the nominal (undistorted) pixel pitch of this binning
        self.sx = binning / camera.fx
        self.sy = binning / camera.fy
        self.x0 = float(xn[ok].min())
        self.y0 = float(yn[ok].min())
        gx = (xn - self.x0) / self.sx
        gy = (yn - self.y0) / self.sy
        self.gw = int(np.floor(gx[ok].max() + 0.5)) + 1
        self.gh = int(np.floor(gy[ok].max() + 0.5)) + 1
        if self.gw * self.gh > max_cells_factor * h * w:
            # strong distortion spreads the rays far beyond the image: BVH instead
            self.usable = False
            return
        ix = np.rint(gx).astype(np.int64)
        iy = np.rint(gy).astype(np.int64)
        cell = np.where(ok, iy * self.gw + ix, -1)
        self.cell = cell.astype(np.int32)
        self.exact = bool(np.all(np.abs(gx[ok] - ix[ok]) < 1e-6) and np.all(np.abs(gy[ok] - iy[ok]) < 1e-6))
        self._face_buf = np.empty(self.gh * self.gw, np.int32)
        self._invz_buf = np.empty(self.gh * self.gw, np.float64)
        self._proj_buf = None
        # With (pinhole) distortion the triangles are rasterised in pixel space
        # instead, their vertices projected through the distortion, so pixel
        # centres are sampled exactly; edges become chords of the true curved
        # edges (a sub-pixel sag for triangles of a few pixels; a miss there
        # falls back to the neighbouring pixels' faces).  Only triangles with
        # a vertex outside the disc where the distortion is invertible (or
        # behind the near plane) go to the normalised grid.
        self.pixel_space = False
        self._pix = np.zeros(10)
        if not self.exact and camera.model == "pinhole":
            cb = camera.binned(binning) if binning > 1 else camera
            k = (list(cb.dist) + [0.0] * 5)[:5]
            r_max = 1.1 * float(np.sqrt((xn[ok] ** 2 + yn[ok] ** 2).max()))
            rr = np.linspace(0.0, r_max, 4001)
            r2 = rr * rr
            radial = rr * (1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[4])))
            if np.all(np.diff(radial) > 0):
                self.pixel_space = True
                self._pix = np.array([cb.fx, cb.fy, cb.cx, cb.cy, *k, r_max * r_max])
        n_pix = h * w if self.pixel_space else 1
        self._pface_buf = np.empty(n_pix, np.int32)
        self._pinvz_buf = np.empty(n_pix, np.float64)
        self._pproj_buf = None


@njit(cache=True, inline="always")
def _raster_tri(ax, ay, az, bx, by, bz, cx, cy, cz, f, face_buf, invz_buf, gw, r0, r1):
    """Rasterise one triangle (grid coordinates, 1/z per vertex) into rows r0..r1.

    Per row the covered cells form one span, found from the three affine
    barycentric functions; inside it only the depth test runs.  The coverage
    test is inclusive by ``_EPS_RASTER`` cells so shared edges leave no cracks.
    """
    area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    if abs(area) < 1e-12:
        return
    j0 = max(r0, int(np.ceil(min(ay, by, cy) - _EPS_RASTER)))
    j1 = min(r1, int(np.floor(max(ay, by, cy) + _EPS_RASTER)))
    if j0 > j1:
        return
    i0 = max(0, int(np.ceil(min(ax, bx, cx) - _EPS_RASTER)))
    i1 = min(gw - 1, int(np.floor(max(ax, bx, cx) + _EPS_RASTER)))
    if i0 > i1:
        return
    inv = 1.0 / area
    # w_k(px, py) = P_k + Q_k py + B_k px; coverage w_k >= e_k bounds px on
    # one side by a line in py, so each row's span costs a few multiply-adds
    B0 = (by - cy) * inv
    Q0 = (cx - bx) * inv
    P0 = (bx * cy - cx * by) * inv
    B1 = (cy - ay) * inv
    Q1 = (ax - cx) * inv
    P1 = (cx * ay - ax * cy) * inv
    B2 = -B0 - B1
    Q2 = -Q0 - Q1
    P2 = 1.0 - P0 - P1
    e0 = -_EPS_RASTER * np.sqrt(B0 * B0 + Q0 * Q0)
    e1 = -_EPS_RASTER * np.sqrt(B1 * B1 + Q1 * Q1)
    e2 = -_EPS_RASTER * np.sqrt(B2 * B2 + Q2 * Q2)
    # px bound of edge k: (e_k - P_k - Q_k py) / B_k = L_k + M_k py
    lo_L = float(i0)
    lo_M = 0.0
    hi_L = float(i1)
    hi_M = 0.0
    lo_L2 = -1e300
    lo_M2 = 0.0
    hi_L2 = 1e300
    hi_M2 = 0.0
    n_lo = 0
    n_hi = 0
    # at most two edges bound each side (B0 + B1 + B2 = 0)
    for k in range(3):
        if k == 0:
            Bk, Qk, Pk, ek = B0, Q0, P0, e0
        elif k == 1:
            Bk, Qk, Pk, ek = B1, Q1, P1, e1
        else:
            Bk, Qk, Pk, ek = B2, Q2, P2, e2
        if Bk == 0.0:
            continue
        L = (ek - Pk) / Bk
        Mq = -Qk / Bk
        if Bk > 0.0:
            if n_lo == 0:
                lo_L2, lo_M2 = L, Mq
            else:
                lo_L, lo_M = lo_L2, lo_M2
                lo_L2, lo_M2 = L, Mq
            n_lo += 1
        else:
            if n_hi == 0:
                hi_L2, hi_M2 = L, Mq
            else:
                hi_L, hi_M = hi_L2, hi_M2
                hi_L2, hi_M2 = L, Mq
            n_hi += 1
    dz = B0 * az + B1 * bz + B2 * cz
    for j in range(j0, j1 + 1):
        py = float(j)
        # an edge with B_k = 0 bounds rows, not columns: check it here
        A0 = P0 + Q0 * py
        A1 = P1 + Q1 * py
        A2 = P2 + Q2 * py
        if (B0 == 0.0 and A0 < e0) or (B1 == 0.0 and A1 < e1) or (B2 == 0.0 and A2 < e2):
            continue
        lo = max(float(i0), lo_L + lo_M * py, lo_L2 + lo_M2 * py)
        hi = min(float(i1), hi_L + hi_M * py, hi_L2 + hi_M2 * py)
        ilo = int(np.ceil(lo))
        ihi = int(np.floor(hi))
        if ilo > ihi:
            continue
        z0 = A0 * az + A1 * bz + A2 * cz      # 1/z is affine in screen space
        row = j * gw
        for i in range(ilo, ihi + 1):
            iz = z0 + dz * i
            k = row + i
            if iz > invz_buf[k]:
                invz_buf[k] = iz
                face_buf[k] = f


@njit(cache=True)
def _to_camera(points, normals, tris, R, c, pc, n_cam, plane_d):
    """Vertices and face normals in the camera frame, face plane offsets n.a
    (plain loops: no BLAS threads competing with the raster threads)."""
    for v in range(points.shape[0]):
        x = points[v, 0] - c[0]
        y = points[v, 1] - c[1]
        z = points[v, 2] - c[2]
        for k in range(3):
            pc[v, k] = x * R[0, k] + y * R[1, k] + z * R[2, k]
    for f in range(normals.shape[0]):
        a = tris[f, 0]
        d = 0.0
        for k in range(3):
            n = normals[f, 0] * R[0, k] + normals[f, 1] * R[1, k] + normals[f, 2] * R[2, k]
            n_cam[f, k] = n
            d += n * pc[a, k]
        plane_d[f] = d


@njit(cache=True)
def _project(pc, znear, x0, y0, sx, sy, proj):
    """Grid coordinates and 1/z of every vertex; 1/z = -1 marks z < znear."""
    for v in range(pc.shape[0]):
        z = pc[v, 2]
        if z >= znear:
            iz = 1.0 / z
            proj[v, 0] = (pc[v, 0] * iz - x0) / sx
            proj[v, 1] = (pc[v, 1] * iz - y0) / sy
            proj[v, 2] = iz
        else:
            proj[v, 0] = 0.0
            proj[v, 1] = 0.0
            proj[v, 2] = -1.0


@njit(cache=True, inline="always")
def _pixel_of(x, y, z, prm):
    """(u, v, 1/z) of a camera-frame point (OpenCV pinhole with distortion)."""
    iz = 1.0 / z
    x = x * iz
    y = y * iz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (prm[4] + r2 * (prm[5] + r2 * prm[8]))
    xd = x * radial + 2.0 * prm[6] * x * y + prm[7] * (r2 + 2.0 * x * x)
    yd = y * radial + prm[6] * (r2 + 2.0 * y * y) + 2.0 * prm[7] * x * y
    return prm[0] * xd + prm[2], prm[1] * yd + prm[3], iz


@njit(cache=True)
def _raster_tessellated(pc, a, b, c, n, prm, f, face_buf, invz_buf, pw, q0, q1):
    """Rasterise face f split into n x n planar sub-triangles in pixel space."""
    inv_n = 1.0 / n
    for i in range(n):
        for j in range(n - i):
            # sub-triangle (i, j), (i+1, j), (i, j+1) and, inside, (i+1, j), (i+1, j+1), (i, j+1)
            for up in range(2):
                if up == 1 and i + j + 1 >= n:
                    continue
                if up == 0:
                    s0, t0, s1, t1, s2, t2 = i, j, i + 1, j, i, j + 1
                else:
                    s0, t0, s1, t1, s2, t2 = i + 1, j, i + 1, j + 1, i, j + 1
                x, y, z = _bary(pc, a, b, c, s0 * inv_n, t0 * inv_n)
                u0, v0, z0 = _pixel_of(x, y, z, prm)
                x, y, z = _bary(pc, a, b, c, s1 * inv_n, t1 * inv_n)
                u1, v1, z1 = _pixel_of(x, y, z, prm)
                x, y, z = _bary(pc, a, b, c, s2 * inv_n, t2 * inv_n)
                u2, v2, z2 = _pixel_of(x, y, z, prm)
                _raster_tri(u0, v0, z0, u1, v1, z1, u2, v2, z2, f, face_buf, invz_buf, pw, q0, q1)


@njit(cache=True, inline="always")
def _bary(pc, a, b, c, s, t):
    """Camera-frame point A + s (B - A) + t (C - A)."""
    return (pc[a, 0] + s * (pc[b, 0] - pc[a, 0]) + t * (pc[c, 0] - pc[a, 0]),
            pc[a, 1] + s * (pc[b, 1] - pc[a, 1]) + t * (pc[c, 1] - pc[a, 1]),
            pc[a, 2] + s * (pc[b, 2] - pc[a, 2]) + t * (pc[c, 2] - pc[a, 2]))


@njit(cache=True)
def _project_pixels(pc, znear, prm, proj):
    """Distorted pixel coordinates and 1/z of every vertex (OpenCV pinhole model);
    1/z = -1 marks vertices behind the near plane or outside the valid disc."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, r2max = (prm[0], prm[1], prm[2], prm[3], prm[4], prm[5],
                                                 prm[6], prm[7], prm[8], prm[9])
    for v in range(pc.shape[0]):
        z = pc[v, 2]
        proj[v, 2] = -1.0
        if z < znear:
            continue
        iz = 1.0 / z
        x = pc[v, 0] * iz
        y = pc[v, 1] * iz
        r2 = x * x + y * y
        if r2 > r2max:
            continue
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        proj[v, 0] = fx * xd + cx
        proj[v, 1] = fy * yd + cy
        proj[v, 2] = iz


@njit(cache=True, parallel=True)
def _rasterise(pc, proj, tris, valid, x0, y0, sx, sy, gw, gh, znear, face_buf, invz_buf, nbands,
               use_pix, pproj, pw, ph, pface_buf, pinvz_buf, prm):
    """Z-buffer of face ids over the grid, in row bands (one per thread).

    With ``use_pix`` triangles whose three vertices have pixel coordinates go
    to the pixel-space buffer, the rest to the normalised grid."""
    for band in prange(nbands):
        r0 = band * gh // nbands
        r1 = (band + 1) * gh // nbands - 1
        face_buf[r0 * gw:(r1 + 1) * gw] = -1
        invz_buf[r0 * gw:(r1 + 1) * gw] = 0.0
        q0 = band * ph // nbands
        q1 = (band + 1) * ph // nbands - 1
        if use_pix:
            pface_buf[q0 * pw:(q1 + 1) * pw] = -1
            pinvz_buf[q0 * pw:(q1 + 1) * pw] = 0.0
        vx = np.empty(4)
        vy = np.empty(4)
        vz = np.empty(4)
        lo_row = r0 - 1.0
        hi_row = r1 + 1.0
        for f in range(tris.shape[0]):
            if not valid[f]:
                continue
            a = tris[f, 0]
            b = tris[f, 1]
            c = tris[f, 2]
            if use_pix and pproj[a, 2] > 0.0 and pproj[b, 2] > 0.0 and pproj[c, 2] > 0.0:
                ya, yb, yc = pproj[a, 1], pproj[b, 1], pproj[c, 1]
                if max(ya, yb, yc) < q0 - 1.0 or min(ya, yb, yc) > q1 + 1.0:
                    continue
                ext = max(max(pproj[a, 0], pproj[b, 0], pproj[c, 0]) - min(pproj[a, 0], pproj[b, 0], pproj[c, 0]),
                          max(ya, yb, yc) - min(ya, yb, yc))
                if ext < _MAX_PIX_EXTENT:
                    _raster_tri(pproj[a, 0], ya, pproj[a, 2], pproj[b, 0], yb, pproj[b, 2],
                                pproj[c, 0], yc, pproj[c, 2], f, pface_buf, pinvz_buf, pw, q0, q1)
                else:
                    # a big triangle's edges are curves in pixel space: tessellate it
                    # (planar sub-triangles, vertices projected exactly) so each chord
                    # stays within a fraction of a pixel of the true edge
                    _raster_tessellated(pc, a, b, c, min(int(ext / _MAX_PIX_EXTENT) + 1, 256), prm,
                                        f, pface_buf, pinvz_buf, pw, q0, q1)
                continue
            if proj[a, 2] > 0.0 and proj[b, 2] > 0.0 and proj[c, 2] > 0.0:
                ya, yb, yc = proj[a, 1], proj[b, 1], proj[c, 1]
                if max(ya, yb, yc) < lo_row or min(ya, yb, yc) > hi_row:
                    continue
                _raster_tri(proj[a, 0], ya, proj[a, 2], proj[b, 0], yb, proj[b, 2],
                            proj[c, 0], yc, proj[c, 2], f, face_buf, invz_buf, gw, r0, r1)
                continue
            if pc[a, 2] < znear and pc[b, 2] < znear and pc[c, 2] < znear:
                continue
            # the triangle crosses z = znear: clip it (Sutherland-Hodgman, one plane)
            n = 0
            for e in range(3):
                p = tris[f, e]
                q = tris[f, (e + 1) % 3]
                zp, zq = pc[p, 2], pc[q, 2]
                if zp >= znear:
                    vx[n] = pc[p, 0]
                    vy[n] = pc[p, 1]
                    vz[n] = zp
                    n += 1
                if (zp >= znear) != (zq >= znear):
                    s = (znear - zp) / (zq - zp)
                    vx[n] = pc[p, 0] + s * (pc[q, 0] - pc[p, 0])
                    vy[n] = pc[p, 1] + s * (pc[q, 1] - pc[p, 1])
                    vz[n] = znear
                    n += 1
            for k in range(n):
                iz = 1.0 / vz[k]
                vx[k] = (vx[k] * iz - x0) / sx
                vy[k] = (vy[k] * iz - y0) / sy
                vz[k] = iz
            for k in range(1, n - 1):
                _raster_tri(vx[0], vy[0], vz[0], vx[k], vy[k], vz[k], vx[k + 1], vy[k + 1],
                            vz[k + 1], f, face_buf, invz_buf, gw, r0, r1)


@njit(cache=True, inline="always")
def _hit(pc, tris, f, dx, dy, dz):
    """Distance along the unit ray from the origin to face f (camera frame), or -1."""
    a, b, c = tris[f, 0], tris[f, 1], tris[f, 2]
    ax, ay, az = pc[a, 0], pc[a, 1], pc[a, 2]
    e1x, e1y, e1z = pc[b, 0] - ax, pc[b, 1] - ay, pc[b, 2] - az
    e2x, e2y, e2z = pc[c, 0] - ax, pc[c, 1] - ay, pc[c, 2] - az
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return -1.0
    inv = 1.0 / det
    tx, ty, tz = -ax, -ay, -az
    u = (tx * px + ty * py + tz * pz) * inv
    if u < -_EPS_BARY or u > 1.0 + _EPS_BARY:
        return -1.0
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < -_EPS_BARY or u + v > 1.0 + _EPS_BARY:
        return -1.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return t if t > 0.0 else -1.0


@njit(cache=True, inline="always")
def _nearest_in_3x3(buf, ci, cj, w, h, skip, best_f, best_t, pc, tris, dx, dy, dz):
    """Nearest exact hit among the faces stored in the 3 x 3 cells of ``buf``
    (a w x h face buffer) around (ci, cj), starting from (best_f, best_t);
    ``skip`` is a face already tried."""
    for jj in range(max(cj - 1, 0), min(cj + 2, h)):
        for ii in range(max(ci - 1, 0), min(ci + 2, w)):
            f = buf[jj * w + ii]
            if f < 0 or f == skip or f == best_f:
                continue
            t = _hit(pc, tris, f, dx, dy, dz)
            if t > 0.0 and t < best_t:
                best_f, best_t = f, t
    return best_f, best_t


@njit(cache=True, inline="always")
def _classify(p, f, t, n_cam, dx, dy, dz, cos_graze, out_face, out_t, out_cos, out_reason,
              out_visible):
    """Write pixel p's result for its nearest hit (face f at distance t)."""
    c = -(n_cam[f, 0] * dx + n_cam[f, 1] * dy + n_cam[f, 2] * dz)
    if c <= 0.0:
        out_reason[p] = 2          # back face: the camera is inside the tissue
    elif c < cos_graze:
        out_reason[p] = 3          # grazing
    else:
        out_reason[p] = 0
        out_visible[p] = True
        out_face[p] = f
        out_t[p] = t
        out_cos[p] = c


@njit(cache=True, parallel=True)
def _resolve(cell, rays, pc, tris, n_cam, plane_d, face_buf, gw, gh, exact, cos_graze,
             out_face, out_t, out_cos, out_reason, out_visible):
    """Per pixel: the exact intersection of its own ray with the face(s) of its cell.

    On an exact grid the cell's face is the one the pixel ray meets first, so
    only the plane distance is needed; otherwise the cell's 3 x 3
    neighbourhood is tried with Moller-Trumbore and the nearest hit wins.
    """
    for p in prange(cell.shape[0]):
        out_face[p] = -1
        out_t[p] = np.inf
        out_cos[p] = 0.0
        out_reason[p] = 1
        out_visible[p] = False
        k = cell[p]
        if k < 0:
            continue
        dx, dy, dz = rays[p, 0], rays[p, 1], rays[p, 2]
        best_f = -1
        best_t = np.inf
        if exact:
            f = face_buf[k]
            if f < 0:
                continue
            nd = n_cam[f, 0] * dx + n_cam[f, 1] * dy + n_cam[f, 2] * dz
            if nd == 0.0:
                continue
            t = plane_d[f] / nd
            if t <= 0.0:
                continue
            best_f, best_t = f, t
        else:
            best_f, best_t = _nearest_in_3x3(face_buf, k % gw, k // gw, gw, gh, -1, best_f, best_t,
                                             pc, tris, dx, dy, dz)
            if best_f < 0:
                continue
        _classify(p, best_f, best_t, n_cam, dx, dy, dz, cos_graze, out_face, out_t, out_cos,
                  out_reason, out_visible)


@njit(cache=True, parallel=True)
def _resolve_pixels(cell, rays, pc, tris, n_cam, pface_buf, pw, ph, face_buf, gw, gh, cos_graze,
                    out_face, out_t, out_cos, out_reason, out_visible):
    """Per pixel, pixel-space buffer: its own face, else its neighbours' faces
    (edge sag), plus any face of the sparse normalised grid nearby; the
    nearest exact (Moller-Trumbore) hit wins."""
    for p in prange(cell.shape[0]):
        out_face[p] = -1
        out_t[p] = np.inf
        out_cos[p] = 0.0
        out_reason[p] = 1
        out_visible[p] = False
        k = cell[p]
        if k < 0:
            continue
        dx, dy, dz = rays[p, 0], rays[p, 1], rays[p, 2]
        best_f = -1
        best_t = np.inf
        f0 = pface_buf[p]
        if f0 >= 0:
            t = _hit(pc, tris, f0, dx, dy, dz)
            if t > 0.0:
                best_f, best_t = f0, t
        if best_f < 0:
            best_f, best_t = _nearest_in_3x3(pface_buf, p % pw, p // pw, pw, ph, f0, best_f, best_t,
                                             pc, tris, dx, dy, dz)
        best_f, best_t = _nearest_in_3x3(face_buf, k % gw, k // gw, gw, gh, -1, best_f, best_t,
                                         pc, tris, dx, dy, dz)
        if best_f < 0:
            continue
        _classify(p, best_f, best_t, n_cam, dx, dy, dz, cos_graze, out_face, out_t, out_cos,
                  out_reason, out_visible)


def raster_cast(grid, points_mm, triangles, valid_face, face_normals, camera_to_world,
                max_view_deg=89.0, znear_mm=1e-3):
    """Cast every ray of ``grid`` from the pose onto the mesh.

    Returns arrays of the grid's image shape: face id (-1 unless visible),
    distance [mm] (inf unless visible), viewing cosine (0 unless visible),
    reason code (0 ok, 1 miss, 2 back face, 3 grazing) and the visible mask.
    """
    M = np.asarray(camera_to_world, float)
    R = M[:3, :3]
    c = M[:3, 3]
    if grid._proj_buf is None or grid._proj_buf.shape[0] != len(points_mm) \
            or grid._ncam_buf.shape[0] != len(triangles):
        grid._proj_buf = np.empty((len(points_mm), 3))
        grid._pc_buf = np.empty((len(points_mm), 3))
        grid._ncam_buf = np.empty((len(triangles), 3))
        grid._pd_buf = np.empty(len(triangles))
    pc, proj, n_cam, plane_d = grid._pc_buf, grid._proj_buf, grid._ncam_buf, grid._pd_buf
    _to_camera(points_mm, face_normals, triangles, np.ascontiguousarray(R), np.ascontiguousarray(c),
               pc, n_cam, plane_d)
    _project(pc, float(znear_mm), grid.x0, grid.y0, grid.sx, grid.sy, proj)
    h, w = grid.shape
    if grid._pproj_buf is None or grid._pproj_buf.shape[0] != len(points_mm):
        grid._pproj_buf = np.empty((len(points_mm), 3))
    pproj = grid._pproj_buf
    if grid.pixel_space:
        _project_pixels(pc, float(znear_mm), grid._pix, pproj)
    _rasterise(pc, proj, triangles, valid_face, grid.x0, grid.y0, grid.sx, grid.sy, grid.gw,
               grid.gh, float(znear_mm), grid._face_buf, grid._invz_buf, get_num_threads(),
               grid.pixel_space, pproj, w, h, grid._pface_buf, grid._pinvz_buf, grid._pix)
    face = np.empty((h, w), np.int32)
    t = np.empty((h, w), np.float64)
    cos = np.empty((h, w), np.float64)
    reason = np.empty((h, w), np.uint8)
    visible = np.empty((h, w), np.bool_)
    cos_graze = float(np.cos(np.deg2rad(max_view_deg)))
    outs = (face.reshape(-1), t.reshape(-1), cos.reshape(-1), reason.reshape(-1), visible.reshape(-1))
    if grid.pixel_space:
        _resolve_pixels(grid.cell, grid._rays_flat, pc, triangles, n_cam, grid._pface_buf, w, h,
                        grid._face_buf, grid.gw, grid.gh, cos_graze, *outs)
    else:
        _resolve(grid.cell, grid._rays_flat, pc, triangles, n_cam, plane_d, grid._face_buf, grid.gw,
                 grid.gh, grid.exact, cos_graze, *outs)
    return face, t, cos, reason, visible
