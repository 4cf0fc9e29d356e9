"""FluoGuide's foundation: what the three module Libs stand on.

Errors (``errors``), progress and cancellation (``progress``; ``kernels``: numba
kernels compiled before long work, reporting), MRML scene I/O and
conventions (``mrml_io``, ``slicer_compat``), JSON of results (``jsonable``), lazy
public ``__init__`` files (``lazy``), digital phantoms (``phantoms``, ``voxelize``,
``optics_table``). It imports no module Lib and nothing of the application
(``fluoapp``): a Slicer build ships it without the web stack.
"""

__version__ = "0.1.0"
