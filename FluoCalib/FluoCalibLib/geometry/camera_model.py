"""Camera intrinsics: projection of camera-frame points and back-projection of pixels.

The model is OpenCV's, so numbers move freely between this code, ``cv2`` and
OpenCV YAML files:

- ``model="pinhole"``: Brown-Conrady distortion, ``dist = (k1, k2, p1, p2, k3)``
  exactly as ``cv2.projectPoints`` / ``cv2.undistortPoints``.
- ``model="fisheye"``: equidistant-type model of ``cv2.fisheye``,
  ``dist = (k1, k2, k3, k4)``; ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 +
  k3 theta^6 + k4 theta^8)``.

Frames and units: camera frame x right, y down, z forward (optical axis);
points in mm, pixels with the centre of pixel (0, 0) at (0.0, 0.0) (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["CameraModel"]

_MODELS = ("pinhole", "fisheye")


@dataclass
class CameraModel:
    """Pinhole or fisheye camera with OpenCV-compatible distortion.

    Parameters
    ----------
    fx, fy : float
        Focal lengths [px].
    cx, cy : float
        Principal point [px] (pixel-centre convention of OpenCV).
    dist : tuple of float
        ``(k1, k2, p1, p2, k3)`` for ``pinhole``; ``(k1, k2, k3, k4)`` for
        ``fisheye``. A 4-element pinhole tuple means k3 = 0.
    width, height : int
        Image size [px].
    model : {"pinhole", "fisheye"}
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 640
    height: int = 480
    model: str = "pinhole"
    _ray_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.model not in _MODELS:
            raise FluoInputError(f"camera model must be one of {_MODELS}", field="model",
                                 value=self.model)
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise FluoInputError("must be finite", field=name, value=v)
            setattr(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise FluoInputError("focal lengths must be positive [px]", field="fx/fy",
                                 value=(self.fx, self.fy))
        d = np.asarray(self.dist, dtype=float).reshape(-1)
        if not np.all(np.isfinite(d)):
            raise FluoInputError("distortion coefficients must be finite", field="dist",
                                 value=tuple(d))
        if self.model == "pinhole":
            if d.size == 4:
                d = np.append(d, 0.0)
            if d.size != 5:
                raise FluoInputError("pinhole distortion must be (k1, k2, p1, p2, k3)",
                                     field="dist", value=tuple(d))
        elif d.size != 4:
            raise FluoInputError("fisheye distortion must be (k1, k2, k3, k4)", field="dist",
                                 value=tuple(d))
        self.dist = tuple(float(x) for x in d)
        w, h = int(self.width), int(self.height)
        if w <= 0 or h <= 0 or w != self.width or h != self.height:
            raise FluoInputError("image size must be positive integers [px]",
                                 field="width/height", value=(self.width, self.height))
        self.width, self.height = w, h

    # ------------------------------------------------------------------ basics
    @property
    def K(self):
        """3x3 intrinsic matrix [px]."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self):
        """Distortion coefficients as a float ndarray (OpenCV order)."""
        return np.asarray(self.dist, dtype=float)

    @property
    def image_size(self):
        """(width, height) [px], the order OpenCV uses."""
        return (self.width, self.height)

    # ------------------------------------------------------------ distortion
    def distort_normalized(self, xy):
        """Map ideal normalised coordinates (x/z, y/z) to distorted ones.

        Parameters
        ----------
        xy : (N, 2) array_like

        Returns
        -------
        (N, 2) ndarray
        """
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        if self.model == "pinhole":
            k1, k2, p1, p2, k3 = self.dist
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            return np.column_stack([xd, yd])
        r = np.hypot(x, y)
        theta = np.arctan(r)
        thd = self._fisheye_theta_d(theta)
        # r -> 0: theta_d / r -> 1 (theta ~ r); avoid 0/0.
        scale = np.where(r > 1e-12, thd / np.where(r > 1e-12, r, 1.0), 1.0)
        return np.column_stack([x * scale, y * scale])

    def _fisheye_theta_d(self, theta):
        k1, k2, k3, k4 = self.dist
        t2 = theta * theta
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def undistort_normalized(self, xyd, iterations=30, tol=1e-14):
        """Invert :meth:`distort_normalized` (Newton's method, vectorised).

        OpenCV's ``undistortPoints`` uses 5 fixed-point steps by default, which
        leaves visible error for strong endoscope distortion; Newton with the
        analytic Jacobian converges to rounding error in a few steps.

        Parameters
        ----------
        xyd : (N, 2) array_like
            Distorted normalised coordinates ((u - cx)/fx, (v - cy)/fy).

        Returns
        -------
        (N, 2) ndarray
            Ideal normalised coordinates; NaN where Newton did not converge
            (outside the invertible part of the distortion).
        """
        xyd = np.asarray(xyd, dtype=float).reshape(-1, 2)
        if self.model == "fisheye":
            return self._undistort_fisheye(xyd, iterations, tol)
        k1, k2, p1, p2, k3 = self.dist
        xy = xyd.copy()
        for _ in range(iterations):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            fx_ = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xyd[:, 0]
            fy_ = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - xyd[:, 1]
            j11 = radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
            j12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
            j21 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
            j22 = radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-300, 1e-300, det)
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j21 * fx_ + j11 * fy_) / det
            xy[:, 0] -= dx
            xy[:, 1] -= dy
            if np.all(np.abs(dx) + np.abs(dy) < tol):
                break
        resid = np.abs(self.distort_normalized(xy) - xyd).max(axis=1)
        xy[~(resid < 1e-9)] = np.nan
        return xy

    def _undistort_fisheye(self, xyd, iterations, tol):
        k1, k2, k3, k4 = self.dist
        rd = np.hypot(xyd[:, 0], xyd[:, 1])
        theta = np.clip(rd, 0.0, np.pi / 2)  # theta_d ~ theta for small distortion
        for _ in range(iterations):
            t2 = theta * theta
            f = self._fisheye_theta_d(theta) - rd
            df = 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            step = f / np.where(np.abs(df) < 1e-300, 1e-300, df)
            theta = theta - step
            if np.all(np.abs(step) < tol):
                break
        ok = (np.abs(self._fisheye_theta_d(theta) - rd) < 1e-9) & (theta >= 0) & (theta < np.pi / 2)
        r = np.tan(np.where(ok, theta, 0.0))
        scale = np.where(rd > 1e-12, r / np.where(rd > 1e-12, rd, 1.0), 1.0)
        out = xyd * scale[:, None]
        out[~ok] = np.nan
        return out

    # ------------------------------------------------------------ projection
    def project(self, points_cam_mm, return_mask=False):
        """Project camera-frame points to distorted pixel coordinates.

        Parameters
        ----------
        points_cam_mm : (N, 3) array_like
            Points in the camera frame [mm].
        return_mask : bool
            Also return the boolean mask of points in front of the camera.

        Returns
        -------
        uv : (N, 2) ndarray
            Pixel coordinates [px]; NaN rows for points with z <= 0.
        in_front : (N,) bool ndarray
            Only if ``return_mask``.
        """
        p = np.asarray(points_cam_mm, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        in_front = z > 0
        zs = np.where(in_front, z, 1.0)
        xy = p[:, :2] / zs[:, None]
        xyd = self.distort_normalized(xy)
        uv = np.column_stack([self.fx * xyd[:, 0] + self.cx, self.fy * xyd[:, 1] + self.cy])
        uv[~in_front] = np.nan
        return (uv, in_front) if return_mask else uv

    def pixel_rays(self, uv):
        """Unit ray directions (camera frame) through pixel positions, distortion removed.

        Parameters
        ----------
        uv : (N, 2) array_like
            Pixel coordinates [px].

        Returns
        -------
        (N, 3) ndarray
            Unit vectors with z > 0; NaN rows where the distortion cannot be inverted.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        xyd = np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
        xy = self.undistort_normalized(xyd)
        d = np.column_stack([xy, np.ones(len(xy))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def pixel_grid_rays(self, binning=1):
        """Rays of every (binned) pixel, cached per binning.

        Block ``(j, i)`` covers pixels ``j*b .. j*b+b-1`` (rows) and
        ``i*b .. i*b+b-1`` (columns); its ray goes through the block centre
        ``(i*b + (b-1)/2, j*b + (b-1)/2)``.

        Parameters
        ----------
        binning : int
            Block size b >= 1.

        Returns
        -------
        (height // b, width // b, 3) ndarray
            Unit ray directions (read-only: the array is shared by the cache).
        """
        b = int(binning)
        if b < 1 or b != binning:
            raise FluoInputError("binning must be a positive integer", field="binning",
                                 value=binning)
        if b not in self._ray_cache:
            h, w = self.height // b, self.width // b
            if h == 0 or w == 0:
                raise FluoInputError("binning larger than the image", field="binning", value=b)
            u = np.arange(w) * b + 0.5 * (b - 1)
            v = np.arange(h) * b + 0.5 * (b - 1)
            uu, vv = np.meshgrid(u, v)
            rays = self.pixel_rays(np.column_stack([uu.ravel(), vv.ravel()])).reshape(h, w, 3)
            rays.setflags(write=False)
            self._ray_cache[b] = rays
        return self._ray_cache[b]

    def binned(self, binning):
        """The camera seen through b x b pixel binning.

        Binned pixel i has its centre at original pixel ``i*b + (b-1)/2``, so
        ``cx' = (cx - (b-1)/2) / b`` and ``fx' = fx / b``; distortion
        coefficients (defined on normalised coordinates) do not change.
        """
        b = int(binning)
        if b < 1 or b != binning:
            raise FluoInputError("binning must be a positive integer", field="binning",
                                 value=binning)
        off = 0.5 * (b - 1)
        return CameraModel(self.fx / b, self.fy / b, (self.cx - off) / b, (self.cy - off) / b,
                           self.dist, self.width // b, self.height // b, self.model)

    # ---------------------------------------------------------- persistence
    def to_dict(self):
        """Plain JSON-able dict (keys fx, fy, cx, cy, dist, width, height, model)."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "dist": list(self.dist), "width": self.width, "height": self.height,
                "model": self.model}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`to_dict`; raises FluoInputError on missing keys."""
        if not isinstance(d, dict):
            raise FluoInputError("camera intrinsics must be a JSON object", value=type(d).__name__)
        missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in d]
        if missing:
            raise FluoInputError("camera intrinsics lack keys", field=",".join(missing))
        model = d.get("model", "pinhole")
        default = (0.0,) * (4 if model == "fisheye" else 5)
        return cls(d["fx"], d["fy"], d["cx"], d["cy"], tuple(d.get("dist", default)),
                   d["width"], d["height"], model)

    @classmethod
    def from_K(cls, K, dist, width, height, model="pinhole"):
        """Build from a 3x3 matrix K (skew must be 0) and OpenCV distortion."""
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise FluoInputError("K must be 3x3", field="K", value=K.shape)
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]):
            raise FluoInputError("skewed camera matrices are not supported", field="K[0,1]",
                                 value=float(K[0, 1]))
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                   tuple(np.asarray(dist, dtype=float).ravel()), width, height, model)
