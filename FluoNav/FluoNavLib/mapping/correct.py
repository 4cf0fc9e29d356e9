"""Correct recorded tracked frames with the navigated illumination model
(``fluo nav correct``): everything it needs comes from the MRML scene.

Reads the frame and its pose from the recording (``frame_store``; a frame
without a valid pose is refused), the intrinsics, ``FluoCalib.Illumination``
(the cone) and ``FluoCalib.Radiometry`` (the camera) from the calibration node
(``FluoCalibration`` unless the caller picks another), the pose chain
``TrackerToReference . CameraToolToTracker . CameraToCameraTool`` and the
surface model (``TissueSurface`` unless the caller picks another);
``FluoNavLogic`` writes the results back as ``FluoNavSurfaceFlux``,
``FluoNavTransport``, ``FluoNavFlux`` and ``FluoNavRaw`` (``mapping.scene``).

:func:`load_context` and :func:`read_frame` read the scene (the caller's thread);
:func:`correct_image` and :func:`map_frames_to_surface` touch no MRML node, so a
live stream or a desktop panel may run them on a worker thread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError

from FluoNavLib.devices import frame_store
from FluoNavLib.mapping.contours import miss_rate
from FluoNavLib.mapping.flux_map import (
    DEFAULT_MAX_MODEL_ERROR,
    ViewModel,
    model_error,
    accumulate_on_faces,
    surface_flux,
    transport_image,
    view_model,
    view_weights,
)
from FluoNavLib.mapping.pixel_cast import PixelHits, SurfaceCaster, cast_camera

__all__ = ["NavContext", "FrameResult", "load_context", "read_frame", "correct_image",
           "correct_frame", "map_frames_to_surface"]


@dataclass
class NavContext:
    """What every frame of a recording shares: camera, light, surface."""

    camera: object
    cone: object
    radiometric: object
    caster: SurfaceCaster
    polydata: object
    tracker_to_reference: np.ndarray
    camera_to_tool: np.ndarray


@dataclass
class FrameResult:
    frame: int
    counts: np.ndarray
    hits: PixelHits
    vm: ViewModel
    transport: np.ndarray          # T_hat, 0 where not mapped
    mapped: np.ndarray             # bool
    flux_w_per_mm2: np.ndarray     # J, 0 where the counts are not valid
    flux_valid: np.ndarray
    saturated: np.ndarray
    weight: np.ndarray             # view quality per pixel
    numbers: dict
    offset_adu: float = 0.0        # the camera's dark offset (counts - offset = signal S)


def load_context(scene, surface_node=None, calibration_node=None):
    """Everything the frames of one recording share, read from the scene.

    Parameters
    ----------
    surface_node : vtkMRMLModelNode, optional
        The tissue surface the pixels are cast onto (default ``TissueSurface``).
    calibration_node : vtkMRMLScriptedModuleNode, optional
        Holds ``FluoCalib.CameraIntrinsics``, ``.Illumination`` and
        ``.Radiometry`` (default ``FluoCalibration``).
    """
    from FluoCalibLib.radiometry import scene as light_scene
    from FluoCalibLib.geometry.scene import load_handeye, load_intrinsics
    from FluoCalibLib.radiometry.illumination_model import IlluminationCone
    from FluoCalibLib.radiometry.radiometric_model import RadiometricCamera

    cam = load_intrinsics(scene, calibration_node)
    il = light_scene.load_calibration(scene, light_scene.ILLUMINATION_KEY, calibration_node)
    if not il or "cone" not in il:
        raise FluoInputError("scene has no illumination calibration", field=light_scene.ILLUMINATION_KEY)
    rad = light_scene.load_calibration(scene, light_scene.RADIOMETRY_KEY, calibration_node)
    if not rad:
        raise FluoInputError("scene has no radiometric calibration", field=light_scene.RADIOMETRY_KEY)
    # the FluoCalib radiometry document holds the camera model under "camera"
    # (our synthetic scenes) or as its top-level keys (fluo calib radiometry)
    rc = RadiometricCamera.from_dict(rad.get("camera", rad))
    model = (surface_node if surface_node is not None
             else mrml_io.get_node(scene, "TissueSurface", "vtkMRMLModelNode"))
    poly = model.GetPolyData()
    if poly is None or poly.GetNumberOfCells() == 0:
        raise FluoInputError("surface model has no triangles", field=model.GetName())
    caster = SurfaceCaster.from_polydata(poly)
    t2r = mrml_io.get_transform(scene, "TrackerToReference")
    c2t = load_handeye(scene)
    return NavContext(cam, IlluminationCone.from_dict(il["cone"]), rc, caster, poly, t2r, c2t)


def read_frame(scene, n):
    """Recorded frame ``n`` as :func:`correct_image` takes it: ``(counts (H, W) [ADU],
    CameraToolToTracker (4, 4) [mm])``, read from the scene (its thread); a frame
    without a valid camera pose is refused (FluoInputError)."""
    img, info, poses = frame_store.read_tracked_frame(scene, n)
    tool = poses.get("CameraToolToTracker")
    if tool is None or not info.get("pose_valid", True):
        raise FluoInputError("frame has no valid camera pose: not mapped", field="frame", value=n)
    return img, tool


def correct_frame(scene, ctx, n, min_intensity=0.05, max_model_error=DEFAULT_MAX_MODEL_ERROR):
    """Transport image, surface flux, weights and miss rates of recorded frame ``n``
    (:func:`read_frame`, then :func:`correct_image`).

    Pixels whose predicted model error (``flux_map.model_error``: the surface
    normal's uncertainty through the light's incidence angle, occluding rims)
    exceeds ``max_model_error`` are not corrected; they are counted in
    ``numbers["unreliable"]`` (None: no guard)."""
    img, tool = read_frame(scene, n)
    return correct_image(ctx, img, tool, frame=n, min_intensity=min_intensity,
                         max_model_error=max_model_error)


def correct_image(ctx, img, tool_to_tracker, frame=0, min_intensity=0.05,
                  max_model_error=DEFAULT_MAX_MODEL_ERROR):
    """Transport image, surface flux, weights and miss rates of one camera image.

    Parameters
    ----------
    img : (H, W) array, counts [ADU]
    tool_to_tracker : (4, 4) camera-tool pose (``CameraToolToTracker``) [mm]
    frame : int, the frame's number in its recording (reported back)
    min_intensity : pixels lit below this fraction of the brightest are not corrected
    max_model_error : pixels whose predicted model error (``flux_map.model_error``)
        exceeds this are not corrected (counted as ``unreliable``); None: no guard
    """
    n = frame
    img = np.asarray(img)
    tool = np.asarray(tool_to_tracker, float)
    if tool.shape != (4, 4) or not np.all(np.isfinite(tool)):
        raise FluoInputError("camera pose must be a finite 4x4 matrix", field="cameraPose",
                             value=tool.shape)
    if img.ndim != 2:
        raise FluoInputError("frame must be one 2D image", field="frame", value=img.shape)
    cam = ctx.camera
    if (cam.width, cam.height) != (img.shape[1], img.shape[0]):
        raise FluoInputError("frame size differs from the camera intrinsics", field="frame",
                             value=(img.shape, cam.width, cam.height))
    world = ctx.tracker_to_reference @ tool @ ctx.camera_to_tool
    counts = img.astype(float)
    rc = ctx.radiometric
    hits = cast_camera(ctx.caster, cam, world)
    vm = view_model(hits, ctx.cone, world)
    _, valid, saturated, _ = rc.radiance_from_counts(counts, min_snr=3.0)
    S = counts - rc.offset_adu
    trusted = valid
    if max_model_error is not None:
        trusted = valid & (model_error(hits, vm, ctx.caster) <= max_model_error)
    T, ok = transport_image(S, vm, ctx.cone, min_intensity=min_intensity, valid=trusted)
    J, jvalid = surface_flux(counts, rc)
    snr = rc.snr(np.maximum(S, 0.0) / rc.gain_adu_per_e)
    w = view_weights(hits, vm, snr)
    numbers = {"frame": int(n), "pixels": int(img.size), "visible": int(hits.visible.sum()),
               "mapped": int(ok.sum()), "saturated": int(saturated.sum()),
               "unreliable": int((hits.visible & valid & ~trusted).sum()),
               "max_model_error": max_model_error,
               "transport_median": float(np.median(T[ok])) if ok.any() else None,
               "transport_iqr": ([float(np.percentile(T[ok], 25)), float(np.percentile(T[ok], 75))]
                                 if ok.any() else None)}
    jv = jvalid & hits.visible
    numbers["surface_flux_median_w_per_mm2"] = float(np.median(J[jv])) if jv.any() else None
    if ok.any():
        raw_rate, _, _ = miss_rate(S, hits.visible & valid)
        cor_rate, _, _ = miss_rate(T, ok)
        numbers.update(miss_rate_raw_pct=raw_rate, miss_rate_corrected_pct=cor_rate)
    return FrameResult(int(n), counts, hits, vm, T, ok, J, jvalid, saturated, w, numbers,
                       float(rc.offset_adu))


def map_frames_to_surface(ctx, results):
    """View-weighted per-face means of T and J over the frames' results.

    Returns (transport, flux, weight, views) per face of the surface."""
    n = ctx.caster.n_faces
    T, wsum = accumulate_on_faces(n, [(r.hits.face, r.transport, r.weight, r.mapped) for r in results])
    J, _ = accumulate_on_faces(n, [(r.hits.face, r.flux_w_per_mm2, r.weight, r.flux_valid & r.mapped)
                                   for r in results])
    views = np.zeros(n, np.int32)
    for r in results:
        m = r.mapped & (r.weight > 0)
        views[np.unique(r.hits.face[m])] += 1
    return T, J, wsum, views
