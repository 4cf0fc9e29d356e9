"""The Monte Carlo engine: MCX-CL (``pmcxcl``, OpenCL; on a CPU through pocl) or
MCX (``pmcx``, CUDA) behind one call.

Monte Carlo eXtreme is photon transport written by others (Q. Fang's group): the
project uses it as an independent reference for its diffusion model, never on the
main job's path.  Nothing here is imported until a Monte Carlo run is asked for,
and the package imports without ``pmcxcl`` installed; asking for a run then fails
with one line (:class:`MonteCarloUnavailable`) that says what to install.

Two things make MCX-CL run on a CPU here:

- Debian's ``pocl-opencl-icd`` (pocl's CPU OpenCL device; ``make system-deps``).
- The system libstdc++ loaded before ``import pmcxcl``: the wheel carries its own
  older copy, and once that one is loaded pocl's kernel build loses its include
  path and fails with "'stdint.h' file not found".  :func:`load_engine` does it.

Units (tested in test_montecarlo.py): MCX's ``outputtype='energy'`` is the energy
absorbed per voxel per launched photon (summing to the absorbed fraction), so the
fluence per unit source power is E / (mua * voxel volume) [1/mm^2]; exit records
carry positions in grid units (``issrcfrom0``: voxel i spans [i, i+1)) and partial
path lengths in grid units (times ``unitinmm`` for mm).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import tempfile
import threading

import numpy as np

from fluoguide.errors import FluoError, FluoInputError

C_MM_PER_NS = 299.792458

ENGINES = ("auto", "mcxcl", "mcx")

# MCX-CL's launch shape (work items, work-group size): see Engine.run
MCXCL_THREADS = 4096
MCXCL_BLOCK = 64


def max_exit_records(photons):
    """Exit records MCX keeps per run: above the launch count (work items round it
    up; in weakly absorbing media nearly every photon exits), so a full buffer
    means records were lost."""
    return int(2 * int(photons) + 4096)


class MonteCarloUnavailable(FluoError):
    """The Monte Carlo engine (pmcxcl / pmcx) or its compute device is missing."""


_lock = threading.Lock()        # MCX writes to fd 1 and is not re-entrant across threads
_loaded = {}


def _preload_system_libstdcxx():
    """Load the system libstdc++ globally before pmcxcl's bundled copy (see module doc)."""
    for name in (ctypes.util.find_library("stdc++"), "libstdc++.so.6"):
        if not name:
            continue
        try:
            ctypes.CDLL(name, mode=os.RTLD_GLOBAL | os.RTLD_NOW)
            return name
        except OSError:
            continue
    return None


@contextlib.contextmanager
def _quiet_fd1():
    """Send MCX's C-level banner and progress (fd 1) to a temporary file, so a
    ``--json`` caller's stdout stays one JSON object; yields the file to read
    MCX's own error text from."""
    import sys

    with tempfile.TemporaryFile(mode="w+b") as log:
        try:
            sys.stdout.flush()
        except (AttributeError, ValueError):
            pass
        saved = os.dup(1)
        try:
            os.dup2(log.fileno(), 1)
            yield log
        finally:
            try:
                sys.stdout.flush()
            except (AttributeError, ValueError):
                pass
            os.dup2(saved, 1)
            os.close(saved)


def _log_tail(log):
    log.flush()
    log.seek(0)
    text = log.read().decode("utf-8", "replace")
    errs = [ln.strip() for ln in text.splitlines() if "ERROR" in ln.upper()]
    return errs[-1] if errs else ""


class Engine:
    """One loaded Monte Carlo engine.

    Attributes
    ----------
    name : "mcxcl" (OpenCL) or "mcx" (CUDA)
    version : the Python binding's version (e.g. "pmcxcl 0.7.5")
    device : the compute device in words (e.g. "OpenCL pthread-skylake-avx512-AMD EPYC, 2 cores")
    """

    fixed_launch = False       # MCX-CL on a CPU: see run()

    def __init__(self, name, module, version, device, gpuid=1):
        self.name = name
        self.module = module
        self.version = version
        self.device = device
        self.gpuid = gpuid

    def __repr__(self):
        return f"Engine({self.name!r}, {self.version!r}, {self.device!r})"

    def run(self, cfg):
        """Run one MCX simulation (a dict of MCX's ``cfg`` fields); returns MCX's result
        dict with ``detp`` as a dict of arrays (``detid``, ``ppath``, ``p``, ``v``
        where saved) whatever the binding returns."""
        cfg = dict(cfg)
        cfg.setdefault("gpuid", self.gpuid)
        if self.fixed_launch and cfg.get("autopilot", 1):
            # A fixed launch shape instead of MCX's autopilot: MCX seeds each work item
            # from the run's seed, and autopilot sizes the launch from the device's
            # compute units, so the same seed drew other photons on a 1-core worker
            # than on the 2-core serial loop (measured).  Fixed, a seed gives the same
            # photons on any CPU count (the fluence then differs only in the float
            # atomics' summation order, ~1e-6 relative) and the time is the same.
            # CPU devices only (pocl): a GPU needs far more work items than this.
            cfg.update(autopilot=0, nthread=MCXCL_THREADS, nblocksize=MCXCL_BLOCK)
        with _lock, _quiet_fd1() as log:
            try:
                res = self.module.run(cfg)
            except Exception as exc:  # the bindings raise bare RuntimeErrors
                detail = _log_tail(log) or str(exc)
                raise MonteCarloUnavailable(f"{self.name} run failed: {detail}") from None
        if not isinstance(res, dict) or "stat" not in res:
            raise MonteCarloUnavailable(f"{self.name} returned no result (got {type(res).__name__})")
        if "detp" in res:
            res["detp"] = _detp_dict(res["detp"], cfg)
        return res


def _detp_dict(detp, cfg):
    """pmcxcl returns exit records as one (fields, photons) array; pmcx as a dict."""
    if isinstance(detp, dict):
        out = dict(detp)
        for k in ("p", "v", "ppath"):
            if k in out:
                out[k] = np.atleast_2d(np.asarray(out[k], float))
        return out
    arr = np.asarray(detp, float)
    if arr.ndim == 1:
        arr = arr.reshape(-1, 1)
    flags = str(cfg.get("savedetflag", "dp")).lower()
    n_media = int(np.asarray(cfg["prop"]).shape[0]) - 1
    widths = {"d": 1, "s": n_media, "p": n_media, "m": n_media, "x": 3, "v": 3, "w": 1}
    names = {"d": "detid", "s": "nscat", "p": "ppath", "m": "mom", "x": "p", "v": "v", "w": "w0"}
    out, row = {}, 0
    for f in "dspmxvw":
        if f in flags:
            w = widths[f]
            out[names[f]] = arr[row:row + w].T.copy()
            row += w
    if "detid" in out:
        out["detid"] = out["detid"][:, 0]
    return out


def _cuda_engine():
    try:
        import pmcx
    except ImportError:
        return None
    try:
        with _quiet_fd1():
            gpus = pmcx.gpuinfo()
    except Exception:  # no CUDA driver or no GPU: pmcx raises "unknown exception"
        return None
    if not gpus:
        return None
    g = gpus[0]
    dev = f"CUDA {g.get('name', 'GPU')}"
    return Engine("mcx", pmcx, f"pmcx {getattr(pmcx, '__version__', '?')}", dev)


def _opencl_engine():
    preload = _preload_system_libstdcxx()
    try:
        with _quiet_fd1():
            import pmcxcl
    except ImportError:
        raise MonteCarloUnavailable(
            "the Monte Carlo engine is not installed: pip install pmcxcl (the 'mc' extra: "
            "pip install -e '.[mc]') and apt-get install pocl-opencl-icd") from None
    if not hasattr(pmcxcl, "run"):
        raise MonteCarloUnavailable("pmcxcl is installed but its binary extension does not load")
    try:
        with _quiet_fd1() as log:
            gpus = pmcxcl.gpuinfo()
    except Exception:
        raise MonteCarloUnavailable(
            "no OpenCL device: install pocl-opencl-icd (CPU) or a GPU's OpenCL driver "
            "(`make system-deps`)") from None
    if not gpus:
        raise MonteCarloUnavailable("no OpenCL device found: install pocl-opencl-icd "
                                    "(`make system-deps`)")
    g = gpus[0]
    version = "pmcxcl"
    try:
        from importlib.metadata import version as _v

        version = f"pmcxcl {_v('pmcxcl')}"
    except Exception:
        pass
    dev = f"OpenCL {g.get('name', 'device')}, {g.get('core', '?')} compute units"
    eng = Engine("mcxcl", pmcxcl, version, dev, gpuid=1)
    eng.preloaded = preload
    # pocl's CPU device ("pthread-..." before pocl 5, "cpu-..." after)
    eng.fixed_launch = str(g.get("name", "")).lower().startswith(("pthread", "cpu"))
    return eng


def load_engine(engine="auto"):
    """The Monte Carlo engine to run with.

    Parameters
    ----------
    engine : "auto" (MCX on CUDA when a GPU answers, else MCX-CL), "mcxcl" or "mcx"

    Raises
    ------
    MonteCarloUnavailable
        One line saying what is missing (package, OpenCL device, GPU).
    """
    if engine not in ENGINES:
        raise FluoInputError(f"unknown Monte Carlo engine; use one of {', '.join(ENGINES)}",
                             field="engine", value=engine)
    if engine in _loaded:
        return _loaded[engine]
    if engine in ("auto", "mcx"):
        eng = _cuda_engine()
        if eng is None and engine == "mcx":
            raise MonteCarloUnavailable("MCX (CUDA) needs pmcx and a CUDA GPU; none answered "
                                        "(use engine 'mcxcl' for the CPU)")
        if eng is not None:
            _loaded[engine] = eng
            return eng
    eng = _opencl_engine()
    _loaded[engine] = eng
    return eng


def engine_available(engine="auto"):
    """True if :func:`load_engine` would succeed (for tests and --help texts)."""
    try:
        load_engine(engine)
        return True
    except MonteCarloUnavailable:
        return False


def time_gate_ns(mua_per_mm, n, loss=1e-6, max_path_mm=2.0e4):
    """One time gate long enough that a photon still travelling at its end carries
    at most ``loss`` of its weight (exp(-mua L) <= loss), capped at ``max_path_mm``
    of path (mua = 0: the cap; the energy balance then shows what was cut)."""
    mua = float(np.min(mua_per_mm))
    path = max_path_mm if mua <= 0 else min(-np.log(loss) / mua, max_path_mm)
    return path * float(np.max(n)) / C_MM_PER_NS


def mcx_props(labels_props, g):
    """MCX's property table [[mua, mus, g, n], ...] (row 0: the outside, air) from
    (mua_per_mm, musp_per_mm, n) per label 1..L; mus = musp / (1 - g)."""
    rows = [[0.0, 0.0, 1.0, 1.0]]
    for mua, musp, n in labels_props:
        rows.append([float(mua), float(musp) / (1.0 - g), float(g), float(n)])
    return np.array(rows, float)


def check_photons(photons, field="photons"):
    try:
        p = int(photons)
    except (TypeError, ValueError):
        raise FluoInputError("must be a whole number", field=field, value=photons) from None
    if p != photons or p < 100 or p > 2 ** 31 - 1:
        raise FluoInputError("must be a whole number from 100 to 2^31-1", field=field,
                             value=photons)
    return p


def check_seed(seed, field="seed"):
    try:
        s = int(seed)
    except (TypeError, ValueError):
        raise FluoInputError("must be a whole number", field=field, value=seed) from None
    if s != seed or s < 1 or s > 2 ** 31 - 1:
        raise FluoInputError("must be a whole number from 1 to 2^31-1", field=field, value=seed)
    return s

