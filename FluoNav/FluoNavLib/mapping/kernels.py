"""The compiled (numba) surface-mapping kernels made ready before long work uses them,
with progress.

The ray caster (``rasterize.py``: moving the mesh into the camera frame,
projecting, rasterising, resolving each pixel's ray) and the illumination cone
(``illumination_kernel.py``) are numba kernels kept in numba's on-disk cache
(``cache=True``). On a first run (an empty cache) they compile for 14-16 s (2
cores) inside whatever step first casts a frame, and that step reports nothing
meanwhile. :func:`prepare_kernels` compiles (or loads from the cache) every one
for the argument types the mapping code calls it with, reporting the seconds
it has run (``fluoguide.kernels.prepare``: the FEM kernels of FluoTomo go
through it too); the logic's long jobs call it first.

The signatures come from :func:`_examples`: tiny arrays of the dtypes,
dimensions, layouts and writeability the call sites pass (``raster_cast``,
``cone_factors_from_cast``). The pixel rays are read-only (the camera shares
its cached rays), so their examples are too: a writable array would be another
signature, compiled again at the first real cast. The kernels declared
``inline="always"`` are compiled into their callers, and ``_raster_tessellated``
with ``_rasterise``, which calls it: none is called from Python.
``FluoNav/Testing/Python/test_mapping_kernels.py`` checks that a cast and an
illumination model after :func:`prepare_kernels` compile nothing more.
"""

from __future__ import annotations

import numpy as np

from fluoguide import kernels as _kernels

__all__ = ["prepare_kernels"]

#: the kernels' name in the reports ("compiling the surface-mapping kernels (first run only)")
WHAT = "surface-mapping kernels"


def _examples():
    """[(dispatcher, example arguments)] of every surface-mapping kernel called from
    Python, with the argument types (dtype, dimensions, layout, writeability) of
    its call site."""
    from FluoNavLib.mapping import illumination_kernel as ik
    from FluoNavLib.mapping import rasterize as rz

    f2 = np.zeros((1, 3))                   # float64 (N, 3), C order: points, buffers
    f1 = np.zeros(1)                        # float64 (N,): plane offsets, buffers, vectors
    tris = np.zeros((1, 3), np.int64)       # SurfaceCaster.triangles
    i32 = np.zeros(1, np.int32)             # RayGrid cells, face buffers, face ids
    u8 = np.zeros(1, np.uint8)              # reason codes
    b1 = np.zeros(1, np.bool_)              # valid faces, visible / lit masks
    rays = np.zeros((1, 3))                 # CameraModel.pixel_grid_rays: read-only
    rays.setflags(write=False)
    x = 1.0                                 # a Python float: numba's float64
    n = 1                                   # a Python int: numba's int64
    flag = True                             # a Python bool: numba's boolean
    outs = (i32, f1, f1, u8, b1)            # face, distance, cosine, reason, visible
    return [
        (rz._to_camera, (f2, f2, tris, f2, f1, f2, f2, f1)),
        (rz._project, (f2, x, x, x, x, x, f2)),
        (rz._project_pixels, (f2, x, f1, f2)),
        (rz._rasterise, (f2, f2, tris, b1, x, x, x, x, n, n, x, i32, f1, n, flag, f2, n, n,
                         i32, f1, f1)),
        (rz._resolve, (i32, rays, f2, tris, f2, f1, i32, n, n, flag, x, *outs)),
        (rz._resolve_pixels, (i32, rays, f2, tris, f2, i32, n, n, i32, n, n, x, *outs)),
        (ik._cone_kernel, (rays, f2, f1, i32, f1, b1, f2, f2, f1, f1, f1, x, x, x, flag, f1,
                           f1, x, x, f1, f1, f1, b1)),
    ]


#: this Lib's kernels (fluoguide.kernels.KernelSet)
KERNELS = _kernels.KernelSet(_examples, WHAT)
#: [(dispatcher, signature)] not compiled in this process yet
missing = KERNELS.missing
#: compile (or load from numba's cache) the kernels not ready in this process, with
#: progress: ``prepare_kernels(progress=None, fraction=0.0, cancel=None, every_s=None)``
#: -> seconds spent (fluoguide.kernels.KernelSet.prepare)
prepare_kernels = KERNELS.prepare
