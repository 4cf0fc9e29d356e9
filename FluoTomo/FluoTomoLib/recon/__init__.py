"""Reconstruction of fluorescence yield (no, soft and hard priors), its grids, partial-volume
membership, self-absorption and the metrics of a result.

Modules
-------
- ``grids``: Fine (forward) and coarse (reconstruction) meshes and the operators between them.
- ``metrics``: Peak yield and centroid from a 1D depth profile (docs/physics.md section 8.5).
- ``partial_volume``: Partial-volume region membership of mesh nodes, for hard priors.
- ``self_absorption``: Fluorophore self-absorption in yield reconstruction.
- ``solver``: Reconstruction of fluorescence yield: no priors, soft priors, hard priors.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "grids": ["interpolation_operator", "mesh_interpolation_operators", "reconstruction_mesh_pair"],
    "metrics": ["depth_profile", "peak_and_centroid"],
    "partial_volume": ["dual_cells", "node_region_fractions", "PartialVolumePrior"],
    "self_absorption": ["absorbing_mua", "absorbing_model", "reconstruct_self_absorbing"],
    "solver": ["ReconResult", "RegionPrior", "diagnose", "region_jacobian", "reconstruct"],
})
