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

from fluoguide.errors import FluoInputError

from FluoTomoLib.fem.operators import (
    DiffusionOperator,
    _nodal,
    check_properties,
    detector_operator,
    geometry,
    point_source_rhs,
    source_positions,
    weighted_mass,
)
from FluoTomoLib.fem.jacobian_kernels import pair_jacobian


def _props(mesh, props, name):
    try:
        return props["mua_per_mm"], props["musp_per_mm"], props["n"]
    except (KeyError, TypeError):
        raise FluoInputError("needs keys mua_per_mm, musp_per_mm and n", field=name) from None


def triple_product_jacobian(mesh, G, F, scale=1.0):
    """J[(s, d), k] = scale * integral G_d F_s phi_k for nodal fields G (N, D), F (N, S).

    Exact P1 triple products, summed per element in compiled code
    (:func:`jacobian_kernels.pair_jacobian`).  Returns a (S * D, N) array (a
    transposed view of a C-ordered (N, S * D) block), row index s * D + d.
    """
    geo = geometry(mesh)
    out = pair_jacobian(geo.elements, geo.vol * (geo.c3 * scale), F, G, adjacency=geo.adjacency)
    return out.reshape(mesh.n_nodes, -1).T


def mua_jacobian(mesh, G, F, D_nodal):
    """d(G_d^T K F_s)/d(mua_k) for K with nodal mua and D = 1/(3 (mua + musp)), negated:
    the Jacobian of the data P_d K^-1 q_s with respect to nodal mua.

    Both ways absorption acts are included: the absorption term (exact P1
    triple products) and, through dD/dmua = -3 D^2, the diffusion term
    (K uses the element-mean D, so node k's D enters each of its elements'
    gradient products with weight 1/(d+1)).  (S * D, N), row s * D + d.
    """
    geo = geometry(mesh)
    out = pair_jacobian(geo.elements, -geo.vol * geo.c3, F, G, grad=geo.grad,
                        grad_weight=geo.vol / (mesh.dim + 1),
                        node_coef=3.0 * np.asarray(D_nodal, float) ** 2, adjacency=geo.adjacency)
    return out.reshape(mesh.n_nodes, -1).T


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
    source_normals : (S, d) outward unit normals of the true surface at the
        sources, to bury them along (default: the nearest facet's normal)
    """

    def __init__(self, mesh, props_x, props_m, sources_mm, detectors_mm, solver="auto",
                 max_snap_mm=5.0, source_normals=None):
        t0 = time.perf_counter()
        mua_x, musp_x, n_x = _props(mesh, props_x, "props_x")
        mua_m, musp_m, n_m = _props(mesh, props_m, "props_m")
        self.mesh = mesh
        self.op_x = DiffusionOperator(mesh, mua_x, musp_x, n_x, solver, name="excitation")
        # The emission operator is assembled on first use: excitation-only work
        # (mua Jacobians, reflectance) never pays for it.
        check_properties(_nodal(mesh, mua_m, "emission.mua_per_mm"),
                         _nodal(mesh, musp_m, "emission.musp_per_mm"), n_m, where="emission")
        self._op_m_args = (mesh, mua_m, musp_m, n_m, solver)
        self._op_m = None
        self.sources_surface_mm = np.atleast_2d(np.asarray(sources_mm, float))
        self.detectors_mm = np.atleast_2d(np.asarray(detectors_mm, float))
        self.sources_mm = source_positions(mesh, self.sources_surface_mm, self.op_x.musp,
                                           self.op_x.mua, max_snap_mm, source_normals)
        self.q = point_source_rhs(mesh, self.sources_mm)
        self.P = detector_operator(mesh, self.detectors_mm, max_snap_mm)
        self.setup_seconds = time.perf_counter() - t0
        self._phi_x = None
        self._adj_m = None
        self._adj_x = None
        self.timings = {"assembly": self.op_x.assembly_seconds}

    @property
    def op_m(self):
        """Emission-wavelength operator (assembled on first use)."""
        if self._op_m is None:
            mesh, mua_m, musp_m, n_m, solver = self._op_m_args
            self._op_m = DiffusionOperator(mesh, mua_m, musp_m, n_m, solver, name="emission")
            self.timings["assembly"] += self._op_m.assembly_seconds
        return self._op_m

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
        return mua_jacobian(self.mesh, self.adjoint_x, self.phi_x, self.op_x.D)


def safe_log(data, floor=1e-300):
    """Natural log of data with non-positive or underflowed values clipped to
    ``floor``; returns (log_data, valid_mask) so callers can drop them."""
    d = np.asarray(data, float)
    valid = np.isfinite(d) & (d > floor)
    return np.log(np.where(valid, d, floor)), valid
