"""The compiled (numba) FEM kernels made ready before long work uses them, with progress.

numba compiles a kernel on its first call with new argument types. The kernels
keep their machine code in numba's on-disk cache (``cache=True``), so this
happens once per installation (and per numba version), but then it takes
11-14 s (the parallel Jacobian kernel most of it) inside whatever step first
calls a kernel, and that step reports nothing meanwhile.
:func:`prepare_kernels` compiles (or loads from the cache) every kernel for the
argument types the FEM code calls it with, on a helper thread, while the
caller's thread says what it is doing and how long it has run, every
``every_s`` seconds, and honours a cancel (``fluoguide.kernels.prepare``, which
FluoNav's surface-mapping kernels use too).

The signatures come from :func:`_examples`: tiny arrays of the dtypes the call
sites pass (``Testing/Python/test_jobs.py``'s slow reconstruction test checks that a
simulation and a reconstruction after it compile nothing more).
"""

from __future__ import annotations

import numpy as np

from fluoguide import kernels as _kernels

#: the kernels' name in the reports ("compiling the FEM kernels (first run only)")
WHAT = "FEM kernels"


def _examples():
    """[(dispatcher, example arguments)] of every FEM kernel, with the argument
    types (dtype, dimensions, layout) of its call sites."""
    from FluoTomoLib.fem import assembly_kernels as ak
    from FluoTomoLib.fem import jacobian_kernels as jk
    from FluoTomoLib.fem import locate, ordering
    from FluoTomoLib.meshing import mesh, voxel

    f2 = np.zeros((1, 3))                   # float64 (N, d), C order
    f1 = np.zeros(1)
    i64_2 = np.zeros((1, 4), np.int64)      # Mesh.elements
    i32_2 = np.zeros((1, 4), np.int32)      # operators' element indices
    i64_1 = np.zeros(1, np.int64)
    i32_1 = np.zeros(1, np.int32)
    n = 1                                   # a Python int: numba's int64
    return [
        (mesh._signed_measures, (f2, i64_2)),
        (mesh._facet_codes, (i64_2, n)),
        (locate._scan_locate, (f2, i64_2, f2, 1e-9)),
        (locate._first_containing, (f2, i64_2, f2, i64_2, 1e-9)),
        (locate._grid_locate, (f2, i64_2, f1, f1, i64_1, np.zeros(1, bool), 1e-9)),
        (voxel.cell_region_shares, (np.zeros((1, 1, 1), np.int32), f1, f1, f2, f2, n, n)),
        (ak.element_gradients, (f2, i32_2)),
        (jk.node_elements, (i32_2, n)),
        (ak.upper_pattern, (i32_2, n, i64_1, i32_1)),
        (ak.upper_values, (i32_2, i32_2, np.zeros((1, 4, 3)), f1, 1.0, f1, f1, n)),
        (ordering._full_adjacency, (i32_1, i32_1, n)),
        (ordering._nested_dissection, (f2, i64_1, i32_1, n)),
        (jk._jacobian_by_node, (i32_2, i64_1, i32_1, f1, np.zeros((1, 4, 3)), f1, f1, f2, f2,
                                np.zeros((1, 3, 3)), n, True)),
    ]


#: this Lib's kernels (fluoguide.kernels.KernelSet)
KERNELS = _kernels.KernelSet(_examples, WHAT)
#: [(dispatcher, signature)] not compiled in this process yet
missing = KERNELS.missing
#: compile (or load from numba's cache) the kernels not ready in this process, with
#: progress: ``prepare_kernels(progress=None, fraction=0.0, cancel=None, every_s=None)``
#: -> seconds spent (fluoguide.kernels.KernelSet.prepare)
prepare_kernels = KERNELS.prepare
