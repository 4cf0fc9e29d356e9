"""Calibration of a broad-beam light (cone model of ``illumination_model``) from
images of a flat phantom of known reflectance, as in docs/physics.md section 6.2.

Per image: 4x4 median filter, active pixels S > S_min + tau (S_max - S_min),
boundary = active minus its erosion (pixels on the image border are not the
cone's edge and are dropped: a cone that leaves the image still calibrates),
pixel rays meet the phantom plane, points go to the light's frame.

- Optimisation 1 (geometry): minimise sum_b [(p_b - p_c).n_c - |p_b - p_c| cos Phi]^2
  over cone origin p_c, axis n_c and half-angle Phi (all images together: the
  plane at several distances fixes the apex).
- Optimisation 2 (radiometry): minimise sum_a [S_a - Dsys I(theta, beta, d) Rd]^2
  over alpha, gamma, Dsys with the geometry of optimisation 1.
- Optionally the non-axisymmetric term (amplitude, phase) is added and kept
  only when it lowers the Bayesian information criterion by more than 10, so
  the simple model is used unless the data need the other.

The light is taken to be coupled to the camera (light frame = camera frame);
for a separately tracked light, pass ``light_from_camera`` per image.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage, optimize

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report

from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoCalibLib.radiometry.synthetic import ray_plane_points

__all__ = ["segment_active", "calibrate_illumination"]


def segment_active(image_adu, tau=0.05, median_px=4):
    """(filtered image, active mask, boundary mask) of one image."""
    img = np.asarray(image_adu, float)
    f = ndimage.median_filter(img, size=median_px)
    lo, hi = float(np.percentile(f, 1)), float(f.max())
    if not hi > lo:
        raise FluoInputError("image has no contrast (flat or black)", field="image")
    active = f > lo + tau * (hi - lo)
    # keep the largest connected spot (stray light elsewhere is not the cone)
    lab, n = ndimage.label(active)
    if n == 0:
        raise FluoInputError("no illuminated region", field="image")
    sizes = ndimage.sum(active, lab, index=np.arange(1, n + 1))
    active = lab == (1 + int(np.argmax(sizes)))
    boundary = active & ~ndimage.binary_erosion(active, iterations=1)
    edge = np.zeros_like(active)
    edge[:2, :] = edge[-2:, :] = True
    edge[:, :2] = edge[:, -2:] = True
    boundary &= ~edge
    return f, active, boundary


def _axis_from_angles(th, ph):
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _angles_from_axis(n):
    n = np.asarray(n, float) / np.linalg.norm(n)
    return float(np.arccos(np.clip(n[2], -1, 1))), float(np.arctan2(n[1], n[0]))


#: an optimisation reports its evaluation count at most this often [s]
REPORT_EVERY_S = 0.5


def _watched(fun, progress, fraction, message, cancel):
    """``fun`` as ``least_squares`` calls it, checking ``cancel`` at every call and
    saying ``message`` with the evaluations so far at most every
    ``REPORT_EVERY_S``: one optimisation runs for seconds (1-2 s each on the
    synthetic set), and a desktop panel must hear from it, and be able to stop
    it, meanwhile."""
    calls = [0, time.monotonic()]

    def watched(x):
        check_cancel(cancel)
        calls[0] += 1
        now = time.monotonic()
        if now - calls[1] >= REPORT_EVERY_S:
            calls[1] = now
            report(progress, fraction, f"{message} ({calls[0]} evaluations)")
        return fun(x)

    return watched


def _fit_geometry(points):
    """Optimisation 1 on boundary points (light frame)."""
    P = np.asarray(points, float)
    c0 = np.zeros(3)
    dirs = P - c0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    n0 = dirs.mean(axis=0)
    n0 /= np.linalg.norm(n0)
    phi0 = float(np.mean(np.arccos(np.clip(dirs @ n0, -1, 1))))
    th0, ph0 = _angles_from_axis(n0)

    def resid(x):
        c = x[:3]
        n = _axis_from_angles(x[3], x[4])
        r = P - c
        return r @ n - np.linalg.norm(r, axis=1) * np.cos(x[5])

    sol = optimize.least_squares(resid, np.r_[c0, th0, ph0, phi0], x_scale="jac", method="lm")
    c = sol.x[:3]
    n = _axis_from_angles(sol.x[3], sol.x[4])
    return c, n, float(np.rad2deg(sol.x[5])), sol


def _check_plane_poses(phantom_to_camera, light_from_camera=None, min_span_mm=5.0,
                       min_tilt_deg=5.0):
    """Raise unless the phantom planes differ in distance or tilt: one plane
    (or several copies of it) cannot separate the cone apex from its angle."""
    h, nrm = [], []
    for k, T in enumerate(phantom_to_camera):
        T = np.asarray(T, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise FluoInputError("must be a finite 4x4 matrix", field=f"phantom_to_camera[{k}]")
        M = np.eye(4) if light_from_camera is None else np.asarray(light_from_camera[k], float)
        n = M[:3, :3] @ T[:3, 2]
        p = M[:3, :3] @ T[:3, 3] + M[:3, 3]
        h.append(abs(float(n @ p)))
        nrm.append(n * np.sign(n @ p or 1.0))
    nrm = np.asarray(nrm)
    tilt = float(np.degrees(np.arccos(np.clip(np.min(nrm @ nrm.T), -1.0, 1.0))))
    if max(h) - min(h) < min_span_mm and tilt < min_tilt_deg:
        raise FluoInputError(f"phantom poses too alike: distances span {max(h) - min(h):.1f} mm "
                             f"(need >= {min_span_mm:g}) and tilts {tilt:.1f} deg (need >= "
                             f"{min_tilt_deg:g}); the cone apex is not determined",
                             field="phantom_to_camera", value=[round(x, 1) for x in h])


def _check_inputs(images, phantom_to_camera, rd, light_from_camera):
    """Raise unless there is one pose per image, at least three images, a
    positive reflectance and poses that fix the cone apex."""
    if len(images) != len(phantom_to_camera):
        raise FluoInputError("one phantom pose per image", field="phantom_to_camera",
                             value=(len(images), len(phantom_to_camera)))
    if len(images) < 3:
        raise FluoInputError("need >= 3 images at different distances to fix the cone apex",
                             field="images", value=len(images))
    if not (np.isfinite(rd) and rd > 0):
        raise FluoInputError("phantom reflectance must be > 0", field="rd", value=rd)
    _check_plane_poses(phantom_to_camera, light_from_camera)


def _view_pixels(k, img, T, camera, offset_adu, tau, light_from_camera, saturation_adu):
    """Image ``k``'s pixels on the phantom plane, in the light frame [mm].

    Returns (boundary points, (counts [ADU], points, normals) of the unsaturated
    active interior, (image, points, normal, unsaturated active mask) for its
    ratio image, number of saturated active pixels).
    """
    raw = np.asarray(img, float)
    if raw.shape != (camera.height, camera.width):
        raise FluoInputError("image size differs from the camera's", field=f"images[{k}]",
                             value=raw.shape)
    if not np.all(np.isfinite(raw)):
        raise FluoInputError("image has NaN or infinite values", field=f"images[{k}]")
    # a clipped pixel under-reports the light and would pull alpha down
    unsat = raw < saturation_adu
    img = raw - offset_adu
    f, active, boundary = segment_active(img, tau)
    pts, valid = ray_plane_points(camera, T)
    M = np.eye(4) if light_from_camera is None else np.asarray(light_from_camera[k], float)
    pts_l = pts @ M[:3, :3].T + M[:3, 3]
    nrm = -np.asarray(T, float)[:3, 2]
    nrm = nrm if nrm[2] < 0 else -nrm               # plane normal towards the camera
    nrm_l = M[:3, :3] @ nrm
    b = boundary & valid
    a = active & valid & ~boundary & unsat
    n_saturated = int((active & ~unsat).sum())
    if b.sum() < 10:
        raise FluoInputError("too few cone-boundary pixels (the cone fills the image?)",
                             field=f"images[{k}]", value=int(b.sum()))
    return (pts_l[b], (img[a], pts_l[a], np.broadcast_to(nrm_l, (int(a.sum()), 3))),
            (img, pts_l, nrm_l, active & valid & unsat), n_saturated)


def _read_views(images, camera, phantom_to_camera, offset_adu, tau, light_from_camera,
                saturation_adu, progress, cancel):
    """``_view_pixels`` of every image, reporting each: (boundary points of all
    images [mm], per-image active pixels, per-image ratio inputs, saturated
    active pixel count)."""
    bnd_pts, act, per_image = [], [], []
    n_saturated = 0
    for k, (img, T) in enumerate(zip(images, phantom_to_camera)):
        check_cancel(cancel)
        report(progress, 0.3 * k / len(images), f"image {k + 1} of {len(images)}: active region")
        b, a, view, n_sat = _view_pixels(k, img, T, camera, offset_adu, tau, light_from_camera,
                                         saturation_adu)
        n_saturated += n_sat
        bnd_pts.append(b)
        act.append(a)
        per_image.append(view)
    return np.concatenate(bnd_pts), act, per_image, n_saturated


def _determined_geometry(P, progress):
    """Optimisation 1 on the boundary points ``P`` [mm]; raise when the views
    leave the apex undetermined.  Returns ``_fit_geometry``'s (origin, axis,
    half-angle [deg], solution)."""
    report(progress, 0.3, "optimisation 1: cone geometry from the boundary")
    c, n, half, sol1 = _fit_geometry(P)
    # identical-looking views let the apex run off to a near-cylinder; the
    # Jacobian is then singular (usable sets lie orders of magnitude below the
    # limit; docs/calibration-radiometry.md)
    cond = float(np.linalg.cond(sol1.jac))
    if not (np.isfinite(cond) and cond < 1e7 and 0.5 < half < 89.5):
        raise FluoInputError("cone apex not determined by these views (image the phantom at "
                             "several distances or tilts)", field="phantom_to_camera",
                             value={"half_angle_deg": half, "condition": cond})
    return c, n, half, sol1


def _lit_pixels(act, base, rd, half, max_pixels, edge_margin_deg):
    """The pixels optimisation 2 fits: counts S [ADU], points X [mm] and normals
    N well inside the cone of optimisation 1 (``base``), at most ``max_pixels``
    of them, and the system gain [ADU] they suggest with alpha = 1, gamma = 0."""
    S = np.concatenate([x[0] for x in act])
    X = np.concatenate([x[1] for x in act])
    N = np.concatenate([x[2] for x in act])
    if len(S) > max_pixels:  # an even subsample keeps the fit fast and unbiased
        idx = np.linspace(0, len(S) - 1, max_pixels).astype(int)
        S, X, N = S[idx], X[idx], N[idx]
    cone0 = IlluminationCone(**base, alpha=1.0, gamma_per_mm=0.0, system_gain_adu=1.0)
    f0 = cone0.factors(X, N)
    # The model drops to zero at the cone edge (to cos^alpha(Phi), ~25 % of the
    # peak for the endoscope): a pixel just outside the refined cone would add
    # a residual of ~sqrt(S) and make the cost jump as the axis moves, so
    # optimisation 2 keeps clear of the edge.
    lit = f0.lit & (f0.theta_rad < np.deg2rad(max(half - edge_margin_deg, 0.5 * half)))
    if lit.sum() < 100:
        raise FluoInputError("the fitted cone leaves almost no active pixel lit", field="images")
    S, X, N = S[lit], X[lit], N[lit]
    # Dsys starts from the ratio with alpha = 1, gamma = 0
    g0 = float(np.median(S / (rd * f0.intensity[lit])))
    return S, X, N, g0


class _Radiometry:
    """Optimisation 2's problem: the counts ``S`` [ADU] at points ``X`` [mm] with
    normals ``N`` of a phantom of reflectance ``rd``, against a cone with the
    origin and half-angle of ``base`` and the parameter vector
    x = (alpha, gamma [1/mm], Dsys [ADU], axis theta, axis phi [rad]
    [, crescent amplitude, crescent phase [rad]])."""

    def __init__(self, base, rd, S, X, N):
        self.base, self.rd, self.S, self.X, self.N = base, rd, S, X, N

    # The axis is refined together with the radiometry: with alpha ~ 7 a tenth
    # of a degree of tilt changes the intensity by ~1 % across the spot, more
    # than the boundary alone resolves (and an unrefined tilt would be
    # mistaken for a crescent by the asymmetric model).
    def cone(self, x, asym=False):
        """The IlluminationCone of x (the crescent terms only when ``asym``)."""
        kw = dict(alpha=max(x[0], 0.0), gamma_per_mm=max(x[1], 0.0), system_gain_adu=max(x[2], 0.0))
        if asym:
            kw.update(asym_amplitude=float(np.clip(x[5], 0.0, 0.95)), asym_phase_rad=float(x[6]))
        geo = dict(self.base, axis=tuple(_axis_from_angles(x[3], x[4])))
        return IlluminationCone(**geo, **kw)

    def residuals(self, x, asym=False):
        """(model - S) / sqrt(S): shot-noise weighted residuals."""
        m = self.cone(x, asym).forward_counts(self.rd, self.X, self.N)
        return (m - self.S) / np.sqrt(np.maximum(self.S, 1.0))

    def crescent_start(self, x):
        """x with the crescent amplitude and phase its ratio suggests."""
        S, X, N = self.S, self.X, self.N
        sw = 1.0 / np.sqrt(np.maximum(S, 1.0))          # same weights as the fit
        # first azimuthal harmonic of the ratio to the symmetric cone x:
        # S / model - 1 ~ (theta / Phi)^2 (A cos phi + B sin phi); its phase
        # is measured in x's azimuth basis, which cone() reproduces
        c2 = self.cone(x)
        fac = c2.factors(X, N)
        e1, e2 = c2.azimuth_basis()
        u = (X - np.asarray(c2.origin_mm)) / np.maximum(fac.distance_mm, 1e-9)[:, None]
        az = np.arctan2(u @ e2, u @ e1)
        w = (fac.theta_rad / np.deg2rad(c2.half_angle_deg)) ** 2
        m2 = c2.forward_counts(self.rd, X, N)
        design = np.stack([m2 * w * np.cos(az), m2 * w * np.sin(az)], axis=1) * sw[:, None]
        (A, B), *_ = np.linalg.lstsq(design, (S - m2) * sw, rcond=None)
        return np.r_[x, float(np.clip(np.hypot(A, B), 0.01, 0.9)), float(np.arctan2(B, A))]


def _bic(sol, n_params):
    """Bayesian information criterion of a least-squares solution."""
    rss = float(np.sum(sol.fun ** 2))
    nobs = len(sol.fun)
    return nobs * np.log(rss / nobs) + n_params * np.log(nobs)


def _fit_axisymmetric(problem, c, th0, ph0, g0, progress, cancel):
    """Optimisation 2 from alpha = 1, the axis of optimisation 1 (``th0``,
    ``ph0`` [rad]) and Dsys from ``g0`` [ADU] scaled to the distance from the
    apex ``c`` [mm].  Returns (solution, lower bounds, upper bounds)."""
    X = problem.X
    x0 = np.array([1.0, 0.01, g0 * (1 + 0.01 * np.median(np.linalg.norm(X - c, axis=1))) ** 2,
                   th0, ph0])
    lo = [0, 0, 0, th0 - 0.1, ph0 - np.pi]
    hi = [50, 5, np.inf, th0 + 0.1, ph0 + np.pi]
    check_cancel(cancel)
    step = "optimisation 2: alpha, gamma, system gain"
    report(progress, 0.4, step)
    sol2 = optimize.least_squares(_watched(problem.residuals, progress, 0.4, step, cancel), x0,
                                  x_scale="jac", bounds=(lo, hi))
    return sol2, lo, hi


def _fit_crescent(problem, sol2, lo, hi, th0, ph0, progress, cancel):
    """The crescent model's best solution from two starts."""
    # Two starts: the symmetric fit tilts its axis to mimic a crescent (a
    # local minimum the crescent fit can stay in), while the boundary axis
    # of optimisation 1 is not biased by the intensity; keep the better.
    sol3 = None
    for i, x in enumerate((sol2.x, np.r_[sol2.x[:3], th0, ph0])):
        check_cancel(cancel)
        step = f"crescent model, start {i + 1} of 2"
        report(progress, 0.6 + 0.15 * i, step)
        s3 = optimize.least_squares(
            _watched(lambda x: problem.residuals(x, True), progress, 0.6 + 0.15 * i, step, cancel),
            problem.crescent_start(x), x_scale="jac",
            bounds=(lo + [0, -2 * np.pi], hi + [0.95, 2 * np.pi]))
        if sol3 is None or s3.cost < sol3.cost:
            sol3 = s3
    return sol3


def _ratio_images(cone, rd, per_image):
    """Measured / model per image (NaN outside the unsaturated active region)
    and all their finite ratios pooled."""
    ratios, all_r = [], []
    for img, pts_l, nrm_l, act_mask in per_image:
        model = cone.forward_counts(rd, pts_l, np.broadcast_to(nrm_l, pts_l.shape))
        ok = act_mask & (model > 0)
        r = np.full(img.shape, np.nan)
        r[ok] = img[ok] / model[ok]
        ratios.append(r)
        all_r.append(r[ok])
    return ratios, np.concatenate(all_r)


def calibrate_illumination(images, camera, phantom_to_camera, rd, offset_adu=0.0, tau=0.05,
                           light_from_camera=None, try_asymmetric=True, max_pixels=60000,
                           frame="Camera", saturation_adu=16383.0, edge_margin_deg=1.0,
                           progress=None, cancel=None):
    """Fit the cone model to images of a flat phantom (reflectance ``rd``).

    Parameters
    ----------
    images : list of (H, W) counts [ADU]
    camera : CameraModel of the images
    phantom_to_camera : list of 4x4 [mm], the phantom plane z = 0 in the camera frame
    rd : phantom reflectance (transport) T
    offset_adu : dark offset subtracted from the images
    light_from_camera : optional list of 4x4 (camera -> light frame) per image
    saturation_adu : raw count at or above which a pixel is saturated (A/D
        ceiling, 14 bit by default); such pixels still shape the active
        region but are left out of optimisation 2 and the ratio statistics
    edge_margin_deg : optimisation 2 uses pixels at least this far inside the
        cone edge of optimisation 1
    progress, cancel : ``progress(fraction, message)`` and a CancelToken
        (``fluoguide.progress``), checked between the steps and, in the
        optimisations, at every residual evaluation (a report every 0.5 s)

    Returns
    -------
    dict
        ``cone`` (IlluminationCone), the JSON keys of ``fluo calib illumination``
        and ``ratio_images`` (measured / model, NaN outside the active region).
    """
    _check_inputs(images, phantom_to_camera, rd, light_from_camera)
    P, act, per_image, n_saturated = _read_views(
        images, camera, phantom_to_camera, offset_adu, tau, light_from_camera, saturation_adu,
        progress, cancel)
    c, n, half, sol1 = _determined_geometry(P, progress)
    base = dict(origin_mm=tuple(c), axis=tuple(n), half_angle_deg=half, frame=frame)
    S, X, N, g0 = _lit_pixels(act, base, rd, half, max_pixels, edge_margin_deg)
    problem = _Radiometry(base, rd, S, X, N)
    th0, ph0 = _angles_from_axis(n)
    sol2, lo, hi = _fit_axisymmetric(problem, c, th0, ph0, g0, progress, cancel)
    xbest, asym_best = sol2.x, False
    nobs = len(S)
    bic_sym = _bic(sol2, 5)
    chosen = "axisymmetric"
    bic_asym = None
    if try_asymmetric:
        sol3 = _fit_crescent(problem, sol2, lo, hi, th0, ph0, progress, cancel)
        bic_asym = _bic(sol3, 7)
        if bic_asym < bic_sym - 10.0:
            chosen = "crescent"
            xbest, asym_best = sol3.x, True
    report(progress, 0.95, "ratio images")
    cone = problem.cone(xbest, asym_best)
    n = cone.unit_axis
    ratios, all_r = _ratio_images(cone, rd, per_image)
    return {
        "cone": cone, "origin_mm": list(map(float, c)), "axis": list(map(float, n)),
        "half_angle_deg": half, "alpha": float(cone.alpha),
        "gamma_per_mm": float(cone.gamma_per_mm), "system_gain_adu": float(cone.system_gain_adu),
        "model": chosen, "bic_axisymmetric": float(bic_sym),
        "bic_crescent": None if bic_asym is None else float(bic_asym),
        "ratio_mean": float(np.mean(all_r)), "ratio_sd": float(np.std(all_r)),
        "boundary_points": int(len(P)), "active_pixels": int(nobs),
        "saturated_pixels": n_saturated,
        "geometry_rms_mm": float(np.sqrt(np.mean(sol1.fun ** 2))),
        "ratio_images": ratios,
    }
