"""Coupled excitation/emission model, adjoints, Jacobians and `fluo forward`."""

import json

import numpy as np
import pytest

from fluoapp.cli import main
from FluoTomoLib.fem.forward import FluorescenceModel, safe_log
from FluoTomoLib.meshing.structured import box_mesh, rectangle_mesh
from FluoTomoLib.meshing.vtu_io import write_vtu

PX = dict(mua_per_mm=0.032, musp_per_mm=1.0, n=1.33)
PM = dict(mua_per_mm=0.025, musp_per_mm=0.9, n=1.33)


def _model_3d():
    m = box_mesh(np.linspace(-6, 6, 13), np.linspace(-4, 4, 9), np.linspace(-5, 0, 11))
    src = [[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]]
    det = [[-1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0]]
    return m, FluorescenceModel(m, PX, PM, src, det)


def test_shapes_and_adjoint_identity_3d():
    m, fm = _model_3d()
    assert fm.phi_x.shape == (m.n_nodes, 2)
    assert fm.adjoint_m.shape == (m.n_nodes, 3)
    y = fm.excitation_data()
    assert y.shape == (2, 3) and np.all(y > 0)
    # y_sd = P_d K^-1 q_s = (K^-1 P_d^T)^T q_s: the adjoint gives the same data
    np.testing.assert_allclose(y, (fm.q.T @ fm.adjoint_x), rtol=1e-10)
    assert fm.solver_name in ("pardiso", "superlu")


def test_yield_jacobian_3d_is_exact_and_reuses_factorisations():
    m, fm = _model_3d()
    J = fm.jacobian_yield()
    assert J.shape == (6, m.n_nodes)
    fx, fmm = fm.op_x._solve, fm.op_m._solve
    rng = np.random.default_rng(3)
    gamma = rng.uniform(0, 2e-3, m.n_nodes)
    y = fm.emission_data(gamma)
    # row index s * D + d
    np.testing.assert_allclose(y.ravel(), J @ gamma, rtol=1e-9)
    assert y[1, 2] == pytest.approx(J[1 * 3 + 2] @ gamma, rel=1e-9)
    # exactly linear in the yield
    np.testing.assert_allclose(fm.emission_data(3 * gamma), 3 * y, rtol=1e-12)
    # one factorisation per wavelength, reused for every source and adjoint
    assert fm.op_x._solve is fx and fm.op_m._solve is fmm
    assert fm.op_x.n_solves == 2 and fm.op_m.n_solves == 3 + 2 + 2


def test_emission_reciprocity_between_wavelengths():
    """Swapping the roles of the wavelengths with identical optics leaves the
    Jacobian of a detector-at-source layout symmetric: the kernel is G_d * Phi_s."""
    m = rectangle_mesh(np.linspace(-10, 10, 41), np.linspace(-6, 0, 13))
    pts = [[-4.0, 0.0], [4.0, 0.0]]
    fm = FluorescenceModel(m, PX, PX, pts, pts)
    # with identical properties, phi_x (buried source) and the adjoint (boundary
    # detector) differ only by the burial depth; the kernel stays positive
    J = fm.jacobian_yield()
    assert np.all(J >= -1e-14 * np.abs(J).max())
    # kernel of pair (0,1) mirrored in x equals kernel of pair (1,0)
    mirror = np.array([np.argmin(np.linalg.norm(m.nodes_mm - [-p[0], p[1]], axis=1))
                       for p in m.nodes_mm])
    np.testing.assert_allclose(J[0 * 2 + 1][mirror], J[1 * 2 + 0], rtol=1e-6,
                               atol=1e-9 * np.abs(J).max())


def test_heterogeneous_yield_2d_finite_difference():
    m = rectangle_mesh(np.linspace(-10, 10, 41), np.linspace(-8, 0, 17))
    mua = np.where(m.nodes_mm[:, 1] < -4, 0.05, 0.02)
    fm = FluorescenceModel(m, dict(PX, mua_per_mm=mua), PM, [[-3.0, 0.0]],
                           [[2.0, 0.0], [6.0, 0.0]])
    J = fm.jacobian_yield()
    gamma = np.full(m.n_nodes, 1e-3)
    k = int(np.argmin(np.linalg.norm(m.nodes_mm - [0.0, -2.5], axis=1)))
    dg = np.zeros(m.n_nodes)
    dg[k] = 1e-4
    fd = (fm.emission_data(gamma + dg) - fm.emission_data(gamma)).ravel() / 1e-4
    np.testing.assert_allclose(J[:, k], fd, rtol=1e-8)


def test_far_detectors_give_finite_logs():
    m = rectangle_mesh(np.linspace(-55, 55, 221), np.linspace(-10, 0, 21))
    p = dict(mua_per_mm=0.1, musp_per_mm=1.0, n=1.4)
    fm = FluorescenceModel(m, p, p, [[-50.0, 0.0]], [[-45.0, 0.0], [50.0, 0.0]])
    y = fm.excitation_data()
    assert np.all(np.isfinite(y))
    logy, valid = safe_log(y)
    assert np.all(np.isfinite(logy)) and valid[0, 0]
    assert np.all(np.isfinite(fm.jacobian_yield()))


def _write_case(tmp_path, src_text):
    m = box_mesh(np.linspace(0, 10, 11), np.linspace(0, 10, 11), np.linspace(-6, 0, 7))
    mesh_path = tmp_path / "slab.vtu"
    write_vtu(m, mesh_path)
    (tmp_path / "s.csv").write_text(src_text)
    (tmp_path / "d.csv").write_text("x,y,z\n2,5,0\n5,5,0\n8,5,0\n")
    return m, mesh_path


def test_cli_forward_json(tmp_path, capsys):
    m, mesh_path = _write_case(tmp_path, "x,y,z\n3,5,0\n7,5,0\n")
    rc = main(["forward", "--mesh", str(mesh_path), "--mua", "0.02", "--musp", "1.0",
               "--n", "1.33", "--sources", str(tmp_path / "s.csv"),
               "--detectors", str(tmp_path / "d.csv"), "--jacobian", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("detector_fluence", "seconds", "solver"):
        assert key in out
    y = np.array(out["detector_fluence"])
    assert y.shape == (2, 3) and np.all(y > 0)
    p = dict(mua_per_mm=0.02, musp_per_mm=1.0, n=1.33)
    ref = FluorescenceModel(m, p, p, [[3, 5, 0], [7, 5, 0]],
                            [[2, 5, 0], [5, 5, 0], [8, 5, 0]]).excitation_data()
    np.testing.assert_allclose(y, ref, rtol=1e-9)
    assert out["jacobian_shape"] == [6, m.n_nodes]


def test_cli_forward_bad_input(tmp_path, capsys):
    _, mesh_path = _write_case(tmp_path, "3,5,0\n5,5,40\n")
    args = ["forward", "--mesh", str(mesh_path), "--mua", "0.02", "--musp", "1.0",
            "--sources", str(tmp_path / "s.csv"), "--detectors", str(tmp_path / "d.csv"), "--json"]
    assert main(args) == 2
    assert "source[1]" in capsys.readouterr().err
    bad = tmp_path / "broken.vtu"
    bad.write_text("<VTKFile>not a mesh")
    assert main(["forward", "--mesh", str(bad)] + args[3:]) == 2
    assert "broken.vtu" in capsys.readouterr().err
    (tmp_path / "s.csv").write_text("3,5\n")
    assert main(args) == 2
    assert "2D but the mesh is 3D" in capsys.readouterr().err


def test_the_used_pairs_jacobian_is_the_whole_ones_rows():
    """``jacobian_yield(mask)`` computes only the used pairs' rows, a group of sources
    at a time (the self-absorption passes and the tissue model never hold the unused ones):
    the same numbers as the whole block's rows, for a ragged mask."""
    from FluoTomoLib.fem.forward import FluorescenceModel
    from FluoTomoLib.meshing.structured import slab_mesh

    mesh = slab_mesh(20.0, 10.0, 1.0)
    src = np.array([[x, 0.0, 0.0] for x in (-6.0, -2.0, 3.0)])
    det = np.array([[x, 2.0, 0.0] for x in (-7.0, -4.0, 0.0, 4.0, 7.0)])
    p = {"mua_per_mm": 0.01, "musp_per_mm": 1.0, "n": 1.4}
    fm = FluorescenceModel(mesh, p, p, src, det)
    mask = np.zeros((3, 5), bool)
    mask[0, [0, 3]] = True
    mask[2, :] = True                   # source 1: no pair used
    whole = fm.jacobian_yield()
    used = fm.jacobian_yield(mask)
    assert used.shape == (int(mask.sum()), mesh.n_nodes) and used.flags.c_contiguous
    np.testing.assert_allclose(used, whole[mask.ravel()], rtol=1e-12, atol=0)
