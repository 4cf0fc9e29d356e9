"""A synthetic navigated acquisition on the oral-cavity phantom: homogeneous
fluorescence (uniform transport T), a light coupled to the camera, tracked
views looking into the cavity, camera noise — the data with known truth that
the surface-flux mapping is tested and benchmarked on.

Frames that grade the software are rendered on the phantom's analytic surface
(:func:`exact_oral_cavity_hits`) from the true poses, while the software gets
a CBCT-derived mesh and tracked poses with errors (:func:`tracked_acquisition`,
``mismatch.py``); :func:`render_view` renders on a given mesh (speed tests,
the live stream: :func:`stream_camera_tool`, :func:`look_at_cavity`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide.errors import FluoInputError, check_number, seeded_rng

from FluoCalibLib.geometry import transforms as tf
from FluoCalibLib.geometry.camera_model import CameraModel
from FluoCalibLib.radiometry.illumination_model import IlluminationCone
from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

from FluoNavLib.mapping.flux_map import forward_image, view_model
from FluoNavLib.mapping.pixel_cast import PixelHits, SurfaceCaster, cast_camera

__all__ = ["oral_cavity_surface", "open_field_camera", "coupled_light", "view_poses",
           "look_at_cavity", "stream_camera_tool", "render_view", "render_hits", "exact_oral_cavity_hits", "PoseError",
           "tracked_acquisition"]


# The largest optical transport a synthetic view renders (dimensionless): far
# above tissue's (< 1), below where the photon counts' Poisson draws overflow
MAX_TRANSPORT = 100.0


def oral_cavity_surface(target_triangles=62000, seed=0, voxel_mm=0.8, source="labels"):
    """(SurfaceCaster, vtkPolyData) of the oral-cavity phantom's air-tissue surface
    (RAS mm), extracted from its CBCT voxelised at ``voxel_mm``: from the label
    map (``source="labels"``) or the CBCT intensities (``"cbct"``, sub-voxel), and
    decimated to about ``target_triangles`` (None: not decimated)."""
    from fluoguide.phantoms import make_phantom

    from FluoNavLib.mapping.surface import surface_from_cbct, surface_from_labelmap

    if source not in ("labels", "cbct"):
        raise FluoInputError("choose labels or cbct", field="source", value=source)
    if target_triangles is not None:
        check_number("target_triangles", target_triangles, 0, 10_000_000, integer=True,
                     what="must be 0 (keep all) .. 10,000,000")
    p = make_phantom("oral-cavity", seed=seed, voxel_mm=voxel_mm)
    ijk = np.diag([*p.spacing_mm, 1.0])
    ijk[:3, 3] = p.origin_mm
    if source == "cbct":
        poly = surface_from_cbct(p.cbct_hu, ijk, target_triangles=target_triangles)
    else:
        poly = surface_from_labelmap(p.labels, ijk, target_triangles=target_triangles)
    return SurfaceCaster.from_polydata(poly), poly


@dataclass(frozen=True)
class PoseError:
    """A rigid pose error: ``translation_mm`` and ``rotation_deg`` are standard
    deviations per axis (``random``) or the magnitudes of one fixed error in a
    random direction (``fixed``, drawn once per session)."""

    translation_mm: float
    rotation_deg: float

    def __post_init__(self):
        # a pose error beyond the size of the scene (1 m) or a half turn describes
        # no tracked camera: refused, not rendered as a view of nothing
        for name, hi in (("translation_mm", 1000.0), ("rotation_deg", 180.0)):
            check_number(name, getattr(self, name), 0.0, hi)

    def random(self, rng):
        """A zero-mean Gaussian error (4x4), independent per call."""
        dr = rng.normal(0.0, np.deg2rad(self.rotation_deg), 3)
        dt = rng.normal(0.0, self.translation_mm, 3)
        return tf.make_rigid(tf.rotvec_to_matrix(dr), dt)

    def fixed(self, rng):
        """An error of exactly these magnitudes in a random direction (4x4)."""
        a = rng.normal(size=3)
        b = rng.normal(size=3)
        R = tf.rotation_matrix(a / np.linalg.norm(a), np.deg2rad(self.rotation_deg))
        return tf.make_rigid(R, self.translation_mm * b / np.linalg.norm(b))


def open_field_camera(binning=1):
    """1392 x 1040 sensor, 6.45 um pixels, a 12 mm lens (f ~ 1860 px): the whole
    oral cavity from 120 mm."""
    check_number("binning", binning, 1, 64, integer=True)
    cam = CameraModel(1860.0, 1860.0, 695.5, 519.5, (0.0, 0.0, 0.0, 0.0, 0.0), 1392, 1040)
    return cam.binned(binning) if binning > 1 else cam


def coupled_light():
    """A ring-light-like source beside the lens, wide enough to light the view."""
    axis = tf.rotation_matrix([1.0, 0.0, 0.0], np.deg2rad(3.0)) @ np.array([0.0, 0.0, 1.0])
    return IlluminationCone(origin_mm=(12.0, 0.0, 0.0), axis=tuple(axis), half_angle_deg=40.0,
                            alpha=2.0, gamma_per_mm=0.01, system_gain_adu=1.5e5, frame="Camera")


def view_poses(n=4, distance_mm=120.0, centre=(0.0, 0.0, -20.0)):
    """CameraToWorld poses looking into the cavity from above at several angles."""
    check_number("views", n, 1, 360, integer=True)
    check_number("distance_mm", distance_mm, 0.0, 10_000.0, lo_open=True)
    poses = []
    for k in range(n):
        az = 2 * np.pi * k / max(n, 1)
        tilt = 0.0 if k == 0 else np.deg2rad(15.0)
        eye = np.asarray(centre) + distance_mm * np.array([np.sin(tilt) * np.cos(az),
                                                           np.sin(tilt) * np.sin(az), np.cos(tilt)])
        poses.append(look_at_cavity(eye, centre))
    return poses


def look_at_cavity(eye_mm, centre=(0.0, 0.0, -20.0)):
    """CameraToWorld (4x4, mm) of a camera at ``eye_mm`` [mm] looking at the
    cavity's ``centre`` [mm], image up along +y (how every view here is aimed)."""
    return tf.look_at(eye_mm, centre, up=(0.0, 1.0, 0.0))


def stream_camera_tool(name="CameraTool", noise_mm=0.05):
    """The simulated tracker's camera tool of a live stream over the phantom
    (``ndi_simulator.SimTool``, tracker frame = phantom frame, mm): a Lissajous
    path 120 mm above the cavity's centre, +-25 mm in x and y (periods 6 s) and
    +-5 mm in z (9 s), with ``noise_mm`` [mm] tracking noise (SD per axis)."""
    from FluoNavLib.devices.ndi_simulator import SimTool

    return SimTool(name, centre_mm=(0.0, 0.0, 100.0), amplitude_mm=(25.0, 25.0, 5.0),
                   period_s=(6.0, 6.0, 9.0), noise_mm=noise_mm)


def render_view(caster, camera, camera_to_world, cone, transport=0.3, radiometric=None, seed=0):
    """(noisy counts [ADU], hits, view model) of one view of homogeneous tissue.

    ``transport`` is the optical transport T (dimensionless, 0..100; tissue's is
    below 1, larger values only saturate the sensor).
    """
    check_number("transport", transport, 0.0, MAX_TRANSPORT)
    hits = cast_camera(caster, camera, camera_to_world)
    counts, vm = render_hits(hits, cone, camera_to_world, transport, radiometric, seed)
    return counts, hits, vm


def render_hits(hits, cone, camera_to_world, transport=0.3, radiometric=None, seed=0):
    """(noisy counts [ADU], view model) of tissue of transport T (dimensionless,
    0..100) seen at ``hits`` (a ray cast, or :func:`exact_oral_cavity_hits`):
    S = Dsys T I, then Poisson shot noise, dark current, full well, bias, read
    noise and the ADC."""
    check_number("transport", transport, 0.0, MAX_TRANSPORT)
    rcam = radiometric or RadiometricCamera(gain_adu_per_e=1.0)
    rng = seeded_rng(seed)
    vm = view_model(hits, cone, camera_to_world)
    S = forward_image(vm, cone, transport)                      # ADU above offset
    e = np.maximum(S / rcam.gain_adu_per_e, 0.0)
    el = rng.poisson(e) + rng.poisson(rcam.dark_current_e_per_s * rcam.exposure_s, e.shape)
    el = np.minimum(el, rcam.full_well_e) + rcam.bias_e + rng.normal(0, rcam.read_noise_e, e.shape)
    counts = np.clip(np.round(el * rcam.gain_adu_per_e), 0, rcam.adc_max_adu)
    return counts, vm


def _ellipsoid_roots(c, d, centre, axes):
    """Both ray parameters where c + t d meets an axis-aligned ellipsoid (NaN if none)."""
    a = np.asarray(axes, float)
    o = (c - np.asarray(centre, float)) / a
    v = d / a
    A = np.sum(v * v, axis=-1)
    B = 2.0 * np.sum(o * v, axis=-1)
    C = np.sum(o * o, axis=-1) - 1.0
    disc = B * B - 4 * A * C
    root = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return (-B - root) / (2 * A), (-B + root) / (2 * A)


def _ellipsoid_normal(p, centre, axes):
    g = (p - np.asarray(centre, float)) / np.asarray(axes, float) ** 2
    return g / np.linalg.norm(g, axis=-1, keepdims=True)


def exact_oral_cavity_hits(camera, camera_to_world, geometry, max_view_deg=89.0):
    """PixelHits of the oral-cavity phantom's *analytic* surface (no mesh, no voxels).

    The tissue is the agar block minus the half-ellipsoid cavity, plus the
    tongue ellipsoid (``Phantom.truth()["geometry"]``).  Each pixel's ray is
    intersected with the block's faces, the cavity wall (from inside) and the
    tongue in closed form, with exact normals: the true surface that frames
    are rendered on when the software's own (voxelised, smoothed, decimated)
    surface must not grade itself.  The camera must be outside the block;
    masks as :func:`cast_camera`.
    """
    M = np.asarray(camera_to_world, float)
    bx, by, bz = (float(v) for v in geometry["block_mm"])
    cav_c = np.asarray(geometry["cavity_centre_mm"], float)
    cav_a = np.asarray(geometry["cavity_semi_axes_mm"], float)
    t_c = np.asarray(geometry["tongue_centre_mm"], float)
    t_a = np.asarray(geometry["tongue_semi_axes_mm"], float)
    top = float(geometry.get("top_z_mm", 0.0))
    lo = np.array([-bx / 2, -by / 2, top - bz])
    hi = np.array([bx / 2, by / 2, top])
    c = M[:3, 3]
    if np.all((c >= lo) & (c <= hi)):
        raise FluoInputError("the exact render needs the camera outside the block",
                             field="camera_to_world", value=c.tolist())
    d = camera.pixel_grid_rays(1) @ M[:3, :3].T
    shape = d.shape[:2]
    # the ray's entry into the block (slab method), and the face it enters through
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - c) / d
        t2 = (hi - c) / d
    t_near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    t_far = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
    axis = np.argmax(t_near, axis=-1)
    t_b = np.max(t_near, axis=-1)
    in_block = (t_b <= np.min(t_far, axis=-1)) & (t_b > 0)
    face_normal = np.zeros(shape + (3,))
    np.put_along_axis(face_normal, axis[..., None],
                      -np.sign(np.take_along_axis(d, axis[..., None], -1)), axis=-1)
    p_b = c + np.where(in_block, t_b, 0.0)[..., None] * d
    through_top = in_block & (axis == 2) & (d[..., 2] < 0)
    in_opening = through_top & (np.sum(((p_b - cav_c) / cav_a) ** 2, axis=-1) < 1.0)
    t = np.full(shape, np.inf)
    normal = np.zeros(shape + (3,))
    solid = in_block & ~in_opening
    t[solid] = t_b[solid]
    normal[solid] = face_normal[solid]
    t_top = t_b
    into = in_opening                            # the ray enters the cavity's air
    _, t_wall = _ellipsoid_roots(c, d, cav_c, cav_a)
    t_in, _ = _ellipsoid_roots(c, d, t_c, t_a)
    p_in = c + np.nan_to_num(t_in)[..., None] * d
    # the tongue is seen where its entry point lies in the cavity's air
    tongue_ok = into & np.isfinite(t_in) & (t_in > t_top) & (p_in[..., 2] <= top) & (
        np.sum(((p_in - cav_c) / cav_a) ** 2, axis=-1) < 1.0)
    wall_ok = into & np.isfinite(t_wall) & (t_wall > t_top)
    use_tongue = tongue_ok & (~wall_ok | (t_in < t_wall))
    use_wall = wall_ok & ~use_tongue
    t[use_tongue] = t_in[use_tongue]
    t[use_wall] = t_wall[use_wall]
    p = c + np.where(np.isfinite(t), t, 0.0)[..., None] * d
    normal[use_tongue] = _ellipsoid_normal(p[use_tongue], t_c, t_a)
    normal[use_wall] = -_ellipsoid_normal(p[use_wall], cav_c, cav_a)   # tissue lies outside
    hit = np.isfinite(t)
    cos_view = -np.sum(d * normal, axis=-1)
    grazing = hit & (cos_view <= np.cos(np.deg2rad(max_view_deg)))
    visible = hit & ~grazing & (cos_view > 0)
    reason = np.where(visible, 0, np.where(~hit, 1, np.where(cos_view <= 0, 2, 3))).astype(np.uint8)
    return PixelHits(face=np.where(visible, 0, -1), distance_mm=np.where(visible, t, np.inf),
                     cos_view=np.where(visible, cos_view, 0.0), visible=visible, reason=reason,
                     camera_center_mm=c, point_mm=np.where(visible[..., None], p, 0.0),
                     normal=np.where(visible[..., None], normal, 0.0))


def tracked_acquisition(n_views=4, binning=4, transport=0.3, tracking=PoseError(0.25, 0.1),
                        hand_eye=PoseError(0.3, 0.15), surface_triangles=62000, seed=0,
                        progress=None, cancel=None):
    """A navigated acquisition as the operating room makes it, for ``fluo nav synth``.

    The frames are rendered on the oral-cavity phantom's analytic surface from
    the true camera poses (:func:`exact_oral_cavity_hits`); what the software
    is given carries the errors it would have: the tissue surface extracted
    from the phantom's CBCT intensities (0.8 mm voxels, decimated to
    ``surface_triangles``), tool poses with optical tracking error (per frame)
    and a hand-eye calibration with a fixed error (the true camera frame is the
    tool frame).

    Returns a dict: ``frames`` (list of uint16 count images), ``tool_poses``
    (reported CameraToolToTracker, list of 4x4), ``hand_eye`` (reported
    camera-to-tool, 4x4), ``true_poses`` (CameraToWorld), ``surface``
    (vtkPolyData), ``camera``, ``cone``, ``radiometric``, ``geometry``.
    """
    from fluoguide.phantoms import make_phantom
    from fluoguide.progress import check_cancel, report, scaled

    from FluoNavLib.mapping.surface import surface_from_cbct

    if not (isinstance(n_views, (int, np.integer)) and 0 <= n_views <= 64):
        raise FluoInputError("must be an integer 0..64", field="views", value=n_views)
    if not (isinstance(binning, (int, np.integer)) and 1 <= binning <= 64):
        raise FluoInputError("must be an integer 1..64", field="binning", value=binning)
    if not (np.isfinite(transport) and 0 < transport <= 10):
        raise FluoInputError("must be a finite number in (0, 10]", field="transport",
                             value=transport)
    if surface_triangles is not None:
        check_number("surface_triangles", surface_triangles, 0, 10_000_000, integer=True,
                     what="must be 0 (keep all) .. 10,000,000")
    report(progress, 0.0, "the phantom's CBCT")
    phantom = make_phantom("oral-cavity", seed=seed)
    ijk = np.diag([*phantom.spacing_mm, 1.0])
    ijk[:3, 3] = phantom.origin_mm
    poly = surface_from_cbct(phantom.cbct_hu, ijk, target_triangles=surface_triangles,
                             progress=scaled(progress, 0.02, 0.2, "the CBCT surface"),
                             cancel=cancel)
    geometry = phantom.truth()["geometry"]
    cam = open_field_camera(binning)
    cone = coupled_light()
    rc = RadiometricCamera(gain_adu_per_e=1.0)
    rng = np.random.default_rng(seed)
    hand_eye_reported = hand_eye.fixed(rng)
    frames, tool_poses, true_poses = [], [], []
    # no views: the room alone (surface, calibrations), for a live stream
    for k, pose in enumerate(view_poses(n_views) if n_views else []):
        check_cancel(cancel)
        report(progress, 0.2 + 0.8 * k / n_views, f"view {k + 1} of {n_views}")
        counts, _ = render_hits(exact_oral_cavity_hits(cam, pose, geometry), cone, pose,
                                transport, rc, seed=seed + k)
        frames.append(counts.astype(np.uint16))
        tool_poses.append(tracking.random(rng) @ pose)
        true_poses.append(pose)
    return {"frames": frames, "tool_poses": tool_poses, "hand_eye": hand_eye_reported,
            "true_poses": true_poses, "surface": poly, "camera": cam, "cone": cone,
            "radiometric": rc, "geometry": geometry}
