"""Compiled assembly (pattern, gradients, values), the few-point locator and the
PARDISO binding, each against an independent reference."""

from math import factorial

import numpy as np
import pytest
import scipy.sparse as sp

from fluoguide.errors import FluoInputError
from FluoTomoLib.fem.assembly_kernels import element_gradients, upper_pattern, upper_values
from FluoTomoLib.fem.operators import geometry
from FluoTomoLib.fem.jacobian_kernels import node_elements
from FluoTomoLib.fem.locate import PointLocator
from FluoTomoLib.meshing.mesh import Mesh
from FluoTomoLib.fem.pardiso import PardisoCholesky, mkl_pardiso
from FluoTomoLib.meshing.structured import box_mesh, rectangle_mesh


def _jittered(dim, seed=0):
    rng = np.random.default_rng(seed)
    if dim == 2:
        m = rectangle_mesh(np.linspace(0, 4, 5), np.linspace(0, 3, 4))
    else:
        m = box_mesh(np.linspace(0, 3, 4), np.linspace(0, 2, 3), np.linspace(0, 2, 3))
    nodes = m.nodes_mm + rng.uniform(-0.1, 0.1, m.nodes_mm.shape)
    return Mesh(nodes, m.elements)


@pytest.mark.parametrize("dim", [2, 3])
def test_gradients_reproduce_linear_functions(dim):
    m = _jittered(dim)
    grad, vol = element_gradients(m.nodes_mm, m.elements)
    np.testing.assert_allclose(vol, m.signed_measures, rtol=1e-12)
    # sum_k x_k grad(phi_k)^T = I for P1 basis functions
    X = np.einsum("ekx,eky->exy", m.nodes_mm[m.elements], grad)
    np.testing.assert_allclose(X, np.broadcast_to(np.eye(dim), X.shape), atol=1e-12)
    np.testing.assert_allclose(grad.sum(axis=1), 0, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_upper_triangle_matches_dense_element_assembly(dim):
    m = _jittered(dim, seed=dim)
    rng = np.random.default_rng(5)
    D = rng.uniform(0.2, 0.5, m.n_nodes)
    w = rng.uniform(0.0, 0.1, m.n_nodes)
    # reference: dense, element by element, from the definitions
    ref = np.zeros((m.n_nodes, m.n_nodes))
    nl = dim + 1
    for e, nodes in enumerate(m.elements):
        p = m.nodes_mm[nodes]
        T = np.linalg.inv((p[1:] - p[0]).T)                 # rows: grad xi_1..d
        g = np.vstack([-T.sum(axis=0), T])
        vol = abs(np.linalg.det((p[1:] - p[0]).T)) / factorial(dim)
        K = vol * D[nodes].mean() * g @ g.T
        Mm = np.zeros((nl, nl))
        for a in range(nl):
            for b in range(nl):
                for c in range(nl):
                    mult = np.bincount([a, b, c], minlength=nl)
                    Mm[a, b] += w[nodes[c]] * vol * factorial(dim) * np.prod(
                        [factorial(x) for x in mult]) / factorial(dim + 3)
        ref[np.ix_(nodes, nodes)] += K + Mm
    start, n2e = node_elements(m.elements, m.n_nodes)
    indptr, indices, pos, diag = upper_pattern(m.elements, m.n_nodes, start, n2e)
    U = sp.csr_matrix((upper_values(m.elements, pos, *element_gradients(m.nodes_mm, m.elements)[:1],
                                    m.measures, factorial(dim) / factorial(dim + 3), D, w,
                                    len(indices)), indices, indptr), shape=ref.shape)
    np.testing.assert_allclose(U.toarray(), np.triu(ref), atol=1e-14)
    assert np.all(np.diff(indices[indptr[0]:indptr[1]]) > 0)          # sorted rows
    assert np.all(indices[diag] == np.arange(m.n_nodes))
    # the pattern is exactly the coupled pairs: no stored zeros beyond them
    assert U.nnz == np.count_nonzero(np.triu(np.abs(ref) > 0))


def test_few_point_scan_agrees_with_kd_tree():
    m = _jittered(3, seed=7)
    rng = np.random.default_rng(2)
    lo, hi = m.bounds()
    pts = np.vstack([rng.uniform(lo, hi, (30, 3)), m.nodes_mm[:3], [hi + 1.0]])
    scan = PointLocator(m).locate(pts)
    tree = PointLocator(m, scan_max=0).locate(pts)
    np.testing.assert_array_equal(scan[0] < 0, tree[0] < 0)
    inside = scan[0] >= 0
    assert scan[0][-1] == -1                              # the point beyond the box
    for elem, bary in (scan, tree):                       # both reproduce the point
        x = np.einsum("pk,pkd->pd", bary[inside], m.nodes_mm[m.elements[elem[inside]]])
        np.testing.assert_allclose(x, pts[inside], atol=1e-12)
        assert np.all(bary[inside] >= -1e-9)


@pytest.mark.skipif(mkl_pardiso() is None, reason="MKL cannot be loaded here")
def test_pardiso_binding_solves_and_reports_indefinite_matrices():
    m = _jittered(3, seed=3)
    g = geometry(m)
    U = g.upper(np.full(m.n_nodes, 0.3), np.full(m.n_nodes, 0.01), g.boundary_weight() / 4)
    K = (U + sp.triu(U, 1).T).toarray()
    B = np.random.default_rng(0).normal(size=(m.n_nodes, 3))
    chol = PardisoCholesky(U, name="test.K")
    np.testing.assert_allclose(chol.solve(B), np.linalg.solve(K, B), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(chol.solve(B[:, 0]), np.linalg.solve(K, B[:, 0]), rtol=1e-10)
    with pytest.raises(FluoInputError, match="test.K.*rows"):
        chol.solve(B[:-1])
    chol.release()
    chol.release()                                        # twice is harmless
    neg = sp.csr_matrix(-U.toarray())                     # negative definite
    neg = sp.triu(neg, format="csr")
    neg.sort_indices()
    with pytest.raises(FluoInputError, match="not positive definite"):
        PardisoCholesky(neg, name="negated")


@pytest.mark.skipif(mkl_pardiso() is None, reason="MKL cannot be loaded here")
def test_operators_of_one_mesh_share_the_analysis():
    from FluoTomoLib.fem.operators import DiffusionOperator

    m = _jittered(3, seed=4)
    b = np.zeros(m.n_nodes)
    b[m.n_nodes // 2] = 1.0
    ops = [DiffusionOperator(m, 0.01 * (k + 1), 1.0, 1.37).factorize() for k in range(6)]
    pattern = ops[0]._solve.pattern
    shared = [op._solve.pattern is pattern for op in ops]
    assert shared == [True] * 4 + [False] * 2         # 4 slots, then handles of their own
    for op in ops:                                    # every factor is its own matrix's
        np.testing.assert_allclose(op.K @ op.solve(b), b, atol=1e-12)
    del ops[:4]
    assert sorted(pattern._free) == [1, 2, 3, 4]      # slots come back with the operators
    again = DiffusionOperator(m, 0.03, 1.0, 1.37).factorize()
    assert again._solve.pattern is pattern


def test_geometric_ordering_is_a_permutation_with_metis_like_fill():
    from FluoTomoLib.fem.ordering import geometric_nested_dissection

    m = box_mesh(np.linspace(0, 20, 21), np.linspace(0, 20, 21), np.linspace(-10, 0, 11))
    g = geometry(m)
    order = geometric_nested_dissection(m.nodes_mm, g.indptr, g.indices, leaf=16)
    assert np.array_equal(np.sort(order), np.arange(m.n_nodes))
    if mkl_pardiso() is None:
        return
    from FluoTomoLib.fem.operators import DiffusionOperator

    op = DiffusionOperator(m, 0.01, 1.0, 1.37).factorize()
    assert op._solve.pattern.ordering == "user"         # grid meshes: geometric ordering
    b = np.zeros(m.n_nodes)
    b[123] = 1.0
    np.testing.assert_allclose(op.K @ op.solve(b), b, atol=1e-12)
    # the fill PARDISO reports for both orderings (iparm(18) = -1 asks for it)
    fills = {}
    for name, ordr in (("geometric", order), ("metis", None)):
        from FluoTomoLib.fem.pardiso import PardisoPattern

        pat = PardisoPattern(g.indptr, g.indices, slots=1, order=ordr)
        pat.iparm[17] = -1
        pat.factor(op.K_upper.data, "test")
        fills[name] = int(pat.iparm[17])
    assert fills["geometric"] < 1.25 * fills["metis"]
