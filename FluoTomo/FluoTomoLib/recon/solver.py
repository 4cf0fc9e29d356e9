"""Reconstruction of fluorescence yield: no priors, soft priors, hard priors.

docs/physics.md section 8.3.  The update of the reference,

    d_mu = (J^T J + R)^-1 J^T (y - F(mu)),

is a Levenberg-Marquardt step whose damping R also regularises.  With the
absorption known the data are linear in yield (F(mu) = J mu), so J is fixed and
the iteration runs until the residual sum of squares changes by less than 2 %
or 40 iterations pass.  Every step is solved in data space,

    (J^T J + R)^-1 J^T r = R^-1 J^T (J R^-1 J^T + I)^-1 r,

which needs only R^-1 applied to M vectors (M = number of measurements), so
the soft-prior matrix L is never formed: L = diag(1 + 1/N_r) - B B^T with B
the region-averaging basis, whose inverse is closed-form per region.  A 3D
reconstruction mesh of 10^5 nodes therefore costs O(M^2 N), not O(N^3).

Non-negativity: yield is a concentration times a quantum yield, so after each
update negative nodal values are set to zero (a projected LM step).  Reported
as ``clipped_fraction``.

Regularisations:
- NP: R = lambda * max(diag(J^T J)) * I
- SP: R = lambda' L^T L,  L_ii = 1, L_ij = -1/N_r (same region r), lambda' as NP
- HP: unknowns are one yield per region, J_r = J K (or a caller's finer region
  Jacobian, :func:`region_jacobian`); Marquardt damping lambda * diag(J_r^T J_r)

Data model (opt-in; the default is the linear update above):
- ``log_data``: fit ln y as NIRFAST's fluorescence reconstruction does
  (reconstruct_fl*.m): residual ln y - ln(J x), Jacobian diag(1 / J x) J.
- ``normalise``: Jacobian columns scaled by the current yield (NIRFAST's
  J diag(gamma)), step multiplied by it; lambda' is taken from the scaled J.
Both re-linearise every iteration; lambda stays fixed for NP and SP, as in
NIRFAST's fluorescence routines.  The thesis's studies A-C are reproduced with
both on (docs/reconstruction.md); with linear data the near-source pairs set
lambda' and a deep target's soft-prior constant is damped ~40x more than its
data can move it (study B, 6.5 mm: -89 % instead of -1 %).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report


@dataclass
class ReconResult:
    method: str
    lam: float
    yield_per_mm: np.ndarray          # nodal yield on the reconstruction mesh
    iterations: int
    residual_history: list
    seconds: float
    region_confidence: dict = field(default_factory=dict)
    clipped_fraction: float = 0.0
    stop_reason: str = ""

    @property
    def residual(self):
        return self.residual_history[-1]

    def summary(self):
        return {"method": self.method, "lambda": self.lam, "iterations": self.iterations,
                "residual_ss": self.residual, "initial_residual_ss": self.residual_history[0],
                "stop_reason": self.stop_reason, "seconds": self.seconds,
                "clipped_fraction": self.clipped_fraction,
                "region_confidence": self.region_confidence}


class RegionPrior:
    """Region structure of the reconstruction nodes (from the CBCT labels).

    Parameters
    ----------
    node_region : (N,) int region label per node
    """

    def __init__(self, node_region):
        r = np.asarray(node_region)
        if r.ndim != 1 or len(r) == 0:
            raise FluoInputError("needs one region label per node", field="node_region",
                                 value=np.shape(node_region))
        self.node_region = r
        self.labels, self.index, self.counts = np.unique(r, return_inverse=True,
                                                         return_counts=True)
        self.index = self.index.ravel()
        for lab, c in zip(self.labels, self.counts):
            if c < 2:
                # one node cannot be smoothed towards its region's mean; say so
                import warnings

                warnings.warn(f"region {int(lab)} has a single node: soft prior leaves it free",
                              stacklevel=2)

    def K(self):
        """(N, n_regions) 0/1 region membership (hard-prior basis), dense."""
        K = np.zeros((len(self.node_region), len(self.labels)))
        K[np.arange(len(self.node_region)), self.index] = 1.0
        return K

    def _sums(self, X):
        """Per-region sums of the rows of X ((N,) or (N, k))."""
        import scipy.sparse as sp

        if not hasattr(self, "_B"):
            n = len(self.node_region)
            self._B = sp.csr_matrix((np.ones(n), (self.index, np.arange(n))),
                                    shape=(len(self.labels), n))
        return self._B @ X

    def region_mean(self, x):
        return self._sums(np.asarray(x, float)) / (self.counts if np.ndim(x) == 1
                                                    else self.counts[:, None])

    def apply_L(self, x):
        """L x with L_ii = 1, L_ij = -1/N_r for i != j in region r."""
        n = self.counts[self.index]
        return x * (1 + 1 / n) - self.region_mean(x)[self.index]

    def apply_L_inv(self, X):
        """L^-1 X: per region L = c I - (1/N) 1 1^T, c = 1 + 1/N, whose inverse is
        (1/c) (I + 1 1^T) (Sherman-Morrison).  X may be (N,) or (N, k)."""
        X = np.asarray(X, float)
        c = 1 + 1 / self.counts[self.index]
        sums = self._sums(X)[self.index]
        return (X + sums) / (c if X.ndim == 1 else c[:, None])

    def apply_LtL_inv(self, X):
        """(L^T L)^-1 applied to X (L is symmetric)."""
        return self.apply_L_inv(self.apply_L_inv(X))


def _chol_solve(L, b):
    """Solve (L L^T) x = b for the Cholesky factor L of the data-space matrix
    S = J R^-1 J^T + I (symmetric positive definite)."""
    from scipy.linalg import solve_triangular

    return solve_triangular(L.T, solve_triangular(L, b, lower=True), lower=False)


def region_jacobian(J_forward, forward_region, labels):
    """Hard-prior Jacobian built at the forward-mesh resolution, J_hp = J_f K_f.

    A hard prior is a piecewise-constant field from the segmentation, so its
    basis can live on the forward mesh, where the data were simulated (or the
    labels are finest).  Mapping a 0/1 basis from the coarser reconstruction
    mesh through the interpolation P (J_r = J_f P K) smears its staircase
    boundary, and the region value must then compensate by an amount that
    depends on how the target sits on the coarse grid (study B: -0.7 / -10 %
    alternating with depth; -1.1 to -1.6 % with this basis).

    Parameters
    ----------
    J_forward : (M, N_f) Jacobian d(data)/d(yield) on the forward mesh
        [data units per (1/mm)]
    forward_region : (N_f,) int region label of every forward-mesh node
    labels : (R,) region labels, in the order of the unknowns (``prior.labels``
        of the reconstruction mesh's RegionPrior)

    Returns
    -------
    (M, R) sensitivity of the data to each region's yield, for
    ``reconstruct(..., region_jacobian=...)``.
    """
    region = np.asarray(forward_region).ravel()
    J_forward = np.asarray(J_forward, float)
    if J_forward.ndim != 2 or len(region) != J_forward.shape[1]:
        raise FluoInputError("one region label per forward-mesh node (Jacobian column)",
                             field="forward_region", value=(len(region), np.shape(J_forward)))
    missing = [int(v) for v in labels if not np.any(region == v)]
    if missing:
        raise FluoInputError("a region of the prior has no node on the forward mesh",
                             field="forward_region", value=missing)
    return np.stack([J_forward[:, region == v].sum(axis=1) for v in labels], axis=1)


def _linearise(A, y, x, log_data):
    """Residual and Jacobian of the data model at ``x``.

    Linear data: r = y - A x, Jacobian A.  Log data (NIRFAST's fluorescence
    reconstruction fits ln of the amplitude): r = ln y - ln(A x), Jacobian
    diag(1 / A x) A.  With relative measurement noise the log residuals have
    equal variance, so every source-detector pair weighs the same instead of
    the near-source pairs (which see only the surface) dominating.
    """
    F = A @ x
    if not log_data:
        return y - F, A
    # non-negative yields and sensitivities keep F >= 0; the floor only guards a
    # detector all of whose sensitive nodes were clipped to zero
    F = np.maximum(F, np.finfo(float).tiny)
    return np.log(y) - np.log(F), A / F[:, None]


def _initial_guess(A, y, x0, K, counts, log_data, positive):
    """Starting unknowns.  ``x0``: None, a scalar (homogeneous yield [1/mm]) or
    nodal values.  None with a scheme that needs positive values (log data,
    normalised Jacobian) starts from the homogeneous yield that fits the data
    best (in the log sense for log data): a zero start gives no signal to take
    the log of and no column scale."""
    n = A.shape[1]
    if x0 is None:
        if not positive:
            return np.zeros(n)
        one = A.sum(axis=1)
        c = (float(np.exp(np.mean(np.log(y) - np.log(one)))) if log_data
             else float(one @ y / (one @ one)))
        return np.full(n, c)
    if np.ndim(x0) == 0:
        return np.full(n, float(x0))
    x0 = np.asarray(x0, float)
    return K.T @ x0 / counts if K is not None else x0.copy()


def _inverse_regulariser(method, prior, Jm, lam_k):
    """R^-1 as a function of X (N,) or (N, k), for the current linearisation ``Jm``.

    NP: R = lambda' I; SP: R = lambda' L^T L, lambda' = lambda * max(diag(Jm^T Jm));
    HP: Marquardt's R = lambda diag(Jm^T Jm): regions differ in size by orders of
    magnitude and one scalar damping scaled by the largest region would freeze a
    small target's value.
    """
    jtj_diag = np.einsum("ij,ij->j", Jm, Jm)
    scale = float(np.max(jtj_diag))
    if scale <= 0:
        raise FluoInputError("the Jacobian is zero: detectors are insensitive to every node",
                             field="J")
    if method == "SP":
        return lambda X: prior.apply_LtL_inv(X) / (lam_k * scale)
    d = lam_k * (np.maximum(jtj_diag, 1e-300 * scale) if method == "HP"
                 else np.full(Jm.shape[1], scale))
    return lambda X: (np.asarray(X).T / d).T


def reconstruct(J, y, method="NP", lam=10.0, prior=None, x0=None, max_iter=40, rel_tol=0.02,
                nonneg=True, lambda_decay=None, log_data=False, normalise=False,
                region_jacobian=None, progress=None, cancel=None):
    """Reconstruct nodal yield from data ``y`` with sensitivity ``J``.

    Parameters
    ----------
    J : (M, N) Jacobian d(data)/d(yield) on the reconstruction mesh
        [data units per (1/mm)]
    y : (M,) measured boundary fluence (same units as J @ yield)
    method : "NP", "SP" or "HP"
    lam : lambda of the reference (lambda' = lambda * max(diag(J^T J)))
    prior : RegionPrior, required for SP and HP
    x0 : starting yield [1/mm]: None (zero; with ``log_data`` or ``normalise``
        the best-fitting homogeneous yield), a scalar (homogeneous) or nodal values
    lambda_decay : lambda is divided by this after every iteration.  Default:
        1 (fixed, as the reference states, so the damping also regularises)
        for NP and SP; 10^0.25 (NIRFAST's schedule) for HP, whose few region
        unknowns are well determined and need damping only for the first steps
    log_data : fit ln y (NIRFAST's fluorescence reconstruction, reconstruct_fl*.m):
        the residual is ln y - ln(J x) and the Jacobian's rows are divided by
        J x, so the problem is re-linearised every iteration.  Needs y > 0.
    normalise : scale the Jacobian's columns by the current yield (NIRFAST's
        J diag(gamma)) and multiply the step by it: the damping then acts on
        relative changes, so nodes that have grown are damped less.  A node at
        zero (start or non-negativity clip) stays there, as in NIRFAST.
    region_jacobian : (M, n_regions) HP only: the data's sensitivity to each
        region's yield (columns in ``prior.labels`` order), e.g. built on the
        forward mesh with :func:`region_jacobian`; default J @ prior.K()

    Returns
    -------
    ReconResult with the nodal yield [1/mm] on the reconstruction mesh.
    """
    t0 = time.perf_counter()
    J = np.asarray(J, float)
    y = np.asarray(y, float).ravel()
    method = str(method).upper()
    _check_inputs(J, y, method, lam, prior, log_data)

    K = prior.K() if method == "HP" else None
    A = J if K is None else _region_matrix(J, K, region_jacobian, prior)
    nonlinear = bool(log_data or normalise)
    counts = prior.counts if K is not None else None
    x = _initial_guess(A, y, x0, K, counts, log_data, nonlinear)
    if nonlinear and not np.any(x > 0):
        raise FluoInputError("the starting yield must be positive for log data or a "
                             "normalised Jacobian", field="x0")
    resid, Jm = _linearise(A, y, x, log_data)
    history = [float(resid @ resid)]
    # data fitted to rounding: the residual only jitters from here on (relative
    # changes of any size), so stop instead of running to max_iter
    fitted = np.log(np.maximum(y, np.finfo(float).tiny)) if log_data else y
    floor = (64 * np.finfo(float).eps) ** 2 * float(np.dot(fitted, fitted))
    stop = "max_iter"
    clipped = 0.0
    lam_k = float(lam)
    if lambda_decay is None:
        lambda_decay = 10 ** 0.25 if method == "HP" else 1.0
    cached_lam = None
    col = None
    for it in range(1, max_iter + 1):
        check_cancel(cancel)
        # J is fixed for linear data and no normalisation: refactor only when
        # lambda changes; otherwise the linearisation moves every iteration
        if nonlinear or lam_k != cached_lam:
            col = x.copy() if normalise else None
            Jc = Jm * col if normalise else Jm
            Rinv = _inverse_regulariser(method, prior, Jc, lam_k)
            RJt = Rinv(Jc.T)
            S = Jc @ RJt
            S[np.diag_indices_from(S)] += 1.0
            S_factor = np.linalg.cholesky(S)
            cached_lam = lam_k
        step = RJt @ _chol_solve(S_factor, resid)
        x = x + (step * col if normalise else step)
        if nonneg:
            neg = x < 0
            clipped = float(np.mean(neg))
            x[neg] = 0.0
        resid, Jm = _linearise(A, y, x, log_data)
        history.append(float(resid @ resid))
        report(progress, it / max_iter, f"{method} iteration {it}: residual {history[-1]:.3g}")
        if history[-1] <= floor:
            stop = "residual at rounding level"
            break
        if history[-2] > 0 and abs(history[-2] - history[-1]) / history[-2] < rel_tol:
            stop = "residual change < {:.0%}".format(rel_tol)
            break
        lam_k /= lambda_decay
    x_nodes = K @ x if K is not None else x
    conf = _region_confidence(Jc, Rinv, S, resid, prior, x_nodes, method, col)
    return ReconResult(method, float(lam), x_nodes, it, history, time.perf_counter() - t0,
                       conf, clipped, stop)


def _check_inputs(J, y, method, lam, prior, log_data):
    """Explain bad input before any work (FluoInputError)."""
    if method not in ("NP", "SP", "HP"):
        raise FluoInputError("method must be NP, SP or HP", field="method", value=method)
    if J.ndim != 2 or J.shape[0] != len(y):
        raise FluoInputError("Jacobian rows must match the data", field="J",
                             value=(J.shape, len(y)))
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(y))):
        raise FluoInputError("data and Jacobian must be finite", field="y")
    if not np.any(y != 0):
        raise FluoInputError("all data are zero: nothing to reconstruct (no fluorescence "
                             "detected, or the detectors saw no light)", field="y")
    if log_data and np.any(y <= 0):
        raise FluoInputError("log data need every measurement > 0: leave out the detectors "
                             "that saw no light", field="y", value=int(np.sum(y <= 0)))
    if not (np.isfinite(lam) and lam > 0):
        raise FluoInputError("lambda must be a positive number", field="lambda", value=lam)
    if method in ("SP", "HP") and prior is None:
        raise FluoInputError(f"{method} needs the region prior (label of each node)",
                             field="prior")
    if prior is not None and len(prior.node_region) != J.shape[1]:
        raise FluoInputError("prior has a different number of nodes than the Jacobian",
                             field="prior", value=(len(prior.node_region), J.shape[1]))


def _region_matrix(J, K, region_jacobian, prior):
    """HP's unknowns are one yield per region: J K, or the caller's finer basis."""
    if region_jacobian is None:
        return J @ K
    A = np.asarray(region_jacobian, float)
    if A.shape != (J.shape[0], len(prior.labels)) or not np.all(np.isfinite(A)):
        raise FluoInputError("region_jacobian must be finite, (measurements, regions)",
                             field="region_jacobian",
                             value=(np.shape(region_jacobian), (J.shape[0], len(prior.labels))))
    return A


def _region_confidence(A, Rinv, S, resid, prior, x_nodes, method, col=None):
    """Per-region mean yield and its standard deviation from the regularised
    Hessian H = J^T J + R:  var(w^T x) = sigma^2 w^T H^-1 w, sigma^2 = residual
    variance, w = region-averaging weights.  Cheap: Woodbury in data space,
    w^T H^-1 w = w^T R^-1 w - (J R^-1 w)^T S^-1 (J R^-1 w).  ``col``: the
    column scaling of a normalised Jacobian (the unknowns are x / col, so the
    weights become w * col)."""
    if prior is None:
        return {}
    m = len(resid)
    sigma2 = float(resid @ resid) / max(m - 1, 1)
    out = {}
    means = prior.region_mean(x_nodes)
    for r, lab in enumerate(prior.labels):
        if method == "HP":
            w = np.zeros(A.shape[1])
            w[r] = 1.0
        else:
            w = (prior.index == r).astype(float) / prior.counts[r]
        if col is not None:
            w = w * col
        Rinv_w = Rinv(w)
        JRw = A @ Rinv_w
        var = float(w @ Rinv_w - JRw @ np.linalg.solve(S, JRw)) * sigma2
        sd = float(np.sqrt(max(var, 0.0)))
        mean = float(means[r])
        out[int(lab)] = {"mean_yield_per_mm": mean, "sd_yield_per_mm": sd,
                         "relative_sd": sd / mean if mean > 0 else float("inf")}
    return out
