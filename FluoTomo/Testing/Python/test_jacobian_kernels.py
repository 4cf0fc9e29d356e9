"""Compiled Jacobian assembly against a brute-force sum, and the 3D mua Jacobian
against finite differences (the 2D one is in test_fem_core)."""

from itertools import product
from math import factorial

import numpy as np
import pytest

from FluoTomoLib.fem.operators import geometry
from FluoTomoLib.fem.jacobian_kernels import pair_jacobian
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.meshing.structured import box_mesh, rectangle_mesh


def _brute(mesh, F, G, c):
    """Element by element, node by node, pair by pair: the definition."""
    geo = geometry(mesh)
    d = mesh.dim
    nl = d + 1
    out = np.zeros((mesh.n_nodes, F.shape[1], G.shape[1]))
    for e, nodes in enumerate(mesh.elements):
        vol = geo.vol[e]
        for a, k in enumerate(nodes):
            for i, j in product(range(nl), range(nl)):
                # integral of phi_i phi_j phi_k over a simplex: |e| d! prod(m!) / (d + 3)!
                m = np.bincount([i, j, a], minlength=nl)
                tri = vol * factorial(d) * np.prod([factorial(x) for x in m]) / factorial(d + 3)
                out[k] += tri * np.outer(F[nodes[i]], G[nodes[j]])
            gF = geo.grad[e].T @ F[nodes]               # (d, S)
            gG = geo.grad[e].T @ G[nodes]
            out[k] += c[k] * vol / nl * (gF.T @ gG)
    return out


@pytest.mark.parametrize("dim, S, D", [(2, 3, 2), (3, 3, 4), (3, 1, 5), (3, 5, 1)])
def test_pair_jacobian_matches_definition(dim, S, D):
    rng = np.random.default_rng(dim * 10 + S)
    if dim == 2:
        m = rectangle_mesh(np.linspace(0, 3, 4), np.linspace(0, 2, 3))
    else:
        m = box_mesh(np.linspace(0, 2, 3), np.linspace(0, 1, 2), np.linspace(0, 1.5, 3))
    # jitter the interior-free structured nodes so elements differ in shape
    m.nodes_mm[:] += rng.uniform(-0.05, 0.05, m.nodes_mm.shape)
    m.meta.pop("_fem_geometry", None)
    F = rng.normal(size=(m.n_nodes, S))
    G = rng.normal(size=(m.n_nodes, D))
    c = rng.uniform(0.5, 2.0, m.n_nodes)
    geo = geometry(m)
    ref = _brute(m, F, G, c)
    got = pair_jacobian(m.elements, geo.vol * geo.c3, F, G, grad=geo.grad,
                        grad_weight=geo.vol / (dim + 1), node_coef=c)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    plain = pair_jacobian(m.elements, geo.vol * geo.c3, F, G)
    np.testing.assert_allclose(plain, _brute(m, F, G, np.zeros(m.n_nodes)), rtol=1e-12,
                               atol=1e-12 * np.abs(ref).max())


def test_mua_jacobian_3d_matches_finite_difference():
    m = box_mesh(np.linspace(-6, 6, 13), np.linspace(-6, 6, 13), np.linspace(-5, 0, 6))
    px = dict(mua_per_mm=0.02, musp_per_mm=1.0, n=1.37)
    src = [[-3.0, 0.0, 0.0], [2.0, 1.0, 0.0]]
    det = [[3.0, 0.0, 0.0], [0.0, -3.0, 0.0], [-1.0, 3.0, 0.0]]
    fm = FluorescenceModel(m, px, px, src, det)
    J = fm.jacobian_mua_x()
    assert J.shape == (6, m.n_nodes)
    k = int(np.argmin(np.linalg.norm(m.nodes_mm - [0.0, 0.0, -2.0], axis=1)))
    h = 1e-6
    mua = np.full(m.n_nodes, 0.02)
    mua[k] += h
    fm2 = FluorescenceModel(m, dict(px, mua_per_mm=mua), px, src, det)
    fd = (fm2.excitation_data() - fm.excitation_data()).ravel() / h
    np.testing.assert_allclose(J[:, k], fd, rtol=1e-3)
    assert np.all(J[:, k] < 0)          # more absorption, less light everywhere
