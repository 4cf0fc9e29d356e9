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

from .fem import (DiffusionOperator, _nodal, check_properties, detector_operator, geometry,
                  point_source_rhs, source_positions, weighted_mass)


def _props(mesh, props, name):
    try:
        return props["mua_per_mm"], props["musp_per_mm"], props["n"]
    except (KeyError, TypeError):
        raise FluoInputError("needs keys mua_per_mm, musp_per_mm and n", field=name) from None


def _chunk_size(S, D, budget=2.0e6):
    """Elements per chunk so one (C, S, D) block holds ~``budget`` doubles (16 MB).

    Each chunk's contribution is added only into the rows of the nodes its
    elements touch (:func:`_scatter_rows`), so chunks can stay small enough
    for the allocator to reuse their memory: blocks above glibc's 32 MB mmap
    threshold are returned to the OS and page-faulted in again every time,
    which cost more than the arithmetic.
    """
    return max(1, int(budget // (S * D)))


def _scatter_rows(incidence, c0, c1, cache):
    """(rows, block) of the incidence columns c0:c1 restricted to the touched rows."""
    key = (c0, c1)
    hit = cache.get(key)
    if hit is None:
        blk = incidence[:, c0:c1]
        rows = np.unique(blk.indices)
        sub = blk.tocsr()[rows]
        if rows[-1] - rows[0] + 1 == len(rows):  # contiguous (ordered meshes): a slice
            rows = slice(int(rows[0]), int(rows[-1]) + 1)     # adds in place, no gather
        hit = (rows, sub)
        cache[key] = hit
    return hit


def _jacobian_threads():
    """Worker threads for the Jacobian's element loop (batched matmuls and sparse
    products release the GIL; the adds into the result stay on one thread)."""
    import os

    return max(1, min(2, os.cpu_count() or 1))


def _accumulate(out, n_el, size, block, incidence, cache):
    """out[rows(chunk)] += incidence[rows, chunk] @ block(c0, c1) over element chunks.

    ``block(c0, c1)`` returns the (C, S*D) per-element values; chunks are
    computed on worker threads and added here in order.
    """
    from concurrent.futures import ThreadPoolExecutor

    def work(c0):
        c1 = min(c0 + size, n_el)
        rows, blk = _scatter_rows(incidence, c0, c1, cache)
        return rows, blk @ block(c0, c1)

    starts = range(0, n_el, size)
    threads = _jacobian_threads()
    if threads == 1 or len(starts) < 3:
        for c0 in starts:
            rows, r = work(c0)
            out[rows] += r
        return out
    with ThreadPoolExecutor(threads) as pool:
        for rows, r in pool.map(work, starts):
            out[rows] += r
    return out


def _incidence_of(elements, n_nodes, weights):
    """(N, M) CSC matrix, entry (k, e) = weights[e] if node k belongs to element e.

    CSC so that column (element) chunks slice cheaply.
    """
    nl = elements.shape[1]
    return sp.csc_matrix((np.repeat(np.asarray(weights, float), nl),
                          (elements.ravel(), np.repeat(np.arange(len(elements)), nl))),
                         shape=(n_nodes, len(elements)))


def _jacobian_operators(mesh):
    """Mesh-only operators of the Jacobian assembly, cached on the mesh's FEM
    geometry so repeated Jacobians (Newton iterations) build them once.

    Elements are taken in order of their lowest node index, so a chunk of
    consecutive elements touches a compact range of nodes and its
    contribution is added into a slice of the result rather than gathered
    and scattered over the whole mesh (6-7x fewer row updates on the
    structured meshes, whose natural order interleaves the Kuhn tetrahedra).
    """
    geo = geometry(mesh)
    ops = getattr(geo, "_jacobian_ops", None)
    if ops is None:
        nl = mesh.dim + 1
        order = np.argsort(geo.elements.min(axis=1), kind="stable")
        el = np.ascontiguousarray(geo.elements[order])
        n_el = len(el)
        Ew = _incidence_of(el, mesh.n_nodes, (geo.vol * geo.c3)[order])   # triple-product weights
        Mw = (Ew @ _incidence_of(el, mesh.n_nodes, np.ones(n_el)).T).tocsr()
        ops = {"elements": el, "GGt": np.ascontiguousarray(geo.GGt[order]),
               "Ew": Ew, "Mw": Mw, "W": np.asarray(Ew.sum(axis=1)).ravel(),
               "E_mean": _incidence_of(el, mesh.n_nodes, np.full(n_el, 1.0 / nl))}
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
    S, D = F.shape[1], G.shape[1]
    F = np.ascontiguousarray(F, dtype=float)
    G = np.ascontiguousarray(G, dtype=float)
    ops = _jacobian_operators(mesh)
    el = ops["elements"]
    Ew, W = ops["Ew"], ops["W"]
    HF, HG = ops["Mw"] @ F, ops["Mw"] @ G
    T = HG + 2.0 * W[:, None] * G
    out = np.empty((mesh.n_nodes, S, D))
    step = max(1, _chunk_size(S, D) // 2)  # row blocks: small temporaries the allocator reuses
    for a in range(0, mesh.n_nodes, step):
        b = a + step
        np.multiply(HF[a:b, :, None], G[a:b, None, :], out=out[a:b])
        out[a:b] += F[a:b, :, None] * T[a:b, None, :]
    out = out.reshape(-1, S * D)
    size = _chunk_size(S, D)

    def block(c0, c1):
        e = el[c0:c1]
        Ge = G[e]
        base = np.matmul(F[e].transpose(0, 2, 1), Ge + Ge.sum(axis=1, keepdims=True))
        return base.reshape(len(e), S * D)

    _accumulate(out, len(el), size, block, Ew, ops.setdefault(("Ew_rows", size), {}))
    return out.T


def gradient_product_jacobian(mesh, G, F):
    """J[(s, d), k] = sum over elements e containing k of |e|/(d+1) grad G_d . grad F_s.

    The derivative of G^T K F with respect to nodal D when K uses the
    element-mean D (fem.stiffness).  Dense (S * D, N), row s * D + d.
    """
    S, D = F.shape[1], G.shape[1]
    F = np.ascontiguousarray(F, dtype=float)
    G = np.ascontiguousarray(G, dtype=float)
    ops = _jacobian_operators(mesh)
    el, GGt = ops["elements"], ops["GGt"]
    E = ops["E_mean"]
    out = np.zeros((mesh.n_nodes, S * D))
    size = _chunk_size(S, D)

    def block(c0, c1):
        e = el[c0:c1]
        KF = np.matmul(GGt[c0:c1], F[e])                 # (C, nl, S): |e| grad_i . grad F_s
        return np.matmul(KF.transpose(0, 2, 1), G[e]).reshape(len(e), S * D)   # (C, S*D)

    _accumulate(out, len(el), size, block, E, ops.setdefault(("E_mean_rows", size), {}))
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
        # The emission operator is assembled on first use: excitation-only work
        # (mua Jacobians, reflectance) never pays for it.
        check_properties(_nodal(mesh, mua_m, "emission.mua_per_mm"),
                         _nodal(mesh, musp_m, "emission.musp_per_mm"), n_m, where="emission")
        self._op_m_args = (mesh, mua_m, musp_m, n_m, solver)
        self._op_m = None
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
        g, f = self.adjoint_x, self.phi_x
        J = triple_product_jacobian(self.mesh, g, f)               # (S*D, N) views, in place:
        grad = gradient_product_jacobian(self.mesh, g, f)          # no extra 100 MB temporaries
        grad *= (-3.0 * self.op_x.D ** 2)[None, :]                 # dD/dmua
        J += grad
        np.negative(J, out=J)
        return J


def safe_log(data, floor=1e-300):
    """Natural log of data with non-positive or underflowed values clipped to
    ``floor``; returns (log_data, valid_mask) so callers can drop them."""
    d = np.asarray(data, float)
    valid = np.isfinite(d) & (d > floor)
    return np.log(np.where(valid, d, floor)), valid
