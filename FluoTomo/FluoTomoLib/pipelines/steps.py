"""The steps both image-guided tomography cases share, whatever the phantom.

The simulation side: the mesh a phantom's truth is simulated on, the true
tissue's emission fields on the filmed surface, the tracked camera's frames of
them.  The software side, :func:`reconstruct_from_frames`: what ``fluo tomo``
makes of the frames (``tomography.acquisition_from_tracked_frames``, then
``tomography.reconstruct_labelmap_methods``), for ``pipelines.tube``
(cylinder-tube) and ``pipelines.oral`` (oral cavity) alike.
"""

from __future__ import annotations

import time

import numpy as np

from fluoguide.progress import check_cancel, report, scaled

from FluoTomoLib.acquisition.camera_frames import (
    camera_pose_above,
    cast,
    exposure_gain,
    expose,
    frame_radiance,
    tomography_camera,
)
from FluoTomoLib.fem.forward import FluorescenceModel


OPTICS_KEYS = ("mua_x_per_mm", "musp_x_per_mm", "mua_m_per_mm", "musp_m_per_mm", "yield_per_mm")


def nodal_optics(node_region, optics, fraction=None, inside=2, outside=1):
    """Nodal property arrays from per-region optics dicts (labels as keys).

    ``fraction`` (N,) in [0, 1]: each node's share of the ``inside`` region
    (``meshing.shares.analytic_fractions``); the properties are then the share-weighted
    mix of ``inside``'s and ``outside``'s (all five are linear in the dye's
    concentration), and ``node_region`` is not read."""
    if fraction is not None:
        f = np.asarray(fraction, float)
        return {key: f * float(optics[int(inside)][key])
                + (1.0 - f) * float(optics[int(outside)][key]) for key in OPTICS_KEYS}
    return {key: np.array([optics[int(r)][key] for r in node_region]) for key in OPTICS_KEYS}


def true_emission_fields(fine, true_props, n, src_true, detectors_mm=None, progress=None,
                         cancel=None):
    """The FEM emission fields of the true tissue (``fine``: the simulation mesh,
    ``true_props``: its nodal optics, :func:`nodal_optics`) from the true source
    positions: (N, S) fluence per W of laser power at every node.  The
    factorisations (GBs on a whole phantom) are freed before it returns, not
    held through the reconstruction that follows.  ``progress`` hears of each
    factorisation as it goes; ``cancel`` is checked there."""
    det = src_true if detectors_mm is None else detectors_mm
    sim = FluorescenceModel(fine, {"mua_per_mm": true_props["mua_x_per_mm"],
                                   "musp_per_mm": true_props["musp_x_per_mm"], "n": n},
                            {"mua_per_mm": true_props["mua_m_per_mm"],
                             "musp_per_mm": true_props["musp_m_per_mm"], "n": n},
                            src_true, det, lean=True)
    sim.progress, sim.cancel = progress, cancel
    _ = sim.phi_x
    fields = sim.emission_fields(true_props["yield_per_mm"])
    del sim
    return fields


def phantom_simulation_mesh(phantom, points_mm, target, fine_mm, simulate_coarse_mm,
                            cancel=None, lm=None):
    """The mesh a phantom's truth is simulated on (RAS), the whole tissue
    (``tomography.simulate.simulation_mesh``): ``fine_mm`` cells, capped at the
    sources' burial depth, in the box of ``points_mm`` (where the laser enters)
    and of the ``target`` label where it is compact, grown by max(4 mm, half the
    decay length); ``simulate_coarse_mm`` elsewhere (the largest power-of-two
    multiple of the fine size at most that); the tissue-air nodes on the label
    map's smooth surface.  ``lm``: the phantom's LabelMap where the caller has
    one already (its surface is then extracted once)."""
    from FluoTomoLib.tomography import LabelMap, optics_from_phantom
    from FluoTomoLib.tomography.accuracy import cap_at_burial
    from FluoTomoLib.tomography.simulate import simulation_mesh

    if lm is None:
        lm = LabelMap(phantom.labels, phantom.spacing_mm, phantom.origin_mm,
                      source=f"{phantom.name} phantom")
    optics = optics_from_phantom({int(k): v["optics"]
                                  for k, v in phantom.truth()["regions"].items()})
    h_sim, mfp = cap_at_burial(fine_mm, optics, lm.labels)
    decay = 1.0 / optics.min_mueff(lm.labels)
    return lm.mesh_to_ras(simulation_mesh(lm, lm.to_local(np.asarray(points_mm, float)), target,
                                          h_sim, max(simulate_coarse_mm, h_sim),
                                          max(4.0, 0.5 * decay), mfp, cancel))


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


def reconstruct_from_frames(lm, frames, laser_poses, beam_origin, beam_dir, phantom_optics,
                            methods, lam, target, accuracy, size_mm, roi_ras, self_absorption,
                            grading, detector_factor=2, exclude_mm=3.0, camera_offset_adu=100.0,
                            laser_power_w=0.01, timings=None, progress=None, cancel=None):
    """What the software makes of a case's tracked frames, as ``fluo tomo`` does:
    the raw route (``acquisition_from_tracked_frames``: beams onto the label
    map's surface, virtual detectors, pixels cast from the reported camera pose,
    ROI counts -> boundary fluence per watt), then
    ``reconstruct_labelmap_methods`` on the label map ``lm`` with the phantom's
    optics less the dye (``optics_from_phantom``).

    ``frames``: :func:`render_frames`' dict; ``laser_poses``: the reported
    LaserToolToRAS poses; the other arguments are those of the two calls.
    ``timings`` gains ``camera_frames`` (added), the reconstruction's steps and
    ``reconstruction`` (every method's solve).

    Returns (Acquisition, {method: result}, the reconstruction mesh in RAS).
    """
    from FluoTomoLib.tomography import (acquisition_from_tracked_frames, optics_from_phantom,
                                        reconstruct_labelmap_methods)

    timings = {} if timings is None else timings
    n = next(iter(phantom_optics.values()))["n"]
    t0 = time.perf_counter()
    acq = acquisition_from_tracked_frames(
        lm, frames["frames"], frames["saturated"], frames["camera"], frames["camera_reported"],
        laser_poses, beam_origin, beam_dir, frames["camera_gain"], camera_offset_adu,
        laser_power_w, n_tissue=n, detector_factor=detector_factor, exclude_mm=exclude_mm)
    timings["camera_frames"] = timings.get("camera_frames", 0.0) + time.perf_counter() - t0
    check_cancel(cancel)
    report(progress, 0.35, "reconstruction")
    solved = reconstruct_labelmap_methods(
        lm, optics_from_phantom(phantom_optics), acq, methods, lam, target=target,
        accuracy=accuracy, size_mm=size_mm, roi_ras=roi_ras, self_absorption=self_absorption,
        grading=grading, progress=scaled(progress, 0.35, 0.98, "reconstruction"), cancel=cancel)
    first = solved[tuple(solved)[0]]
    timings.update({k: v for k, v in first["summary"]["timings"].items()
                    if k != "reconstruction"})
    timings["reconstruction"] = sum(o["result"].seconds for o in solved.values())
    return acq, solved, lm.mesh_to_ras(first["mesh"])


def method_result(out):
    """What every case reports of one method's solution (``out``: one value of
    ``reconstruct_labelmap_methods``): the solver's summary, the nodal yield,
    the self-absorption passes, the region values and the warnings."""
    s = out["summary"]
    return {**out["result"].summary(), "yield": out["result"].yield_per_mm,
            "self_absorption_peaks": s["solver"]["self_absorption_peaks"],
            "regions": s["regions"], "warnings": s["warnings"]}


def case_record(src_true, acq, frames, solved, n_frame, timings):
    """The numbers every case reports beside its methods' results: optodes and
    their tracking error, measurements, camera gain and ROI pixels, an example
    frame, the region of interest, timings, solver (``solved``:
    :func:`reconstruct_from_frames`' methods, one model; the mesh sizes are the
    caller's to add)."""
    first = solved[tuple(solved)[0]]
    return {
        "sources_true_mm": src_true, "sources_reported_mm": acq.sources_ras_mm,
        "detectors_mm": acq.detectors_ras_mm,
        "source_error_mm": float(np.mean(np.linalg.norm(src_true - acq.sources_ras_mm,
                                                        axis=1))),
        "measurements": int(acq.mask.sum()), "camera_gain": frames["camera_gain"],
        "roi_pixels_median": float(np.median(acq.meta["roi_pixels"][acq.mask])),
        "frame_example": frames["frames"][n_frame], "frame_example_source": n_frame,
        "camera_pose_error_mm": float(np.linalg.norm(frames["camera_reported"][:3, 3]
                                                     - frames["camera_true"][:3, 3])),
        "region_of_interest": first["summary"]["region_of_interest"],
        "timings": timings, "solver": first["model"].model.solver_name,
    }
