"""Monte Carlo photon transport (MCX / MCX-CL, written by others) as an independent
reference for the diffusion model: the engine, the semi-infinite pencil-beam set-up,
the comparison with the FEM, stored reference sets, and MC acquisitions on label maps.

Nothing here is on the main job's path; every module imports ``pmcxcl`` / ``pmcx``
only when a run is asked for (engine.py says how MCX-CL runs on a CPU).

Modules
-------
- ``engine``: Loads MCX-CL (OpenCL, CPU by default) or MCX (CUDA) and runs one simulation quietly.
- ``halfspace``: Pencil beam on a semi-infinite medium: R(rho), interior fluence, energy balance; runs merged with standard errors.
- ``compare``: The FEM and the closed forms on the Monte Carlo's media, and the comparison tables.
- ``acquisition``: Excitation and emission (reciprocity) data of source-detector pairs on a label map by Monte Carlo.
- ``reference``: Stored reference sets (data/): reading, writing, the fluorescence case.
- ``plots``: The validation figure.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "engine": ["MonteCarloUnavailable", "Engine", "load_engine", "engine_available", "time_gate_ns", "mcx_props"],
    "halfspace": ["HalfSpace", "run_halfspace", "merge_halfspace", "simulate_halfspace", "annulus_widths"],
    "compare": ["fem_halfspace", "fem_acquisition", "validate_halfspace", "quarter_box_mesh", "diffusion_operator_with_A", "agreement_from_mm"],
    "acquisition": ["simulate_acquisition", "LabelMapGeometry", "detector_launch_icdf", "detector_acceptance"],
    "reference": ["read_set", "set_path", "read_independent_reflectance", "fluorescence_case", "halfspace_set", "fluorescence_set"],
    "plots": ["validation_figure"],
})
