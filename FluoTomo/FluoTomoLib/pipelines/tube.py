"""Image-guided fluorescence tomography of the cylinder-tube phantom, end to end,
through the public label-map path (FluoTomoLib.tomography).

Simulation (what the operating room would give):
  the true emission fields on the filmed surface (:mod:`.tube_truth`: the
  whole phantom on its own graded mesh, fine near the laser raster and the
  tube, never the reconstruction's; the analytic tube absorbs and fluoresces;
  stored for the demo's depths, simulated for other options) -> tracked laser
  raster (true beam) -> tracked camera frames of the emission exitance (every
  pixel ray-cast onto the surface), through the camera's radiometric model
  with shot/read noise drawn from the case's seed.
Reconstruction (what the software does with it, the raw route of an
acquisition folder, ``acquisition_from_tracked_frames``):
  reported (tracked, noisy) laser poses -> sources where the beams meet the
  label map's surface; virtual detectors at the sources and between them,
  excluding those within 3 mm of the active source; pixels cast onto the
  surface from the reported camera pose, ROI counts -> boundary fluence per
  watt; then ``reconstruct_labelmap_methods`` as ``fluo tomo reconstruct``
  runs it: region of interest from the decay length with its truncation
  error estimated against the whole phantom, the anchored, refined,
  optode-graded reconstruction mesh, NP / SP / HP with the CBCT labels as the
  prior and the ICG's absorption fed back for HP.  The depth profile through
  the tube (x = y = 0) gives the thesis's peak and centroid.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.progress import check_cancel, report, scaled

from FluoTomoLib.acquisition.tracked_scan import TrackingError, raster_scan
from FluoTomoLib.fem.kernels import prepare_kernels
from FluoTomoLib.optics import robin_A
from FluoTomoLib.pipelines.steps import (case_record, method_result, reconstruct_from_frames,
                                         render_frames)
from FluoTomoLib.pipelines.tube_truth import (raster_targets, simulate_truth, stored_truth,
                                              true_yield_at)
from FluoTomoLib.recon.metrics import depth_profile, peak_and_centroid
from FluoTomoLib.recon.self_absorption import SELF_ABSORPTION


def simulate_and_reconstruct(phantom, fine_mm=0.8, coarse_mm=None, n_sources=16,
                             source_spacing_mm=2.5, detector_factor=2, exclude_mm=3.0,
                             roi_half_mm=None, methods=("NP", "SP", "HP"), lam=10.0,
                             laser_power_w=0.01, camera_gain=None, camera_offset_adu=100.0,
                             camera_binning=4, camera_distance_mm=150.0,
                             camera_read_noise_adu=2.0, tracking=TrackingError(), seed=0,
                             progress=None, cancel=None, recon_labels=None, accuracy="balanced",
                             simulate_coarse_mm=1.5, self_absorption=SELF_ABSORPTION, grading=False,
                             truth="stored"):
    """Run one tube depth through acquisition simulation and NP/SP/HP reconstruction.

    ``fine_mm`` is the element size of the simulation mesh near the raster and
    the tube (``simulate_coarse_mm`` elsewhere in the whole phantom);
    ``coarse_mm`` (default: the ``accuracy`` level's) that of the
    reconstruction near the optodes.  ``roi_half_mm`` = (x, y) half sizes of a
    region of interest to force (the full liquid depth); by default it is
    chosen from the decay length and its truncation error is reported.
    ``camera_gain`` is G of docs/physics.md section 5.1 in ADU per (W/mm^2/sr); by
    default it is chosen so the brightest pixel farther than ``exclude_mm``
    from the active source sits at ~60 % of a 14-bit range (what a user does
    with the exposure time).  ``recon_labels = (labels_kji, spacing_mm,
    origin_mm[, direction])`` is the label map the reconstruction and its
    priors come from (e.g. the user's segmentation of the CBCT in the app); by
    default the phantom's own labels.  The measurement is always simulated on
    the phantom's truth.  ``self_absorption``: the methods that feed the
    reconstructed ICG's absorption back (``fluo tomo reconstruct``'s default, HP
    and SP: ``recon.self_absorption.SELF_ABSORPTION``).  ``truth``: ``"stored"``
    reads the depth's stored true fields when the simulation options are the
    stored ones
    (:func:`.tube_truth.stored_truth`) and simulates them otherwise;
    ``"simulate"`` always simulates (how the stored sets are made).  Returns a
    dict of numbers, profiles, the reconstruction mesh and fields (RAS) for
    figures and the scene, ``true_yield_at`` (the analytic truth at points)
    and ``surface_truth`` (:class:`.tube_truth.SurfaceTruth`, with where it
    came from in its ``info``).
    """
    from FluoTomoLib.tomography import LabelMap

    if truth not in ("stored", "simulate"):
        raise FluoInputError("truth must be 'stored' or 'simulate'", field="truth", value=truth)
    t_all = time.perf_counter()
    rng = seeded_rng(seed)
    if phantom.name != "cylinder-tube":
        raise FluoInputError("this study needs the cylinder-tube phantom", field="phantom",
                             value=phantom.name)
    phantom_truth = phantom.truth()
    geo = phantom_truth["geometry"]
    optics = {int(k): v["optics"] for k, v in phantom_truth["regions"].items()}
    n = optics[1]["n"]
    A = float(robin_A(n))
    timings = {}

    # --- the simulation: the true fields on the filmed surface (stored or simulated)
    prepare_kernels(progress, 0.0, cancel)       # first run: compiled, reported as it goes
    t0 = time.perf_counter()
    sim_options = {"fine_mm": fine_mm, "simulate_coarse_mm": simulate_coarse_mm,
                   "n_sources": n_sources, "source_spacing_mm": source_spacing_mm}
    surface = (stored_truth(geo["tube_depth_mm"], sim_options, phantom=phantom)
               if truth == "stored" else None)
    if surface is None:
        surface = simulate_truth(phantom, **sim_options,
                                 progress=scaled(progress, 0.02, 0.25, "true fields"),
                                 cancel=cancel)
    timings["forward_simulation"] = time.perf_counter() - t0
    check_cancel(cancel)

    # --- tracked laser raster across the tube (along y at x = 0)
    report(progress, 0.25, "tracked laser scan")
    beam_origin, beam_dir = np.zeros(3), np.array([0.0, 0.0, 1.0])
    scan = raster_scan(raster_targets(n_sources, source_spacing_mm), beam_origin, beam_dir,
                       surface.vertices_mm, surface.facets, error=tracking, rng=rng)
    if np.any(scan["miss"]):
        raise FluoInputError("a reported laser beam misses the CBCT surface",
                             field="laser pose", value=int(np.flatnonzero(scan["miss"])[0]))
    src_true = scan["true_points_mm"]
    if not np.allclose(src_true, surface.sources_mm, atol=1e-6):
        raise FluoInputError("the true fields were simulated from other laser positions "
                             "than this raster's", file=surface.info.get("source"),
                             field="sources_mm")
    frames = render_frames(surface.vertices_mm, surface.facets, surface.fields_per_w, A,
                           src_true, (0.0, 0.0, 0.0), tracking, rng, exclude_mm=exclude_mm,
                           laser_power_w=laser_power_w, camera_gain=camera_gain,
                           camera_offset_adu=camera_offset_adu,
                           camera_read_noise_adu=camera_read_noise_adu,
                           camera_binning=camera_binning, camera_distance_mm=camera_distance_mm,
                           timings=timings, progress=progress, cancel=cancel)

    # --- the software: the raw route (tracked frames -> acquisition) on the CBCT labels
    if recon_labels is not None:
        r_labels, r_spacing, r_origin, *r_dir = recon_labels
        lm = LabelMap(r_labels, r_spacing, r_origin, r_dir[0] if r_dir else np.eye(3),
                      source="CBCT labels")
    else:
        lm = LabelMap(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                      source="cylinder-tube phantom")
    r = roi_half_mm
    roi_ras = None if r is None else (-r[0], r[0], -r[1], r[1], -float(geo["liquid_depth_mm"]), 0.0)
    acq, solved, coarse = reconstruct_from_frames(
        lm, frames, scan["reported_poses"], beam_origin, beam_dir, optics, methods, lam, 2,
        accuracy, coarse_mm, roi_ras, self_absorption, grading, detector_factor, exclude_mm,
        camera_offset_adu, laser_power_w, timings, progress, cancel)

    # --- truth and the reconstructions on the profile line x = y = 0
    depth = float(geo["tube_depth_mm"])
    results, profiles, zc = profile_results(solved, coarse, phantom)
    timings["total"] = time.perf_counter() - t_all
    report(progress, 1.0, "done")
    counts = acq.meta["roi_counts"]
    return {
        "depth_mm": depth, "results": results, "profile_depth_mm": zc, "profiles": profiles,
        "coarse": coarse, "surface_truth": surface,
        "true_yield_at": lambda points_mm: true_yield_at(points_mm, phantom),
        **case_record(src_true, acq, frames, solved, n_sources // 2, timings),
        "counts_range": [float(counts[acq.mask].min()), float(counts[acq.mask].max())],
        "truth": {k: v for k, v in surface.info.items()},
        "mesh_nodes": {"forward": surface.info["mesh_nodes"], "reconstruction": coarse.n_nodes},
        "mesh_elements": {"forward": surface.info["mesh_elements"],
                          "reconstruction": coarse.n_elements},
    }


def profile_results(solved, coarse, phantom):
    """Each method's depth profile through the tube (x = y = 0) on the
    reconstruction mesh ``coarse`` (RAS), its peak and half-maximum centroid
    against the analytic tube's, with the solver's summary, the nodal yield,
    the region values and the warnings.  Returns (results, profiles, depths):
    {method: numbers}, {"truth" | method: profile}, the profile's depths [mm]."""
    truth = phantom.truth()
    depth = float(truth["geometry"]["tube_depth_mm"])
    true_peak = float(truth["regions"]["2"]["optics"]["yield_per_mm"])
    results, profiles = {}, {}
    zc = np.arange(0.0, 20.0 + 1e-9, 0.05)         # depth_profile's line, through the tube
    profiles["truth"] = true_yield_at(np.stack([0 * zc, 0 * zc, -zc], axis=1), phantom)
    for method, out in solved.items():
        z, prof = depth_profile(coarse, out["result"].yield_per_mm, (0.0, 0.0))
        peak, centroid = peak_and_centroid(z, prof)
        profiles[method] = prof
        results[method] = {
            "true_peak": true_peak, "peak": peak,
            "peak_error_pct": 100.0 * (peak - true_peak) / true_peak,
            "true_centroid_mm": depth, "centroid_mm": centroid,
            "centroid_error_pct": 100.0 * (centroid - depth) / depth, **method_result(out),
        }
    return results, profiles, zc
