"""Image-guided fluorescence tomography of the oral-cavity phantom.

The phantom is an agar block (0.4 ug/mL ICG) with an open ellipsoidal cavity
whose floor holds an ICG-rich tongue (2 ug/mL, 5x the agar's yield) bulging
8 mm into the cavity.  Unlike the cylinder-tube case the surface is curved
and the light enters and leaves through the cavity: the tracked laser scans a
line across the tongue from above (the beams hit the tongue or the cavity
floor wherever they land), the tracked camera looks into the cavity, and
pixels are cast onto the tissue-air surface (the cavity walls can hide parts
of it).

Simulation (:func:`simulate_oral_truth`): the whole tissue on a mesh of its
own, fine at the laser line and the tongue, the analytic tongue's optics by
its nodes' shares of it, the FEM emission fields on its surface, rendered into
tracked camera frames.  Reconstruction: the tube's and ``fluo tomo reconstruct``'s path
(``steps.reconstruct_from_frames``), so the oral case's numbers come with the
label-map path's intervals and warnings.

What is measured is the tongue's yield and the agar's (each region's value as
the reconstruction reports it, with its 95 % interval) against the truth; the
profile metrics of the tube study (peak and centroid along a depth line) do
not apply to a bulk target.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.progress import check_cancel, report, scaled

from FluoTomoLib.acquisition.tracked_scan import TrackingError, raster_scan
from FluoTomoLib.fem.kernels import prepare_kernels
from FluoTomoLib.optics import robin_A
from FluoTomoLib.meshing.shares import analytic_fractions
from FluoTomoLib.pipelines.steps import (case_record, method_result, nodal_optics,
                                         phantom_simulation_mesh, reconstruct_from_frames,
                                         render_frames, surface_of, true_emission_fields)
from FluoTomoLib.recon.self_absorption import SELF_ABSORPTION


def _ellipsoid(points_mm, centre, semi_axes):
    q = (np.asarray(points_mm, float) - np.asarray(centre, float)) / np.asarray(semi_axes, float)
    return np.einsum("ij,ij->i", q, q) <= 1.0


def oral_yield_at(points_mm, phantom):
    """The true fluorescence yield [1/mm] at points (N, 3): the analytic
    tongue's inside it, the agar's elsewhere in the tissue (the label map's
    non-zero voxels), NaN in the air."""
    from FluoTomoLib.meshing.voxel import node_labels_from_labelmap

    truth = phantom.truth()
    geo = truth["geometry"]
    p = np.asarray(points_mm, float)
    lab = node_labels_from_labelmap(p, phantom.labels, phantom.spacing_mm, phantom.origin_mm)
    tongue = _ellipsoid(p, geo["tongue_centre_mm"], geo["tongue_semi_axes_mm"])
    y = {int(r): float(v["optics"]["yield_per_mm"]) for r, v in truth["regions"].items()}
    return np.where(lab == 0, np.nan, np.where(tongue, y[2], y[1]))


def line_targets(phantom, n_sources=16, source_spacing_mm=1.5):
    """Where the laser line's beams are aimed (S, 3) [mm]: along y across the
    tongue's centre, 9 mm below the cavity's rim (each beam's direction, straight
    down into the cavity; where it lands is where it meets the surface)."""
    centre = np.asarray(phantom.truth()["geometry"]["tongue_centre_mm"], float)
    ys = centre[1] + (np.arange(n_sources) - 0.5 * (n_sources - 1)) * source_spacing_mm
    return np.stack([np.full_like(ys, centre[0]), ys, np.full_like(ys, -9.0)], axis=1)


#: the laser's beam in its tool frame: from the origin along +z
BEAM_ORIGIN, BEAM_DIR = np.zeros(3), np.array([0.0, 0.0, 1.0])


def simulate_oral_truth(phantom, fine_mm=1.0, simulate_coarse_mm=2.0, n_sources=16,
                        source_spacing_mm=1.5, progress=None, cancel=None, lm=None):
    """The true phantom's emission fields on its surface, on a mesh of its own.

    As the tube's truth (``tube_truth.simulate_truth``): the whole tissue meshed
    (``tomography.simulate.simulation_mesh``) with ``fine_mm`` cells at the
    laser line and the tongue (capped at the sources' burial depth) and
    ``simulate_coarse_mm`` elsewhere (the largest power-of-two multiple of the
    fine size at most that), the tissue-air nodes on the label map's smooth
    surface (not a voxel staircase); the analytic tongue's optics by the nodes' shares
    of it (``meshing.shares.analytic_fractions``);
    the FEM emission fields from each beam of :func:`line_targets` (no tracking
    error: where the true beams land).  ``lm``: the phantom's LabelMap where
    the caller has one (its surface is extracted once).

    Returns
    -------
    tube_truth.SurfaceTruth
        On the whole tissue surface (the camera sees the cavity through its rim).
    """
    from FluoTomoLib.pipelines.tube_truth import SurfaceTruth
    from FluoTomoLib.tomography import LabelMap

    t0 = time.perf_counter()
    truth = phantom.truth()
    geo = truth["geometry"]
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    report(progress, 0.02, "simulation mesh (whole phantom)")
    targets = line_targets(phantom, n_sources, source_spacing_mm)
    # where the beams land, on the label map's surface: the simulation mesh is fine there
    if lm is None:
        lm = LabelMap(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                      source="oral-cavity phantom")
    surf = lm.surface()
    aimed = raster_scan(targets, BEAM_ORIGIN, BEAM_DIR, lm.to_ras(surf.points),
                        surf.triangles)["true_points_mm"]
    fine = phantom_simulation_mesh(phantom, aimed, 2, fine_mm, simulate_coarse_mm, cancel, lm)
    check_cancel(cancel)
    report(progress, 0.15, "forward simulation (true tissue)")
    # the nodes' shares of the analytic tongue: its true volume of dye
    true_props = nodal_optics(None, optics, analytic_fractions(
        fine, lambda p: _ellipsoid(p, geo["tongue_centre_mm"], geo["tongue_semi_axes_mm"])))
    vertices, facets, nodes = surface_of(fine)
    src_true = raster_scan(targets, BEAM_ORIGIN, BEAM_DIR, vertices, facets)["true_points_mm"]
    fields = true_emission_fields(fine, true_props, optics[1]["n"], src_true,
                                  progress=scaled(progress, 0.15, 1.0, "forward simulation"),
                                  cancel=cancel)[nodes]
    info = {"fine_mm": float(fine_mm), "simulate_coarse_mm": float(simulate_coarse_mm),
            "n_sources": int(n_sources), "source_spacing_mm": float(source_spacing_mm),
            "mesh_nodes": int(fine.n_nodes), "mesh_elements": int(fine.n_elements),
            "seconds": time.perf_counter() - t0, "source": "simulated"}
    return SurfaceTruth(vertices, facets, fields, src_true, info)


def region_results(solved, phantom_optics, names):
    """Each method's region values as the reconstruction reports them, against the
    truth: ``<name>_yield_per_mm``, ``_true_yield_per_mm``, ``_yield_error_pct``,
    ``_ci95_per_mm`` and ``_ci95_covers_truth`` per region (``names``: {label:
    name}), with the solver's summary, the nodal yield and the warnings."""
    results = {}
    for method, out in solved.items():
        row = {}
        for label, name in names.items():
            reg = out["summary"]["regions"][str(label)]
            true = float(phantom_optics[label]["yield_per_mm"])
            value, ci = reg["yield_per_mm"], reg["ci95_per_mm"]
            row[f"{name}_yield_per_mm"] = value
            row[f"{name}_true_yield_per_mm"] = true
            row[f"{name}_yield_error_pct"] = 100.0 * (value - true) / true
            row[f"{name}_ci95_per_mm"] = ci
            row[f"{name}_ci95_covers_truth"] = None if ci is None else bool(ci[0] <= true <= ci[1])
        results[method] = {**row, **method_result(out)}
    return results


def simulate_and_reconstruct_oral(phantom, fine_mm=1.0, coarse_mm=None, n_sources=16,
                                  source_spacing_mm=1.5, detector_factor=2, exclude_mm=3.0,
                                  methods=("NP", "SP", "HP"), lam=10.0, laser_power_w=0.01,
                                  tracking=TrackingError(), seed=0,
                                  self_absorption=SELF_ABSORPTION, roi=None, accuracy="balanced",
                                  grading=None, simulate_coarse_mm=2.0, camera_gain=None,
                                  camera_offset_adu=100.0, camera_read_noise_adu=2.0,
                                  camera_binning=4, camera_distance_mm=150.0, progress=None,
                                  cancel=None):
    """One tracked laser line across the tongue, rendered camera frames, NP / SP
    / HP with the CBCT labels (agar, tongue) as the prior.

    ``fine_mm``, ``simulate_coarse_mm``: the simulation mesh's element sizes
    [mm] (:func:`simulate_oral_truth`); ``coarse_mm``, ``accuracy``,
    ``grading`` (None: the label-map path's default), ``roi`` (x0, x1, y0, y1,
    z0, z1) [mm] (None: from the decay length): the reconstruction's, as
    ``reconstruct_labelmap_methods`` takes them.  Returns a dict of numbers
    (per method the tongue's and the agar's value, error and 95 % interval:
    :func:`region_results`), the reconstruction mesh and fields for figures and
    the scene, and ``true_yield_at`` (the analytic truth, :func:`oral_yield_at`).
    """
    from FluoTomoLib.tomography import LabelMap
    from FluoTomoLib.tomography.reconstruct import DEFAULT_GRADING

    t_all = time.perf_counter()
    rng = seeded_rng(seed)
    if phantom.name != "oral-cavity":
        raise FluoInputError("this case needs the oral-cavity phantom", field="phantom",
                             value=phantom.name)
    truth = phantom.truth()
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    timings = {}

    # the CBCT labels: the truth's surface and the reconstruction's (extracted once)
    lm = LabelMap(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                  source="oral-cavity phantom")

    # --- the simulation: the true fields on the tissue surface, on a mesh of its own
    prepare_kernels(progress, 0.0, cancel)       # first run: compiled, reported as it goes
    surface = simulate_oral_truth(phantom, fine_mm, simulate_coarse_mm, n_sources,
                                  source_spacing_mm, progress, cancel, lm)
    timings["forward_simulation"] = surface.info["seconds"]
    report(progress, 0.25, "tracked laser scan")
    scan = raster_scan(line_targets(phantom, n_sources, source_spacing_mm), BEAM_ORIGIN,
                       BEAM_DIR, surface.vertices_mm, surface.facets, error=tracking, rng=rng)
    if np.any(scan["miss"]):
        raise FluoInputError("a reported laser beam misses the CBCT surface",
                             field="laser pose", value=int(np.flatnonzero(scan["miss"])[0]))
    src_true = scan["true_points_mm"]
    centre = np.asarray(truth["geometry"]["tongue_centre_mm"], float)
    look_at = np.array([centre[0], centre[1], float(np.mean(src_true[:, 2]))])
    frames = render_frames(surface.vertices_mm, surface.facets, surface.fields_per_w,
                           float(robin_A(optics[1]["n"])), src_true, look_at, tracking, rng,
                           exclude_mm=exclude_mm, laser_power_w=laser_power_w,
                           camera_gain=camera_gain, camera_offset_adu=camera_offset_adu,
                           camera_read_noise_adu=camera_read_noise_adu,
                           camera_binning=camera_binning, camera_distance_mm=camera_distance_mm,
                           timings=timings, progress=progress, cancel=cancel)

    # --- the software: what fluo tomo makes of the frames, on the CBCT labels
    acq, solved, coarse = reconstruct_from_frames(
        lm, frames, scan["reported_poses"], BEAM_ORIGIN, BEAM_DIR, optics, methods, lam, 2,
        accuracy, coarse_mm, None if roi is None else tuple(roi), self_absorption,
        DEFAULT_GRADING if grading is None else grading, detector_factor, exclude_mm,
        camera_offset_adu, laser_power_w, timings, progress, cancel)
    results = region_results(solved, optics, {2: "tongue", 1: "agar"})
    timings["total"] = time.perf_counter() - t_all
    report(progress, 1.0, "done")
    return {
        "results": results, "coarse": coarse,
        "true_yield_at": lambda points_mm: oral_yield_at(points_mm, phantom),
        **case_record(src_true, acq, frames, solved, n_sources // 2, timings),
        "truth": dict(surface.info),
        "mesh_nodes": {"forward": surface.info["mesh_nodes"], "reconstruction": coarse.n_nodes},
        "mesh_elements": {"forward": surface.info["mesh_elements"],
                          "reconstruction": coarse.n_elements},
    }
