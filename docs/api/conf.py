"""Sphinx configuration of FluoGuide's API reference (``make docs``).

Built from the docstrings with autodoc and napoleon (numpy style) only: no
extension that needs the network. ``sphinx-build -W`` (CI, and
Testing/Python/test_api_reference.py) turns every warning into an error.
"""

import os
import sys

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
# the checkout first, then the module folders (FluoTomo/FluoTomo.py, ...), as in
# Slicer and pyproject.toml's pytest ``pythonpath``
for folder in ("FluoTomo", "FluoNav", "FluoCalib", ""):
    sys.path.insert(0, os.path.join(ROOT, folder))
# the numerical libraries on one thread while the modules import (numba, BLAS)
for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

project = "FluoGuide"
author = "FluoGuide contributors"
copyright = "FluoGuide contributors, BSD-3-Clause"
release = version = "0.1.0"

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon"]

napoleon_google_docstring = False
napoleon_numpy_docstring = True
# Types as plain text, as numpydoc renders them: the project's types carry shapes and
# units ("(K, J, I) int array", "(3,) [mm]"), and Sphinx would cross-reference each
# word of them, linking shape letters to unrelated attributes (K -> CameraModel.K).
# Attributes sections are laid out as Parameters are, for the same reason (napoleon's
# own ``.. attribute::`` entries cross-reference their types too).
napoleon_use_param = False
napoleon_custom_sections = [("Attributes", "params_style")]
napoleon_use_rtype = False

autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"members": True}

html_theme = "alabaster"
html_static_path = []
exclude_patterns = ["_build"]
