"""Finite-element CW diffusion on linear triangles (2D) and tetrahedra (3D).

Weak form of -div(D grad Phi) + mua Phi = q with the Robin boundary
Phi + 2 A D dPhi/dn = 0 (physics.md sections 1-2):

    (K + M_mua + B / (2A)) Phi = b

K: stiffness with element-mean D (exact for nodal, linearly varying D),
M_mua: mass matrix weighted by nodal mua (exact P1 triple products),
B: boundary-facet mass, b: point-source load (barycentric weights).

What is expensive is computed once per mesh and cached on it (gradients,
sparsity pattern, boundary mass); a new set of optical properties only
rebuilds the values, and one factorisation serves every source and adjoint.
"""

from __future__ import annotations

import time
from math import factorial

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fluoguide.errors import FluoInputError

from .locate import boundary_locator, locator
from .optics import check_properties, diffusion_coefficient, robin_A


# ---------------------------------------------------------------- geometry cache

def _inverse_3x3(J):
    """Inverses of a stack of 3x3 matrices by the adjugate (4x faster than
    np.linalg.inv's batched LU for 10^5-10^6 tetrahedra; the elements were
    checked non-degenerate before)."""
    a, b, c = J[:, 0, 0], J[:, 0, 1], J[:, 0, 2]
    d, e, f = J[:, 1, 0], J[:, 1, 1], J[:, 1, 2]
    g, h, i = J[:, 2, 0], J[:, 2, 1], J[:, 2, 2]
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    inv = np.empty_like(J)
    inv[:, 0, 0], inv[:, 1, 0], inv[:, 2, 0] = A, B, C
    inv[:, 0, 1], inv[:, 1, 1], inv[:, 2, 1] = c * h - b * i, a * i - c * g, b * g - a * h
    inv[:, 0, 2], inv[:, 1, 2], inv[:, 2, 2] = b * f - c * e, c * d - a * f, a * e - b * d
    return inv / det[:, None, None]


class _Geometry:
    """Per-mesh quantities that do not depend on optical properties."""

    def __init__(self, mesh):
        mesh.check_elements()
        if np.any(mesh.signed_measures < 0):
            raise FluoInputError(
                f"{int(np.sum(mesh.signed_measures < 0))} inverted element(s); "
                "orient the mesh (Mesh.oriented()) before solving",
                field=f"{mesh.name}.elements[{int(np.flatnonzero(mesh.signed_measures < 0)[0])}]")
        d = mesh.dim
        el = mesh.elements
        p = mesh.nodes_mm[el]
        J = (p[:, 1:, :] - p[:, :1, :]).transpose(0, 2, 1)      # x = p0 + J xi
        Jinv = _inverse_3x3(J) if d == 3 else np.linalg.inv(J)  # rows: grad xi_k
        G = np.concatenate([-Jinv.sum(axis=1, keepdims=True), Jinv], axis=1)  # (M, d+1, d)
        self.vol = mesh.measures
        # G G^T as d rank-one products of contiguous columns: ~2x faster than
        # einsum or a batched matmul on (M, 4, 3) stacks
        Gt = np.ascontiguousarray(G.transpose(2, 0, 1))          # (d, M, d+1)
        GGt = Gt[0][:, :, None] * Gt[0][:, None, :]
        for k in range(1, d):
            GGt += Gt[k][:, :, None] * Gt[k][:, None, :]
        GGt *= self.vol[:, None, None]
        self.GGt = GGt
        nl = d + 1
        # 32-bit indices where they fit: scipy's COO -> CSR conversion (every
        # assembly) runs about 2x faster on them (0.27 vs 0.61 s, 5.3 M entries)
        idx = el.astype(np.int32) if mesh.n_nodes < 2 ** 31 - 1 else el
        self.rows = np.repeat(idx, nl, axis=1).ravel()
        self.cols = np.tile(idx, (1, nl)).ravel()
        self.n = mesh.n_nodes
        self.dim = d
        # exact integral of a product of three P1 functions: |e| d! a!b!c!/(d+a+b+c)!
        self.c3 = factorial(d) / factorial(d + 3)
        # boundary facet mass (facets are (d-1)-simplices)
        f = mesh.boundary_facets
        fm = mesh.boundary_facet_measures
        k = d  # nodes per facet
        # Row-sum lumped facet mass: the consistent one has positive off-diagonal
        # terms that outweigh the (negative) stiffness couplings when D is small
        # (musp ~ 100/mm), which breaks the M-matrix property and makes boundary
        # fluence oscillate negative.  Lumping keeps it positive at O(h^2) cost.
        local = np.eye(k) / k
        self._facet_vals = fm[:, None, None] * local[None]
        fi = f.astype(idx.dtype)
        self._facet_rows = np.repeat(fi, k, axis=1)
        self._facet_cols = np.tile(fi, (1, k))
        self.boundary_mass = self.boundary_mass_on(None)
        self.elements = el

    def boundary_mass_on(self, facet_mask):
        """Boundary mass over the facets where ``facet_mask`` is True (all if None)."""
        sel = slice(None) if facet_mask is None else np.asarray(facet_mask, bool)
        return sp.csr_matrix((self._facet_vals[sel].ravel(),
                              (self._facet_rows[sel].ravel(), self._facet_cols[sel].ravel())),
                             shape=(self.n, self.n))


def geometry(mesh):
    return mesh.cached("_fem_geometry", _Geometry)


def _nodal(mesh, value, name):
    v = np.asarray(value, dtype=float)
    if v.ndim == 0:
        return np.full(mesh.n_nodes, float(v))
    if v.shape != (mesh.n_nodes,):
        raise FluoInputError(f"needs a scalar or one value per node ({mesh.n_nodes})", field=name,
                             value=v.shape)
    return v


def weighted_mass(mesh, w_nodal):
    """Mass matrix weighted by a nodal field w: M_ij = integral w phi_i phi_j (exact)."""
    g = geometry(mesh)
    w = _nodal(mesh, w_nodal, "weight")
    we = w[g.elements]                                      # (M, d+1)
    S = we.sum(axis=1)
    nl = g.dim + 1
    eye = np.eye(nl)
    # sum_k w_k c_ijk = S (1 + d_ij) + w_i + w_j + 2 d_ij w_i
    local = (S[:, None, None] * (1 + eye)[None] + we[:, :, None] + we[:, None, :]
             + 2 * eye[None] * we[:, :, None])
    vals = (local * (g.vol * g.c3)[:, None, None]).ravel()
    return sp.csr_matrix((vals, (g.rows, g.cols)), shape=(g.n, g.n))


def stiffness(mesh, D_nodal):
    g = geometry(mesh)
    D = _nodal(mesh, D_nodal, "D")
    De = D[g.elements].mean(axis=1)
    vals = (g.GGt * De[:, None, None]).ravel()
    return sp.csr_matrix((vals, (g.rows, g.cols)), shape=(g.n, g.n))


# ---------------------------------------------------------------- solver

def _pardiso():
    try:
        import pypardiso

        return pypardiso
    except Exception:  # not installed, or MKL cannot load on this CPU
        return None


class _PardisoFactor:
    """MKL PARDISO, real symmetric positive definite (mtype 2), upper triangle.

    Measured on this 2-core machine (33k-node slab): factorisation 0.7 s and
    32 solves 0.3 s, against 6.6 s and 0.6 s for SuperLU (docs/fem.md).
    """

    def __init__(self, K, pypardiso):
        self.Ku = sp.triu(K, format="csr")
        self.solver = pypardiso.PyPardisoSolver()
        self.solver.set_matrix_type(2)
        # Our own iparm (iparm(1) = 1; pypardiso's zeros mean "all defaults",
        # which include two iterative-refinement steps per solve).  Measured on
        # the 60k-node benchmark slab, medians of 3: factorisation 1.13 -> 0.92 s
        # with OpenMP nested dissection (iparm(2) = 3), 16 solves 0.38 -> 0.19 s
        # with one refinement step; residual 8e-13 relative, against 3e-14.
        self.solver.set_iparm(1, 1)
        self.solver.set_iparm(2, 3)
        self.solver.set_iparm(8, 1)
        self.solver.set_iparm(10, 8)
        self.solver.factorize(self.Ku)

    def __call__(self, B):
        X = self.solver.solve(self.Ku, np.ascontiguousarray(B))
        return X.reshape(B.shape)


class MeshResolutionWarning(UserWarning):
    """Elements are large compared with the light's decay length 1/mueff."""


def _check_resolution(mesh, mua, musp, name):
    import warnings

    from .optics import mueff

    h = float(np.median(mesh.measures)) ** (1.0 / mesh.dim) * (2.0 if mesh.dim == 3 else 1.5)
    me = float(np.max(mueff(mua, musp)))
    if h * me > 2.0:
        warnings.warn(f"{name}: elements (~{h:.2g} mm) are coarse for a decay length 1/mueff = "
                      f"{1 / me:.2g} mm; far-field values will be inaccurate and may underflow",
                      MeshResolutionWarning, stacklevel=3)


class DiffusionOperator:
    """System matrix of one wavelength and its factorisation.

    Parameters
    ----------
    mesh : Mesh
    mua_per_mm, musp_per_mm : scalar or (N,) nodal
    n : refractive index of the tissue (outside: air)
    robin_facets : bool mask over ``mesh.boundary_facets`` where the tissue-air
        Robin condition applies; elsewhere the boundary is reflecting (zero
        flux), e.g. the cut sides of a column modelling an infinite slab.
        Default: every boundary facet.
    solver : "auto" (PARDISO if MKL loads, else SuperLU), "pardiso", "splu" or "amg"
        (smoothed-aggregation AMG preconditioned CG, for meshes too big to factorise)
    """

    def __init__(self, mesh, mua_per_mm, musp_per_mm, n, solver="auto", name="operator",
                 robin_facets=None):
        mua = _nodal(mesh, mua_per_mm, f"{name}.mua_per_mm")
        musp = _nodal(mesh, musp_per_mm, f"{name}.musp_per_mm")
        check_properties(mua, musp, n, where=name)
        _check_resolution(mesh, mua, musp, name)
        self.mesh = mesh
        self.mua = mua
        self.musp = musp
        self.n = float(n)
        self.A = float(robin_A(self.n))
        self.D = diffusion_coefficient(mua, musp)
        t0 = time.perf_counter()
        g = geometry(mesh)
        self.K = (stiffness(mesh, self.D) + weighted_mass(mesh, mua)
                  + (g.boundary_mass if robin_facets is None else g.boundary_mass_on(robin_facets))
                  * (1.0 / (2.0 * self.A))).tocsc()
        self.assembly_seconds = time.perf_counter() - t0
        self.factor_seconds = 0.0
        self._solver_request = solver
        self._solve = None
        self.solver_name = None
        self.n_solves = 0

    def factorize(self):
        if self._solve is not None:
            return self
        t0 = time.perf_counter()
        req = self._solver_request
        if req not in ("auto", "pardiso", "splu", "amg"):
            raise FluoInputError("unknown solver; use auto, pardiso, splu or amg", field="solver",
                                 value=req)
        pardiso = _pardiso() if req in ("auto", "pardiso") else None
        if req == "pardiso" and pardiso is None:
            raise FluoInputError("PARDISO (pypardiso/MKL) is not available", field="solver",
                                 value=req)
        if pardiso is not None:
            self._solve = _PardisoFactor(self.K, pardiso)
            self.solver_name = "pardiso"
        elif req == "amg":
            import pyamg

            ml = pyamg.smoothed_aggregation_solver(self.K.tocsr(), symmetry="symmetric")

            def solve(B):
                B2 = B.reshape(len(B), -1)
                X = np.column_stack([ml.solve(B2[:, j], tol=1e-10, accel="cg", maxiter=500)
                                     for j in range(B2.shape[1])])
                return X.reshape(B.shape)
            self._solve = solve
            self.solver_name = "amg-cg"
        else:
            lu = spla.splu(self.K, permc_spec="MMD_AT_PLUS_A")
            self._solve = lu.solve
            self.solver_name = "superlu"
        self.factor_seconds = time.perf_counter() - t0
        return self

    def solve(self, B):
        """Solve K X = B for a vector (N,) or a block (N, k); dense result."""
        self.factorize()
        if sp.issparse(B):
            B = B.toarray()
        B = np.asarray(B, dtype=float)
        X = self._solve(B)
        self.n_solves += 1 if B.ndim == 1 else B.shape[1]
        return np.asarray(X)


# ---------------------------------------------------------------- sources / detectors

def snap_to_surface(mesh, points_mm, max_snap_mm=5.0, what="source"):
    """Closest boundary points to ``points_mm``; error for points farther than max_snap_mm."""
    pts = np.atleast_2d(np.asarray(points_mm, float))
    if pts.shape[1] != mesh.dim:
        raise FluoInputError(f"points must have {mesh.dim} coordinates", field=what,
                             value=pts.shape)
    if not np.all(np.isfinite(pts)):
        raise FluoInputError("coordinates must be finite", field=what)
    q, facet, bary, dist = boundary_locator(mesh).closest(pts)
    far = np.flatnonzero(dist > max_snap_mm)
    if len(far):
        raise FluoInputError(f"is {dist[far[0]]:.3g} mm from the mesh surface (more than "
                             f"{max_snap_mm:g} mm): off the mesh", field=f"{what}[{far[0]}]",
                             value=pts[far[0]].tolist())
    return q, facet, bary


def source_positions(mesh, surface_points_mm, musp_per_mm, mua_per_mm, max_snap_mm=5.0):
    """Buried isotropic sources: one transport MFP below the nearest surface point,
    along the inward normal (physics.md section 2)."""
    q, facet, bary = snap_to_surface(mesh, surface_points_mm, max_snap_mm, "source")
    mua = _nodal(mesh, mua_per_mm, "mua_per_mm")
    musp = _nodal(mesh, musp_per_mm, "musp_per_mm")
    fnodes = mesh.boundary_facets[facet]
    mut = np.einsum("ij,ij->i", bary, (mua + musp)[fnodes])
    normal = mesh.boundary_normals[facet]
    return q - normal / mut[:, None]


def point_source_rhs(mesh, positions_mm):
    """(N, S) sparse load of unit-power point sources at interior positions."""
    P = locator(mesh).interpolation_matrix(positions_mm, what="source (buried)")
    return P.T.tocsc()


def detector_operator(mesh, surface_points_mm, max_snap_mm=5.0):
    """(D, N) sparse operator: boundary fluence at the surface point nearest each detector."""
    _, facet, bary = snap_to_surface(mesh, surface_points_mm, max_snap_mm, "detector")
    nodes = mesh.boundary_facets[facet]
    rows = np.repeat(np.arange(len(facet)), mesh.dim)
    return sp.csr_matrix((bary.ravel(), (rows, nodes.ravel())),
                         shape=(len(facet), mesh.n_nodes))
