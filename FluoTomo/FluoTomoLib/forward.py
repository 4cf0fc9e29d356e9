"""Coupled excitation/emission forward model, adjoint fields and Jacobians.

Excitation: (K_x) Phi_x = q_s            (unit-power buried point sources)
Emission:   (K_m) Phi_m = M(gamma) Phi_x (gamma = eta mua_f,x, nodal yield)
Data:       y_sd = P_d Phi_m,s           (boundary fluence at detector d)

With the adjoint g_d = K_m^-1 P_d^T (K symmetric), y_sd = g_d^T M(gamma) Phi_x,s,
which is linear in gamma:  J[sd, k] = integral g_d Phi_x,s phi_k,
computed exactly per element from the P1 triple products.  One factorisation
per wavelength serves all sources and adjoints.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from fluoguide.errors import FluoInputError

from .fem import (DiffusionOperator, detector_operator, geometry, point_source_rhs,
                  source_positions, weighted_mass)


def _props(mesh, props, name):
    try:
        return props["mua_per_mm"], props["musp_per_mm"], props["n"]
    except (KeyError, TypeError):
        raise FluoInputError("needs keys mua_per_mm, musp_per_mm and n", field=name) from None


def _chunk_size(S, D, budget=1.5e7):
    """Elements per chunk so one (C, S, D) block holds ~``budget`` doubles (120 MB).

    Large chunks matter: each chunk adds a (C, S*D) block into the (N, S*D)
    result, and that sum, not the arithmetic, dominates with small chunks.
    """
    return max(1, int(budget // (S * D)))


def _incidence(mesh, weights):
    """(N, M) CSC matrix, entry (k, e) = weights[e] if node k belongs to element e.

    CSC so that column (element) chunks slice cheaply.
    """
    el = geometry(mesh).elements
    nl = mesh.dim + 1
    return sp.csc_matrix((np.repeat(np.asarray(weights, float), nl),
                          (el.ravel(), np.repeat(np.arange(len(el)), nl))),
                         shape=(mesh.n_nodes, len(el)))


def _jacobian_operators(mesh):
    """Mesh-only sparse operators of the Jacobian assembly, cached on the mesh's
    FEM geometry so repeated Jacobians (Newton iterations) build them once."""
    geo = geometry(mesh)
    ops = getattr(geo, "_jacobian_ops", None)
    if ops is None:
        nl = mesh.dim + 1
        n_el = len(geo.elements)
        Ew = _incidence(mesh, geo.vol * geo.c3)                 # triple-product weights
        Mw = (Ew @ _incidence(mesh, np.ones(n_el)).T).tocsr()  # sum of w over shared elements
        ops = {"Ew": Ew, "Mw": Mw, "W": np.asarray(Ew.sum(axis=1)).ravel(),
               "E_mean": _incidence(mesh, np.full(n_el, 1.0 / nl))}
        geo._jacobian_ops = ops
    return ops


def triple_product_jacobian(mesh, G, F):
    """J[(s, d), k] = integral G_d F_s phi_k for nodal fields G (N, D) and F (N, S).

    Exact P1 triple products.  Per element e with weight w = |e| d!/(d+3)!,
    the contribution to node k of e is
    w [sum_ij (1 + delta_ij) f_j g_i + g_k Fs + f_k Gs + 2 g_k f_k]
    (Fs, Gs: sums over the element's nodes).  The last three terms factor into
    node-level products with the sparse pattern matrix Mw[k, j] = sum of w over
    the elements containing k and j, so only the first needs per-element work:
    one batched matmul F_e^T (G_e + Gs) per chunk, scattered with a sparse
    incidence product.  Returns a dense (S * D, N) array, row index s * D + d.
    """
    geo = geometry(mesh)
    el = geo.elements
    S, D = F.shape[1], G.shape[1]
    ops = _jacobian_operators(mesh)
    Ew, W = ops["Ew"], ops["W"]
    HF, HG = ops["Mw"] @ F, ops["Mw"] @ G
    out = (HF[:, :, None] * G[:, None, :]
           + F[:, :, None] * (HG + 2.0 * W[:, None] * G)[:, None, :]).reshape(-1, S * D)
    size = _chunk_size(S, D)
    for c0 in range(0, len(el), size):
        e = el[c0:c0 + size]
        Ge = G[e]
        base = np.matmul(F[e].transpose(0, 2, 1), Ge + Ge.sum(axis=1, keepdims=True))
        out += Ew[:, c0:c0 + size] @ base.reshape(len(e), S * D)
    return out.T


def gradient_product_jacobian(mesh, G, F):
    """J[(s, d), k] = sum over elements e containing k of |e|/(d+1) grad G_d . grad F_s.

    The derivative of G^T K F with respect to nodal D when K uses the
    element-mean D (fem.stiffness).  Dense (S * D, N), row s * D + d.
    """
    geo = geometry(mesh)
    el = geo.elements
    S, D = F.shape[1], G.shape[1]
    E = _jacobian_operators(mesh)["E_mean"]
    out = np.zeros((mesh.n_nodes, S * D))
    size = _chunk_size(S, D)
    for c0 in range(0, len(el), size):
        e = el[c0:c0 + size]
        KF = np.matmul(geo.GGt[c0:c0 + size], F[e])           # (C, nl, S): |e| grad_i . grad F_s
        val = np.matmul(KF.transpose(0, 2, 1), G[e])          # (C, S, D)
        out += E[:, c0:c0 + size] @ val.reshape(len(e), S * D)
    return out.T


class FluorescenceModel:
    """Forward model of one tissue: sources, detectors, both wavelengths.

    Parameters
    ----------
    mesh : Mesh
    props_x, props_m : dicts with ``mua_per_mm``, ``musp_per_mm`` (scalar or
        nodal) and ``n``, at excitation (mua_x includes the fluorophore) and
        emission
    sources_mm, detectors_mm : (S, d), (D, d) surface points; sources are
        buried one MFP' below the nearest surface point
    solver : see DiffusionOperator
    """

    def __init__(self, mesh, props_x, props_m, sources_mm, detectors_mm, solver="auto",
                 max_snap_mm=5.0):
        t0 = time.perf_counter()
        mua_x, musp_x, n_x = _props(mesh, props_x, "props_x")
        mua_m, musp_m, n_m = _props(mesh, props_m, "props_m")
        self.mesh = mesh
        self.op_x = DiffusionOperator(mesh, mua_x, musp_x, n_x, solver, name="excitation")
        self.op_m = DiffusionOperator(mesh, mua_m, musp_m, n_m, solver, name="emission")
        self.sources_surface_mm = np.atleast_2d(np.asarray(sources_mm, float))
        self.detectors_mm = np.atleast_2d(np.asarray(detectors_mm, float))
        self.sources_mm = source_positions(mesh, self.sources_surface_mm, self.op_x.musp,
                                           self.op_x.mua, max_snap_mm)
        self.q = point_source_rhs(mesh, self.sources_mm)
        self.P = detector_operator(mesh, self.detectors_mm, max_snap_mm)
        self.setup_seconds = time.perf_counter() - t0
        self._phi_x = None
        self._adj_m = None
        self._adj_x = None
        self.timings = {"assembly": self.op_x.assembly_seconds + self.op_m.assembly_seconds}

    @property
    def n_sources(self):
        return len(self.sources_mm)

    @property
    def n_detectors(self):
        return self.P.shape[0]

    @property
    def solver_name(self):
        return self.op_x.solver_name or self.op_x.factorize().solver_name

    @property
    def phi_x(self):
        """(N, S) excitation fluence for unit-power sources [1/mm^2 in 3D, 1/mm in 2D]."""
        if self._phi_x is None:
            t0 = time.perf_counter()
            self._phi_x = self.op_x.solve(self.q)
            self.timings["forward_x"] = time.perf_counter() - t0
            self.timings["factor"] = self.op_x.factor_seconds
        return self._phi_x

    @property
    def adjoint_m(self):
        """(N, D) emission-wavelength adjoint fields (Green's function of each detector)."""
        if self._adj_m is None:
            t0 = time.perf_counter()
            self._adj_m = self.op_m.solve(self.P.T.tocsc())
            self.timings["adjoint_m"] = time.perf_counter() - t0
            self.timings["factor"] = self.timings.get("factor", 0) + self.op_m.factor_seconds
        return self._adj_m

    @property
    def adjoint_x(self):
        """(N, D) excitation-wavelength adjoint fields."""
        if self._adj_x is None:
            self._adj_x = self.op_x.solve(self.P.T.tocsc())
        return self._adj_x

    def excitation_data(self):
        """(S, D) excitation boundary fluence per unit source power."""
        return np.asarray((self.P @ self.phi_x).T)

    def emission_fields(self, yield_per_mm):
        """(N, S) emission fluence for a nodal yield (forward solves, no adjoint)."""
        gamma = np.asarray(yield_per_mm, float)
        rhs = weighted_mass(self.mesh, gamma) @ self.phi_x
        return self.op_m.solve(rhs)

    def emission_data(self, yield_per_mm):
        """(S, D) emission boundary fluence per unit excitation power."""
        gamma = np.asarray(yield_per_mm, float)
        if gamma.shape != (self.mesh.n_nodes,) or not np.all(np.isfinite(gamma)):
            raise FluoInputError("needs one finite value per node", field="yield_per_mm",
                                 value=gamma.shape)
        return np.asarray(self.P @ self.emission_fields(gamma)).T

    def jacobian_yield(self):
        """(S*D, N): d(emission data)/d(nodal yield), row s*D + d."""
        t0 = time.perf_counter()
        J = triple_product_jacobian(self.mesh, self.adjoint_m, self.phi_x)
        self.timings["jacobian"] = time.perf_counter() - t0
        return J

    def jacobian_mua_x(self):
        """(S*D, N): d(excitation data)/d(nodal mua_x), row s*D + d.

        Includes both ways absorption acts: the absorption term itself and,
        through D = 1/(3 (mua + musp)), the diffusion coefficient.
        """
        g, f = self.adjoint_x, self.phi_x
        absorption = triple_product_jacobian(self.mesh, g, f)
        dD_dmua = -3.0 * self.op_x.D ** 2
        return -(absorption + gradient_product_jacobian(self.mesh, g, f) * dD_dmua[None, :])


def safe_log(data, floor=1e-300):
    """Natural log of data with non-positive or underflowed values clipped to
    ``floor``; returns (log_data, valid_mask) so callers can drop them."""
    d = np.asarray(data, float)
    valid = np.isfinite(d) & (d > floor)
    return np.log(np.where(valid, d, floor)), valid
