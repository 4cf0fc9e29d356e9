"""The steps every image-guided tomography case shares, whatever the phantom:
the tracked camera's acquisition of a laser scan (rendered frames -> ROI
counts -> normalised boundary fluence), the reconstruction model and prior
from the CBCT labels, and NP / SP / HP with the optional self-absorption
feedback.  ``pipelines.tube`` (cylinder-tube) and ``pipelines.oral`` (oral cavity) put them
together."""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.optics_table import icg_absorption_per_yield
from fluoguide.progress import check_cancel, report, scaled

from FluoTomoLib.acquisition.camera_frames import (
    camera_pose_above,
    cast,
    detector_counts,
    exposure_gain,
    expose,
    frame_radiance,
    tomography_camera,
)
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.acquisition.noncontact_optodes import counts_to_boundary_fluence, detector_mask, virtual_detectors
from FluoTomoLib.recon.partial_volume import PartialVolumePrior, node_region_fractions
from FluoTomoLib.recon.solver import RegionPrior, reconstruct
from FluoTomoLib.recon.self_absorption import reconstruct_self_absorbing
from FluoTomoLib.meshing.voxel import node_regions_volume_preserving

def nodal_optics(node_region, optics):
    """Nodal property arrays from per-region optics dicts (labels as keys)."""
    out = {}
    for key in ("mua_x_per_mm", "musp_x_per_mm", "mua_m_per_mm", "musp_m_per_mm", "yield_per_mm"):
        out[key] = np.array([optics[int(r)][key] for r in node_region])
    return out


def true_emission_fields(fine, true_props, n, src_true, detectors_mm=None):
    """The FEM emission fields of the true tissue (``fine``: the simulation mesh,
    ``true_props``: its nodal optics, :func:`nodal_optics`) from the true source
    positions: (N, S) fluence per W of laser power at every node.  The
    factorisations (GBs on a whole phantom) are freed before it returns, not
    held through the reconstruction that follows."""
    det = src_true if detectors_mm is None else detectors_mm
    sim = FluorescenceModel(fine, {"mua_per_mm": true_props["mua_x_per_mm"],
                                   "musp_per_mm": true_props["musp_x_per_mm"], "n": n},
                            {"mua_per_mm": true_props["mua_m_per_mm"],
                             "musp_per_mm": true_props["musp_m_per_mm"], "n": n},
                            src_true, det, lean=True)
    fields = sim.emission_fields(true_props["yield_per_mm"])
    del sim
    return fields


def surface_of(mesh, facet_mask=None):
    """The surface the camera films as its own small mesh: (vertices_mm (V, 3),
    facets (F, 3) into them, node index (V,) into ``mesh``) of the boundary
    facets (``facet_mask``: some of them only)."""
    facets = mesh.boundary_facets if facet_mask is None else mesh.boundary_facets[facet_mask]
    nodes, inverse = np.unique(facets, return_inverse=True)
    return mesh.nodes_mm[nodes], inverse.reshape(facets.shape).astype(np.int64), nodes


def render_frames(vertices_mm, facets, fields, robin_A, src_true, camera_centre_mm, tracking,
                  rng, exclude_mm=3.0, laser_power_w=0.01, camera_gain=None,
                  camera_offset_adu=100.0, camera_read_noise_adu=2.0, camera_binning=4,
                  camera_distance_mm=150.0, timings=None, progress=None, cancel=None):
    """What the tracked camera records during a laser scan (the simulation side):
    the true emission fields on the filmed surface (``vertices_mm``, ``facets``:
    :func:`surface_of`; ``fields``: (V, S) fluence per W at the vertices, one
    column per source at its true position ``src_true``) rendered into one
    frame per source from the *true* camera pose, with shot/read noise and 14
    bits; the camera's *reported* pose carries the tracking error.
    ``camera_gain`` None: exposure such that the brightest pixel farther than
    ``exclude_mm`` from the active source sits at ~60 % of 14 bits.

    Returns a dict: ``frames`` (S, H, W) [ADU], ``saturated``, ``camera``
    (CameraModel), ``camera_true`` / ``camera_reported`` (CameraToWorld),
    ``camera_gain``, ``caster`` (the surface's SurfaceCaster, for the
    software side's casts).
    """
    from FluoNavLib.mapping.pixel_cast import SurfaceCaster

    timings = {} if timings is None else timings
    check_cancel(cancel)
    report(progress, 0.27, "camera frames")
    t0 = time.perf_counter()
    camera = tomography_camera(camera_binning)
    cam_true = camera_pose_above(camera_centre_mm, camera_distance_mm)
    cam_rep = cam_true @ tracking.perturb(np.eye(4), rng)
    caster = SurfaceCaster(vertices_mm, facets)
    hits_true = cast(caster, camera, cam_true, scaled(progress, 0.27, 0.27, "camera frames"),
                     cancel)
    radiance = frame_radiance(hits_true, facets, vertices_mm, fields, robin_A, laser_power_w)
    if camera_gain is None:
        camera_gain = exposure_gain(hits_true, radiance, src_true, exclude_mm)
    frames, saturated = expose(radiance, camera_gain, camera_offset_adu, camera_read_noise_adu,
                               rng)
    timings["camera_frames"] = timings.get("camera_frames", 0.0) + time.perf_counter() - t0
    return {"frames": frames, "saturated": saturated, "camera": camera, "camera_true": cam_true,
            "camera_reported": cam_rep, "camera_gain": float(camera_gain), "caster": caster}


def acquire(fine, true_props, n, robin_A, src_true, src_rep, facet_mask, camera_centre_mm,
            tracking, rng, detector_factor=2, exclude_mm=3.0, laser_power_w=0.01,
            camera_gain=None, camera_offset_adu=100.0, camera_read_noise_adu=2.0,
            camera_binning=4, camera_distance_mm=150.0, project_detectors=False, timings=None,
            progress=None, cancel=None):
    """Simulated acquisition of one laser scan with the tracked camera, mapped
    to the surface of the simulation mesh (the oral-cavity case; the
    cylinder-tube case maps its frames onto the label map's surface with
    FluoTomoLib.tomography.acquisition_from_tracked_frames).

    The frames (:func:`render_frames`) are mapped to the surface with the
    *reported* pose, ~1 mm^2 ROIs averaged at the virtual detectors (the
    reported sources plus points between them), excluding those within
    ``exclude_mm`` of the active source.  ``project_detectors``: the points
    interpolated between sources are moved onto the surface (straight down,
    along the beams); needed where the surface is curved, a no-op on a plane.

    Returns a dict: ``detectors_mm``, ``mask`` (S, D), ``y`` (S, D) boundary
    fluence per watt [1/mm^2] (0 where masked out), ``counts``, ``roi_pixels``,
    ``frames`` (S, H, W), ``camera_gain``, ``camera_true`` / ``camera_reported``
    (CameraToWorld).
    """
    timings = {} if timings is None else timings
    det_rep = virtual_detectors(src_rep, factor=detector_factor)
    if project_detectors:
        det_rep = onto_surface_from_above(det_rep, fine.nodes_mm, fine.boundary_facets[facet_mask])
    mask = detector_mask(src_rep, det_rep, exclude_mm)
    report(progress, 0.2, "forward simulation (true tissue)")
    t0 = time.perf_counter()
    vertices, facets, nodes = surface_of(fine, facet_mask)
    fields = true_emission_fields(fine, true_props, n, src_true, det_rep)[nodes]
    timings["forward_simulation"] = time.perf_counter() - t0
    r = render_frames(vertices, facets, fields, robin_A, src_true, camera_centre_mm, tracking,
                      rng, exclude_mm, laser_power_w, camera_gain, camera_offset_adu,
                      camera_read_noise_adu, camera_binning, camera_distance_mm, timings,
                      progress, cancel)
    t0 = time.perf_counter()
    hits_rep = cast(r["caster"], r["camera"], r["camera_reported"], cancel=cancel)  # compiled
    counts, roi_pixels = detector_counts(r["frames"], r["saturated"], hits_rep, det_rep)
    lost = mask & ~np.isfinite(counts)
    if np.any(lost):
        raise FluoInputError(f"{int(lost.sum())} detector ROIs have too few unsaturated pixels "
                             "(saturated, or not seen by the camera)", field="camera_gain",
                             value=r["camera_gain"])
    y = np.where(mask, counts_to_boundary_fluence(np.nan_to_num(counts), camera_offset_adu,
                                                  r["camera_gain"], robin_A, laser_power_w), 0.0)
    timings["camera_frames"] += time.perf_counter() - t0
    return {"detectors_mm": det_rep, "mask": mask, "y": y, "counts": counts,
            "roi_pixels": roi_pixels, "frames": r["frames"], "camera_gain": r["camera_gain"],
            "camera_true": r["camera_true"], "camera_reported": r["camera_reported"]}


def onto_surface_from_above(points_mm, vertices_mm, triangles, height_mm=50.0):
    """The surface point straight below (along -z) each point: where a virtual
    detector interpolated between two sources on a curved surface really lies."""
    from FluoTomoLib.acquisition.noncontact_optodes import ray_triangle_intersect

    p = np.asarray(points_mm, float)
    origins = p + np.array([0.0, 0.0, height_mm])
    hit, _, face = ray_triangle_intersect(origins, np.tile([0.0, 0.0, -1.0], (len(p), 1)),
                                          vertices_mm, triangles)
    if np.any(face < 0):
        raise FluoInputError("a virtual detector has no surface below it", field="detectors_mm",
                             value=p[np.flatnonzero(face < 0)[0]].tolist())
    return hit


def reconstruction_model(coarse, bg, n, src_rep, det_rep, mask, labels, spacing_mm, origin_mm,
                         h_mm, partial_volume=True, timings=None):
    """Jacobian with the background properties on the reconstruction mesh, a
    factory for models with other nodal absorption (self-absorption), and the
    region prior from the CBCT labels.  Returns (J, model, make_model, prior)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    model = FluorescenceModel(coarse, {"mua_per_mm": bg["mua_x_per_mm"],
                                       "musp_per_mm": bg["musp_x_per_mm"], "n": n},
                              {"mua_per_mm": bg["mua_m_per_mm"], "musp_per_mm": bg["musp_m_per_mm"],
                               "n": n}, src_rep, det_rep)
    J = model.jacobian_yield()[mask.ravel()]
    timings["jacobian"] = time.perf_counter() - t0

    def make_model(mua_x_nodes, mua_m_nodes):
        """The reconstruction model with the dye's absorption (self_absorption.py)."""
        return FluorescenceModel(coarse, {"mua_per_mm": mua_x_nodes,
                                          "musp_per_mm": bg["musp_x_per_mm"], "n": n},
                                 {"mua_per_mm": mua_m_nodes,
                                  "musp_per_mm": bg["musp_m_per_mm"], "n": n}, src_rep, det_rep)

    # SP: each region's nodes carry its label-map volume; HP: partial volumes
    node_region = node_regions_volume_preserving(coarse, labels, spacing_mm, origin_mm)
    if partial_volume:
        prior = PartialVolumePrior(node_region, *node_region_fractions(
            coarse.nodes_mm, labels, spacing_mm, origin_mm, h_mm,
            edges_mm=coarse.meta.get("edges_mm")))
    else:
        prior = RegionPrior(node_region)
    return J, model, make_model, prior


def reconstruct_methods(J, y, mask, prior, make_model, bg, methods=("NP", "SP", "HP"), lam=10.0,
                        self_absorption=("HP",), progress=None, cancel=None):
    """NP / SP / HP (and the self-absorption feedback for the methods listed).
    Returns {method: (ReconResult, per-pass peaks, seconds)}."""
    out = {}
    for i, method in enumerate(methods):
        check_cancel(cancel)
        report(progress, 0.5 + 0.45 * i / len(methods), f"reconstruction {method}")
        t0 = time.perf_counter()
        passes = []
        if method in tuple(self_absorption or ()):
            res, passes = reconstruct_self_absorbing(
                method, J, y, mask, prior, make_model,
                (bg["mua_x_per_mm"], bg["mua_m_per_mm"]), bg["yield_per_mm"],
                icg_absorption_per_yield(), lam=lam, cancel=cancel)
        else:
            res = reconstruct(J, y, method=method, lam=lam, prior=prior)
        res.seconds = time.perf_counter() - t0
        out[method] = (res, passes, res.seconds)
    return out
