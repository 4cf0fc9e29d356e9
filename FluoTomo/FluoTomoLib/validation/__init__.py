"""The label-map tomography graded on a seeded scene family it was not tuned on
(issue #31; docs/validation.md, "The scene family").

Modules
-------
- ``family``: the seeded scene generator (bodies, inclusions, directions, voxels,
  optics, noise, segmentation errors) with each scene's truth, and its simulation
  on the true label map with the simulation's own finer mesh.
- ``grade``: one scene reconstructed and graded: yield error, centroid error,
  the stated interval and whether it holds the truth, the warnings; the family's
  table (median, 90th percentile, worst, coverage).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "family": ["Scene", "make_scene", "simulate", "BODY_LABEL", "INCLUSION_LABELS"],
    "grade": ["grade_scene", "summarise"],
})
