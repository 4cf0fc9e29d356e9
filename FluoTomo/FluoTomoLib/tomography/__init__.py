"""Tomography on any label map (the user's own scene): file formats, geometry in
the label map's frame, the region of interest, the reconstruction model, the
simulated acquisition and the reconstruction.

Modules
-------
- ``labelmap``: A label map with its geometry, and the frame the tomography works in.
- ``optics_file``: ``optics.json``: the optical properties of every label, written by hand.
- ``acquisition_file``: An acquisition folder a person can write by hand, and the tracked-frames route.
- ``accuracy``: The accuracy knob of the label-map pipelines.
- ``roi``: The region of interest of a reconstruction, chosen from the decay length and graded against a larger domain.
- ``model``: The reconstruction mesh and model of a label map, with the tube study's accuracy machinery for any target label.
- ``simulate``: Simulated acquisitions of a label map: the scan, the engines, the noise.
- ``reconstruct``: Reconstruction of fluorescence yield on a user's label map.
- ``plan``: Planning a scan: the laser's entry points that narrow the targets' intervals.
- ``batch``: Many own scenes at once: a batch file of cases on the run engine.
- ``segment``: A CBCT turned into a label map by HU thresholds, headless (largest component, holes filled).
- ``recording``: A recorded tracked laser scan turned into an acquisition, and a recording rendered from a label map's truth.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "labelmap": ["LabelMap", "SurfaceInfo", "place_on_surface", "MAX_OFFSET_MM"],
    "optics_file": ["Optics", "optics_from_dict", "read_optics", "homogeneous_optics",
                    "optics_from_phantom"],
    "acquisition_file": ["Acquisition", "read_acquisition", "write_acquisition",
                         "acquisition_from_tracked_frames", "write_tracked_frames",
                         "read_points_csv"],
    "accuracy": ["LEVELS", "accuracy_settings"],
    "roi": ["choose_roi", "roi_from_ras"],
    "model": ["reconstruction_mesh", "membership", "check_prior_volumes", "TissueModel"],
    "simulate": ["ENGINES", "DEFAULT_SCAN", "MC_PHOTONS", "MAX_SCAN_PATCHES",
                 "check_scan_targets", "default_scan", "add_noise",
                 "simulation_mesh", "simulate_mc",
                 "simulate_fem", "simulate_acquisition"],
    "reconstruct": ["reconstruct_labelmap", "reconstruct_labelmap_methods", "nodal_to_grid",
                    "write_reconstruction"],
    "plan": ["plan_scan", "predict_scan", "check_plan_inputs", "write_plan", "plan_document"],
    "batch": ["load_batch", "reconstruct_case", "batch_tasks", "run_batch",
              "write_case_outputs"],
    "segment": ["clean_mask", "parse_thresholds", "threshold_labels"],
    "recording": ["read_scan_recording", "read_calibration", "detect_spot", "pose_at",
                  "acquire_recording", "write_recorded_acquisition", "record_scan",
                  "SPOT_TOLERANCE_MM", "TIME_SYNC_TOLERANCE_S"],
})
