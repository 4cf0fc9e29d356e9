"""Broad-beam illumination model: a right circular cone with angular, obliquity
and distance roll-off (docs/physics.md section 6.1)::

    I(theta, beta, d) = A(theta, phi) * cos(beta) / (1 + gamma d)^2
    A(theta, phi)     = cos(theta)^alpha * (1 + a * (theta / Phi_L)^2 * cos(phi - phi0))
    S(u, v)           = Dsys * T(p_s) * I           (forward image, ADU)

with r = p_s - p_L, d = |r|, theta = angle(r, n_L) (lit only for theta <= Phi_L),
cos(beta) = n_s . (-r / d).  ``a = 0`` (the default) is the thesis's
axisymmetric model; ``a > 0`` adds the first azimuthal harmonic that turns the
spot into the crescent seen with endoscope light guides (phi is the azimuth
about the axis measured from ``azimuth_ref``; the term grows from 0 on the axis
to ``a`` at the cone edge, so the model stays continuous on the axis).  It
grows with the square of theta because a term linear in theta is, to first
order, the same as a tilt of the axis, and a fit could not tell them apart.

Origin and axis are in the frame named by ``frame`` (``Camera`` for a light
coupled to the camera, or a tracked light tool's frame); callers transform the
surface points and normals into that frame first.

This module only evaluates the model; fitting is in ``illumination_fit.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["IlluminationCone", "IlluminationFactors"]


@dataclass
class IlluminationFactors:
    """Per-point factors of the model (arrays of one shape; NaN-free).

    ``lit`` is False where the point is outside the cone, behind the surface
    (cos beta <= 0) or at the source; there every factor is 0.
    """

    theta_rad: np.ndarray
    cos_beta: np.ndarray
    distance_mm: np.ndarray
    angular: np.ndarray
    foreshortening: np.ndarray
    distance: np.ndarray
    lit: np.ndarray

    @property
    def intensity(self):
        """I = angular * foreshortening * distance factor (0 where not lit)."""
        return self.angular * self.foreshortening * self.distance


def _unit(v, name):
    v = np.asarray(v, float).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-12:
        raise FluoInputError("must be a non-zero finite 3-vector", field=name, value=v.tolist())
    return v / n


@dataclass(frozen=True)
class IlluminationCone:
    """Parameters of the cone model (see module docstring); lengths in mm."""

    origin_mm: tuple = (0.0, 0.0, 0.0)
    axis: tuple = (0.0, 0.0, 1.0)
    half_angle_deg: float = 30.0
    alpha: float = 1.0
    gamma_per_mm: float = 0.0
    system_gain_adu: float = 1.0
    asym_amplitude: float = 0.0
    asym_phase_rad: float = 0.0
    azimuth_ref: tuple | None = None
    frame: str = "Camera"
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        o = np.asarray(self.origin_mm, float).reshape(-1)
        if o.size != 3 or not np.all(np.isfinite(o)):
            raise FluoInputError("must be a finite 3-vector", field="origin_mm", value=o.tolist())
        _unit(self.axis, "axis")
        if not (0.0 < self.half_angle_deg < 90.0):
            raise FluoInputError("must be in (0, 90) degrees", field="half_angle_deg",
                                 value=self.half_angle_deg)
        for name in ("alpha", "gamma_per_mm", "system_gain_adu"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise FluoInputError("must be a finite number >= 0", field=name, value=v)
        if not (0.0 <= self.asym_amplitude < 1.0):
            raise FluoInputError("must be in [0, 1)", field="asym_amplitude", value=self.asym_amplitude)

    # -- geometry helpers ----------------------------------------------------
    @property
    def unit_axis(self):
        return _unit(self.axis, "axis")

    def azimuth_basis(self):
        """Two unit vectors (e1, e2) perpendicular to the axis; phi = atan2(r.e2, r.e1)."""
        n = self.unit_axis
        if self.azimuth_ref is not None:
            ref = np.asarray(self.azimuth_ref, float).reshape(3)
        else:  # any fixed vector not parallel to the axis
            ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - np.dot(ref, n) * n
        e1 = _unit(e1, "azimuth_ref")
        return e1, np.cross(n, e1)

    @property
    def is_axisymmetric(self):
        return self.asym_amplitude == 0.0

    # -- evaluation ----------------------------------------------------------
    def factors(self, points_mm, normals=None):
        """Model factors at surface points ``(..., 3)`` with unit ``normals``.

        ``normals=None`` means every point faces the source (cos beta = 1),
        which is what the separate angular/distance maps show.
        """
        p = np.asarray(points_mm, float)
        r = p - np.asarray(self.origin_mm, float)
        d = np.linalg.norm(r, axis=-1)
        safe_d = np.where(d > 1e-12, d, 1.0)
        u = r / safe_d[..., None]
        n_axis = self.unit_axis
        cos_t = np.clip(u @ n_axis, -1.0, 1.0)
        theta = np.arccos(cos_t)
        phi_max = np.deg2rad(self.half_angle_deg)
        inside = (d > 1e-12) & (theta <= phi_max) & np.all(np.isfinite(p), axis=-1)
        if normals is None:
            cos_b = np.ones_like(d)
        else:
            nrm = np.asarray(normals, float)
            cos_b = -np.einsum("...i,...i->...", nrm, u)
            cos_b = np.where(np.isfinite(cos_b), cos_b, 0.0)
        lit = inside & (cos_b > 0)
        ang = np.where(lit, np.maximum(cos_t, 0.0) ** self.alpha, 0.0)
        if not self.is_axisymmetric:
            e1, e2 = self.azimuth_basis()
            phi = np.arctan2(u @ e2, u @ e1)
            crescent = 1.0 + self.asym_amplitude * (theta / phi_max) ** 2 * np.cos(phi - self.asym_phase_rad)
            ang = np.where(lit, ang * np.where(lit, crescent, 1.0), 0.0)
        fore = np.where(lit, np.clip(cos_b, 0.0, 1.0), 0.0)
        dist = np.where(lit, 1.0 / (1.0 + self.gamma_per_mm * d) ** 2, 0.0)
        return IlluminationFactors(theta_rad=np.where(np.isfinite(theta), theta, np.pi),
                                   cos_beta=cos_b, distance_mm=d, angular=ang,
                                   foreshortening=fore, distance=dist, lit=lit)

    def intensity(self, points_mm, normals=None):
        """I(theta, beta, d) (0 outside the cone or facing away)."""
        return self.factors(points_mm, normals).intensity

    def forward_counts(self, transport, points_mm, normals):
        """Forward image S = Dsys T I [ADU above offset] for transport ``T`` (e.g. Rd)."""
        return self.system_gain_adu * np.asarray(transport, float) * self.intensity(points_mm, normals)

    def to_dict(self):
        return {"origin_mm": np.asarray(self.origin_mm, float).tolist(),
                "axis": self.unit_axis.tolist(), "half_angle_deg": float(self.half_angle_deg),
                "alpha": float(self.alpha), "gamma_per_mm": float(self.gamma_per_mm),
                "system_gain_adu": float(self.system_gain_adu),
                "asym_amplitude": float(self.asym_amplitude),
                "asym_phase_rad": float(self.asym_phase_rad),
                "azimuth_ref": None if self.azimuth_ref is None else list(map(float, self.azimuth_ref)),
                "frame": self.frame}

    @classmethod
    def from_dict(cls, doc):
        known = {k: doc[k] for k in cls.__dataclass_fields__ if k in doc and k != "extra"}
        for k in ("origin_mm", "axis", "azimuth_ref"):
            if known.get(k) is not None:
                known[k] = tuple(known[k])
        return cls(**known)
