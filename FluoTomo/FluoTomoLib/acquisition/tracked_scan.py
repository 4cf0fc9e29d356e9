"""A tracked laser raster scan and a tracked camera, with realistic tracking error.

The laser's calibration gives its beam in laser-tool coordinates (origin on
the collimator face, unit direction).  To aim it at a surface point the tool
must be posed so the beam passes through that point; the tracker then reports
that pose with its own error.  Sources used by the reconstruction come from
the *reported* pose (beam cast onto the CBCT surface), while the light really
enters where the *true* beam hits: the same error chain as in the operating
room.  The camera is handled alike: images are rendered from its true pose and
mapped to the surface with the reported one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError
from FluoCalibLib.geometry.transforms import invert_rigid, make_rigid, rotvec_to_matrix

from FluoTomoLib.acquisition.noncontact_optodes import ray_triangle_intersect


def rotation_between(a, b):
    """Smallest rotation matrix taking unit vector a onto unit vector b."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # 180 deg: any axis perpendicular to a
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return rotvec_to_matrix(np.pi * perp / np.linalg.norm(perp))
    return rotvec_to_matrix(axis / s * np.arctan2(s, c))


@dataclass
class TrackingError:
    """Zero-mean Gaussian pose error of a tracked tool (per reported pose).

    Defaults are typical of an optical tracker (NDI Polaris: ~0.25 mm RMS
    position, ~0.1 deg orientation for a small tool).
    """

    translation_sd_mm: float = 0.25
    rotation_sd_deg: float = 0.1

    def perturb(self, pose, rng):
        dr = rng.normal(0.0, np.deg2rad(self.rotation_sd_deg), 3)
        dt = rng.normal(0.0, self.translation_sd_mm, 3)
        noise = make_rigid(rotvec_to_matrix(dr), dt)
        return noise @ pose


def laser_tool_pose_for_target(target_mm, beam_origin_tool_mm, beam_dir_tool, beam_dir_world,
                               standoff_mm=150.0):
    """LaserToolToReference pose that sends the calibrated beam through ``target_mm``.

    The beam leaves its origin ``standoff_mm`` before the target, travelling
    along ``beam_dir_world``.
    """
    d_world = np.asarray(beam_dir_world, float)
    d_world = d_world / np.linalg.norm(d_world)
    R = rotation_between(beam_dir_tool, d_world)
    origin_world = np.asarray(target_mm, float) - standoff_mm * d_world
    t = origin_world - R @ np.asarray(beam_origin_tool_mm, float)
    return make_rigid(R, t)


def beam_in_world(pose_tool_to_world, beam_origin_tool_mm, beam_dir_tool):
    """Beam origin [mm] and unit direction in the world frame for a tool pose."""
    R = pose_tool_to_world[:3, :3]
    o = R @ np.asarray(beam_origin_tool_mm, float) + pose_tool_to_world[:3, 3]
    d = R @ np.asarray(beam_dir_tool, float)
    return o, d / np.linalg.norm(d)


def raster_scan(targets_mm, beam_origin_tool_mm, beam_dir_tool, surface_vertices,
                surface_triangles, beam_dir_world=(0.0, 0.0, -1.0), error=None, rng=None,
                standoff_mm=150.0):
    """Aim the laser at each target; return true and reported entry points.

    Returns
    -------
    dict with ``true_poses`` and ``reported_poses`` (S, 4, 4) LaserToolToReference,
    ``true_points_mm`` (where the light enters) and ``reported_points_mm`` (what
    the navigation computes), both (S, 3), and ``miss`` (S,) bool for beams
    that do not hit the surface with the reported pose.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    targets = np.atleast_2d(np.asarray(targets_mm, float))
    true_poses, rep_poses = [], []
    for p in targets:
        T = laser_tool_pose_for_target(p, beam_origin_tool_mm, beam_dir_tool, beam_dir_world,
                                       standoff_mm)
        true_poses.append(T)
        rep_poses.append(T if error is None else error.perturb(T, rng))
    true_poses = np.asarray(true_poses)
    rep_poses = np.asarray(rep_poses)

    def cast(poses):
        o, d = zip(*(beam_in_world(T, beam_origin_tool_mm, beam_dir_tool) for T in poses))
        pts, _, face = ray_triangle_intersect(np.asarray(o), np.asarray(d), surface_vertices,
                                              surface_triangles)
        return pts, face < 0

    true_pts, true_miss = cast(true_poses)
    if np.any(true_miss):
        raise FluoInputError("laser target is not on the surface", field="targets_mm",
                             value=targets[np.flatnonzero(true_miss)[0]].tolist())
    rep_pts, rep_miss = cast(rep_poses)
    return {"true_poses": true_poses, "reported_poses": rep_poses, "true_points_mm": true_pts,
            "reported_points_mm": rep_pts, "miss": rep_miss}


def camera_pose_looking_at(eye_mm, target_mm, up=(0.0, 1.0, 0.0)):
    """CameraToReference pose (OpenCV camera frame: z forward, y down)."""
    from FluoCalibLib.geometry.transforms import look_at

    return look_at(np.asarray(eye_mm, float), np.asarray(target_mm, float), np.asarray(up, float))


def world_to_camera(pose_camera_to_world):
    return invert_rigid(pose_camera_to_world)
