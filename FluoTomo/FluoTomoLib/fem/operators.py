"""Finite-element CW diffusion on linear triangles (2D) and tetrahedra (3D).

Weak form of -div(D grad Phi) + mua Phi = q with the Robin boundary
Phi + 2 A D dPhi/dn = 0 (docs/physics.md sections 1-2):

    (K + M_mua + B / (2A)) Phi = b

K: stiffness with element-mean D (exact for nodal, linearly varying D),
M_mua: mass matrix weighted by nodal mua (exact P1 triple products),
B: boundary-facet mass (row-sum lumped), b: point-source load (barycentric
weights).

What is expensive is computed once per mesh and cached on it (gradients,
the upper-triangle sparsity pattern and each element's place in it, boundary
weights); a new set of optical properties only refills the values (compiled
loops, assembly_kernels.py), and one Cholesky factorisation (MKL PARDISO,
pardiso.py) serves every source and adjoint.
"""

from __future__ import annotations

import time
from math import factorial

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fluoguide.errors import FluoInputError

from FluoTomoLib.fem.assembly_kernels import element_gradients, upper_pattern, upper_values
from FluoTomoLib.fem.jacobian_kernels import node_elements
from FluoTomoLib.fem.locate import boundary_locator, locator
from FluoTomoLib.optics import check_properties, diffusion_coefficient, robin_A
from FluoTomoLib.fem.ordering import geometric_nested_dissection
from FluoTomoLib.fem.pardiso import PardisoCholesky, PardisoPattern, mkl_pardiso


# ---------------------------------------------------------------- geometry cache

class _Geometry:
    """Per-mesh quantities that do not depend on optical properties: basis
    gradients, measures, the upper-triangle CSR pattern with each element's
    positions in it, and the lumped boundary mass per node."""

    def __init__(self, mesh):
        mesh.check_elements()
        if np.any(mesh.signed_measures < 0):
            raise FluoInputError(
                f"{int(np.sum(mesh.signed_measures < 0))} inverted element(s); "
                "orient the mesh (Mesh.oriented()) before solving",
                field=f"{mesh.name}.elements[{int(np.flatnonzero(mesh.signed_measures < 0)[0])}]")
        d = mesh.dim
        # int32 element indices: half the memory traffic in every element loop
        el = np.ascontiguousarray(mesh.elements, dtype=np.int32 if mesh.n_nodes < 2 ** 31 - 1
                                  else np.int64)
        self.elements = el
        self.grad, _ = element_gradients(np.ascontiguousarray(mesh.nodes_mm, dtype=float), el)
        self.vol = mesh.measures
        self.n = mesh.n_nodes
        self.dim = d
        # exact integral of a product of three P1 functions: |e| d! a!b!c!/(d+a+b+c)!
        self.c3 = factorial(d) / factorial(d + 3)
        # elements around each node: the CSR pattern and the Jacobians use it
        self.adjacency = node_elements(el, self.n)
        self.indptr, self.indices, self.pos, self.diag = upper_pattern(el, self.n, *self.adjacency)
        self._mesh = mesh
        self._boundary_weight = None
        self._pardiso_pattern = None

    def pardiso_pattern(self):
        """The PARDISO analysis of this mesh's pattern, shared by its operators.

        Meshes on a grid (meshing.structured, meshing.voxel: meta "method" =
        "structured") are ordered by geometric nested dissection (0.05 s, fill
        within 2 % of METIS or below it, 0.13-0.22 s less analysis on 60-86k
        nodes);
        others by PARDISO's METIS, which gave a third of the geometric
        ordering's factorisation time on an fTetWild mesh (docs/fem.md).
        """
        if self._pardiso_pattern is None:
            order = None
            if self._mesh.meta.get("method") == "structured":
                order = geometric_nested_dissection(self._mesh.nodes_mm, self.indptr,
                                                    self.indices)
            self._pardiso_pattern = PardisoPattern(self.indptr, self.indices, slots=4,
                                                   name=f"{self._mesh.name}.K", order=order)
        return self._pardiso_pattern

    def boundary_weight(self, facet_mask=None):
        """Lumped boundary mass per node over the facets where ``facet_mask`` is
        True (all if None): each facet gives a 1/d share of its measure to each
        of its nodes.

        Row-sum lumping: the consistent facet mass has positive off-diagonal
        terms that outweigh the (negative) stiffness couplings when D is small
        (musp ~ 100/mm), which breaks the M-matrix property and makes boundary
        fluence oscillate negative.  Lumping keeps it positive at O(h^2) cost.
        """
        if facet_mask is None and self._boundary_weight is not None:
            return self._boundary_weight
        f = self._mesh.boundary_facets
        fm = self._mesh.boundary_facet_measures
        if facet_mask is not None:
            sel = np.asarray(facet_mask, bool)
            f, fm = f[sel], fm[sel]
        w = np.bincount(f.ravel(), weights=np.repeat(fm / self.dim, self.dim), minlength=self.n)
        if facet_mask is None:
            self._boundary_weight = w
        return w

    def upper(self, D_nodal, w_nodal, diag_add=None):
        """Upper triangle (CSR, sorted) of K(D) + M(w) [+ diag(diag_add)]."""
        data = upper_values(self.elements, self.pos, self.grad, self.vol, self.c3,
                            np.ascontiguousarray(D_nodal, dtype=float),
                            np.ascontiguousarray(w_nodal, dtype=float), len(self.indices))
        if diag_add is not None:
            data[self.diag] += diag_add
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    @property
    def boundary_mass(self):
        """Lumped boundary mass over every boundary facet (diagonal, CSR)."""
        return sp.diags(self.boundary_weight(), format="csr")


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


def symmetric_from_upper(U):
    """Full symmetric CSR from its upper triangle."""
    return (U + sp.triu(U, k=1, format="csr").T).tocsr()


def weighted_mass(mesh, w_nodal):
    """Mass matrix weighted by a nodal field w: M_ij = integral w phi_i phi_j (exact)."""
    g = geometry(mesh)
    w = _nodal(mesh, w_nodal, "weight")
    return symmetric_from_upper(g.upper(np.zeros(g.n), w))


def stiffness(mesh, D_nodal):
    """Stiffness K_ij = integral D_e grad phi_i . grad phi_j (element-mean D)."""
    g = geometry(mesh)
    D = _nodal(mesh, D_nodal, "D")
    return symmetric_from_upper(g.upper(D, np.zeros(g.n)))


# ---------------------------------------------------------------- solver

#: the linear solvers a DiffusionOperator knows (docs/fem.md)
SOLVERS = ("auto", "pardiso", "splu", "amg")


def check_solver(name, field="solver"):
    """``name`` if it is one of :data:`SOLVERS`, else FluoInputError naming them."""
    if name not in SOLVERS:
        raise FluoInputError(f"unknown solver; use {', '.join(SOLVERS)}", field=field, value=name)
    return name


def _pardiso_available():
    return mkl_pardiso() is not None


#: operators with at least this many nodes are factorised on a helper thread
#: beside one that reports (DiffusionOperator.factorize). Measured on structured
#: cubes, a loaded 2-core machine: PARDISO 0.15-0.3 s at 22,000 nodes, 0.65-0.85 s
#: at 47,000, 2.7-2.9 s at 97,000, as fast on the helper as on the caller's
#: thread; the helper costs 5-10 ms (a thread and its OpenMP team), which only
#: a small mesh's factorisation (1 ms at 1,300 nodes) would notice
REPORTING_NODES = 20_000


class MeshResolutionWarning(UserWarning):
    """Elements are large compared with the light's decay length 1/mueff."""


# mueff h from which the discrete solution goes negative: measured on Kuhn
# cubes (benchmarks/bench_fem_accuracy.py), a few far-field nodes at 1.0 and
# tens of thousands of nodes, down to -1 % of the peak, at 1.4 (docs/fem.md)
NEGATIVE_FROM_MUEFF_H = 1.0


def _check_resolution(mesh, mua, musp, name):
    """Warn when the elements are so coarse that the fluence oscillates.

    The operator knows no optodes; FluorescenceModel.accuracy() estimates
    the error of each source-detector pair (fem/resolution.py)."""
    import warnings

    from FluoTomoLib.fem.resolution import element_sizes
    from FluoTomoLib.optics import mueff

    # the median of at most ~20k elements: this runs on every operator
    h = float(np.median(element_sizes(mesh, np.arange(0, mesh.n_elements,
                                                      max(1, mesh.n_elements // 20000)))))
    me = float(np.max(mueff(mua, musp)))
    if h * me >= NEGATIVE_FROM_MUEFF_H:
        warnings.warn(f"{name}: elements (~{h:.2g} mm) are coarse for a decay length 1/mueff = "
                      f"{1 / me:.2g} mm (mueff h = {h * me:.2g} >= {NEGATIVE_FROM_MUEFF_H:g}): "
                      "the fluence goes negative and far-field values are wrong; elements of "
                      f"{0.3 / me:.2g} mm or less are needed for a few percent (docs/fem.md)",
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
    cut_facets : bool mask over ``mesh.boundary_facets`` where the tissue goes on
        beyond the mesh (a label map cropped through tissue): the continuation
        condition -D dPhi/dn = sqrt(mua D) Phi of a field decaying as
        exp(-mueff x) into the same tissue, instead of the tissue-air condition
        (docs/physics.md section 2.5). Default: none.
    solver : "auto" (PARDISO if MKL loads, else SuperLU), "pardiso", "splu" or "amg"
        (smoothed-aggregation AMG preconditioned CG, for meshes too big to factorise)
    boundary : the boundary constant A's method for ``optics.robin_A`` ("empirical" or
        "fresnel"; None: ``optics.DEFAULT_BOUNDARY``), e.g. "empirical" to reproduce
        work made with NIRFAST's constant (the thesis studies)
    """

    def __init__(self, mesh, mua_per_mm, musp_per_mm, n, solver="auto", name="operator",
                 robin_facets=None, boundary=None, cut_facets=None):
        mesh.check_topology()
        mua = _nodal(mesh, mua_per_mm, f"{name}.mua_per_mm")
        musp = _nodal(mesh, musp_per_mm, f"{name}.musp_per_mm")
        check_properties(mua, musp, n, where=name)
        _check_resolution(mesh, mua, musp, name)
        self.mesh = mesh
        self.name = name
        self.mua = mua
        self.musp = musp
        self.n = float(n)
        self.boundary = boundary
        self.A = float(robin_A(self.n, boundary))
        self.D = diffusion_coefficient(mua, musp)
        t0 = time.perf_counter()
        g = geometry(mesh)
        self.robin_facets = robin_facets
        self.cut_facets = cut_facets
        boundary_coef = g.boundary_weight(robin_facets) * (1.0 / (2.0 * self.A))
        if cut_facets is not None and np.any(cut_facets):
            cut = np.asarray(cut_facets, bool)
            air = ~cut if robin_facets is None else (np.asarray(robin_facets, bool) & ~cut)
            boundary_coef = (g.boundary_weight(air) * (1.0 / (2.0 * self.A))
                             + g.boundary_weight(cut) * np.sqrt(mua * self.D))
        # assembled as the upper triangle PARDISO factorises; the full matrix
        # (K) is built only when asked for (SuperLU, AMG, matrix products)
        self.K_upper = g.upper(self.D, mua, boundary_coef)
        self._K = None
        self.assembly_seconds = time.perf_counter() - t0
        self.factor_seconds = 0.0
        self._solver_request = check_solver(solver)
        self._solve = None
        self.solver_name = None
        self.n_solves = 0
        self.unconverged = None

    @property
    def K(self):
        """The full symmetric system matrix (CSC)."""
        if self._K is None:
            self._K = symmetric_from_upper(self.K_upper).tocsc()
        return self._K

    def factorize(self, progress=None, fraction=0.0, message=None, cancel=None):
        """Factorise K for the solves (once; :meth:`release` frees it).

        Parameters
        ----------
        progress : progress(fraction, message) or None. With one, an operator of
            at least :data:`REPORTING_NODES` nodes is factorised on a helper
            thread while the calling thread reports ``message`` and the seconds
            so far, every second (``fluoguide.progress.run_reporting``): the
            factorisation is one call into the solver's library, seconds long
            on a large mesh, that cannot report from inside.
        fraction : where on ``progress``'s bar these reports go (0..1)
        message : what they say (default: "factorising the <name> operator")
        cancel : CancelToken: checked at each report; a cancelled factorisation
            runs to its end on its helper thread and is then freed, unused.

        Returns
        -------
        self
        """
        if self._solve is not None:
            return self
        t0 = time.perf_counter()
        if progress is not None and self.mesh.n_nodes >= REPORTING_NODES:
            from fluoguide.progress import run_reporting

            what = message or f"factorising the {self.name} operator ({self.mesh.n_nodes} nodes)"
            made = run_reporting(self._factorization, progress, fraction, what, cancel)
        else:
            made = self._factorization()
        # set here, on the caller's thread, only once it is whole
        self._solve, self.solver_name, self._amg = made
        self.factor_seconds = time.perf_counter() - t0
        return self

    def _factorization(self):
        """(solve, solver name, AMG hierarchy or None) of K; nothing of this
        operator is changed but its caches of K (any thread may run it)."""
        req = self._solver_request
        pardiso = req in ("auto", "pardiso") and _pardiso_available()
        if req == "pardiso" and not pardiso:
            raise FluoInputError("PARDISO (MKL) is not available", field="solver", value=req)
        if pardiso:
            return (PardisoCholesky(self.K_upper, name=f"{self.name}.K",
                                    pattern=geometry(self.mesh).pardiso_pattern()),
                    "pardiso", None)
        if req == "amg":
            import pyamg

            amg = pyamg.smoothed_aggregation_solver(self.K.tocsr(), symmetry="symmetric")
            return self._amg_solve, "amg-cg", amg
        lu = spla.splu(self.K, permc_spec="MMD_AT_PLUS_A")
        return lu.solve, "superlu", None

    def release(self):
        """Free the factorisation (on a 150k-node mesh about a GB); the matrix
        stays, and the next solve factorises again."""
        release = getattr(self._solve, "release", None)
        if release is not None:
            release()
        self._solve = None
        self._amg = None

    # AMG-CG: the relative residual of each step, and the change of the read-out
    # values below which a solve counts as converged.  A residual of 1e-10
    # (the old fixed tolerance) left detectors at 1e-13 of the peak +125 % off
    # and ones 60 mm away x8e4 (issue 18); the tolerance now follows them.
    AMG_TOLERANCES = (1e-8, 1e-10, 1e-12, 1e-14)
    AMG_READOUT_RTOL = 1e-4

    def _amg_solve(self, B, readout=None):
        """AMG-CG, tightening the tolerance until the values ``readout @ x``
        (detectors, sources) change by less than AMG_READOUT_RTOL; without a
        read-out, until the whole solution does (relative to its peak)."""
        B2 = B.reshape(len(B), -1)
        X = np.empty_like(B2)
        bad = []
        for j in range(B2.shape[1]):
            x, prev = None, None
            for tol in self.AMG_TOLERANCES:
                x = self._amg.solve(B2[:, j], x0=x, tol=tol, accel="cg", maxiter=1000)
                y = readout @ x if readout is not None else x
                if prev is not None:
                    scale = np.abs(y) if readout is not None else np.max(np.abs(y))
                    change = np.abs(y - prev) / np.maximum(scale, 1e-300)
                    if np.all(change < self.AMG_READOUT_RTOL):
                        break
                prev = y
            else:
                bad.append((j, int(np.sum(change >= self.AMG_READOUT_RTOL))))
            X[:, j] = x
        if bad:
            n = sum(k for _, k in bad)
            self.unconverged = (f"AMG-CG did not converge for {n} read-out value(s) of "
                                f"{len(bad)} right-hand side(s) at a relative residual of "
                                f"{self.AMG_TOLERANCES[-1]:g} (values too small against the "
                                "peak for an iterative solver): use solver='pardiso'")
        return X.reshape(B.shape)

    def solve(self, B, readout=None):
        """Solve K X = B for a vector (N,) or a block (N, k); dense result.

        ``readout`` (sparse (k, N), optional): the values the caller will read
        from X (detectors); an iterative solver (AMG) converges until they
        stop changing.  Direct solvers ignore it.
        """
        self.factorize()
        if sp.issparse(B):
            B = B.toarray()
        B = np.asarray(B, dtype=float)
        if self.solver_name == "amg-cg":
            X = self._amg_solve(B, readout)
        else:
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


def _inward_directions(mesh, q, facet, bary, tol=1e-9):
    """Unit inward directions at boundary points: the facet's normal inside a
    facet, the angle-weighted mean of the normals of the facets around an
    edge or a vertex (a side facet's normal alone would bury a source at an
    edge sideways, along the top surface)."""
    bf = mesh.boundary_facets
    nrm = mesh.boundary_normals
    p = mesh.nodes_mm
    out = nrm[facet].copy()
    for i in np.flatnonzero(np.any(bary <= tol, axis=1)):
        on = bf[facet[i]][bary[i] > tol]          # the nodes spanning q's edge or vertex
        around = np.flatnonzero(np.isin(bf, on).sum(axis=1) == len(on))
        if len(on) == 1 and mesh.dim == 3:
            # vertex: each facet weighted by its angle there
            w = np.empty(len(around))
            for k, f in enumerate(around):
                a = p[bf[f][bf[f] != on[0]]] - p[on[0]]
                c = np.dot(a[0], a[1]) / max(np.linalg.norm(a[0]) * np.linalg.norm(a[1]), 1e-300)
                w[k] = np.arccos(np.clip(c, -1.0, 1.0))
        else:
            w = np.ones(len(around))               # an edge (or a 2D vertex): two facets
        v = (w[:, None] * nrm[around]).sum(axis=0)
        if np.linalg.norm(v) > 1e-12:
            out[i] = v / np.linalg.norm(v)
    return -out


def source_positions(mesh, surface_points_mm, musp_per_mm, mua_per_mm, max_snap_mm=5.0,
                     notes=None, normals=None):
    """Buried isotropic sources: one transport MFP (1/mut') inside the tissue
    below the nearest surface point (docs/physics.md section 2.2).

    Inside a facet the source moves along its inward normal.  At an edge or
    a corner it moves along the mean inward normal of the facets there, as
    far as it takes to be 1/mut' from every surface (1/mut' * sqrt(2) along
    the bisector of a right-angled edge).  A source that cannot be buried
    that deep (the tissue is thinner than 1/mut' there) is refused; one
    that ends closer than 1/mut' to another surface (thin tissue, near an
    edge) is kept and, when ``notes`` is a list, described there.

    ``normals``: (S, d) outward unit normals of the true surface to bury
    along instead of the facets' (a voxel mesh's facet normals are axis
    directions on a curved surface, and its edges are staircase steps, not
    corners of the tissue: no bisector search there).
    """
    q, facet, bary = snap_to_surface(mesh, surface_points_mm, max_snap_mm, "source")
    mua = _nodal(mesh, mua_per_mm, "mua_per_mm")
    musp = _nodal(mesh, musp_per_mm, "musp_per_mm")
    fnodes = mesh.boundary_facets[facet]
    depth = 1.0 / np.einsum("ij,ij->i", bary, (mua + musp)[fnodes])
    if normals is None:
        inward = _inward_directions(mesh, q, facet, bary)
        wedge = np.any(bary <= 1e-9, axis=1)      # on an edge or a vertex
    else:
        inward = -np.atleast_2d(np.asarray(normals, float))
        wedge = np.zeros(len(q), bool)
    bl = boundary_locator(mesh)
    t = depth.copy()
    pos = q + inward * t[:, None]
    for _ in range(4 if np.any(wedge) else 0):
        d = bl.closest(pos)[3]
        short = wedge & (d < depth * (1 - 1e-6))
        if not np.any(short):
            break
        # in a wedge of planar faces the distance grows linearly along the
        # bisector: one step lands on it; never more than 3 depths along
        t = np.where(short, np.minimum(t * depth / np.maximum(d, 1e-12 * depth), 3 * depth), t)
        pos = q + inward * t[:, None]
    elem, _ = locator(mesh).locate(pos)
    for i in np.flatnonzero(elem < 0):
        # a facet of a voxel mesh's staircase (or a sloped facet shared with air)
        # can point the normal across a thin shelf while the tissue is thick a
        # little to the side: try the inward normals of the facets around it
        alt = _bury_around(mesh, q[i], facet[i], depth[i], bl)
        if alt is None:
            raise FluoInputError(f"cannot be buried 1/mut' = {depth[i]:.3g} mm deep: the tissue "
                                 "under it is thinner than that", field=f"source[{i}]",
                                 value=np.round(q[i], 4).tolist())
        pos[i] = alt
        if notes is not None:
            notes.append(f"source[{i}]: its facet's normal leaves the tissue within 1/mut' = "
                         f"{depth[i]:.3g} mm; buried along a neighbouring facet's normal instead")
    d = bl.closest(pos)[3]
    for i in np.flatnonzero(d < 0.7 * depth):
        if notes is not None:
            notes.append(f"source[{i}] is {d[i]:.3g} mm from the nearest surface, less than its "
                         f"burial depth 1/mut' = {depth[i]:.3g} mm (thin tissue or an edge "
                         "nearby): the diffusion model is less accurate there")
    return pos


def _bury_around(mesh, q, facet, depth, bl):
    """A point ``depth`` inside the mesh from boundary point ``q`` along the
    inward normal of a boundary facet next to ``facet`` (sharing a node with it,
    or the next ring), the one that ends farthest from the surface; None when
    every such direction leaves the mesh."""
    bf = mesh.boundary_facets
    nodes = set(bf[facet].tolist())
    ring = np.flatnonzero(np.isin(bf, list(nodes)).any(axis=1))
    ring2 = np.flatnonzero(np.isin(bf, np.unique(bf[ring])).any(axis=1))
    dirs = -mesh.boundary_normals[np.unique(np.concatenate([ring, ring2]))]
    cand = q[None, :] + dirs * depth
    elem, _ = locator(mesh).locate(cand)
    inside = np.flatnonzero(elem >= 0)
    if not len(inside):
        return None
    d = bl.closest(cand[inside])[3]
    return cand[inside[int(np.argmax(d))]]


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
