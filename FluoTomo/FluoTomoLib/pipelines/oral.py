"""Image-guided fluorescence tomography of the oral-cavity phantom.

The phantom is an agar block (0.4 ug/mL ICG) with an open ellipsoidal cavity
whose floor holds an ICG-rich tongue (2 ug/mL, 5x the agar's yield) bulging
8 mm into the cavity.  Unlike the cylinder-tube case the surface is curved
and the light enters and leaves through the cavity: the tracked laser scans a
line across the tongue from above (the beams hit the tongue or the cavity
floor wherever they land), the tracked camera looks into the cavity, pixels
are cast onto the tissue-air surface (the cavity walls can hide parts of it),
and only the tissue-air facets of the cropped CBCT mesh carry sources and
detectors.

What is measured is the tongue's yield (its volume-weighted mean over the
reconstruction nodes wholly inside the tongue, against the truth) and the
agar's, per method; the profile metrics of the tube study (peak and centroid along a
depth line) do not apply to a bulk target.
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
from FluoTomoLib.acquisition.tracked_scan import TrackingError, raster_scan
from FluoTomoLib.fem.kernels import prepare_kernels
from FluoTomoLib.meshing.voxel import mesh_labelmap_structured, nodal_volumes

#: region of interest around the tongue (x0, x1, y0, y1, z0, z1) [mm]: the
#: tongue's box plus 6-8 mm of agar; the cavity air above it is not meshed
ORAL_ROI_MM = (-20.0, 20.0, -16.0, 26.0, -40.0, -8.0)


def tissue_air_facets(mesh, labels_kji, spacing_mm, origin_mm, probe_mm=None):
    """Boundary facets of a cropped mesh that face air in the label map (the
    real tissue surface), not the faces where the region of interest cut the
    tissue: the label ``probe_mm`` outside each facet's centre is 0 (default
    0.75 element: a structured mesh's surface lies up to half a cell off the
    label map's)."""
    if probe_mm is None:
        probe_mm = 0.75 * float(mesh.meta.get("size_mm", 1.0))
    f = mesh.boundary_facets
    c = mesh.nodes_mm[f].mean(axis=1) + probe_mm * mesh.boundary_normals
    ijk = np.round((c - np.asarray(origin_mm, float)) / np.asarray(spacing_mm, float)).astype(int)
    shape = np.array(np.shape(labels_kji)[::-1])
    inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
    lab = np.zeros(len(f), dtype=np.int64)
    i, j, k = ijk[inside].T
    lab[inside] = np.asarray(labels_kji)[k, j, i]
    return lab == 0


def _ellipsoid(points_mm, centre, semi_axes):
    q = (np.asarray(points_mm, float) - np.asarray(centre, float)) / np.asarray(semi_axes, float)
    return np.einsum("ij,ij->i", q, q) <= 1.0


def simulate_and_reconstruct_oral(phantom, fine_mm=1.0, coarse_mm=1.5, n_sources=16,
                                  source_spacing_mm=1.5, detector_factor=2, exclude_mm=3.0,
                                  methods=("NP", "SP", "HP"), lam=10.0, laser_power_w=0.01,
                                  tracking=TrackingError(), seed=0, self_absorption=("HP",),
                                  roi=ORAL_ROI_MM, progress=None, cancel=None, **camera):
    """One tracked laser line across the tongue, rendered camera frames,
    NP / SP / HP with the CBCT labels (agar, tongue) as the prior.

    ``camera`` takes the camera options of ``steps.acquire``
    (``camera_gain``, ``camera_offset_adu``, ``camera_read_noise_adu``,
    ``camera_binning``, ``camera_distance_mm``).  Returns a dict of numbers,
    the meshes and fields for figures and the scene.
    """
    t_all = time.perf_counter()
    rng = seeded_rng(seed)
    if phantom.name != "oral-cavity":
        raise FluoInputError("this case needs the oral-cavity phantom", field="phantom",
                             value=phantom.name)
    truth = phantom.truth()
    geo = truth["geometry"]
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    timings = {}

    prepare_kernels(progress, 0.0, cancel)       # first run: compiled, reported as it goes
    report(progress, 0.02, "meshing")
    t0 = time.perf_counter()
    fine = mesh_labelmap_structured(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                                    fine_mm, roi=roi, name="forward")
    coarse = mesh_labelmap_structured(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                                      coarse_mm, roi=roi, name="reconstruction")
    timings["meshing"] = time.perf_counter() - t0
    check_cancel(cancel)

    # true tissue on the simulation mesh: the analytic tongue, agar elsewhere
    in_tongue = _ellipsoid(fine.nodes_mm, geo["tongue_centre_mm"], geo["tongue_semi_axes_mm"])
    true_props = nodal_optics(np.where(in_tongue, 2, 1), optics)
    n = optics[1]["n"]
    A = float(robin_A(n))
    surface = tissue_air_facets(fine, phantom.labels, phantom.spacing_mm, phantom.origin_mm)

    # laser line along y across the tongue, beams straight down into the cavity
    report(progress, 0.1, "tracked laser scan")
    centre = np.asarray(geo["tongue_centre_mm"], float)
    ys = centre[1] + (np.arange(n_sources) - 0.5 * (n_sources - 1)) * source_spacing_mm
    targets = np.stack([np.full_like(ys, centre[0]), ys, np.full_like(ys, roi[5] - 1.0)], axis=1)
    scan = raster_scan(targets, np.zeros(3), np.array([0.0, 0.0, 1.0]), fine.nodes_mm,
                       fine.boundary_facets[surface], error=tracking, rng=rng)
    if np.any(scan["miss"]):
        raise FluoInputError("a reported laser beam misses the CBCT surface",
                             field="laser pose", value=int(np.flatnonzero(scan["miss"])[0]))
    src_true, src_rep = scan["true_points_mm"], scan["reported_points_mm"]
    look_at = np.array([centre[0], centre[1], float(np.mean(src_true[:, 2]))])
    acq = acquire(fine, true_props, n, A, src_true, src_rep, surface, look_at, tracking, rng,
                  detector_factor=detector_factor, exclude_mm=exclude_mm,
                  laser_power_w=laser_power_w, project_detectors=True, timings=timings,
                  progress=progress, cancel=cancel, **camera)
    det_rep, mask = acq["detectors_mm"], acq["mask"]

    report(progress, 0.35, "Jacobian")
    bg = optics[1]
    J, model, make_model, prior = reconstruction_model(
        coarse, bg, n, src_rep, det_rep, mask, phantom.labels, phantom.spacing_mm,
        phantom.origin_mm, coarse_mm, timings=timings)
    solved = reconstruct_methods(J, acq["y"][mask], mask, prior, make_model, bg, methods, lam,
                                 self_absorption, progress, cancel)

    # region yields are read over the nodes wholly inside each region (partial
    # volume >= 0.99): a node on the tongue's rim carries half agar, whatever
    # the method, and would bias every mean towards the other region
    vol = nodal_volumes(coarse)
    K = prior.K()
    results = {}
    for method, (res, passes, _) in solved.items():
        x = res.yield_per_mm
        row = {}
        for label, name in ((2, "tongue"), (1, "agar")):
            sel = K[:, list(prior.labels).index(label)] >= 0.99
            mean = float(np.sum(x[sel] * vol[sel]) / np.sum(vol[sel]))
            true = float(optics[label]["yield_per_mm"])
            row[f"{name}_yield_per_mm"] = mean
            row[f"{name}_true_yield_per_mm"] = true
            row[f"{name}_yield_error_pct"] = 100.0 * (mean - true) / true
        results[method] = {**row, **res.summary(), "yield": x, "self_absorption_peaks": passes}
    timings["reconstruction"] = sum(v[2] for v in solved.values())
    timings["total"] = time.perf_counter() - t_all
    report(progress, 1.0, "done")
    return {
        "results": results, "fine": fine, "coarse": coarse,
        "true_yield_fine": true_props["yield_per_mm"],
        "sources_true_mm": src_true, "sources_reported_mm": src_rep, "detectors_mm": det_rep,
        "source_error_mm": float(np.mean(np.linalg.norm(src_true - src_rep, axis=1))),
        "measurements": int(mask.sum()), "camera_gain": acq["camera_gain"],
        "roi_pixels_median": float(np.median(acq["roi_pixels"][mask])),
        "frame_example": acq["frames"][n_sources // 2], "frame_example_source": n_sources // 2,
        "timings": timings, "solver": model.solver_name,
        "mesh_nodes": {"forward": fine.n_nodes, "reconstruction": coarse.n_nodes},
        "mesh_elements": {"forward": fine.n_elements, "reconstruction": coarse.n_elements},
    }
