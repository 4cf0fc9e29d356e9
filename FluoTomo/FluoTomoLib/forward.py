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


def _chunks(mesh, S, D, budget=1.5e7):
    nl = mesh.dim + 1
    size = max(1, int(budget // (nl * S * D)))
    for c0 in range(0, mesh.n_elements, size):
        yield slice(c0, min(c0 + size, mesh.n_elements))


def triple_product_jacobian(mesh, G, F):
    """J[(s, d), k] = integral G_d F_s phi_k for nodal fields G (N, D) and F (N, S).

    Exact P1 triple products, all source-detector pairs at once per chunk of
    elements (BLAS-friendly einsums), scattered to nodes with a sparse sum.
    Returns a dense (S * D, N) array, row index s * D + d.
    """
    import scipy.sparse as sp

    geo = geometry(mesh)
    el = geo.elements
    nl = mesh.dim + 1
    S, D = F.shape[1], G.shape[1]
    w = geo.vol * geo.c3
    out = np.zeros((mesh.n_nodes, S * D))
    for sl in _chunks(mesh, S, D):
        e = el[sl]
        C = len(e)
        Ge, Fe = G[e], F[e]                                   # (C, nl, D), (C, nl, S)
        Gs, Fs = Ge.sum(axis=1), Fe.sum(axis=1)               # (C, D), (C, S)
        base = np.einsum("cs,cd->csd", Fs, Gs) + np.einsum("cjs,cjd->csd", Fe, Ge)
        # local[k] = base + g_k F + G f_k + 2 g_k f_k (exact triple products)
        loc = (base[:, None] + Fs[:, None, :, None] * Ge[:, :, None, :]
               + Fe[:, :, :, None] * (Gs[:, None, None, :] + 2.0 * Ge[:, :, None, :]))
        loc *= w[sl][:, None, None, None]
        scatter = sp.csr_matrix((np.ones(C * nl), (e.ravel(), np.arange(C * nl))),
                                shape=(mesh.n_nodes, C * nl))
        out += scatter @ loc.reshape(C * nl, S * D)
    return out.T


def gradient_product_jacobian(mesh, G, F):
    """J[(s, d), k] = sum over elements e containing k of |e|/(d+1) grad G_d . grad F_s.

    The derivative of G^T K F with respect to nodal D when K uses the
    element-mean D (fem.stiffness).  Dense (S * D, N), row s * D + d.
    """
    import scipy.sparse as sp

    geo = geometry(mesh)
    el = geo.elements
    nl = mesh.dim + 1
    S, D = F.shape[1], G.shape[1]
    out = np.zeros((mesh.n_nodes, S * D))
    for sl in _chunks(mesh, S, D, budget=6e7):
        e = el[sl]
        C = len(e)
        KF = np.einsum("cij,cjs->cis", geo.GGt[sl], F[e])      # |e| grad_i . grad F_s
        val = np.einsum("cid,cis->csd", G[e], KF) / nl          # (C, S, D)
        scatter = sp.csr_matrix((np.ones(C * nl), (e.ravel(), np.repeat(np.arange(C), nl))),
                                shape=(mesh.n_nodes, C))
        out += scatter @ val.reshape(C, S * D)
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
