"""Synthetic radiometric data with known truth: camera stacks, images of a flat
phantom under a broad-beam cone, and laser spots.

Each generator returns the data and a truth dict; the ``write_*`` functions
put them on disk in the formats the ``fluo calib`` commands read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng

from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.camera_response import Frame, write_stack
from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

__all__ = ["synthetic_stack", "synthetic_lens_spectral_frames", "endoscope_camera",
           "endoscope_cone", "plane_poses", "synthetic_illumination", "synthetic_laser",
           "ray_plane_points", "write_illumination_set", "write_laser_set"]


# ----------------------------------------------------------------- camera stacks

def synthetic_stack(camera=None, shape=(260, 348), n_light=12, n_dark=6, pairs=2,
                    max_dark_exposure_s=20.0, nonlinearity=0.0, seed=0):
    """Dark and light frame pairs of a uniform scene with known camera parameters.

    Light exposures are spaced so the last ones saturate (to test that
    saturated levels are flagged and skipped).  ``nonlinearity`` bends the
    response: S' = S (1 - nonlinearity * S / S_max).
    """
    cam = camera or RadiometricCamera()
    rng = seeded_rng(seed)
    # radiance that fills the full well in 1 s
    L = cam.full_well_e / cam.with_(exposure_s=1.0).electrons_per_radiance()
    field = np.full(shape, L)
    frames = []
    for t in np.linspace(0.0, max_dark_exposure_s, n_dark):
        for p in range(pairs):
            img = cam.with_(exposure_s=float(t)).sample_counts(np.zeros(shape), rng)
            frames.append(Frame(img, float(t), "dark", name=f"dark_{t:07.3f}s_{p}.png"))
    for t in np.geomspace(0.01, 1.3, n_light):
        for p in range(pairs):
            img = cam.with_(exposure_s=float(t)).sample_counts(field, rng)
            if nonlinearity:
                s = img - cam.offset_adu
                img = np.clip(np.round(cam.offset_adu + s * (1 - nonlinearity * s / cam.adc_max_adu)),
                              0, cam.adc_max_adu)
            frames.append(Frame(img, float(t), "light", name=f"light_{t:07.4f}s_{p}.png"))
    truth = {"camera": cam.to_dict(), "radiance_w_per_mm2_sr": float(L),
             "nonlinearity": nonlinearity}
    return frames, truth


# Relative spectral QE of a front-illuminated CCD (illustrative shape; the
# reference quotes 15 % at 760 nm only).
DEFAULT_QE_BY_WAVELENGTH = {600.0: 0.40, 700.0: 0.25, 760.0: 0.15, 800.0: 0.11, 850.0: 0.07}


def synthetic_lens_spectral_frames(camera=None, f_numbers=(1.4, 2.0, 2.8, 4.0, 5.6),
                                   qe_by_wavelength=None, exposure_s=0.3, fill=0.5,
                                   radiance_w_per_mm2_sr=None, shape=(260, 348), pairs=2,
                                   seed=0):
    """Extra light frames for the lens f-number exponent and the spectral
    responsivity, to append to a ``synthetic_stack`` of the same camera.

    - one radiance, one exposure, frames at each of ``f_numbers``
      (S ~ f#^-lens_exponent); pass the stack's radiance (same light source,
      only the aperture turned) so the frame at the stack's f-number is one
      more point of its exposure series; by default the brightest frame
      fills ``fill`` of the full well;
    - one frame pair per wavelength with that wavelength's QE, each at a
      radiance that fills ``fill`` of the full well, frames labelled with
      ``wavelength_nm`` and ``radiance_w_per_mm2_sr``.

    Returns (frames, truth) with ``lens_exponent`` and
    ``spectral_e_per_radiance_s`` {wavelength_nm: e- / (W/mm^2/sr) / s}.
    """
    cam = (camera or RadiometricCamera()).with_(exposure_s=float(exposure_s))
    qe = dict(DEFAULT_QE_BY_WAVELENGTH if qe_by_wavelength is None else qe_by_wavelength)
    rng = seeded_rng(seed)
    frames = []
    f_min = min(f_numbers) if len(f_numbers) else cam.f_number
    L = radiance_w_per_mm2_sr
    if L is None:
        L = fill * cam.full_well_e / cam.with_(f_number=f_min).electrons_per_radiance()
    for fn in f_numbers:
        c = cam.with_(f_number=float(fn))
        for p in range(pairs):
            frames.append(Frame(c.sample_counts(np.full(shape, L), rng), cam.exposure_s, "light",
                                f_number=float(fn), name=f"lens_f{fn:04.1f}_{p}.png"))
    spectral = {}
    for wl, q in sorted(qe.items()):
        c = cam.with_(wavelength_nm=float(wl), quantum_efficiency=float(q))
        Lw = fill * cam.full_well_e / c.electrons_per_radiance()
        spectral[float(wl)] = float(c.electrons_per_radiance() / cam.exposure_s)
        for p in range(pairs):
            frames.append(Frame(c.sample_counts(np.full(shape, Lw), rng), cam.exposure_s, "light",
                                wavelength_nm=float(wl), radiance_w_per_mm2_sr=float(Lw),
                                name=f"spectral_{wl:05.1f}nm_{p}.png"))
    truth = {"lens_exponent": cam.lens_exponent, "lens_radiance_w_per_mm2_sr": float(L), "f_numbers": [float(f) for f in f_numbers],
             "spectral_e_per_radiance_s": spectral}
    return frames, truth


# ------------------------------------------------------- flat phantom, cone light

def endoscope_camera(binning=4):
    """The thesis's 10 mm endoscope camera (1392 x 1040, f 949 px, strong barrel
    distortion), binned for speed."""
    cam = CameraModel(949.1, 949.1, 780.4, 465.9, (-0.4709, 0.3153, 0.0, 0.0, -0.134), 1392, 1040)
    return cam.binned(binning) if binning > 1 else cam


def endoscope_cone(system_gain_adu=2.4e5):
    """A light guide beside the lens: origin 3 mm off the optical centre, axis
    tilted 4 deg, thesis parameters of the 10 mm scope (alpha 6.9, gamma 0.12,
    half-angle 35 deg); the gain puts the nearest view's peak near 60 % of a
    14-bit range for Rd 0.5."""
    axis = tf.rotation_matrix([0.0, 1.0, 0.2], np.deg2rad(4.0)) @ np.array([0.0, 0.0, 1.0])
    return IlluminationCone(origin_mm=(3.0, -1.5, 0.5), axis=tuple(axis), half_angle_deg=35.0,
                            alpha=6.9, gamma_per_mm=0.12, system_gain_adu=system_gain_adu,
                            frame="Camera")


def plane_poses(distances_mm=(25.0, 32.0, 40.0, 50.0, 60.0), tilts_deg=(0.0, 12.0, -10.0, 18.0, -15.0)):
    """PhantomToCamera poses: plane z = 0 of the phantom facing the camera at
    the given distances, tilted about varying axes."""
    poses = []
    for k, (d, a) in enumerate(zip(distances_mm, tilts_deg)):
        R = tf.rotation_matrix([np.cos(k), np.sin(k), 0.0], np.deg2rad(a)) @ np.diag([1.0, -1.0, -1.0])
        poses.append(tf.make_rigid(R, [1.5 * np.sin(k), -1.0 * np.cos(k), d]))
    return poses


def ray_plane_points(camera, phantom_to_camera, pixels=None):
    """Camera-frame points where pixel rays meet the phantom plane z = 0.

    Returns (points (H, W, 3) or (P, 3), valid mask): invalid where the ray is
    parallel to the plane or the plane is behind the camera.
    """
    T = np.asarray(phantom_to_camera, float)
    n = T[:3, 2]
    p0 = T[:3, 3]
    rays = camera.pixel_grid_rays() if pixels is None else camera.pixel_rays(pixels)
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (p0 @ n) / denom
    valid = np.isfinite(s) & (s > 0) & (np.abs(denom) > 1e-9)
    pts = rays * np.where(valid, s, 0.0)[..., None]
    return pts, valid


def synthetic_illumination(camera=None, cone=None, poses=None, rd=0.5, radiometric=None,
                           seed=0):
    """Images [ADU] of a flat phantom of reflectance ``rd`` under ``cone`` (light
    coupled to the camera), with camera noise; returns (images, truth)."""
    cam = camera or endoscope_camera()
    cone = cone or endoscope_cone()
    poses = poses or plane_poses()
    rcam = radiometric or RadiometricCamera(gain_adu_per_e=1.0)
    rng = seeded_rng(seed)
    images = []
    for T in poses:
        pts, valid = ray_plane_points(cam, T)
        normal = -np.asarray(T, float)[:3, 2]  # plane normal towards the camera
        normal = np.broadcast_to(normal if normal[2] < 0 else -normal, pts.shape)
        signal = cone.forward_counts(rd, pts, normal) * valid
        # signal in ADU above offset -> electrons -> noisy counts
        e = np.maximum(signal / rcam.gain_adu_per_e, 0)
        photo = rng.poisson(e).astype(float)
        dark = rng.poisson(rcam.dark_current_e_per_s * rcam.exposure_s, size=e.shape)
        el = np.minimum(photo + dark, rcam.full_well_e) + rcam.bias_e
        el += rng.normal(0.0, rcam.read_noise_e, size=e.shape)
        images.append(np.clip(np.round(el * rcam.gain_adu_per_e), 0, rcam.adc_max_adu))
    # counts at which a pixel is clipped: the full well or the A/D ceiling,
    # less 5 read-noise sigmas so noisy clipped pixels are caught too
    sat = min(rcam.adc_max_adu, rcam.gain_adu_per_e * (rcam.full_well_e + rcam.bias_e)
              - 5.0 * rcam.gain_adu_per_e * rcam.read_noise_e)
    truth = {"cone": cone.to_dict(), "camera": cam.to_dict(), "rd": rd,
             "offset_adu": rcam.offset_adu, "saturation_adu": float(sat),
             "phantom_to_camera": [np.asarray(T).tolist() for T in poses]}
    return images, truth


def _write_pngs(folder, images, prefix):
    """16-bit PNGs ``<prefix>_NN.png``; returns their names."""
    import cv2

    names = []
    for i, img in enumerate(images):
        name = f"{prefix}_{i:02d}.png"
        if not cv2.imwrite(str(folder / name), np.asarray(img).astype(np.uint16)):
            raise FluoInputError("cannot write image", file=folder / name)
        names.append(name)
    return names


def write_illumination_set(folder, images, truth):
    """``illumination.json`` (camera, offset, Rd, per-image PhantomToCamera) + PNGs,
    the folder as a whole (a kill leaves the old set or the new one)."""
    from fluoguide import atomic

    folder = Path(folder)
    with atomic.staged_folder(folder, last=("illumination.json",)) as stage:
        names = _write_pngs(stage, images, "illum")
        doc = {"camera": truth["camera"], "offset_adu": truth["offset_adu"], "rd": truth["rd"],
               "saturation_adu": truth["saturation_adu"], "images": names,
               "phantom_to_camera": truth["phantom_to_camera"], "truth": {"cone": truth["cone"]}}
        (stage / "illumination.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    return folder


# ------------------------------------------------------------------- laser spots

def synthetic_laser(camera=None, n_images=10, seed=0, pose_noise_mm=0.1, pose_noise_deg=0.05,
                    spot_sigma_px=2.0, peak_adu=9000.0):
    """Laser spot images on a tracked flat phantom at several distances.

    Frames (all 4x4, mm): ``laser_to_tracker`` (the tracked laser tool, with
    tracking noise), ``camera_to_tracker`` and ``phantom_to_tracker``.  The
    true beam is a line in laser-tool coordinates.  Returns (images, truth).
    """
    cam = camera or CameraModel(4279.0 / 4, 4279.0 / 4, 739.3 / 4, 510.2 / 4, (0, 0, 0, 0, 0), 348, 260)
    rng = seeded_rng(seed)
    origin_tool = np.array([2.0, -1.0, 15.0])                 # collimator exit in tool coords
    direction_tool = tf.rotation_matrix([1.0, 0.3, 0.0], np.deg2rad(2.0)) @ np.array([0.0, 0.0, 1.0])
    # the laser tool hangs above the phantom, beam pointing down (-z of tracker)
    laser_to_tracker = tf.make_rigid(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 400.0])
    camera_to_tracker = tf.make_rigid(tf.rotation_matrix([1, 0, 0], np.pi) @
                                      tf.rotation_matrix([0, 1, 0], np.deg2rad(-8.0)),
                                      [45.0, 0.0, 500.0])
    images, truth_pts, lt_meas, ph_meas = [], [], [], []
    heights = np.linspace(20.0, 140.0, n_images)
    ys, xs = np.mgrid[0:cam.height, 0:cam.width]
    cam_inv = np.linalg.inv(camera_to_tracker)
    for k, h in enumerate(heights):
        R = tf.rotation_matrix([np.cos(k), np.sin(k), 0], np.deg2rad(6.0 * np.sin(1.7 * k)))
        phantom_to_tracker = tf.make_rigid(R, [0.0, 0.0, h])
        # true hit: beam line (tracker frame) with the phantom plane
        o = (laser_to_tracker @ np.append(origin_tool, 1))[:3]
        d = laser_to_tracker[:3, :3] @ direction_tool
        n, p0 = phantom_to_tracker[:3, 2], phantom_to_tracker[:3, 3]
        s = ((p0 - o) @ n) / (d @ n)
        hit = o + s * d
        uv = cam.project((cam_inv @ np.append(hit, 1))[None, :3])[0]
        img = 100.0 + peak_adu * np.exp(-((xs - uv[0]) ** 2 + (ys - uv[1]) ** 2) / (2 * spot_sigma_px ** 2))
        img = rng.poisson(np.maximum(img, 0)).astype(float) + rng.normal(0, 5.0, img.shape)
        images.append(np.clip(np.round(img), 0, 16383))
        truth_pts.append(hit)
        noise = tf.make_rigid(tf.rotation_matrix(rng.normal(size=3), np.deg2rad(rng.normal(0, pose_noise_deg))),
                              rng.normal(0, pose_noise_mm, 3))
        lt_meas.append(noise @ laser_to_tracker)
        ph_meas.append(phantom_to_tracker)
    pointer_origin_tool = origin_tool + np.array([0.3, -0.2, 0.0])  # touched near the exit
    truth = {"origin_mm": origin_tool.tolist(), "direction": direction_tool.tolist(),
             "camera": cam.to_dict(), "camera_to_tracker": camera_to_tracker.tolist(),
             "laser_to_tracker": [T.tolist() for T in lt_meas],
             "phantom_to_tracker": [T.tolist() for T in ph_meas],
             "pointer_origin_tool_mm": pointer_origin_tool.tolist(),
             "hits_tracker_mm": [p.tolist() for p in truth_pts]}
    return images, truth


def write_laser_set(folder, images, truth):
    """``laser.json`` (camera, poses, pointer origin) + PNGs, the folder as a whole."""
    from fluoguide import atomic

    folder = Path(folder)
    with atomic.staged_folder(folder, last=("laser.json",)) as stage:
        names = _write_pngs(stage, images, "laser")
        doc = {k: truth[k] for k in ("camera", "camera_to_tracker", "laser_to_tracker",
                                     "phantom_to_tracker", "pointer_origin_tool_mm")}
        doc["images"] = names
        doc["truth"] = {"origin_mm": truth["origin_mm"], "direction": truth["direction"]}
        (stage / "laser.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    return folder
