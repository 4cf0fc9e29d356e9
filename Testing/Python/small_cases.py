"""Small inputs that several test files share (issue #29: one of each, built once).

- :data:`SMALL_TUBE`: the demo's tube case at coarser settings (a 1.2 mm
  simulation mesh, six sources: about 25 s and 2.3 GB a depth, against 105 s
  and 9.7 GB for a quick-demo depth), for tests of the demo's machinery rather
  than of its accuracy.
- :func:`write_own_scene`: a user's own label map unlike the tube: an
  ellipsoidal body with a spherical inclusion under its curved top, labels 3
  and 7, anisotropic voxels, direction diag(-1, -1, 1), the origin far from
  zero; with its ``optics.json``. The ``own_scene`` fixture (conftest.py) adds
  an acquisition simulated from it at the ``fast`` level.
"""

from __future__ import annotations

import json
from pathlib import Path

SMALL_TUBE = {"fine_mm": 1.2, "simulate_coarse_mm": 3.0, "n_sources": 6, "accuracy": "fast",
              "coarse_mm": 2.0}

# the own scene's geometry (fluoguide.phantoms.ellipsoid_inclusion_labelmap's options)
OWN_SCENE = {"semi_axes_mm": (14.0, 12.0, 8.0), "spacing_mm": (0.8, 0.9, 1.0),
             "inclusion_gap_mm": 2.5, "inclusion_offset_mm": (1.0, -1.0)}
TRUE_YIELD = 2.6e-3          # label 7; 2 ug/mL ICG (its absorption is in the simulation)


def write_scene(folder, **options):
    """``labels.nrrd`` and ``optics.json`` of an ellipsoid-inclusion scene
    (``fluoguide.phantoms.ellipsoid_inclusion_labelmap(**options)``, its
    defaults where none are given) in ``folder``; returns its scene dict (truth
    included)."""
    from fluoguide.labelmap_io import write_volume_nrrd
    from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sc = ellipsoid_inclusion_labelmap(**options)
    write_volume_nrrd(folder / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"],
                      sc["origin_mm"], sc["direction"])
    (folder / "optics.json").write_text(json.dumps(ellipsoid_inclusion_optics(), indent=1))
    return sc


def write_own_scene(folder):
    """The shared own scene (:data:`OWN_SCENE`) in ``folder``: :func:`write_scene`."""
    return write_scene(folder, **OWN_SCENE)
