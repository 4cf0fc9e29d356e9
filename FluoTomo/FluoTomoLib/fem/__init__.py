"""The finite-element diffusion model: operators, compiled assembly and Jacobian kernels,
the PARDISO binding, fill-reducing ordering, point location and the coupled forward model.

Modules
-------
- ``assembly_kernels``: Compiled (numba) FEM assembly straight into the upper triangle in CSR.
- ``forward``: Coupled excitation/emission forward model, adjoint fields and Jacobians.
- ``halfspace``: The analytic fast path: the exact solution where the tissue is a half-space.
- ``jacobian_kernels``: Compiled (numba) loops of the Jacobians of boundary data.
- ``kernels``: The compiled (numba) FEM kernels made ready before long work uses them, with progress.
- ``locate``: Point location in simplex meshes and closest points on their boundary.
- ``mesh_data``: Boundary data on a mesh file: the half-space answer where it applies, else the FEM, refused where too coarse.
- ``operators``: Finite-element CW diffusion on linear triangles (2D) and tetrahedra (3D).
- ``ordering``: Fill-reducing ordering of FEM matrices from the node coordinates.
- ``pardiso``: MKL PARDISO through ctypes: sparse Cholesky for the diffusion operators.
- ``resolution``: The FEM's discretisation error, estimated from measured tables: the resolution guard.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "assembly_kernels": ["upper_pattern", "element_gradients", "upper_values"],
    "forward": ["triple_product_jacobian", "mua_jacobian", "FluorescenceModel", "safe_log"],
    "halfspace": ["half_space_check", "half_space_excitation_data"],
    "jacobian_kernels": ["node_elements", "pair_jacobian"],
    "kernels": ["prepare_kernels"],
    "locate": ["barycentric", "PointLocator", "locator", "BoundaryLocator", "boundary_locator"],
    "mesh_data": ["read_forward_mesh", "read_points", "check_optodes", "half_space_data",
                  "fem_data", "mesh_boundary_data"],
    "operators": ["SOLVERS", "check_solver", "geometry", "symmetric_from_upper", "weighted_mass", "stiffness", "MeshResolutionWarning", "DiffusionOperator", "snap_to_surface", "source_positions", "point_source_rhs", "detector_operator"],
    "ordering": ["geometric_nested_dissection"],
    "pardiso": ["mkl_pardiso", "PardisoPattern", "PardisoCholesky"],
    "resolution": ["element_sizes", "log_error_estimate", "required_size", "pair_sizes"],
})
