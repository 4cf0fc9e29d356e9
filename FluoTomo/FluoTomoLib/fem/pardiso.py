"""MKL PARDISO through ctypes: sparse Cholesky for the diffusion operators.

The CW diffusion matrix is real symmetric positive definite, so PARDISO's
mtype 2 (supernodal Cholesky on the upper triangle) serves every source and
adjoint from one factorisation.  Our own binding rather than pypardiso's:
  - pypardiso searches the whole environment for the library every time a
    solver is created (a recursive glob over site-packages: 0.55 s per
    operator here); the library is found once per process instead;
  - zero-based indices (iparm(35)) and C-contiguous inputs are passed as
    they are, with no per-call copies of the matrix;
  - the factorisation's memory is released when the object goes away.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
import site
import sys
import threading
import time

import numpy as np

from fluoguide.errors import FluoInputError

_ERRORS = {
    -1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
    -4: "zero or negative pivot: the matrix is not positive definite",
    -5: "unclassified (internal) error", -6: "reordering failed", -7: "diagonal matrix is singular",
    -8: "32-bit integer overflow", -9: "not enough memory for the out-of-core solver",
    -10: "error opening out-of-core files", -11: "read/write error with out-of-core files",
}


def _candidates():
    env = os.environ.get("FLUOGUIDE_MKL_RT") or os.environ.get("PYPARDISO_MKL_RT")
    if env:
        yield env
    from ctypes.util import find_library

    for name in ("mkl_rt", "mkl_rt.2", "mkl_rt.1"):
        found = find_library(name)
        if found:
            yield found
    # pip's mkl wheel puts libmkl_rt.so.N in <prefix>/lib (not on the loader path)
    for base in (sys.prefix, site.USER_BASE):
        for pattern in ("lib/libmkl_rt.so*", "lib/libmkl_rt*.dylib", "Library/bin/mkl_rt*.dll"):
            yield from sorted(glob.glob(os.path.join(base, pattern)), key=len)


@functools.lru_cache(maxsize=1)
def mkl_pardiso():
    """The ``pardiso`` entry point of MKL's runtime library, or None when MKL
    cannot be loaded (not installed, or a CPU it does not support)."""
    for path in _candidates():
        try:
            lib = ctypes.CDLL(path)
            fn = lib.pardiso
        except (OSError, AttributeError):
            continue
        fn.restype = None
        fn.argtypes = [ctypes.c_void_p] + [ctypes.POINTER(ctypes.c_int32)] * 5 + [
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.POINTER(ctypes.c_int32), ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32),
            ctypes.c_void_p, ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32)]
        return fn
    return None


def _i32(v):
    return ctypes.byref(ctypes.c_int32(int(v)))


def _default_iparm():
    ip = np.zeros(64, dtype=np.int32)
    ip[0] = 1      # our own values below, defaults elsewhere
    ip[1] = 3      # OpenMP nested dissection
    ip[7] = 0      # no iterative refinement: Cholesky of these SPD matrices
    #                leaves a 3e-15 relative residual without it (benchmark slab)
    ip[9] = 8      # pivot perturbation 1e-8 (unused for SPD)
    ip[34] = 1     # zero-based indices
    return ip


class PardisoPattern:
    """One PARDISO handle for every matrix with one sparsity pattern.

    The analysis (fill-reducing ordering, symbolic factorisation: 0.25 s of
    the 0.9 s factorisation on the benchmark slab) depends on the pattern
    only, so the operators of one mesh (excitation, emission, every update
    of the optical properties in a reconstruction) share it; each holds one
    of ``slots`` numeric factors (PARDISO's maxfct / mnum) and gives it back
    when it goes away.

    iparm, measured on the 60k-node benchmark slab (docs/fem.md): OpenMP
    nested dissection (iparm(2) = 3) factorises in 0.92 s against 1.13 s with
    the serial METIS; no iterative refinement (iparm(8) = 0) instead of the
    default two steps: 16 solves 0.38 -> 0.14 s, relative residual 3e-15
    either way (Cholesky without pivot perturbation is backward stable).
    """

    def __init__(self, indptr, indices, slots=4, name="matrix", order=None):
        fn = mkl_pardiso()
        if fn is None:
            raise FluoInputError("PARDISO (MKL) cannot be loaded", field="solver", value="pardiso")
        self._fn = fn
        self.name = name
        self.n = len(indptr) - 1
        self._ia = np.ascontiguousarray(indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(indices, dtype=np.int32)
        self._pt = np.zeros(64, dtype=np.int64)
        self.iparm = _default_iparm()
        # order[k]: the node eliminated k-th, when the caller has a better
        # (or cheaper) fill-reducing ordering than PARDISO's METIS
        self._perm = None
        if order is not None:
            self._perm = np.ascontiguousarray(order, dtype=np.int32)
            if self._perm.shape != (self.n,):
                raise FluoInputError("ordering must have one entry per row", field=name,
                                     value=self._perm.shape)
            self.iparm[4] = 1
        self.ordering = "user" if order is not None else "metis"
        self.slots = int(slots)
        self._free = list(range(self.slots, 0, -1))
        self._analysed = False
        self.analysis_seconds = 0.0
        # one call at a time on the handle: a factorisation may run on a helper
        # thread (DiffusionOperator.factorize reporting beside it) and a factor's
        # memory is freed by whichever thread collects its owner; re-entrant, as
        # a collection can run on this thread while the arguments are built
        self._lock = threading.RLock()

    def _call(self, phase, mnum, a, b, x, name):
        with self._lock:
            self._call_locked(phase, mnum, a, b, x, name)

    def _call_locked(self, phase, mnum, a, b, x, name):
        err = ctypes.c_int32(0)
        nrhs = b.shape[1] if b.ndim == 2 else 1
        self._fn(self._pt.ctypes.data, _i32(self.slots), _i32(mnum), _i32(2), _i32(phase),
                 _i32(self.n), a.ctypes.data, self._ia.ctypes.data, self._ja.ctypes.data,
                 None if self._perm is None else self._perm.ctypes.data,
                 _i32(nrhs), self.iparm.ctypes.data, _i32(0), b.ctypes.data, x.ctypes.data,
                 ctypes.byref(err))
        if err.value:
            raise FluoInputError(f"PARDISO phase {phase} failed: "
                                 f"{_ERRORS.get(err.value, 'unknown error')}",
                                 field=name, value=int(err.value))

    def factor(self, a, name):
        """Numeric factorisation of the values ``a``; returns its slot, or None
        when every slot is taken (the caller then uses a handle of its own)."""
        with self._lock:          # the analysis and the slots too
            return self._factor(a, name)

    def _factor(self, a, name):
        if not self._free:
            return None
        z = np.zeros((self.n, 1))
        if not self._analysed:
            t0 = time.perf_counter()
            self._call(11, 1, a, z, z, name)
            self._analysed = True
            self.analysis_seconds = time.perf_counter() - t0
        mnum = self._free.pop()
        try:
            self._call(22, mnum, a, z, z, name)
        except Exception:
            self._free.append(mnum)
            raise
        return mnum

    def solve(self, mnum, a, B, name):
        X = np.empty_like(B)
        self._call(33, mnum, a, B, X, name)
        return X

    def release_slot(self, mnum):
        """Free the factor in ``mnum`` (PARDISO phase 0) for the next matrix."""
        with self._lock:
            if self._analysed and mnum not in self._free:
                z = np.zeros((self.n, 1))
                self._call(0, mnum, np.zeros(1), z, z, self.name)
                self._free.append(mnum)

    def __del__(self):
        try:
            if self._analysed:
                z = np.zeros((self.n, 1))
                self._call(-1, 1, np.zeros(1), z, z, self.name)
                self._analysed = False
        except Exception:  # interpreter shutdown: the library may be gone
            pass


class PardisoCholesky:
    """Factorisation of a real SPD matrix given by its upper triangle.

    Parameters
    ----------
    upper : scipy CSR, upper triangle with the diagonal, sorted column indices
    name : what the matrix is, for error messages
    pattern : PardisoPattern of the same sparsity pattern to share its analysis
        (a new one of a single slot if None or full)
    """

    def __init__(self, upper, name="matrix", pattern=None):
        self.name = name
        self.n = int(upper.shape[0])
        self._a = np.ascontiguousarray(upper.data, dtype=np.float64)
        self.mnum = None
        if pattern is not None:
            if pattern.n != self.n or len(pattern._ja) != len(self._a):
                raise FluoInputError("matrix does not have the shared pattern", field=name,
                                     value=(self.n, len(self._a)))
            self.mnum = pattern.factor(self._a, name)
        if self.mnum is None:
            pattern = PardisoPattern(upper.indptr, upper.indices, slots=1, name=name)
            self.mnum = pattern.factor(self._a, name)
        self.pattern = pattern
        self.iparm = pattern.iparm

    def solve(self, B):
        """X with K X = B for B (N,) or (N, k); X has B's shape."""
        B = np.asarray(B, dtype=np.float64)
        if B.shape[0] != self.n:
            raise FluoInputError(f"right-hand side has {B.shape[0]} rows, the matrix {self.n}",
                                 field=self.name, value=B.shape)
        if self.mnum is None:
            raise FluoInputError("factorisation was released", field=self.name)
        X = self.pattern.solve(self.mnum, self._a, np.asfortranarray(B.reshape(self.n, -1)),
                               self.name)
        return X.reshape(B.shape)

    __call__ = solve

    def release(self):
        """Free this factorisation's memory (also done when the object is collected)."""
        if self.mnum is not None:
            mnum, self.mnum = self.mnum, None
            self.pattern.release_slot(mnum)

    def __del__(self):
        try:
            self.release()
        except Exception:  # interpreter shutdown: the library may be gone
            pass
