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

import enum
import time
from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report, scaled


class Stop(enum.Enum):
    """Why the iterations ended; the value is the reason's words
    (``{:.0%}``: the relative tolerance)."""
    MAX_ITER = "max_iter"
    ROUNDING = "residual at rounding level"
    CONVERGED = "residual change < {:.0%}"
    RUNAWAY = "diverged"
    NOT_FINITE = "diverged (not finite)"
    ALL_ZERO = "diverged (every unknown clipped to zero)"


class Rise(enum.Enum):
    """What became of a run whose residual ended above its lowest value."""
    NONE = "the residual ended at its lowest"
    LOWEST_KEPT = "the iterate with the lowest residual kept"
    CLIP = "left at the non-negativity clip's rise"


@dataclass
class StopReason:
    """Why a run ended: the words a reader sees (``text``, the result's
    ``stop_reason``) and, carried alongside, the facts the solver and
    :func:`diagnose` act on, so that no decision reads the words."""
    kind: Stop
    text: str
    rise: Rise = Rise.NONE
    stalled: bool = False

    @classmethod
    def of(cls, kind, rel_tol):
        return cls(kind, kind.value.format(rel_tol))

    def __str__(self):
        return self.text

    @property
    def diverged(self):
        return self.kind in (Stop.RUNAWAY, Stop.NOT_FINITE, Stop.ALL_ZERO)

    @property
    def clip_fought(self):
        """The non-negativity clip fought the steps: the residual rose at it, or
        every unknown was clipped to zero (and the lowest iterate kept)."""
        return self.rise is Rise.CLIP or (self.rise is Rise.LOWEST_KEPT
                                          and self.kind is Stop.ALL_ZERO)

    def lowest_kept(self, it_best):
        self.rise = Rise.LOWEST_KEPT
        self.text = f"{self.text}; residual rose: iteration {it_best} (lowest residual) kept"

    def rose_at_clip(self, rose):
        self.rise = Rise.CLIP
        self.text = (f"{self.text}; residual rose {rose:.3g}x above its lowest "
                     "(non-negativity clip)")

    def stalled_by_damping(self):
        self.stalled = True
        self.text = f"{self.text} (stalled by the damping)"


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
    diagnostics: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    #: the stop reason reports a divergence (the solver's, or the self-absorption
    #: feedback's), and ``stop_warned``: one of ``warnings`` opens with the stop
    #: reason; a caller decides on these, not on the words (not in ``summary``)
    diverged: bool = False
    stop_warned: bool = False
    #: HP with ``reconstruct(optodes=...)``: the fit of the same data with the
    #: optodes' gains (recon.coupling.OptodeCoupling, or None where they cannot be
    #: told from the values); not in ``summary``
    coupling: object = None

    @property
    def residual(self):
        return self.residual_history[-1]

    def summary(self):
        """Plain dict of the result for JSON (without the nodal yield): the
        diagnostics (:func:`diagnose`) and the ``warnings`` a caller must show."""
        return {"method": self.method, "lambda": self.lam, "iterations": self.iterations,
                "residual_ss": self.residual, "initial_residual_ss": self.residual_history[0],
                "stop_reason": self.stop_reason, "seconds": self.seconds,
                "clipped_fraction": self.clipped_fraction,
                "region_confidence": self.region_confidence,
                "diagnostics": dict(self.diagnostics), "warnings": list(self.warnings)}


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
        # in place on the one (N, k) result: with k the measurements, each
        # temporary is as large as the Jacobian
        out = self._sums(X)[self.index]
        out += X
        out /= (c if X.ndim == 1 else c[:, None])
        return out

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
        def sp_inverse(X):
            out = prior.apply_LtL_inv(X)
            out /= lam_k * scale
            return out
        return sp_inverse
    d = lam_k * (np.maximum(jtj_diag, 1e-300 * scale) if method == "HP"
                 else np.full(Jm.shape[1], scale))
    return lambda X: (np.asarray(X).T / d).T


def reconstruct(J, y, method="NP", lam=10.0, prior=None, x0=None, max_iter=40, rel_tol=0.02,
                nonneg=True, lambda_decay=None, log_data=False, normalise=False,
                region_jacobian=None, progress=None, cancel=None, noise_sd=None, noise_rel=None,
                region_weights=None, optodes=None):
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
    log_data : bool
        Fit ln y (NIRFAST's fluorescence reconstruction, ``reconstruct_fl*.m``):
        the residual is ln y - ln(J x) and the Jacobian's rows are divided by
        J x, so the problem is re-linearised every iteration.  Needs y > 0.
    normalise : scale the Jacobian's columns by the current yield (NIRFAST's
        J diag(gamma)) and multiply the step by it: the damping then acts on
        relative changes, so nodes that have grown are damped less.  A node at
        zero (start or non-negativity clip) stays there, as in NIRFAST.
    region_jacobian : (M, n_regions) HP only: the data's sensitivity to each
        region's yield (columns in ``prior.labels`` order), e.g. built on the
        forward mesh with :func:`region_jacobian`; default J @ prior.K()
    noise_sd, noise_rel : the measurement noise model, used to grade the fit
        (not to weight it): standard deviation sqrt(noise_sd^2 + (noise_rel y)^2)
        per measurement, ``noise_sd`` in the data's units (scalar or (M,)),
        ``noise_rel`` a fraction (0.01 = 1 %).  Without them the goodness of fit
        is judged from the residual alone (:func:`diagnose`).
    region_weights : {label: (N,) nodal weights summing to 1}, NP and SP: each
        region's mean (``region_confidence``) is this weighted mean of the nodal
        yield and its standard deviation that of the same functional (the label
        map path: the volume-weighted mean over the label's voxels). Default: the
        mean over the prior's node region. HP's region means are its unknowns.
    optodes : (sources, detectors), each (M,) the measurement's source and detector
        index, or None. HP with linear data: the result's ``coupling`` is the same
        data's fit with each source's and detector's gain as an unknown beside the
        region values (``recon.coupling``: its residual, for comparing models on
        what the optodes' gains leave); the fit itself is not changed.

    Returns
    -------
    ReconResult with the nodal yield [1/mm] on the reconstruction mesh, its
    ``diagnostics`` and ``warnings`` (:func:`diagnose`): a result whose
    ``warnings`` is not empty may be far from the truth, for the reasons given.
    """
    t0 = time.perf_counter()
    J = np.asarray(J, float)
    y = np.asarray(y, float).ravel()
    method = str(method).upper()
    _check_inputs(J, y, method, lam, prior, log_data)
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise FluoInputError("max_iter must be a whole number of iterations, at least 1",
                             field="max_iter", value=max_iter)
    sigma = _noise_model(y, noise_sd, noise_rel)
    K = prior.K() if method == "HP" else None
    A = _unknowns_matrix(J, K, region_jacobian, prior)
    A_s, y_s, x_exp, b_exp = _exact_scaling(A, y, log_data)
    nonlinear = bool(log_data or normalise)
    x = _start(A_s, y_s, x0, x_exp, K, prior, log_data, nonlinear)
    x_start = x.copy()
    if lambda_decay is None:
        lambda_decay = 10 ** 0.25 if method == "HP" else 1.0
    run = _Run.start(A_s, y_s, x, log_data)
    _iterate(run, method, prior, A_s, y_s, x_start, log_data, normalise, nonneg, lam,
             lambda_decay, max_iter, rel_tol, progress, cancel)
    relinearise = _keep_lowest(run, nonlinear, rel_tol)
    if relinearise and (not normalise or np.any(run.x > 0)):
        # diagnostics and confidence at the final linearisation
        run.system = _step_system(method, prior, run.Jm, run.x, normalise, run.lam)
    diag, warn = diagnose(method, A_s, y_s, run.x, run.resid, run.system[4], log_data,
                          sigma if sigma is None else np.ldexp(sigma, -b_exp), run.history,
                          run.stop, run.it, max_iter, rel_tol, x0_given=x0 is not None,
                          x_start=x_start, x_exp=x_exp,
                          region_labels=prior.labels if K is not None else None,
                          lam_final=run.lam)
    if diag["over_regularised"]:
        run.stop.stalled_by_damping()
    # for the intervals: what the damped iterations kept of the start (the
    # solver's bias at its own result), and how much of the residual the stated
    # noise cannot explain (the model's own error, in the data's units)
    resolution = None if relinearise else _resolution(
        run, method, prior, K, x_start, lam, lambda_decay, progress, max_iter, cancel)
    gain = None if relinearise or run.system[4] is None else _iterated_gain(
        method, prior, run.Jm, len(run.history) - 1, lam, lambda_decay,
        {run.lam: run.system[3:]})
    s_fit, excess = _model_excess(run.resid, y, sigma, log_data, b_exp, diag["residual_dof"])
    res = _result(run, method, lam, prior, K, x_exp, b_exp, diag, warn, resolution, excess,
                  s_fit, region_weights, t0, gain)
    if optodes is not None and method == "HP" and not log_data:
        from FluoTomoLib.recon.coupling import optode_coupling

        res.coupling = optode_coupling(A, y, *optodes, sigma=sigma)
    return res

def _unknowns_matrix(J, K, region_jacobian, prior):
    """The data's sensitivity to the unknowns: J (NP, SP) or to each region's yield
    (HP, :func:`_region_matrix`); refused where it is zero."""
    A = J if K is None else _region_matrix(J, K, region_jacobian, prior)
    if not np.any(A):
        raise FluoInputError("the Jacobian is zero: no detector is sensitive to any node "
                             "(detectors away from the tissue, or sources outside it)",
                             field="J")
    return A


#: the solver works on the caller's matrix A as it is where its largest entry lies
#: within 2^-this .. 2^this (J^T J and the damping then stay far from under- and
#: overflow); beyond, on a scaled copy (:func:`_exact_scaling`)
SCALE_FREE_EXP = 100


def _exact_scaling(A, y, log_data):
    """Work with A / 2^a and y / 2^b (x scaled by 2^(a-b)): exact in floating
    point, so results are bit for bit those of the unscaled problem, but a
    Jacobian in units that make J^T J underflow (1e-160) or overflow still
    works; log data are fitted as they are (a scale is a shift of ln y).
    A is scaled only where its largest entry is beyond 2^+-SCALE_FREE_EXP
    (a = 0 and A itself otherwise, never written to): the scaled copy of an SP
    Jacobian is an M x N array beside the caller's at the solver's peak.
    Returns (A_s, y_s, x_exp, b_exp): x_scaled = x * 2^x_exp, y_s = y / 2^b_exp."""
    a_exp = int(np.frexp(np.max(np.abs(A)))[1])
    b_exp = 0 if log_data else int(np.frexp(np.max(np.abs(y)))[1])
    if abs(a_exp) <= SCALE_FREE_EXP:
        return A, np.ldexp(y, -b_exp), -b_exp, b_exp
    return np.ldexp(A, -a_exp), np.ldexp(y, -b_exp), a_exp - b_exp, b_exp


def _start(A_s, y_s, x0, x_exp, K, prior, log_data, positive):
    """The starting unknowns in the solver's units: :func:`_initial_guess` of the
    caller's ``x0`` [1/mm] scaled by 2^x_exp. ``positive`` (log data or a
    normalised Jacobian): a start without a positive value is refused, as those
    schemes cannot move from it."""
    if x0 is not None and np.ndim(x0) == 0:
        x0 = float(x0)
    if x0 is not None:
        x0 = np.ldexp(np.asarray(x0, float), x_exp)
    counts = prior.counts if K is not None else None
    x = _initial_guess(A_s, y_s, x0, K, counts, log_data, positive)
    if positive and not np.any(x > 0):
        raise FluoInputError("the starting yield must be positive for log data or a "
                             "normalised Jacobian", field="x0")
    return x


@dataclass
class _Run:
    """The state of one run of the iterations, in the solver's rescaled units:
    the iterate ``x``, its residual and linearisation ``Jm``, the residual sums
    of squares so far (``history``), the lowest one's (rss, iteration, x,
    residual, Jacobian) as ``best``, why the run ended (``stop``), its last
    iteration ``it``, the fraction of unknowns the last step clipped, and the
    step system (:func:`_step_system`: col, Jc, R^-1, R^-1 Jc^T, data-space
    system) with the damping ``lam`` it was built for."""
    x: np.ndarray
    resid: np.ndarray
    Jm: np.ndarray
    history: list
    best: tuple
    stop: StopReason | None = None
    it: int = 0
    clipped: float = 0.0
    lam: float | None = None
    system: tuple = (None, None, None, None, None)

    @classmethod
    def start(cls, A, y, x, log_data):
        resid, Jm = _linearise(A, y, x, log_data)
        history = [float(resid @ resid)]
        return cls(x, resid, Jm, history, (history[0], 0, x, resid, Jm))


def _iterate(run, method, prior, A, y, x_start, log_data, normalise, nonneg, lam, decay,
             max_iter, rel_tol, progress, cancel):
    """The projected Levenberg-Marquardt iterations (the module's docstring) from
    ``run``'s start, until a stop test (:func:`_stop_test`) ends them or
    ``max_iter`` pass; ``run`` holds the state they leave and the
    :class:`StopReason`. ``x_start``: the start, for the units check of a run
    that clipped every unknown to zero."""
    nonlinear = bool(log_data or normalise)
    # data fitted to rounding: the residual only jitters from here on (relative
    # changes of any size), so stop instead of running to max_iter
    fitted = np.log(np.maximum(y, np.finfo(float).tiny)) if log_data else y
    floor = (64 * np.finfo(float).eps) ** 2 * float(np.dot(fitted, fitted))
    run.stop = StopReason.of(Stop.MAX_ITER, rel_tol)
    history = run.history
    lam_k = float(lam)
    for it in range(1, max_iter + 1):
        run.it = it
        check_cancel(cancel)
        # J is fixed for linear data and no normalisation: refactor only when
        # lambda changes; otherwise the linearisation moves every iteration
        if nonlinear or lam_k != run.lam:
            run.system = _step_system(method, prior, run.Jm, run.x, normalise, lam_k)
            run.lam = lam_k
        col, _, _, RJt, ds = run.system
        step = RJt @ ds.solve(run.resid)
        x = run.x + (step * col if normalise else step)
        if nonneg:
            neg = x < 0
            run.clipped = float(np.mean(neg))
            x[neg] = 0.0
        if normalise and not np.any(x > 0):
            # a normalised Jacobian cannot move a zero yield: the run ends here,
            # at the iterate before
            ratio = _data_to_model(A, y, x_start, log_data)
            if not (1e-3 <= ratio <= 1e3):
                raise FluoInputError(
                    f"iteration {it} drove every unknown to zero: the data are {ratio:.3g} "
                    "times what the model predicts at the starting yield; are the data in "
                    "the Jacobian's units (boundary fluence per W of source, 1/mm^2)?",
                    field="y")
            history.append(history[-1])
            run.stop = StopReason.of(Stop.ALL_ZERO, rel_tol)
            return
        resid, Jm = _linearise(A, y, x, log_data)
        history.append(float(resid @ resid))
        report(progress, it / max_iter, f"{method} iteration {it}: residual {history[-1]:.3g}")
        if not (np.isfinite(history[-1]) and np.all(np.isfinite(x))):
            # the iterate before is kept
            history[-1] = history[-2]
            run.stop = StopReason.of(Stop.NOT_FINITE, rel_tol)
            return
        run.x, run.resid, run.Jm = x, resid, Jm
        kind = _stop_test(run, floor, rel_tol)
        if kind is not None:
            run.stop = StopReason.of(kind, rel_tol)
            return
        lam_k /= decay


def _stop_test(run, floor, rel_tol):
    """After iteration ``run.it``: note it if its residual is the lowest so far,
    and say which :class:`Stop` ends the run (None: go on): a residual run away
    from its lowest, at rounding level, or changed by less than ``rel_tol``."""
    history = run.history
    if history[-1] < run.best[0]:
        run.best = (history[-1], run.it, run.x, run.resid, run.Jm)
    elif history[-1] > RUNAWAY * run.best[0]:
        return Stop.RUNAWAY
    if history[-1] <= floor:
        return Stop.ROUNDING
    if history[-2] > 0 and abs(history[-2] - history[-1]) / history[-2] < rel_tol:
        return Stop.CONVERGED
    return None


def _keep_lowest(run, nonlinear, rel_tol):
    """The end of a run whose residual rose above its lowest value. An
    under-damped log / normalised model overshoots (lambda 1e-10 ran NP to a
    yield of 1e64): the iterate with the lowest residual is returned (a step
    may overshoot and the next recover: only the end is judged). With linear
    data the residual can rise only by the non-negativity clip; that is left as
    it is (and :func:`diagnose` warns of it). Returns whether the diagnostics
    need the step system rebuilt at the final iterate (a nonlinear model, or
    the lowest iterate kept)."""
    rose = run.history[-1] / run.best[0] if run.best[0] > 0 else 1.0
    if rose > RUNAWAY or (nonlinear and rose > 1 + rel_tol) or run.stop.diverged:
        _, it_best, run.x, run.resid, run.Jm = run.best
        run.stop.lowest_kept(it_best)
        run.history.append(run.best[0])
        return True
    if rose > 1 + rel_tol:
        run.stop.rose_at_clip(rose)
    return nonlinear


def _resolution(run, method, prior, K, x_start, lam, decay, progress, max_iter, cancel):
    """For the intervals (:func:`_region_confidence`'s ``resolution``): the region
    basis and what the damped iterations left unresolved of it and of the start
    (:func:`_unresolved`: the solver's bias at its own result); None where no
    step system was built. Linear data only: the caller passes nothing else."""
    RJt, ds = run.system[3:]
    if ds is None:
        return None
    Kb = np.eye(run.Jm.shape[1]) if K is not None else prior.K()
    return (Kb, _unresolved(method, prior, run.Jm, np.column_stack([Kb, x_start]),
                            len(run.history) - 1, lam, decay, {run.lam: (RJt, ds)},
                            scaled(progress, run.it / max_iter, 1.0), cancel))


def _model_excess(resid, y, sigma, log_data, b_exp, dof):
    """The stated noise in the fit's units and how much of the residual it cannot
    explain (the model's own error, in the fit's units, for the intervals).
    Without a noise model (None, the whole residual's norm): nothing says how
    much of the misfit is noise, so all of it may be the model's error. The
    demo's tracked-frames tube cases state no noise; their 3-9 % misfit is mostly
    the model's (the frames' shot noise is far below it), and without this bound
    SP's interval at 5.7 mm (balanced) missed the truth by 8 % with no warning."""
    if sigma is None:
        return None, float(np.sqrt(float(resid @ resid)))
    s_fit = np.broadcast_to(sigma / np.abs(y) if log_data else np.ldexp(sigma, -b_exp),
                            y.shape)
    expected = float(np.sum(s_fit ** 2)) * max(dof, 0.0) / len(y)
    return s_fit, float(np.sqrt(max(float(resid @ resid) - expected, 0.0)))


def _result(run, method, lam, prior, K, x_exp, b_exp, diag, warn, resolution, excess, s_fit,
            region_weights, t0, gain=None):
    """The :class:`ReconResult` in the caller's units: the nodal yield [1/mm], each
    region's confidence (:func:`_region_confidence`, with the iterations' ``gain``)
    and the residual history in the data's units."""
    col, Jc, Rinv, _, ds = run.system
    x = np.ldexp(run.x, -x_exp)
    x_nodes = K @ x if K is not None else x
    conf = _region_confidence(Jc, Rinv, ds, run.resid, prior, x_nodes, method, col,
                              diag["residual_dof"], diag.get("noise_variance_fit"),
                              undetermined=diag["underdetermined"],
                              x_scale=2.0 ** (-x_exp), region_weights=region_weights,
                              region_values=x if K is not None else None,
                              resolution=resolution, x_scaled=np.ldexp(x, x_exp),
                              model_excess=excess, noise_sd=s_fit, gain=gain)
    diag.pop("noise_variance_fit", None)
    history = [float(np.ldexp(h, 2 * b_exp)) for h in run.history]    # in the data's units
    return ReconResult(method, float(lam), x_nodes, run.it, history, time.perf_counter() - t0,
                       conf, run.clipped, run.stop.text, diag, warn,
                       diverged=run.stop.diverged)


def _unresolved(method, prior, Jm, V, iterations, lam, decay, cache, progress=None,
                cancel=None):
    """(I - T_k) ... (I - T_1) V for the columns of V, T_j = H_j^-1 J^T J the step
    operator of iteration j (damping lambda / decay^(j-1)). For linear data the
    solver's result from the start x0 is, in expectation, x0 + (I - P)(x - x0)
    for a truth x, P = (I - T_k)...(I - T_1): what the iterations leave
    unresolved of the truth. The non-negativity clip is not modelled.
    ``cache``: {lambda: (R^-1 J^T, data-space system)} already built.
    ``progress`` hears of each iteration replayed: with a decaying lambda (HP)
    each builds its own data-space system, as long as an iteration of the
    solve itself (seconds each where BLAS threads compete for the cores)."""
    V = np.array(V, float)
    lam_j = float(lam)
    n = max(int(iterations), 0)
    if n and float(decay) == 1.0:
        return _unresolved_fixed(method, prior, Jm, V, n, lam_j, cache, progress, cancel)
    for j in range(n):
        check_cancel(cancel)
        report(progress, j / n, f"{method} intervals: iteration {j + 1} of {n} replayed")
        RJt, ds, cache = _replay_system(method, prior, Jm, lam_j, cache)
        V = V - RJt @ ds.solve(Jm @ V)
        lam_j /= decay
    return V


def _replay_system(method, prior, Jm, lam, cache):
    """(R^-1 J^T, data-space system, cache) at damping ``lam``: the cached one, or
    built at x = 0 and cached alone (one at a time: (N, M) each)."""
    if lam not in cache:
        _, _, _, RJt, ds = _step_system(method, prior, Jm, np.zeros(Jm.shape[1]), False, lam)
        cache = {lam: (RJt, ds)}
    return (*cache[lam], cache)


def _unresolved_fixed(method, prior, Jm, V, n, lam, cache, progress, cancel):
    """:func:`_unresolved` where every iteration had the same damping (NP, SP): with
    T = R^-1 J^T S^-1 J and S = J R^-1 J^T + I, (I - T) = I - R^-1 J^T S^-1 J, and
    since S^-1 J R^-1 J^T = I - S^-1, (I - T)^n V = V - R^-1 J^T sum_{j=1..n} S^-j J V:
    the n steps in data space (M x M solves), one product with R^-1 J^T and one with
    J instead of n of each (NP's 20-odd replayed iterations on a 45k-node mesh:
    1.4 s, the N x M products of every step)."""
    check_cancel(cancel)
    report(progress, 0.0, f"{method} intervals: {n} iterations replayed in data space")
    RJt, ds, _ = _replay_system(method, prior, Jm, lam, cache)
    z = Jm @ V
    acc = np.zeros_like(z)
    for _ in range(n):
        z = ds.solve(z)
        acc += z
    return V - RJt @ acc


def _iterated_gain(method, prior, Jm, iterations, lam, decay, cache):
    """w -> g (M,): the weights of the data in w^T x_k, x_k the result of the damped
    iterations (linear data, ``iterations`` steps from a start that does not depend
    on the data; damping lambda / decay^(j-1) at step j): the estimator's gain, for
    its noise SD under the stated noise and its model error bound.

    Step j is x_j = x_{j-1} + M_j (y - J x_{j-1}), M_j = R_j^-1 J^T S_j^-1, so
    w^T x_k = ... + sum_j a_j^T y with a_j = S_j^-1 J R_j^-1 u_j, u_k = w and
    u_{j-1} = u_j - J^T a_j. With one damping (NP, SP) J R^-1 u_{j-1} = a_j, so
    g = sum_{j=1..k} S^-j J R^-1 w: k data-space solves. One step's gain
    S^-1 J R^-1 w (the damped estimator at the last damping) understated HP's
    spread over 200 noise draws by 1.33x (docs/reconstruction.md, "Intervals")."""
    n = max(int(iterations), 1)
    if float(decay) == 1.0:
        RJt, ds, _ = _replay_system(method, prior, Jm, float(lam), cache)

        def fixed(w):
            z, g = RJt.T @ w, 0.0
            for _ in range(n):
                z = ds.solve(z)
                g = g + z
            return g
        return fixed
    if LOW_RANK_SHARE * Jm.shape[1] > Jm.shape[0]:
        # a decaying damping on many unknowns (no path asks for it: HP's few regions
        # decay, NP and SP do not) would hold one (N, M) system per step: the last
        # step's gain is kept there
        return None
    lams = [float(lam) / float(decay) ** j for j in range(n)]
    systems = dict(cache)        # (R^-1 J^T, data-space system) per damping, R x M each

    def decaying(w):
        u, g = np.array(w, float), 0.0
        for lam_j in reversed(lams):
            if lam_j not in systems:
                systems[lam_j] = _replay_system(method, prior, Jm, lam_j, {})[:2]
            RJt, ds = systems[lam_j]
            a = ds.solve(RJt.T @ u)
            g = g + a
            u = u - Jm.T @ a
        return g
    return decaying


#: two-sided 95 % point of the normal distribution: the intervals' noise part
Z95 = 1.959964


def _interval(mean, sd, corrected, model_bound):
    """The 95 % interval of a region's yield [1/mm] (None where no SD can be given):
    it reaches from the result to the value corrected for what the damped
    iterations leave unresolved of a region-wise constant truth (``corrected``),
    widened by the noise part +-Z95 sd and the model's error bound
    (``model_bound``: the largest change of this value a data error of the
    unexplained residual's size can make) on both sides; clipped at zero (a
    yield is not negative)."""
    if not np.isfinite(sd):
        return None
    lo_c = hi_c = mean
    if corrected is not None and np.isfinite(corrected):
        lo_c, hi_c = min(mean, corrected), max(mean, corrected)
    half = Z95 * sd + (model_bound or 0.0)
    return [max(lo_c - half, 0.0), hi_c + half]


#: measurement columns of R^-1 J^T computed at a time: SP's (L^T L)^-1 makes a few
#: (N, k) temporaries per block; on all M columns at once they were several
#: Jacobian-sized arrays (6.9 GB above the Jacobian at 315k nodes and 684 pairs)
RINV_BLOCK = 32


def _rinv_jt(Rinv, J):
    """R^-1 J^T (N, M) column block by column block into one array (R^-1 acts on
    each column alone): the peak is that array and a block's temporaries."""
    M, N = J.shape
    out = np.empty((N, M))
    for a in range(0, M, RINV_BLOCK):
        out[:, a:a + RINV_BLOCK] = Rinv(J[a:a + RINV_BLOCK].T)
    return out


def _step_system(method, prior, Jm, x, normalise, lam):
    """What one step needs at the linearisation ``Jm``: the column scaling (the
    current yield, normalised Jacobian only), the scaled Jacobian Jc, R^-1,
    R^-1 Jc^T and the data-space system S = Jc R^-1 Jc^T + I."""
    col = x.copy() if normalise else None
    Jc = Jm * col if normalise else Jm
    Rinv = _inverse_regulariser(method, prior, Jc, lam)
    RJt = _rinv_jt(Rinv, Jc)
    if LOW_RANK_SHARE * Jc.shape[1] <= Jc.shape[0]:
        # few unknowns (HP's regions): G = Jc R^-1 Jc^T has their rank, and its
        # thin eigen-decomposition replaces the M x M matrix and its Cholesky
        return col, Jc, Rinv, RJt, _LowRankDataSpace(Jc, RJt)
    S = Jc @ RJt
    S[np.diag_indices_from(S)] += 1.0
    return col, Jc, Rinv, RJt, _DataSpace(S)


#: a step system with at most 1/LOW_RANK_SHARE as many unknowns as data is solved
#: through the thin eigen-decomposition of its rank (:class:`_LowRankDataSpace`)
LOW_RANK_SHARE = 4


class _DataSpace:
    """Solves with the data-space matrix S = G + I, G = J R^-1 J^T symmetric
    positive semi-definite.  Cholesky while it succeeds; where rounding has
    made G indefinite (a lambda so small that G dwarfs the identity: SP with
    log data at lambda 1e-10 raised numpy's LinAlgError), the eigen-
    decomposition of G with its negative rounding eigenvalues set to zero.
    ``effective_parameters()`` and ``predicted_rss()`` serve the diagnostics."""

    def __init__(self, S):
        self.S = S
        self._eig = None
        try:
            self.L = np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            self.L = None
            self.spectrum()

    def spectrum(self):
        if self._eig is None:
            G = self.S - np.eye(len(self.S))
            g, V = np.linalg.eigh(0.5 * (G + G.T))
            self._eig = (np.maximum(g, 0.0), V)
        return self._eig

    def solve(self, b):
        if self.L is not None:
            return _chol_solve(self.L, b)
        # (I + V g V^T)^-1 b for orthonormal V, whole (M x M) or thin (M x r)
        g, V = self._eig
        c = V.T @ b
        return b - V @ ((c.T * (g / (1.0 + g))).T)

    def effective_parameters(self):
        """p = trace(I - S^-1) = M - ||L^-1||_F^2 (one triangular inverse, about
        a Cholesky's cost; an eigen-decomposition costs ~10 of them)."""
        if self.L is None:
            g, _ = self._eig
            return float(np.sum(g / (1.0 + g)))
        from scipy.linalg import solve_triangular

        M = len(self.S)
        Linv = solve_triangular(self.L, np.eye(M), lower=True)
        return float(M - np.einsum("ij,ij->", Linv, Linv))

    def predicted_rss(self, r, t=1.0):
        """||S_t^-1 r||^2 with S_t = I + t G: the residual sum of squares one
        linearised step would leave with the damping divided by t."""
        if t == 1.0 and self.L is not None:
            z = _chol_solve(self.L, r)
            return float(z @ z)
        if self.L is not None:
            St = t * self.S
            St[np.diag_indices_from(St)] += 1.0 - t        # I + t (S - I)
            try:
                z = _chol_solve(np.linalg.cholesky(St), r)
                return float(z @ z)
            except np.linalg.LinAlgError:
                self.spectrum()
        g, V = self._eig
        c = V.T @ r
        out = max(float(r @ r) - float(c @ c), 0.0)     # r outside G's range
        return out + float(np.sum((c / (1.0 + t * g)) ** 2))


class _LowRankDataSpace(_DataSpace):
    """:class:`_DataSpace` for G = Jc R^-1 Jc^T of rank r << M (r unknowns), on its
    eigen path from the start: with Jc = Q Rq (thin QR) G = Q C Q^T, C = Rq (R^-1
    Jc^T) Q (r x r), whose eigenpairs (g, U) give G = V diag(g) V^T with V = Q U
    orthonormal (M x r); no M x M matrix is formed. HP, 2-3 regions and 130-500
    data: that matrix and its Cholesky, rebuilt at every damping of the
    iterations, were a tenth of a tube case's time."""

    def __init__(self, Jc, RJt):
        Q, Rq = np.linalg.qr(Jc)
        C = Rq @ (RJt @ Q)
        g, U = np.linalg.eigh(0.5 * (C + C.T))
        self.S, self.L = None, None
        self._eig = (np.maximum(g, 0.0), Q @ U)


def _noise_model(y, noise_sd, noise_rel):
    """Per-measurement noise standard deviation in the data's units, or None."""
    if noise_sd is None and noise_rel is None:
        return None
    var = np.zeros_like(y)
    for name, v, scale in (("noise_sd", noise_sd, 1.0), ("noise_rel", noise_rel, y)):
        if v is None:
            continue
        v = np.asarray(v, float)
        if v.ndim > 1 or (v.ndim == 1 and len(v) != len(y)) or not np.all(np.isfinite(v)) \
                or np.any(v < 0):
            raise FluoInputError("noise must be finite, >= 0, a scalar or one value per "
                                 "measurement", field=name, value=np.shape(v) if v.ndim else
                                 float(v))
        var = var + (v * scale) ** 2
    if not np.all(var > 0):
        raise FluoInputError("the noise model gives some measurement zero noise (a "
                             "relative noise of a zero measurement): add an absolute noise_sd",
                             field="noise_sd", value=int(np.sum(var <= 0)))
    return np.sqrt(var)


def _data_to_model(A, y, x, log_data):
    """Typical ratio of the data to the model's prediction A x (geometric mean for
    log data, least squares otherwise); 0 where the model predicts nothing."""
    F = A @ x
    if log_data:
        ok = F > 0
        return float(np.exp(np.mean(np.log(y[ok]) - np.log(F[ok])))) if np.any(ok) else 0.0
    FF = float(F @ F)
    return float(F @ y) / FF if FF > 0 else 0.0


# Diagnostic thresholds, each measured (docs/reconstruction.md, "Diagnostics"):
PLAUSIBLE_YIELD_PER_MM = (1e-9, 1.0)   # ~1 pM ICG (eta 4 %) up to mua_f 1/mm at quantum yield 1
MISFIT_WARN = 0.10        # rms relative residual without a noise model
CHI2_WARN = 4.0           # residual rms > 2 x the stated noise
#: the fit graded by the residual's rms over the stated noise's (sqrt(chi^2/dof)):
#: up to FIT_GOOD "good"; to FIT_FAIR "fair" (the model's own error shows, and the
#: intervals count it: a note); to FIT_POOR "poor" (a warning: the model's error
#: dominates the data's); beyond, "fails" (the model does not explain the data)
#: when the rms relative residual also exceeds MISFIT_WARN, else still "poor"
FIT_GOOD, FIT_FAIR, FIT_POOR = 2.0, 5.0, 15.0
STALL_FRACTION = 0.1      # a damped step doing < 10 % of what a 1e4x weaker one would
WEAK_DAMPING = 1e4
P_EFF_WARN = 0.1          # effective parameters > 10 % of the measurements
RUNAWAY = 1e4             # residual this many times its lowest: diverged, stop


#: a region at the non-negativity bound is consistent with zero when its
#: unconstrained estimate lies less than this many standard deviations below it,
ZERO_BOUND_SD = 3.0
#: or when the data that negative yield would explain are less than this
#: fraction of the data (the model's own mismatch, a few %, pulls a large
#: background region a hair below zero: -0.07 % of the target's yield on the
#: own scene, 3 SD below zero, while the target was +1.8 %)
ZERO_BOUND_DATA_FRACTION = 0.02


def _zero_bound_check(A, y, x, sigma, frozen, log_data):
    """For HP regions clipped at zero (indices ``frozen`` of ``x``): is zero
    consistent with the data? The unconstrained weighted least-squares fit of the
    region yields (every region free, no damping), its standard deviation from the
    noise model (or, without one, from its own residual), and whether it lies less
    than ZERO_BOUND_SD standard deviations below zero or explains less than
    ZERO_BOUND_DATA_FRACTION of the data. Log data, or a fit the columns do not
    determine, are reported as not testable (not consistent).
    Returns {index: {"unconstrained", "sd", "data_fraction", "consistent_with_zero"}}."""
    out = {}
    M, R = A.shape
    untestable = {int(r): {"unconstrained": None, "sd": None, "data_fraction": None,
                           "consistent_with_zero": False} for r in frozen}
    if log_data or M <= R:
        return untestable
    w = np.ones(M) if sigma is None else 1.0 / np.broadcast_to(np.asarray(sigma, float), (M,))
    Aw, yw = A * w[:, None], y * w
    try:
        q, r_ = np.linalg.qr(Aw)
        if np.min(np.abs(np.diag(r_))) <= 1e-12 * np.max(np.abs(np.diag(r_))):
            return untestable
        free = np.linalg.solve(r_, q.T @ yw)
        rinv = np.linalg.inv(r_)
    except np.linalg.LinAlgError:
        return untestable
    cov = rinv @ rinv.T
    res = yw - Aw @ free
    s2 = float(res @ res) / (M - R)
    # with a noise model, a fit worse than the noise widens the interval (never narrows it)
    scale = s2 if sigma is None else max(1.0, s2)
    norm_y = float(np.linalg.norm(yw)) or 1.0
    for r in frozen:
        sd = float(np.sqrt(cov[r, r] * scale))
        est = float(free[r])
        frac = float(np.linalg.norm(Aw[:, r] * est)) / norm_y
        out[int(r)] = {"unconstrained": est, "sd": sd, "data_fraction": frac,
                       "consistent_with_zero": bool(est >= -ZERO_BOUND_SD * sd
                                                    or frac < ZERO_BOUND_DATA_FRACTION)}
    return out


def diagnose(method, A, y, x, resid, ds, log_data, sigma, history, stop, iterations,
             max_iter, rel_tol, x0_given=False, x_start=None, x_exp=0, region_labels=None,
             lam_final=1.0):
    """Diagnostics of a reconstruction and the warnings they imply.

    All from the final linearisation's data-space matrix S = G + I
    (G = J R^-1 J^T) and its Cholesky factor (two more factorisations' cost):

    - ``effective_parameters`` p = trace(I - S^-1) = sum g/(1+g) over G's
      eigenvalues g (the trace of the hat matrix): how many combinations of the unknowns the data determine at
      this damping; ``residual_dof`` = M - p.  ``underdetermined``: fewer
      than one residual degree of freedom (the data are fitted exactly, so
      the residual says nothing about the noise and no standard deviation
      can be given), or more region unknowns than measurements (HP).
    - ``relative_misfit``: rms of ln y - ln F (log data) or ||y - F|| / ||y||;
      with a noise model ``chi2_per_dof`` = sum((y - F)/sigma)^2 / (M - p).
    - ``over_regularised``: the run stopped (small residual change or
      max_iter) while a step damped 1e4 times less would remove most of a
      residual larger than the noise: the damping stalled it.
    - ``signal_to_noise`` (absolute noise given): sqrt(sum (y/sigma)^2 / M);
      ``structure_F``: F statistic of the fit against the best homogeneous
      yield (1 = the extra structure explains no more than noise would).
    - ``homogeneous_yield_per_mm``: the single yield that fits the data best,
      the units check (outside 1e-9 .. 1 /mm no fluorophore explains them);
      ``data_to_start_ratio``: data / model at a given start ``x0``.
    - ``effective_measurements``: linear data, (sum y^2)^2 / sum y^4, how many
      measurements carry a least-squares fit (a 1e-200 dynamic range: ~1).
    - ``damped_step_fraction``: the share of the weakly damped step's residual
      reduction that the damped step achieves (the stall test).

    Thresholds: the module constants PLAUSIBLE_YIELD_PER_MM, MISFIT_WARN,
    CHI2_WARN, STALL_FRACTION, WEAK_DAMPING, P_EFF_WARN (docs/reconstruction.md,
    "Diagnostics").  ``A``, ``y``, ``x``, ``resid`` and ``sigma`` are in the
    solver's rescaled units (``x_exp``: x_scaled = x 2^x_exp).  ``stop``: the
    run's :class:`StopReason` (its flags decide, its words are quoted).

    Returns (diagnostics dict, list of warning strings).
    """
    M = len(y)
    diag = {"measurements": M, "unknowns": int(A.shape[1])}
    warn = []
    p, nu, rss, misfit = _determination(method, A, y, resid, ds, log_data, region_labels,
                                        diag, warn)
    if method == "HP" and region_labels is not None:
        _zero_bound_warnings(A, y, x, sigma, log_data, region_labels, x_exp, diag, warn)
    noise_var_fit = _fit_grade(y, resid, sigma, log_data, nu, misfit, diag, warn)
    _structure_and_units(A, y, sigma, log_data, p, nu, rss, x_exp, x0_given, x_start, diag,
                         warn)
    _damping(ds, resid, rss, lam_final, noise_var_fit, M, stop, sigma, misfit, iterations,
             max_iter, history, diag, warn)
    return diag, warn


def _determination(method, A, y, resid, ds, log_data, region_labels, diag, warn):
    """:func:`diagnose`'s effective parameters, misfit and under-determination (into
    ``diag`` and ``warn``); returns (p, residual dof, rss, relative misfit)."""
    M = len(y)
    p = ds.effective_parameters() if ds is not None else 0.0
    nu = M - p
    rss = float(resid @ resid)
    diag["effective_parameters"] = p
    diag["residual_dof"] = nu
    if log_data:
        misfit = float(np.sqrt(rss / M))
    else:
        misfit = float(np.sqrt(rss / float(y @ y)))
    diag["relative_misfit"] = misfit
    # linear data weigh each measurement by its size: with a large dynamic
    # range a few carry the fit (participation ratio of y^2); log data weigh
    # all alike
    m_eff = float(M) if log_data else float((y @ y) ** 2 / np.sum(y ** 4))
    diag["effective_measurements"] = m_eff
    # HP: a region clipped to zero still counts as an unknown (it is frozen at
    # zero by the normalised Jacobian, not determined by the data)
    under = nu < 1.0 or (method == "HP" and M - A.shape[1] < 1) or m_eff - p < 1.0
    if method == "HP" and region_labels is not None:
        norms = np.linalg.norm(A, axis=0)
        blind = [int(region_labels[r]) for r in np.flatnonzero(norms <= 1e-6 * norms.max())]
        if blind:
            under = True
            warn.append(f"no measurement is sensitive to region(s) {blind}: their yield is "
                        "not determined by the data")
    diag["underdetermined"] = bool(under)
    if method == "HP" and M - A.shape[1] < 1:
        warn.append(f"under-determined: {M} measurement(s) for {A.shape[1]} region unknowns; "
                    "the result is one of many that fit equally well (or fits exactly), and "
                    "no standard deviation can be given")
    elif nu >= 1.0 and m_eff - p < 1.0:
        warn.append(f"under-determined: the data span {np.ptp(np.log10(np.abs(y[y != 0]))):.0f} "
                    f"decades, so with linear residuals ~{m_eff:.1f} of the {M} measurements "
                    f"carry the fit of {p:.1f} effective parameters; fit log data (log_data) "
                    "or leave out the far detectors")
    elif nu < 1.0:
        warn.append(f"under-determined: {M} measurement(s) fitted exactly by {p:.1f} "
                    "effective parameters, so the residual cannot measure the noise and no "
                    "standard deviation can be given; add measurements or raise lambda")

    if method != "HP" and p > P_EFF_WARN * M and M - p >= 1.0:
        # the nodal field is then shaped by the noise and the model error, not by
        # the damping: study B at lambda 1e-2 / 1e-3 has SP peaks +26 / +42 %
        # with chi^2 ~ 1 and region means that still agree
        warn.append(f"weakly regularised: {p:.0f} effective parameters from {M} "
                    "measurements, so nodal values (peaks, profiles) follow noise and model "
                    "error; read region means with their SD, or raise lambda")
    return p, nu, rss, misfit


def _zero_bound_warnings(A, y, x, sigma, log_data, region_labels, x_exp, diag, warn):
    """:func:`diagnose`'s HP regions at the non-negativity bound: which the data
    ask to go negative (the model does not explain them there)."""
    frozen = np.flatnonzero(x <= 0)
    if len(frozen):
        # a region without dye is clipped at zero whenever noise pulls its
        # estimate below: that is a fit, not a failure. Only a region whose
        # unconstrained estimate lies well below zero (the data ask for a
        # negative yield) is one the model does not explain
        checked = _zero_bound_check(A, y, x, sigma, frozen, log_data)
        for c in checked.values():          # the solver's units -> 1/mm
            for k in ("unconstrained", "sd"):
                if c[k] is not None:
                    c[k] = float(np.ldexp(c[k], -x_exp))
        diag["at_zero_bound"] = {int(region_labels[r]): c for r, c in checked.items()}
        bad = [(int(region_labels[r]), c) for r, c in checked.items()
               if not c["consistent_with_zero"]]
        if bad:
            what = "; ".join(
                f"region {lab}: {c['unconstrained']:.3g} +- {c['sd']:.2g} /mm"
                if c["sd"] is not None else f"region {lab}: not testable"
                for lab, c in bad)
            warn.append(f"region(s) {[lab for lab, _ in bad]} reconstructed at zero yield "
                        "(the non-negativity bound) where the data ask for a negative "
                        f"one ({what}): the model does not explain "
                        "these data there (optical properties, geometry, or fluorescence "
                        "the prior's regions miss)")


def _fit_grade(y, resid, sigma, log_data, nu, misfit, diag, warn):
    """:func:`diagnose`'s goodness of fit against the stated noise (or the misfit
    alone); returns the noise variance in the fit's units (None without noise)."""
    noise_var_fit = None
    if sigma is not None:
        s_fit = sigma / np.abs(y) if log_data else sigma
        chi2 = float(np.sum((resid / s_fit) ** 2))
        diag["chi2_per_dof"] = chi2 / max(nu, 1.0)
        noise_var_fit = float(np.mean(s_fit ** 2))
        diag["noise_variance_fit"] = noise_var_fit
        ratio = float(np.sqrt(diag["chi2_per_dof"]))
        # "fails" needs the model to leave much of the data unexplained, not only
        # much more than a quiet camera's noise: 7 % rms against 0.5 % noise
        # (a recording's tracking error) is a poor fit, not a failed one
        grade = ("good" if ratio <= FIT_GOOD else "fair" if ratio <= FIT_FAIR
                 else "poor" if ratio <= FIT_POOR or misfit <= MISFIT_WARN else "fails")
        diag["fit"] = {"residual_over_noise": ratio, "grade": grade}
        if grade == "poor":
            warn.append(f"poor fit: the residual is {ratio:.3g} times the stated noise: the "
                        "model's own error (mesh, optical properties, geometry, the prior's "
                        "regions) dominates the data's; the intervals include a bound for it, "
                        "but the values may be off by more than they say")
        elif grade == "fails":
            warn.append(f"poor fit: the residual is {ratio:.3g} times the stated noise: the "
                        "model does not explain these data (optical properties, geometry, "
                        "units or the prior's regions are wrong); the values are not "
                        "measurements")
    elif misfit > MISFIT_WARN:
        warn.append(f"poor fit: the model leaves {100 * misfit:.3g} % rms of the data "
                    "unexplained; the result does not describe these data (wrong geometry, "
                    "optical properties or units, or mostly noise)")

    return noise_var_fit


def _structure_and_units(A, y, sigma, log_data, p, nu, rss, x_exp, x0_given, x_start, diag,
                         warn):
    """:func:`diagnose`'s checks that the result stands out from noise and that the
    data's scale is a fluorophore's."""
    one = A.sum(axis=1)
    if log_data:
        c = float(np.exp(np.mean(np.log(y) - np.log(one)))) if np.all(one > 0) else 0.0
        r0 = np.log(y) - np.log(c * one) if c > 0 else None
    else:
        c = float(one @ y / (one @ one))
        r0 = y - c * one
    diag["homogeneous_yield_per_mm"] = float(np.ldexp(c, -x_exp))
    if r0 is not None and p > 1.0 + 1e-6 and nu >= 1.0:
        rss0 = float(r0 @ r0)
        Fstat = ((rss0 - rss) / (p - 1.0)) / (rss / nu) if rss > 0 else float("inf")
        diag["structure_F"] = float(Fstat)
        if rss > 0 and Fstat < 2.0 and rss0 > 0:
            warn.append(f"the data support no structure beyond a homogeneous yield (F = "
                        f"{Fstat:.2g}: the fitted contrast explains no more than noise would); "
                        "region and target values are noise")
    if sigma is not None:
        snr = float(np.sqrt(np.mean((y / sigma) ** 2)))
        diag["signal_to_noise"] = snr
        if snr < 3.0:
            warn.append(f"the data are at the noise level (rms signal / noise {snr:.2g}): "
                        "nothing can be reconstructed from them")

    # units
    lo, hi = PLAUSIBLE_YIELD_PER_MM
    c_phys = diag["homogeneous_yield_per_mm"]
    if not (lo <= c_phys <= hi):
        warn.append(f"implausible scale: the data imply a homogeneous yield of {c_phys:.3g} "
                    f"/mm (a fluorophore gives {lo:g} .. {hi:g}); are the data and the Jacobian "
                    "in the same units (boundary fluence per W of source, 1/mm^2)?")
    if x0_given and x_start is not None:
        ratio = _data_to_model(A, y, x_start, log_data)
        diag["data_to_start_ratio"] = ratio
        if not (1e-3 <= ratio <= 1e3):
            warn.append(f"the data are {ratio:.3g} times what the model predicts at the "
                        "starting yield: check their units or the starting yield")


def _damping(ds, resid, rss, lam_final, noise_var_fit, M, stop, sigma, misfit, iterations,
             max_iter, history, diag, warn):
    """:func:`diagnose`'s convergence: a run the damping stalled, one that ran out of
    iterations, one whose residual rose or diverged (from ``stop``'s flags)."""
    stalled = False
    if ds is not None and rss > 0:
        # the weak reference: 1e4 x less damping, and at most lambda 1e-4
        damped = ds.predicted_rss(resid)
        weak = ds.predicted_rss(resid, WEAK_DAMPING * max(1.0, lam_final))
        possible = rss - weak
        floor = noise_var_fit * M if noise_var_fit is not None else 0.0
        diag["damped_step_fraction"] = float((rss - damped) / possible) if possible > 0 else 1.0
        stalled = (stop.kind is not Stop.ROUNDING
                   and not stop.diverged and stop.rise is Rise.NONE
                   and possible > 0.5 * rss
                   and diag["damped_step_fraction"] < STALL_FRACTION
                   and rss > max(floor * CHI2_WARN, 0.0)
                   and (sigma is not None or misfit > 0.01))
    diag["over_regularised"] = bool(stalled)
    if stalled:
        warn.append(f"over-regularised: stopped ({stop}) after {iterations} iteration(s) "
                    "because the damping keeps every step small, not because the fit "
                    f"converged: a 1e4 times weaker damping would remove "
                    f"{100 * (1 - weak / rss):.0f} % of the residual; lower lambda")
    elif stop.kind is Stop.MAX_ITER and stop.rise is Rise.NONE:
        last = abs(history[-2] - history[-1]) / history[-2] if history[-2] > 0 else 0.0
        warn.append(f"not converged: {max_iter} iterations, the residual still changed by "
                    f"{100 * last:.2g} % in the last one")
    if stop.clip_fought:
        warn.append(f"the residual ended above its lowest value ({stop}): the non-negativity "
                    "clip fights the steps at this damping; raise lambda")
    elif stop.diverged or stop.rise is not Rise.NONE:
        warn.append(f"diverging ({stop}): the log / normalised model's linearisation fails "
                    "at this damping, or rounding dominates the step; the iterate with the "
                    "lowest residual is returned; raise lambda")


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


#: the region system W (B - U_B) is taken as singular beyond this condition number
RESOLUTION_COND_MAX = 1e6

#: SP reports a region's resolution-corrected value when it lies within this factor
#: of the soft-prior image's mean over the region (either way). A correctly segmented
#: region's image keeps a share of its constant set by the damped solver's smoothing
#: across the region's rim; a correction far beyond that share says the region-wise
#: constant model behind it does not describe the image (a segmentation that is off),
#: so the image's mean is kept and the result says why (the shares and corrections
#: measured on the scene family: docs/reconstruction.md, "Intervals")
SP_CORRECTION_MAX = 3.0


def _resolution_corrected(resolution, x_scaled, prior, method, weighted, region_weights, n,
                          x_scale):
    """Region values [1/mm] whose region-wise constant yield the damped solver
    would have turned into the result's region means (:func:`_region_confidence`),
    or None (no resolution given, or the regions not resolved)."""
    if resolution is None or x_scaled is None:
        return None
    B, U = resolution
    R = len(prior.labels)
    if method == "HP":
        W = np.eye(n)
    elif weighted:
        W = np.stack([np.asarray(region_weights.get(int(lab), np.zeros(n)), float)
                      for lab in prior.labels])
    else:
        W = (prior.K() / prior.counts).T
    P = W @ (B - U[:, :R])
    rhs = W @ (x_scaled - U[:, R])
    if P.shape[0] != P.shape[1] or not np.all(np.isfinite(P)) or \
            np.linalg.cond(P) > RESOLUTION_COND_MAX:
        return None
    return np.linalg.solve(P, rhs) * x_scale


def _sp_value(row, corrected):
    """SP's region value: the resolution-corrected value where it is within
    :data:`SP_CORRECTION_MAX` of the image's mean, else the image's mean
    (``row`` is changed in place; ``image_mean_yield_per_mm`` keeps the mean,
    ``sp_value`` says in words which was taken and ``sp_correction_refused`` holds
    the ratio corrected / mean of a refused correction, else None). The soft prior's damped image spreads a
    small region's yield over its rim into the neighbours, so the image's mean
    over the label is biased low (docs/validation.md, the scene family); the
    corrected value undoes that spreading under the region-wise constant model
    the prior states (docs/physics.md section 8.3). Its noise SD is the image
    mean's scaled by the same factor (the correction is near-diagonal); the 95 %
    interval already reaches from the one to the other and is kept."""
    mean = row["mean_yield_per_mm"]
    row["image_mean_yield_per_mm"] = mean
    row["sp_correction_refused"] = None
    if corrected is None or not np.isfinite(corrected):
        row["sp_value"] = "image mean (no resolution correction)"
        return
    ratio = corrected / mean if mean > 0 else float("inf")
    if not (1.0 / SP_CORRECTION_MAX <= ratio <= SP_CORRECTION_MAX):
        row["sp_correction_refused"] = float(ratio)
        row["sp_value"] = (f"image mean (the resolution correction, {ratio:.3g}x, is beyond "
                           f"{SP_CORRECTION_MAX:g}x)")
        return
    row["sp_value"] = "resolution corrected"
    row["mean_yield_per_mm"] = float(corrected)
    if np.isfinite(row["sd_yield_per_mm"]):
        row["sd_yield_per_mm"] = float(row["sd_yield_per_mm"] * ratio)
    row["relative_sd"] = row["sd_yield_per_mm"] / corrected if corrected > 0 else float("inf")


def _region_confidence(A, Rinv, ds, resid, prior, x_nodes, method, col=None, dof=None,
                       noise_var=None, undetermined=False, x_scale=1.0, region_weights=None,
                       region_values=None, resolution=None, x_scaled=None,
                       model_excess=None, noise_sd=None, gain=None):
    """Per-region mean yield and its standard deviation from the regularised
    Hessian H = J^T J + R:  var(w^T x) = sigma^2 w^T H^-1 w, w = region-averaging
    weights, sigma^2 the residual variance rss / (M - p) with p the effective
    number of parameters (and at least the stated noise's variance).  Cheap:
    Woodbury in data space, w^T H^-1 w = w^T R^-1 w - (J R^-1 w)^T S^-1 (J R^-1 w).
    ``col``: the column scaling of a normalised Jacobian (the unknowns are
    x / col, so the weights become w * col).  ``undetermined``: no standard
    deviation can be given (inf, null in JSON).  ``x_scale``: the matrices
    were built for the unknowns x / x_scale (reconstruct's exact rescaling).
    ``region_weights`` (NP, SP): {label: nodal weights} defining each region's
    mean instead of the node region's plain mean; the SD is of that mean. With
    them, HP's region means are its unknowns (``region_values``, 1/mm): the
    volume-weighted mean over each label of the partial-volume model's yield.
    ``noise_sd`` (M,): the stated noise per measurement in the solver's units;
    the SD is then that of the unweighted estimator under it (the sandwich
    sum_i (sigma_i g_i)^2), and the residual's excess over it goes to the
    model's error bound instead of the variance.

    The 95 % interval (``ci95_yield_per_mm``, :func:`_interval`) adds to the noise
    part the resolution's bias: ``resolution`` = (B, U), B the region basis (its
    columns a region-wise constant yield) and U the unresolved part
    (:func:`_unresolved`) of [B, x_start]; the region values v that the solver
    would turn into the result's region means solve W (B - U_B) v = W (x - U_x0),
    W the regions' averaging functionals (``bias_corrected_per_mm``; none where
    that system is near-singular: the data do not resolve the regions). And the
    model's error: ``model_excess`` is
    the norm of the residual the stated noise cannot explain (None without a noise
    model: then the interval cannot include it), and a data error of that norm
    changes the region's value by at most ||S^-1 J R^-1 w|| times it (the
    estimator's gain along its most sensitive direction)."""
    if prior is None:
        return {}
    rss = float(resid @ resid)
    if dof is None:
        dof = max(len(resid) - 1, 1)
    sigma2 = rss / dof if dof >= 1.0 else float("inf")
    if noise_var is not None:
        sigma2 = max(sigma2, noise_var) if np.isfinite(sigma2) else noise_var
    out = {}
    means = prior.region_mean(x_nodes)
    weighted = region_weights is not None and method != "HP"
    corrected = _resolution_corrected(resolution, x_scaled, prior, method, weighted,
                                      region_weights, A.shape[1], x_scale)
    for r, lab in enumerate(prior.labels):
        mean = float(means[r])
        if region_weights is not None and method == "HP" and region_values is not None:
            mean = float(region_values[r])
        if weighted:
            w_lab = np.asarray(region_weights.get(int(lab), np.zeros(A.shape[1])), float)
            mean = float(w_lab @ x_nodes)
        if undetermined or not np.isfinite(sigma2):
            sd = float("inf")
        else:
            if method == "HP":
                w = np.zeros(A.shape[1])
                w[r] = 1.0
            elif weighted:
                w = w_lab
            else:
                w = (prior.index == r).astype(float) / prior.counts[r]
            if col is not None:
                w = w * col
            Rinv_w = Rinv(w)
            JRw = A @ Rinv_w
            SJRw = ds.solve(JRw)
            # the estimator's gain: the whole run's (:func:`_iterated_gain`), else its
            # last step's, g = J H^-1 w = S^-1 J R^-1 w
            g = SJRw if gain is None else gain(w)
            if noise_sd is not None:
                # the stated noise, measurement by measurement: the solver fits
                # unweighted, so the largest data (and their largest noise) carry
                # the estimate; var = sum (sigma_i g_i)^2
                # (a single mean variance understated HP's SD 2.5x: 57 % coverage)
                var = float(np.sum((noise_sd * g) ** 2))
            else:
                var = float(w @ Rinv_w - JRw @ SJRw) * sigma2
            sd = float(np.sqrt(max(var, 0.0))) * x_scale
        row = {"mean_yield_per_mm": mean, "sd_yield_per_mm": sd,
               "relative_sd": sd / mean if mean > 0 else float("inf")}
        c = None if corrected is None else float(corrected[r])
        if np.isfinite(sd):
            bound = None if model_excess is None else \
                float(np.linalg.norm(g)) * model_excess * x_scale
            row.update({"ci95_yield_per_mm": _interval(mean, sd, c, bound),
                        "resolution_corrected_per_mm": c, "model_error_bound_per_mm": bound})
        else:
            row.update({"ci95_yield_per_mm": None, "resolution_corrected_per_mm": c,
                        "model_error_bound_per_mm": None})
        if method == "SP":
            _sp_value(row, c)
        out[int(lab)] = row
    return out
