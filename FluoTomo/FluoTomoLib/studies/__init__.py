"""The thesis's 2D simulation studies A, B and C and their figures.

Modules
-------
- ``plots``: Figures of the simulation studies: forward model | NP | SP | HP on one colour scale.
- ``thesis``: The thesis's 2D simulation studies A, B and C (docs/physics.md section 8.5).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "plots": ["plot_case"],
    "thesis": ["study_meshes", "disc", "node_regions_from_shape", "run_case", "run_study", "run_sweep"],
})
