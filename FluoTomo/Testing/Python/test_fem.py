"""FEM assembly, solver, sources and detectors on triangles and tetrahedra."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.special import k0

from fluoguide.errors import FluoInputError
from FluoTomoLib.fem.operators import (
    DiffusionOperator,
    detector_operator,
    geometry,
    point_source_rhs,
    source_positions,
    stiffness,
    weighted_mass,
)
from FluoTomoLib.optics import diffusion_coefficient, mueff, robin_A
from FluoTomoLib.meshing.structured import (
    box_mesh,
    graded_axis,
    rectangle_mesh,
    slab_mesh,
)


def _rect():
    return rectangle_mesh(np.linspace(-10, 10, 21), np.linspace(-6, 0, 13))


def _box():
    return box_mesh(np.linspace(0, 4, 5), np.linspace(0, 3, 4), np.linspace(-2, 0, 5))


@pytest.mark.parametrize("make, measure", [(_rect, 20 * 6), (_box, 4 * 3 * 2)])
def test_assembly_integrates_exactly(make, measure):
    m = make()
    ones = np.ones(m.n_nodes)
    # stiffness annihilates constants and is symmetric positive semi-definite
    Kd = stiffness(m, 0.3)
    np.testing.assert_allclose(Kd @ ones, 0, atol=1e-12)
    assert abs(Kd - Kd.T).max() < 1e-12
    # weighted mass integrates products of P1 functions exactly
    assert ones @ weighted_mass(m, ones) @ ones == pytest.approx(measure)
    x = m.nodes_mm[:, 0]
    # integral of x over the domain: measure * centroid_x
    assert ones @ weighted_mass(m, x) @ ones == pytest.approx(measure * x.mean(), abs=1e-9)
    # stiffness reproduces the Dirichlet energy of a linear field: D |grad|^2 * measure
    assert x @ Kd @ x == pytest.approx(0.3 * measure)
    # boundary mass sums to the perimeter / surface area
    g = geometry(m)
    span = np.ptp(m.nodes_mm, axis=0)
    area = 2 * span.sum() if m.dim == 2 else 2 * (span[0] * span[1] + span[1] * span[2]
                                                  + span[0] * span[2])
    assert ones @ g.boundary_mass @ ones == pytest.approx(area)


def test_structured_meshes_are_conforming():
    m = slab_mesh(20.0, 10.0, 2.0, fine_mm=0.5, fine_until_mm=2.0)
    assert m.dim == 3 and np.all(m.signed_measures > 0)
    assert m.measures.sum() == pytest.approx(20 * 20 * 10)
    # a conforming box has exactly its six faces as boundary
    assert m.boundary_facet_measures.sum() == pytest.approx(2 * (400 + 2 * 200))
    z = graded_axis(-10, 0, 0.5, 2.0, 2.0)
    assert z[0] == -10 and z[-1] == 0 and np.all(np.diff(z) > 0)
    assert np.diff(z)[-1] == pytest.approx(0.5)
    r = _rect()
    assert np.all(r.signed_measures > 0) and r.measures.sum() == pytest.approx(120)


def test_system_matrix_and_solver_reuse():
    m = _rect()
    op = DiffusionOperator(m, 0.02, 1.0, 1.4)
    assert sp.isspmatrix_csc(op.K) or op.K.format == "csc"
    assert abs(op.K - op.K.T).max() < 1e-14
    assert op.A == pytest.approx(robin_A(1.4))
    np.testing.assert_allclose(op.D, diffusion_coefficient(0.02, 1.0))
    b = np.zeros(m.n_nodes)
    b[m.n_nodes // 2] = 1.0
    x1 = op.solve(b)
    factor = op._solve
    X = op.solve(np.column_stack([b, 2 * b]))
    assert op._solve is factor, "the factorisation must be reused"
    assert op.solver_name in ("pardiso", "superlu")
    np.testing.assert_allclose(op.K @ x1, b, atol=1e-12)
    np.testing.assert_allclose(X[:, 1], 2 * x1, rtol=1e-10)
    assert op.n_solves == 3
    # every solver answers the same system
    ref = DiffusionOperator(m, 0.02, 1.0, 1.4, solver="splu").solve(b)
    np.testing.assert_allclose(x1, ref, rtol=1e-8)
    assert DiffusionOperator(m, 0.02, 1.0, 1.4, solver="splu").factorize().solver_name == "superlu"
    with pytest.raises(FluoInputError, match="solver"):
        DiffusionOperator(m, 0.02, 1.0, 1.4, solver="magic").solve(b)


def test_point_source_2d_matches_infinite_medium_green_function():
    """Far from every boundary the 2D fluence is K0(mueff r) / (2 pi D)."""
    mua, musp = 0.05, 1.0
    x = np.linspace(-25, 25, 201)
    m = rectangle_mesh(x, x)
    op = DiffusionOperator(m, mua, musp, 1.33)
    phi = op.solve(point_source_rhs(m, [[0.0, 0.0]]))[:, 0]
    r = np.linalg.norm(m.nodes_mm, axis=1)
    sel = (r > 2) & (r < 12)
    exact = k0(mueff(mua, musp) * r[sel]) / (2 * np.pi * diffusion_coefficient(mua, musp))
    assert np.max(np.abs(phi[sel] / exact - 1)) < 0.01


def test_sources_are_buried_along_the_inward_normal():
    m = _rect()
    mua, musp = 0.02, 0.98
    pos = source_positions(m, [[1.3, 0.4], [-10.2, -3.0]], musp, mua)
    np.testing.assert_allclose(pos[0], [1.3, -1.0], atol=1e-12)       # top face, down
    np.testing.assert_allclose(pos[1], [-9.0, -3.0], atol=1e-12)      # left face, right
    b = _box()
    nodal_musp = np.full(b.n_nodes, 1.9)
    pos3 = source_positions(b, [[2.0, 1.5, 0.3]], nodal_musp, 0.1)
    np.testing.assert_allclose(pos3[0], [2.0, 1.5, -0.5], atol=1e-12)


def test_point_source_rhs_and_detector_operator():
    m = _box()
    q = point_source_rhs(m, [[1.2, 1.3, -0.7], [3.9, 0.1, -1.9]])
    assert q.shape == (m.n_nodes, 2)
    np.testing.assert_allclose(np.asarray(q.sum(axis=0)).ravel(), 1.0)  # unit power
    # linear fields are reproduced exactly by the barycentric weights
    np.testing.assert_allclose(q.T @ m.nodes_mm, [[1.2, 1.3, -0.7], [3.9, 0.1, -1.9]], atol=1e-12)
    P = detector_operator(m, [[2.5, 1.5, 0.6], [4.3, 2.2, -1.0]])
    assert P.shape == (2, m.n_nodes)
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0)
    used = np.unique(P.nonzero()[1])
    assert np.isin(used, m.boundary_nodes).all()
    np.testing.assert_allclose(P @ m.nodes_mm, [[2.5, 1.5, 0.0], [4.0, 2.2, -1.0]], atol=1e-12)


def test_sources_and_detectors_off_the_mesh_are_named():
    m = _box()
    with pytest.raises(FluoInputError, match=r"detector\[1\].*off the mesh"):
        detector_operator(m, [[1.0, 1.0, 0.0], [50.0, 1.0, 0.0]])
    with pytest.raises(FluoInputError, match=r"source"):
        point_source_rhs(m, [[1.0, 1.0, -1.0], [1.0, 1.0, 9.0]])
    with pytest.raises(FluoInputError, match="coordinates"):
        source_positions(m, [[1.0, 1.0]], 1.0, 0.01)
    with pytest.raises(FluoInputError, match="finite"):
        detector_operator(m, [[np.nan, 1.0, 0.0]])


def test_nodal_property_shapes_are_checked():
    m = _rect()
    with pytest.raises(FluoInputError, match="one value per node"):
        DiffusionOperator(m, np.full(5, 0.01), 1.0, 1.33)
    musp = np.full(m.n_nodes, 1.0)
    musp[3] = 0.0
    with pytest.raises(FluoInputError, match=r"musp_per_mm\[3\]"):
        DiffusionOperator(m, 0.01, musp, 1.33)
    mua = np.full(m.n_nodes, 0.01)
    mua[4] = -0.1
    with pytest.raises(FluoInputError, match=r"mua_per_mm\[4\]"):
        DiffusionOperator(m, mua, 1.0, 1.33)
