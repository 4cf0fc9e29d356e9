"""The thesis's 2D simulation studies A, B and C and their figures.

Modules
-------
- ``plots``: Figures of the simulation studies: forward model | NP | SP | HP on one colour
  scale; error against time.
- ``thesis``: The thesis's 2D simulation studies A, B and C (docs/physics.md section 8.5):
  meshes, shared Jacobians, the reconstruction task, run_study / run_sweep.
- ``spec``: Studies as data: a grid (study file, --grid, named sweeps) expanded into tasks.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "plots": ["plot_case", "plot_error_vs_time"],
    "thesis": ["study_meshes", "disc", "node_regions_from_shape", "run_case", "run_study", "run_sweep",
               "run_spec", "forward_jacobian", "mapped_jacobian", "reconstruction_task"],
    "spec": ["StudySpec", "study_spec", "sweep_spec", "spec_from_mapping", "study_tasks"],
})
