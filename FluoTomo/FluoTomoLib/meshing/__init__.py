"""Meshes: the simplex ``Mesh``, structured and voxel meshers, the fTetWild quality mesher,
quality reports, and VTU / NIRFAST file I/O.

Modules
-------
- ``mesh``: The simplex mesh shared by meshing, FEM and reconstruction.
- ``nirfast_io``: NIRFAST mesh files: ``.node``, ``.elem``, ``.region``, ``.param``.
- ``shares``: Analytic shapes on a mesh: each node's share of a target given as a function.
- ``report``: Quality report of a tetrahedral mesh: counts, region volumes, angles, bad elements.
- ``structured``: Structured simplex meshes: rectangles into triangles, boxes into tetrahedra.
- ``to_file``: A label map to a tetrahedral mesh file with its quality report.
- ``tetwild``: Quality tetrahedral meshing of a label map with fTetWild (pytetwild).
- ``voxel``: Fast structured meshing of a label map: voxels to tetrahedra.
- ``vtu_io``: Meshes to and from VTK: .vtu files, unstructured grids and surface polydata.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "mesh": ["Mesh"],
    "nirfast_io": ["write_nirfast", "read_nirfast", "write_optodes", "read_optodes"],
    "report": ["dihedral_angles_deg", "aspect_ratio", "quality_report"],
    "shares": ["analytic_fractions", "simplex_points"],
    "structured": ["graded_axis", "optode_axis", "rectangle_mesh", "kuhn_paths", "box_mesh", "slab_mesh"],
    "to_file": ["optode_edges", "mesh_to_file"],
    "tetwild": ["labelmap_volumes", "labelmap_surface", "decimate_surface", "mesh_labelmap_quality"],
    "voxel": ["mesh_labelmap_structured", "labelmap_region_volumes", "node_labels_from_labelmap", "nodal_volumes", "node_regions_volume_preserving", "region_centroid_mm", "target_refinement", "cell_region_shares"],
    "vtu_io": ["to_vtk", "from_vtk", "write_vtu", "read_vtu", "read_mesh", "boundary_polydata"],
})
