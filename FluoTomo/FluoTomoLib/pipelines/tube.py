"""Image-guided fluorescence tomography of the cylinder-tube phantom, end to end.

Simulation (what the operating room would give):
  CBCT label map -> fine forward mesh -> tracked laser raster (true beam) ->
  FEM excitation and emission fields with the true optical properties (tube
  absorbs and fluoresces) -> tracked camera frames of the emission exitance
  (every pixel ray-cast onto the surface), through the camera's radiometric
  model with shot/read noise.
Reconstruction (what the software does with it):
  reported (tracked, noisy) laser poses -> virtual sources on the CBCT surface;
  virtual detectors at the source positions and between them, excluding
  those within 3 mm of the active source; ROI counts -> radiance -> exitance
  -> boundary fluence / laser power; Jacobian on the fine mesh with the
  background properties, mapped to a coarser reconstruction mesh; NP / SP /
  HP with the CBCT labels as the prior.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.progress import check_cancel, report

from FluoTomoLib.pipelines.steps import (
    acquire,
    nodal_optics,
    reconstruct_methods,
    reconstruction_model,
)
from FluoTomoLib.optics import robin_A
from FluoTomoLib.recon.metrics import depth_profile, peak_and_centroid
from FluoTomoLib.acquisition.tracked_scan import TrackingError, raster_scan
from FluoTomoLib.meshing.voxel import mesh_labelmap_structured, region_centroid_mm, target_refinement


def _tube_indicator(points_mm, geometry):
    c = np.asarray(geometry["tube_centre_mm"], float)
    r = float(geometry["tube_radius_mm"])
    d = points_mm - c
    return (d[:, 1] ** 2 + d[:, 2] ** 2) <= r * r


def simulate_and_reconstruct(phantom, fine_mm=0.8, coarse_mm=1.0, n_sources=16,
                             source_spacing_mm=2.5, detector_factor=2, exclude_mm=3.0,
                             roi_half_mm=(15.0, 25.0), methods=("NP", "SP", "HP"),
                             lam=10.0, laser_power_w=0.01, camera_gain=None, camera_offset_adu=100.0,
                             camera_binning=4, camera_distance_mm=150.0,
                             camera_read_noise_adu=2.0, tracking=TrackingError(), seed=0,
                             progress=None, cancel=None, recon_labels=None, anchor_target=True,
                             refine_target=True, partial_volume=True, self_absorption=("HP",)):
    """Run one tube depth through acquisition simulation and NP/SP/HP reconstruction.

    ``fine_mm`` is the element size of the simulation (forward) mesh, ``coarse_mm``
    that of the reconstruction mesh, on which the Jacobian is computed
    directly (the data-space solver makes a 10^4-10^5 node reconstruction
    mesh affordable, so the thesis's mapping from the forward mesh is not
    needed; using two different meshes keeps the simulation from being an
    inverse crime).  ``camera_gain`` is G of docs/physics.md section 5.1 in ADU per (W/mm^2/sr); by
    default it is chosen so the brightest pixel farther than ``exclude_mm``
    from the active source sits at ~60 % of a 14-bit range (what a user does
    with the exposure time); ``camera_binning`` and ``camera_distance_mm`` set
    the rendered frames (``steps.acquire``).  Returns a dict of
    numbers, profiles and the meshes/fields for figures and the scene.

    ``recon_labels = (labels_kji, spacing_mm, origin_mm)`` is the label map the
    reconstruction mesh and the priors come from (e.g. the user's segmentation
    of the CBCT in the app); by default the phantom's own labels.  The
    measurement is always simulated on the phantom's truth.
    ``anchor_target``: anchor the reconstruction grid at the centre of the
    smallest segmented region (see mesh_labelmap_structured's ``anchor_mm``).
    ``partial_volume``: the hard prior's region basis is each node's partial
    volume of every region (partial_volume.py), not 0/1 node labels.
    ``self_absorption``: the methods ("SP", "HP") that feed the absorption of
    the reconstructed ICG back into their forward model (self_absorption.py).
    HP only by default: it took HP's mean |yield error| over the five tube
    depths from 23 % to 5 %, while SP, whose smoother field spreads the
    absorption, went from 10.5 % to 13.7 % at 6-9 s more per case.
    """
    t_all = time.perf_counter()
    rng = seeded_rng(seed)
    truth = phantom.truth()
    if phantom.name != "cylinder-tube":
        raise FluoInputError("this study needs the cylinder-tube phantom", field="phantom",
                             value=phantom.name)
    geo = truth["geometry"]
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    timings = {}

    # --- meshes from the CBCT label map.  The region of interest spans whole
    # reconstruction cells so that x = y = 0 (the profile line through the tube)
    # is a line of reconstruction nodes, as the thesis read its profiles.
    report(progress, 0.02, "meshing")
    hx = coarse_mm * round(roi_half_mm[0] / coarse_mm)
    hy = coarse_mm * round(roi_half_mm[1] / coarse_mm)
    hz = coarse_mm * np.floor(float(geo["liquid_depth_mm"]) / coarse_mm)
    roi = (-hx, hx, -hy, hy, -hz, 0.0)
    t0 = time.perf_counter()
    fine = mesh_labelmap_structured(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                                    fine_mm, roi=roi, name="forward")
    r_labels, r_spacing, r_origin = recon_labels or (phantom.labels, phantom.spacing_mm,
                                                     phantom.origin_mm)
    # The reconstruction grid passes through the segmented target's centre
    # depth, so its nodes sample the target symmetrically: on an unanchored 1 mm grid the
    # tube's 50 %-of-peak region was off by up to half a cell (0.3 mm, 11 % of
    # the 2.7 mm depth).  The surface stays a node layer (the roi's top face).
    # Laterally the grid keeps x = y = 0, the line the depth profile is read on.
    anchor = refine = None
    if anchor_target:
        anchor = np.array([0.0, 0.0, region_centroid_mm(r_labels, r_spacing, r_origin)[2]])
        if refine_target:
            refine = target_refinement(r_labels, r_spacing, r_origin, roi, 0.5 * coarse_mm,
                                       margin_mm=2.0 * coarse_mm)
    coarse = mesh_labelmap_structured(r_labels, r_spacing, r_origin, coarse_mm, roi=roi,
                                      anchor_mm=anchor, refine=refine, name="reconstruction")
    timings["meshing"] = time.perf_counter() - t0
    check_cancel(cancel)

    # --- true optical properties on the fine mesh: the analytic tube, not its voxels
    in_tube = _tube_indicator(fine.nodes_mm, geo)
    node_label = np.where(in_tube, 2, 1)
    true_props = nodal_optics(node_label, optics)
    n = optics[1]["n"]
    A = float(robin_A(n))

    # --- tracked laser raster across the tube (along y at x = 0)
    report(progress, 0.1, "tracked laser scan")
    ys = (np.arange(n_sources) - 0.5 * (n_sources - 1)) * source_spacing_mm
    targets = np.stack([np.zeros_like(ys), ys, np.zeros_like(ys)], axis=1)
    surf_pts = fine.nodes_mm
    top = fine.boundary_normals[:, 2] > 0.99
    scan = raster_scan(targets, np.zeros(3), np.array([0.0, 0.0, 1.0]), surf_pts,
                       fine.boundary_facets[top], error=tracking, rng=rng)
    if np.any(scan["miss"]):
        raise FluoInputError("a reported laser beam misses the CBCT surface",
                             field="laser pose", value=int(np.flatnonzero(scan["miss"])[0]))
    src_true, src_rep = scan["true_points_mm"], scan["reported_points_mm"]
    acq = acquire(fine, true_props, n, A, src_true, src_rep, top, (0.0, 0.0, 0.0), tracking, rng,
                  detector_factor=detector_factor, exclude_mm=exclude_mm,
                  laser_power_w=laser_power_w, camera_gain=camera_gain,
                  camera_offset_adu=camera_offset_adu,
                  camera_read_noise_adu=camera_read_noise_adu, camera_binning=camera_binning,
                  camera_distance_mm=camera_distance_mm, timings=timings, progress=progress,
                  cancel=cancel)
    det_rep, mask = acq["detectors_mm"], acq["mask"]

    # --- reconstruction model: background properties, reported geometry,
    # Jacobian on the reconstruction mesh, priors from the CBCT labels
    report(progress, 0.35, "Jacobian")
    bg = optics[1]
    J, model, make_model, prior = reconstruction_model(
        coarse, bg, n, src_rep, det_rep, mask, r_labels, r_spacing, r_origin, coarse_mm,
        partial_volume=partial_volume, timings=timings)
    y = acq["y"][mask]

    # --- truth on the profile line
    depth = float(geo["tube_depth_mm"])
    true_peak = float(optics[2]["yield_per_mm"])
    results = {}
    profiles = {}
    zc, truth_profile = depth_profile(fine, true_props["yield_per_mm"], (0.0, 0.0))
    profiles["truth"] = truth_profile
    solved = reconstruct_methods(J, y, mask, prior, make_model, bg, methods, lam,
                                 self_absorption, progress, cancel)
    for method, (res, passes, _) in solved.items():
        z, prof = depth_profile(coarse, res.yield_per_mm, (0.0, 0.0))
        peak, centroid = peak_and_centroid(z, prof)
        profiles[method] = prof
        results[method] = {
            "true_peak": true_peak, "peak": peak,
            "peak_error_pct": 100.0 * (peak - true_peak) / true_peak,
            "true_centroid_mm": depth, "centroid_mm": centroid,
            "centroid_error_pct": 100.0 * (centroid - depth) / depth,
            **res.summary(), "yield": res.yield_per_mm,
            "self_absorption_peaks": passes,
        }
    timings["reconstruction"] = sum(r["seconds"] for r in results.values())
    timings["total"] = time.perf_counter() - t_all
    report(progress, 1.0, "done")
    return {
        "depth_mm": depth, "results": results, "profile_depth_mm": zc, "profiles": profiles,
        "fine": fine, "coarse": coarse, "true_yield_fine": true_props["yield_per_mm"],
        "sources_true_mm": src_true, "sources_reported_mm": src_rep, "detectors_mm": det_rep,
        "source_error_mm": float(np.mean(np.linalg.norm(src_true - src_rep, axis=1))),
        "measurements": int(mask.sum()), "camera_gain": acq["camera_gain"],
        "counts_range": [float(acq["counts"][mask].min()), float(acq["counts"][mask].max())],
        "roi_pixels_median": float(np.median(acq["roi_pixels"][mask])),
        "frame_example": acq["frames"][n_sources // 2], "frame_example_source": n_sources // 2,
        "camera_pose_error_mm": float(np.linalg.norm(acq["camera_reported"][:3, 3]
                                                     - acq["camera_true"][:3, 3])),
        "timings": timings, "solver": model.solver_name,
        "mesh_nodes": {"forward": fine.n_nodes, "reconstruction": coarse.n_nodes},
        "mesh_elements": {"forward": fine.n_elements, "reconstruction": coarse.n_elements},
    }
