"""The structured meshes model the tissue the label map holds, whatever the
element size (issue #31: "the error follows the forward model's
discretisation error, not the level's promise").

Two faults measured on the scene family and kept out here:

- **Cavities.** A small region's volume matching released rim cells that the
  region sharing them did not claim: holes inside the tissue, whose faces the
  model took for skin (a Robin boundary 7 mm deep). On family scene 3 the
  excitation at its inclusion fell 12 % between 0.75 and 0.7 mm elements, and
  the fluorescence data 25 %; 3 of 12 reconstruction meshes of scenes 3, 5 and
  8 had 2-8 boundary surfaces.
- **Staircase skin.** Fitting the tissue-air nodes onto the smooth surface held
  back nearly every node of a tilted plane (a step's convex corner tetrahedron,
  all four corners on the surface, is flattened by any fit), leaving each
  optode's coupling 4-11 % off the exact half-space solution.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from FluoTomoLib.analytic import robin_surface_fluence
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.fem.operators import detector_operator
from FluoTomoLib.tomography import LabelMap
from FluoTomoLib.tomography.model import reconstruction_mesh
from FluoTomoLib.tomography.simulate import default_scan
from FluoTomoLib.validation import make_scene


def _boundary_surfaces(mesh):
    """Connected pieces of the mesh's boundary: 1 for a body without cavities."""
    f = mesh.boundary_facets
    rows = np.repeat(np.arange(len(f)), f.shape[1])
    a = sp.csr_matrix((np.ones(f.size), (f.ravel(), rows)), shape=(mesh.n_nodes, len(f)))
    return connected_components((a.T @ a) > 0, directed=False)[0]


@pytest.mark.parametrize("seed, size_mm", [(3, 0.75), (3, 0.7), (5, 0.65)])
def test_no_cavity_inside_the_tissue(seed, size_mm):
    """The cases that had 2, 7 and 8 boundary surfaces; the smaller regions keep
    their volumes (the cells go to the largest region)."""
    sc = make_scene(seed)
    lm = sc.labelmap()
    s, d, _ = default_scan(lm, sc.target())
    opt = lm.to_local(np.vstack([s, d]))
    mesh = reconstruction_mesh(lm.labels_kji, lm.spacing_mm, size_mm, None, sc.target(), 0.5,
                               optodes=opt, optode_normals=lm.surface().closest(opt)[1],
                               burial_mm=0.9)
    assert _boundary_surfaces(mesh) == 1
    for label, err in mesh.meta["volume_error_pct"].items():
        assert abs(err) < 1.0, (label, err)


def test_the_fit_reaches_a_tilted_skin():
    """A half-space whose skin is tilted 25 degrees off the grid: after the fit
    each source's data are the exact solution's within 6 % (measured 1-4 %
    high, as on a flat grid-aligned skin; before: 5-11 % low)."""
    mua, musp, n, sp_mm = 0.01, 1.0, 1.37, 0.5
    theta = np.deg2rad(25.0)
    k, j, i = np.indices((44, 80, 80))
    x, z = (i + 0.5) * sp_mm, (k + 0.5) * sp_mm
    nrm = np.array([-np.sin(theta), 0.0, np.cos(theta)])        # the skin's outward normal
    lab = (((x - 20.0) * nrm[0] + (z - 12.0) * nrm[2]) < 0).astype(np.uint8)
    lm = LabelMap(lab, np.array([sp_mm] * 3), np.zeros(3), np.eye(3))
    surf = lm.surface()
    u, v = np.array([np.cos(theta), 0.0, np.sin(theta)]), np.array([0.0, 1.0, 0.0])
    centre = np.array([20.0, 20.0, 12.0])
    rng = np.random.default_rng(1)
    src = surf.closest(np.array([centre + a * u + b * v
                                 for a, b in rng.uniform(-2, 2, (4, 2))]))[0]
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    det = surf.closest(np.array([s + r * (np.cos(a) * u + np.sin(a) * v) for s in src
                                 for r in (3.0, 4.5, 6.0) for a in ang]))[0]
    opt = np.vstack([src, det])
    mesh = reconstruction_mesh(lab, lm.spacing_mm, 0.9, None, None, None, surface=surf,
                               optodes=opt, optode_normals=surf.closest(opt)[1],
                               burial_mm=1 / (mua + musp))
    fit = mesh.meta["surface_fit_mm"]
    assert fit["held_back"] < 0.15 * fit["nodes"] and fit["corner_elements_cut"] > 0
    props = {"mua_per_mm": mua, "musp_per_mm": musp, "n": n}
    model = FluorescenceModel(mesh, props, props, src, det[:1],
                              source_normals=surf.closest(src)[1], lean=True)
    fem = detector_operator(mesh, det, 5.0) @ model.phi_x
    per = len(det) // len(src)
    for s in range(len(src)):
        rows = slice(s * per, (s + 1) * per)
        rho = np.linalg.norm(det[rows] - src[s], axis=1)
        ratio = fem[rows, s] / robin_surface_fluence(rho, mua, musp, n)
        assert abs(np.median(ratio) - 1.0) < 0.06, (s, np.median(ratio))
        # single detectors: on facets of the fitted surface, within +-10 % for
        # four in five (measured 0.96-1.08) and +-20 % for all (0.91-1.15)
        assert np.all(np.abs(np.percentile(ratio, [10, 90]) - 1.0) < 0.10), ratio
        assert np.all(np.abs(ratio - 1.0) < 0.20), (s, ratio.min(), ratio.max())
