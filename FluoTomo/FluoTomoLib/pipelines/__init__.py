"""Image-guided fluorescence tomography end to end: the steps every case shares
(acquisition, forward model, reconstruction) and the phantom cases (cylinder tube, oral cavity).

Modules
-------
- ``cases``: The demo's tomography cases as run-engine tasks (one per tube depth, the oral cavity): plain values in, plain arrays out, so they run on Dask workers and resume.
- ``oral``: Image-guided fluorescence tomography of the oral-cavity phantom.
- ``steps``: The steps both image-guided tomography cases share, whatever the phantom: the truth's simulation mesh, fields and rendered frames, and what the software makes of the frames (the label-map path).
- ``tube``: Image-guided fluorescence tomography of the cylinder-tube phantom, end to end.
- ``tube_truth``: The cylinder-tube cases' ground truth: the true phantom's emission fields on the surface the camera films, simulated on the whole phantom or read from the stored sets (``data/tube_truth``).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "cases": ["tube_case", "oral_case", "case_tasks", "case_of_record", "section_images"],
    "oral": ["line_targets", "simulate_oral_truth", "region_results", "oral_yield_at",
             "simulate_and_reconstruct_oral"],
    "steps": ["nodal_optics", "true_emission_fields", "surface_of", "render_frames",
              "phantom_simulation_mesh", "reconstruct_from_frames", "method_result",
              "case_record"],
    "tube": ["simulate_and_reconstruct"],
    "tube_truth": ["SurfaceTruth", "simulate_truth", "stored_truth", "read_truth", "write_truth",
                   "true_yield_at"],
})
