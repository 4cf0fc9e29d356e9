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
    snap_to_surface,
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


#: groups of sources whose Jacobian rows are computed at a time where only the used
#: pairs' are asked for (``FluorescenceModel.jacobian_yield(mask)``): the transient
#: block is 1/4 of the whole, for 4 kernel calls instead of one
JACOBIAN_SOURCE_CHUNKS = 4


class FluorescenceModel:
    """Forward model of one tissue: sources, detectors, both wavelengths.

    Parameters
    ----------
    mesh : Mesh
    props_x, props_m : dicts with ``mua_per_mm``, ``musp_per_mm`` (scalar or
        nodal) and ``n``, at excitation (mua_x includes the fluorophore) and
        emission; optionally ``boundary`` (the boundary constant's method,
        ``optics.robin_A``; default ``optics.DEFAULT_BOUNDARY``)
    sources_mm, detectors_mm : (S, d), (D, d) surface points; sources are
        buried one MFP' below the nearest surface point
    solver : see DiffusionOperator
    source_normals : (S, d) outward unit normals of the true surface at the
        sources, to bury them along (default: the nearest facet's normal)
    cut_facets : bool mask over ``mesh.boundary_facets`` where the tissue goes on
        beyond the mesh (DiffusionOperator); default none
    lean : bool
        Free the excitation's factorisation as soon as its fields are solved,
        before the emission's is made (one large factor alive at a time: on the
        demo's 300k-node simulation mesh about 2 GB less at the peak).  For a
        model that solves each wavelength once (a simulation, a Jacobian, a
        self-absorption pass); a later excitation solve (``adjoint_x``)
        factorises again.  :meth:`release` frees what is left.
    """

    def __init__(self, mesh, props_x, props_m, sources_mm, detectors_mm, solver="auto",
                 max_snap_mm=5.0, source_normals=None, cut_facets=None, lean=False):
        t0 = time.perf_counter()
        self.lean = bool(lean)
        mua_x, musp_x, n_x = _props(mesh, props_x, "props_x")
        mua_m, musp_m, n_m = _props(mesh, props_m, "props_m")
        # the boundary constant's method (optics.robin_A), "boundary" in either dict
        self.boundary = props_x.get("boundary", props_m.get("boundary"))
        self.mesh = mesh
        self.cut_facets = cut_facets
        self.op_x = DiffusionOperator(mesh, mua_x, musp_x, n_x, solver, name="excitation",
                                      boundary=self.boundary, cut_facets=cut_facets)
        # The emission operator is assembled on first use: excitation-only work
        # (mua Jacobians, reflectance) never pays for it.
        check_properties(_nodal(mesh, mua_m, "emission.mua_per_mm"),
                         _nodal(mesh, musp_m, "emission.musp_per_mm"), n_m, where="emission")
        self._op_m_args = (mesh, mua_m, musp_m, n_m, solver)
        self._op_m = None
        self.sources_surface_mm = np.atleast_2d(np.asarray(sources_mm, float))
        self.detectors_mm = np.atleast_2d(np.asarray(detectors_mm, float))
        # what the model cannot do well here, in words (accuracy() adds more)
        self.notes = []
        self.sources_mm = source_positions(mesh, self.sources_surface_mm, self.op_x.musp,
                                           self.op_x.mua, max_snap_mm, notes=self.notes,
                                           normals=source_normals)
        self.max_snap_mm = max_snap_mm
        self.q = point_source_rhs(mesh, self.sources_mm)
        self.P = detector_operator(mesh, self.detectors_mm, max_snap_mm)
        self.setup_seconds = time.perf_counter() - t0
        self._phi_x = None
        self._adj_m = None
        self._adj_x = None
        self.timings = {"assembly": self.op_x.assembly_seconds}
        # progress(fraction, message) of the steps a Jacobian takes (set by the
        # caller: TissueModel); each step says what it is doing before it starts,
        # and a large factorisation its seconds as it goes (_factorized); cancel:
        # a CancelToken checked there
        self.progress = None
        self.cancel = None

    def _say(self, fraction, message):
        if self.progress is not None:
            self.progress(fraction, message)

    def _factorized(self, op, fraction, message):
        """``op`` factorised, reporting from beside a large factorisation."""
        return op.factorize(self.progress, fraction, message, self.cancel)

    @property
    def op_m(self):
        """Emission-wavelength operator (assembled on first use)."""
        if self._op_m is None:
            mesh, mua_m, musp_m, n_m, solver = self._op_m_args
            self._op_m = DiffusionOperator(mesh, mua_m, musp_m, n_m, solver, name="emission",
                                           boundary=self.boundary, cut_facets=self.cut_facets)
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
            self._say(0.0, f"excitation: factorising ({self.mesh.n_nodes} nodes) and solving "
                           f"{self.n_sources} source(s)")
            self._factorized(self.op_x, 0.0, f"excitation: factorising ({self.mesh.n_nodes} "
                                             "nodes)")
            self._phi_x = self.op_x.solve(self.q, readout=self.P)
            self.timings["forward_x"] = time.perf_counter() - t0
            self.timings["factor"] = self.op_x.factor_seconds
            if self.lean:
                self.op_x.release()
        return self._phi_x

    @property
    def adjoint_m(self):
        """(N, D) emission-wavelength adjoint fields (Green's function of each detector)."""
        if self._adj_m is None:
            t0 = time.perf_counter()
            self._say(0.4, f"emission: factorising and solving {self.n_detectors} detector "
                           "adjoint(s)")
            self._factorized(self.op_m, 0.4, "emission: factorising")
            self._adj_m = self.op_m.solve(self.P.T.tocsc(), readout=self.q.T)
            self.timings["adjoint_m"] = time.perf_counter() - t0
            self.timings["factor"] = self.timings.get("factor", 0) + self.op_m.factor_seconds
        return self._adj_m

    @property
    def adjoint_x(self):
        """(N, D) excitation-wavelength adjoint fields."""
        if self._adj_x is None:
            self._factorized(self.op_x, 0.0, "excitation: factorising")
            self._adj_x = self.op_x.solve(self.P.T.tocsc(), readout=self.q.T)
        return self._adj_x

    def release(self):
        """Free both wavelengths' factorisations once the solves are done (the
        fields solved so far are kept; a later solve factorises again)."""
        self.op_x.release()
        if self._op_m is not None:
            self._op_m.release()

    def excitation_data(self):
        """(S, D) excitation boundary fluence per unit source power."""
        return np.asarray((self.P @ self.phi_x).T)

    def emission_fields(self, yield_per_mm):
        """(N, S) emission fluence for a nodal yield (forward solves, no adjoint)."""
        gamma = np.asarray(yield_per_mm, float)
        rhs = weighted_mass(self.mesh, gamma) @ self.phi_x
        self._factorized(self.op_m, 0.4, "emission: factorising")
        return self.op_m.solve(rhs)

    def emission_data(self, yield_per_mm):
        """(S, D) emission boundary fluence per unit excitation power."""
        gamma = np.asarray(yield_per_mm, float)
        if gamma.shape != (self.mesh.n_nodes,) or not np.all(np.isfinite(gamma)):
            raise FluoInputError("needs one finite value per node", field="yield_per_mm",
                                 value=gamma.shape)
        return np.asarray(self.P @ self.emission_fields(gamma)).T

    def jacobian_yield(self, mask=None):
        """(S*D, N): d(emission data)/d(nodal yield), row s*D + d.

        ``mask`` (S, D) bool: only the used pairs' rows, (mask.sum(), N) in the
        order of ``mask.ravel()`` (the same as ``jacobian_yield()[mask.ravel()]``),
        computed for :data:`JACOBIAN_SOURCE_CHUNKS` groups of sources in turn, so
        that the whole S*D block is never held (on the oral case's 89k-node mesh it
        was 365 MB beside the 275 MB of the used rows). One kernel call per source
        instead cost 1.8x the time (each call walks every element)."""
        phi, adj = self.phi_x, self.adjoint_m
        t0 = time.perf_counter()
        if mask is not None:
            mask = np.asarray(mask, bool).reshape(self.n_sources, self.n_detectors)
            self._say(0.8, f"Jacobian kernel ({int(mask.sum())} pairs x "
                           f"{self.mesh.n_nodes} nodes)")
            J = np.empty((int(mask.sum()), self.mesh.n_nodes))
            row = 0
            for group in np.array_split(np.arange(self.n_sources), JACOBIAN_SOURCE_CHUNKS):
                rows = mask[group].ravel()
                if group.size and rows.any():
                    block = triple_product_jacobian(self.mesh, adj, phi[:, group])
                    J[row:row + int(rows.sum())] = block[rows]
                    row += int(rows.sum())
                    del block
            self.timings["jacobian"] = time.perf_counter() - t0
            self._say(1.0, "Jacobian done")
            return J
        self._say(0.8, f"Jacobian kernel ({self.n_sources * self.n_detectors} pairs x "
                       f"{self.mesh.n_nodes} nodes)")
        J = triple_product_jacobian(self.mesh, adj, phi)
        self.timings["jacobian"] = time.perf_counter() - t0
        self._say(1.0, "Jacobian done")
        return J

    def accuracy(self, target=0.05, wavelengths=("excitation",)):
        """How far this model's data can be from the exact solution of its
        equations, and whether they can be used at all.

        Estimates the discretisation error of every source-detector pair from
        the measured tables of :mod:`fem.resolution` (worst case over where
        the optodes sit in their elements, and the median), checks the solved
        fields for negative values (solving them if needed: the excitation
        fields, and the emission adjoints when "emission" is asked for), and
        collects what else limits the model (diffusion validity, sources near
        edges or in thin tissue, iterative solves that did not converge).

        Parameters
        ----------
        target : relative error [-] above which a pair is reported (0.05: 5 %)
        wavelengths : "excitation" and/or "emission"

        Returns
        -------
        dict with ``warnings`` (list of str), ``refuse`` (list of str: reasons
        the data must not be used unless the caller insists; negative or
        zero detector values, oscillating fields, elements beyond the
        measured range), ``estimated_rel_err`` per wavelength, ``negative_nodes``
        and ``element_size_needed_mm`` (the largest size that keeps every pair
        within ``target``, NaN if none does; None if every pair already is).
        """
        warnings_, refuse = list(self.notes), []
        report = {"target_rel_err": float(target), "estimated_rel_err": {},
                  "negative_nodes": {}, "element_size_needed_mm": None}
        q_src = snap_to_surface(self.mesh, self.sources_surface_mm, self.max_snap_mm)[0]
        q_det = snap_to_surface(self.mesh, self.detectors_mm, self.max_snap_mm, "detector")[0]
        needed = []
        for w in wavelengths:
            if w not in ("excitation", "emission"):
                raise FluoInputError("use excitation and/or emission", field="wavelengths",
                                     value=w)
            need = self._pair_errors(w, target, q_src, q_det, report, warnings_, refuse)
            if need is not None:
                needed.append(need)
        if needed:
            self._size_needed(needed, target, report, warnings_)
        self._field_signs(wavelengths, report, warnings_, refuse)
        y = self.excitation_data()
        if np.any(y <= 0):
            refuse.append(f"excitation: {int(np.sum(y <= 0))} detector value(s) are zero or "
                          "negative")
        for op in (self.op_x, self._op_m):
            if op is not None and getattr(op, "unconverged", None):
                warnings_.append(f"{op.name}: {op.unconverged}")
        report["warnings"] = warnings_
        report["refuse"] = refuse
        return report

    def _pair_errors(self, w, target, q_src, q_det, report, warnings_, refuse):
        """:meth:`accuracy`'s estimate for wavelength ``w`` of every source-detector
        pair's discretisation error (into ``report["estimated_rel_err"][w]``),
        with the diffusion validity, pairs too near their source and pairs over
        ``target`` in ``warnings_``, and elements beyond the measured range in
        ``refuse``.  ``q_src``, ``q_det``: the optodes on the surface [mm].
        Returns the largest element size [mm] that keeps every pair within
        ``target`` (NaN if none does), or None if every pair already is."""
        from FluoTomoLib.fem.resolution import log_error_estimate, pair_sizes, required_size
        from FluoTomoLib.optics import NEAR_SOURCE_MFP, diffusion_validity, mueff

        op = self.op_x if w == "excitation" else self.op_m
        me = float(np.max(mueff(op.mua, op.musp)))
        mt = float(np.max(op.mua + op.musp))
        warnings_ += [f"{w}: {m}" for m in diffusion_validity(op.mua, op.musp)]
        h, rho = pair_sizes(self.mesh, self.sources_mm, q_src, q_det, mueff(op.mua, op.musp))
        worst = np.expm1(log_error_estimate(me * h, mt * h, rho / h, op.n))
        median = np.expm1(log_error_estimate(me * h, mt * h, rho / h, op.n, worst=False))
        over = worst > target
        near = rho < NEAR_SOURCE_MFP / mt
        report["estimated_rel_err"][w] = {
            "worst_case": _finite_or_none(worst), "median_case": _finite_or_none(median),
            "worst_case_max": _finite_or_none(np.max(worst)),
            "median_case_max": _finite_or_none(np.max(median)),
            "pairs": int(worst.size), "pairs_over_target": int(over.sum()),
            "element_size_mm": h.tolist(), "mueff_h_max": float(me * h.max())}
        if np.any(near):
            warnings_.append(f"{w}: {int(near.sum())} pair(s) are within {NEAR_SOURCE_MFP:g} "
                             f"transport mean free paths ({NEAR_SOURCE_MFP / mt:.3g} mm): "
                             "diffusion theory itself over-predicts there")
        needed = None
        if np.any(over):
            need = required_size(me, mt, rho[over], h[over], op.n, target)
            needed = float(np.min(need)) if np.all(np.isfinite(need)) else np.nan
            s, d = np.unravel_index(np.argmax(np.where(over, worst, -1)), worst.shape)
            worst_txt = ("beyond the measured range" if not np.isfinite(worst[s, d])
                         else f"up to {100 * worst[s, d]:.3g} %")
            warnings_.append(
                f"{w}: {int(over.sum())} of {over.size} source-detector pairs may be off by "
                f"more than {100 * target:g} % ({worst_txt} for source {s} -> detector {d}, "
                f"rho {rho[s, d]:.3g} mm, elements ~{h[s, d]:.3g} mm there, mueff "
                f"{me:.3g} /mm; median case {100 * np.max(median[over]):.3g} %)")
        if np.any(~np.isfinite(worst)):
            refuse.append(f"{w}: elements of ~{float(np.max(h)):.3g} mm are too coarse for "
                          f"mueff {me:.3g} /mm (mueff h = {me * float(np.max(h)):.3g}; "
                          "measured on Kuhn cubes, the fluence goes negative from mueff h "
                          "1.0-1.4 on, docs/fem.md)")
        return needed

    def _size_needed(self, needed, target, report, warnings_):
        """The element size [mm] that keeps every pair of every wavelength within
        ``target`` (the smallest of ``needed``, NaN if none does) into
        ``report["element_size_needed_mm"]``, and in ``warnings_`` how many of
        the elements around the optodes are larger."""
        from FluoTomoLib.fem.resolution import element_sizes

        size = float(np.nanmin(needed)) if np.any(np.isfinite(needed)) else np.nan
        report["element_size_needed_mm"] = size
        h_el = element_sizes(self.mesh)
        region = self._optode_region_elements()
        if np.isfinite(size):
            big = region & (h_el > size)
            warnings_.append(f"elements of at most {size:.3g} mm around the optodes and along "
                             f"the paths between them would keep every pair within "
                             f"{100 * target:g} %; {int(big.sum())} of the {int(region.sum())} "
                             "elements there are larger")
        else:
            warnings_.append("some detectors are so close to their source that no element "
                             "size keeps them within the target: read them with care")

    def _field_signs(self, wavelengths, report, warnings_, refuse):
        """The solved fields' negative values (the excitation fields, and the
        emission adjoints when ``wavelengths`` asks for "emission"; solved here if
        not yet) into ``report["negative_nodes"]``: oscillation, refused in
        ``refuse`` when deep enough to reach the weakest datum, else a warning."""
        # the solved fields themselves: negative values show oscillation
        fields = [("excitation", lambda: self.phi_x)]
        if "emission" in wavelengths:
            fields.append(("emission", lambda: self.adjoint_m))
        # A dip matters when it reaches the weakest datum: refuse where a negative value
        # is more than 1e-3 of the weakest detector's reading (both relative to the
        # field's peak), and never below 1e-10 of the peak (rounding).
        y_all = self.excitation_data()
        weakest = float(np.min(y_all) / max(float(np.max(y_all)), 1e-300)) if y_all.size else 1.0
        floor = -max(1e-10, 1e-3 * max(weakest, 0.0))
        for w, get in fields:
            phi = get()
            neg = int(np.sum(phi < 0))
            ratio = float(np.min(phi.min(axis=0) / np.maximum(phi.max(axis=0), 1e-300)))
            report["negative_nodes"][w] = {"count": neg, "nodes": int(phi.size),
                                           "min_over_max": ratio,
                                           "refuse_below": floor}
            if ratio < floor:
                refuse.append(f"{w}: {neg} of {phi.size} nodal values are negative (down to "
                              f"{ratio:.2g} of the peak): the mesh is too coarse for these "
                              "properties and the data are not usable")
            elif neg:
                warnings_.append(f"{w}: {neg} nodal values are negative (at most {-ratio:.2g} of "
                                 "the peak): the far field there is below what this mesh resolves")

    def _optode_region_elements(self):
        """Elements within the box around the optodes, 3 decay lengths deep."""
        from FluoTomoLib.optics import mueff

        pts = np.concatenate([self.sources_surface_mm, self.detectors_mm])
        me = float(np.max(mueff(self.op_x.mua, self.op_x.musp)))
        pad = min(3.0 / max(me, 1e-12), float(np.max(np.ptp(self.mesh.nodes_mm, axis=0))))
        c = self.mesh.nodes_mm[self.mesh.elements].mean(axis=1)
        return np.all((c >= pts.min(axis=0) - pad) & (c <= pts.max(axis=0) + pad), axis=1)

    def jacobian_mua_x(self):
        """(S*D, N): d(excitation data)/d(nodal mua_x), row s*D + d.

        Includes both ways absorption acts: the absorption term itself and,
        through D = 1/(3 (mua + musp)), the diffusion coefficient.
        """
        return mua_jacobian(self.mesh, self.adjoint_x, self.phi_x, self.op_x.D)


def _finite_or_none(a):
    """JSON-ready: floats, with None where the estimate is beyond the table."""
    a = np.asarray(a, float)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_finite_or_none(v) for v in a]


def safe_log(data, floor=1e-300):
    """Natural log of data with non-positive or underflowed values clipped to
    ``floor``; returns (log_data, valid_mask) so callers can drop them."""
    d = np.asarray(data, float)
    valid = np.isfinite(d) & (d > floor)
    return np.log(np.where(valid, d, floor)), valid
