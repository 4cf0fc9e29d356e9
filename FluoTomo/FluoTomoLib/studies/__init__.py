"""The thesis's 2D simulation studies A, B and C and their figures.

Modules
-------
- ``plots``: Figures of the simulation studies: forward model | NP | SP | HP on one colour
  scale; error against time.
- ``thesis``: The thesis's 2D simulation studies A, B and C (docs/physics.md section 8.5):
  meshes, shared Jacobians, the reconstruction task, the studies' targets and sweeps.
- ``spec``: Studies as data: a grid (study file, --grid, named sweeps) expanded into tasks.
- ``run``: A study, sweep, case or spec run on the run engine, with its table and figures.

Each imports only the ones listed before it (``plots`` stands alone).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "plots": ["plot_case", "plot_error_vs_time"],
    "thesis": ["study_meshes", "disc", "node_regions_from_shape", "forward_jacobian",
               "mapped_jacobian", "reconstruction_task"],
    "spec": ["StudySpec", "study_spec", "sweep_spec", "spec_from_mapping", "study_tasks"],
    "run": ["run_case", "run_study", "run_sweep", "run_spec", "case_fields"],
})
