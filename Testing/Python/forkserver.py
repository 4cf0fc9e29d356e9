"""``fluo`` commands as forked children of one process that imported the stack once.

A fresh ``python -m fluoapp`` spends one to three seconds importing numpy,
SciPy, VTK, MRML, SimpleITK and the Libs before it reads its first argument.
The CLI fuzz runs several hundred commands and the CLI tests dozens, so that
start-up was most of their time (issue #29). Here one server process imports
the stack once; each command runs in a child forked from it, with the same
contract as a real process:

- its own working folder, stdin from ``/dev/null``, stdout and stderr to files;
- its own session (process group), so a hung command is killed with all it started;
- a wall-clock limit, a memory limit (``RLIMIT_DATA`` above what the server
  already holds) and its peak resident size sampled from ``/proc`` (``VmHWM``;
  it includes the pages the child shares with the server: the imports);
- exit code, stdout and stderr as ``python -m fluoapp`` gives them: ``main()``'s
  return value, ``SystemExit`` (argparse's exit 2), and for an exception that
  escapes ``main()`` the interpreter's own traceback and exit 1; exit handlers
  (``atexit``) and non-daemon threads are run and joined as at interpreter exit.

What differs from a real process: variables that libraries read when they are
imported (thread counts, ``VTK_LOG_LEVEL``) are the server's, fixed when it
starts; per-command ``env`` changes apply from the command's start. Tests of
start-up itself (``python -m fluoapp`` as a user types it) keep a real
subprocess: the fuzz runs each subcommand's valid invocation that way.

The server is single-threaded (a fork of a threaded process can deadlock): it
reads requests as JSON lines on one pipe, forks, and polls its children every
20 ms, answering each finished one with a JSON line on the other pipe.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import itertools
import json
import os
import resource
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TREE = [str(ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]

# What the server imports before its first fork: the CLI, every command module
# and the heavy libraries the commands import lazily. Nothing here may start a
# thread (numba's pool, OpenMP's, tqdm's monitor start on first use, not import).
PRELOAD = (
    "numpy", "scipy.sparse", "scipy.sparse.linalg", "scipy.spatial", "scipy.ndimage",
    "scipy.optimize", "SimpleITK", "vtk", "cv2", "matplotlib", "PIL.Image", "yaml",
    "fluoapp.cli", "fluoapp.format", "fluoguide.mrml_io", "fluoguide.labelmap_io",
    "fluoguide.phantoms", "FluoTomoLib.tomography", "FluoTomoLib.fem", "FluoTomoLib.meshing",
    "FluoTomoLib.recon", "FluoTomoLib.studies", "FluoNavLib", "FluoCalibLib",
    "numba", "tqdm", "multiprocessing", "asyncio", "uuid", "ssl",
)
# The Slicer module files whose logic every handler calls (``module_logic``):
# imported as the handlers import them (their import pulls in slicer-core's
# extension modules, a second a child paid before it read its first option).
MODULE_FILES = ("FluoTomo", "FluoCalib", "FluoNav")


# ----------------------------------------------------------------- the server
def _vm_kb(pid, key):
    """``key`` (``VmHWM``, ``VmData``) of ``/proc/PID/status`` in kB (0 when gone)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _child(req, proto_fds):
    """In the forked child: become the command (never returns)."""
    code = 1
    try:
        os.setsid()
        for fd in proto_fds:
            os.close(fd)
        os.chdir(req["cwd"])
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY),
                                (1, req["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                (2, req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
            f = os.open(path, flags, 0o644)
            os.dup2(f, fd)
            os.close(f)
        # fresh text streams on the new descriptors, encoded as the server's were
        # (the interpreter chose them for a process whose stdout is not a tty)
        old_out, old_err = sys.stdout, sys.stderr
        sys.stdin = io.TextIOWrapper(io.FileIO(0, "r", closefd=False), encoding=sys.stdin.encoding,
                                     errors=sys.stdin.errors)
        sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False),
                                      encoding=old_out.encoding, errors=old_out.errors)
        sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False),
                                      encoding=old_err.encoding, errors=old_err.errors,
                                      write_through=True)
        sys.__stdin__, sys.__stdout__, sys.__stderr__ = sys.stdin, sys.stdout, sys.stderr
        for k, v in req.get("env", {}).items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        limit_mb = req.get("memory_limit_mb")
        if limit_mb:
            lim = _vm_kb(os.getpid(), "VmData") * 1024 + int(limit_mb) * 2**20
            with contextlib.suppress(OSError, ValueError):
                resource.setrlimit(resource.RLIMIT_DATA, (lim, lim))
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.argv = [req.get("prog", "fluo"), *req["argv"]]
        code = _as_interpreter(req["argv"])
    except BaseException:  # the forking itself failed: say so like a crashed interpreter
        import traceback

        with contextlib.suppress(Exception):
            traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os._exit(code)


def _exit_code(value):
    """The process exit code ``sys.exit(value)`` gives (a message goes to stderr)."""
    if value is None:
        return 0
    if isinstance(value, int):
        return value & 0xFF
    print(value, file=sys.stderr)
    return 1


def _as_interpreter(argv):
    """Run ``fluoapp.cli.main(argv)`` as ``python -m fluoapp`` would, to its exit code."""
    import atexit
    import traceback

    try:
        from fluoapp.cli import main

        code = _exit_code(main(argv))
    except SystemExit as exc:
        code = _exit_code(exc.code)
    except BaseException:  # what the interpreter prints for an uncaught exception
        traceback.print_exc()
        code = 1
    # interpreter shutdown: wait for non-daemon threads, then the exit handlers
    with contextlib.suppress(Exception):
        threading._shutdown()
    with contextlib.suppress(Exception):
        atexit._run_exitfuncs()
    return code


def serve(in_fd, out_fd, preload=PRELOAD):
    """The server's loop: JSON requests on ``in_fd``, JSON results on ``out_fd``."""
    for name in preload:
        with contextlib.suppress(ImportError):
            importlib.import_module(name)
    from fluoguide.slicer_compat import import_module_file

    for name in MODULE_FILES:
        with contextlib.suppress(ImportError):
            import_module_file(name)
    import matplotlib

    matplotlib.use("Agg")
    os.write(out_fd, (json.dumps({"ready": os.getpid(),
                                  "rss_kb": _vm_kb(os.getpid(), "VmRSS")}) + "\n").encode())
    children = {}       # pid -> request, deadline, peak kB, started
    buf = b""
    eof = False
    while not eof or children:
        timeout = 0.02 if children else None
        if not eof:
            ready, _, _ = select.select([in_fd], [], [], timeout)
            if ready:
                chunk = os.read(in_fd, 65536)
                if not chunk:
                    eof = True
                buf += chunk
        else:
            time.sleep(0.02)
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            req = json.loads(line)
            pid = os.fork()
            if pid == 0:
                _child(req, (in_fd, out_fd))
            children[pid] = [req, time.monotonic() + float(req.get("timeout_s", 600)), 0,
                             time.monotonic(), False]
        for pid in list(children):
            req, deadline, peak, t0, killed = children[pid]
            peak = max(peak, _vm_kb(pid, "VmHWM"))
            children[pid][2] = peak
            done, status, _ = os.wait4(pid, os.WNOHANG)
            served = False
            if done == pid:
                del children[pid]
                os.write(out_fd, (json.dumps({
                    "id": req["id"], "rc": os.waitstatus_to_exitcode(status), "peak_kb": peak,
                    "hung": killed == "hung", "served": killed == "served",
                    "seconds": round(time.monotonic() - t0, 3)}) + "\n").encode())
                continue
            if killed:
                if time.monotonic() > deadline + 10:    # SIGTERM ignored: no more waiting
                    with contextlib.suppress(OSError):
                        os.killpg(pid, signal.SIGKILL)
                continue
            marker = req.get("serve_marker")
            if marker:
                with contextlib.suppress(OSError):
                    served = marker in Path(req["stdout"]).read_text(errors="replace")
            if served:
                children[pid][4] = "served"
                children[pid][1] = time.monotonic()
                with contextlib.suppress(OSError):
                    os.killpg(pid, signal.SIGTERM)
            elif time.monotonic() > deadline or eof:
                children[pid][4] = "hung" if not eof else "stopped"
                with contextlib.suppress(OSError):
                    os.killpg(pid, signal.SIGKILL)


# ----------------------------------------------------------------- the client
@dataclass
class Result:
    """What a finished command left: like ``subprocess.CompletedProcess``, plus
    the peak resident size [MB], wall seconds, and whether the limit killed it
    (``hung``) or it was stopped after printing its serve marker (``served``)."""
    args: list
    returncode: int
    stdout: str
    stderr: str
    peak_mb: float
    seconds: float
    hung: bool = False
    served: bool = False


class Forkserver:
    """A running server; :meth:`run` is thread-safe (the fuzz runs two at a time).

    Parameters
    ----------
    env : dict, optional
        The server's environment (default: this process's). Thread counts and
        other variables read at import are fixed by it.
    """

    def __init__(self, env=None, preload=PRELOAD):
        env = dict(os.environ if env is None else env)
        env["PYTHONPATH"] = os.pathsep.join(
            TREE + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p not in TREE])
        self._to_r, self._to_w = os.pipe()
        self._from_r, self._from_w = os.pipe()
        code = ("import sys; sys.path[:0] = {tree!r}; sys.path.insert(0, {here!r}); "
                "import forkserver; forkserver.serve({r}, {w}, {preload!r})").format(
                    tree=TREE, here=str(Path(__file__).parent), r=self._to_r, w=self._from_w,
                    preload=tuple(preload))
        self._proc = subprocess.Popen([sys.executable, "-c", code], env=env, cwd=str(ROOT),
                                      pass_fds=(self._to_r, self._from_w),
                                      stdin=subprocess.DEVNULL, start_new_session=True)
        os.close(self._to_r)
        os.close(self._from_w)
        self._reader = os.fdopen(self._from_r, "rb")
        hello = self._reader.readline()
        if not hello:
            raise RuntimeError("the fork server did not start (see stderr above)")
        info = json.loads(hello)
        self.pid, self.rss_mb = info["ready"], info["rss_kb"] / 1024.0
        self._ids = itertools.count()
        self._lock = threading.Lock()
        self._waiting = {}
        self._results = {}
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        for line in self._reader:
            msg = json.loads(line)
            with self._cond:
                self._results[msg["id"]] = msg
                self._cond.notify_all()
        with self._cond:
            self._results[None] = "closed"
            self._cond.notify_all()

    def run(self, argv, cwd=None, timeout=600.0, env=None, memory_limit_mb=None,
            serve_marker=None, prog="fluo"):
        """Run ``fluo ARGV`` in a forked child; returns a :class:`Result`.

        ``env``: variables to set (a value of None removes one) for this command.
        ``serve_marker``: stop the command (SIGTERM) once its stdout shows this.
        """
        argv = [str(a) for a in argv]
        cwd = str(cwd or os.getcwd())
        with tempfile.TemporaryDirectory(prefix="fork-") as logs:
            req = {"id": next(self._ids), "argv": argv, "cwd": cwd, "timeout_s": timeout,
                   "stdout": os.path.join(logs, "stdout"), "stderr": os.path.join(logs, "stderr"),
                   "env": env or {}, "memory_limit_mb": memory_limit_mb,
                   "serve_marker": serve_marker, "prog": prog}
            with self._lock:
                os.write(self._to_w, (json.dumps(req) + "\n").encode())
            with self._cond:
                while req["id"] not in self._results:
                    if None in self._results:
                        raise RuntimeError("the fork server stopped")
                    self._cond.wait(1.0)
                msg = self._results.pop(req["id"])
            read = lambda p: Path(p).read_text(errors="replace") if Path(p).exists() else ""  # noqa: E731
            return Result(argv, msg["rc"], read(req["stdout"]), read(req["stderr"]),
                          msg["peak_kb"] / 1024.0, msg["seconds"], msg["hung"], msg["served"])

    def close(self):
        """Stop the server (children still running are killed)."""
        with contextlib.suppress(OSError):
            os.close(self._to_w)
        try:
            self._proc.wait(30)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._thread.join(5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_SHARED = None
_SHARED_LOCK = threading.Lock()


def fluo(*args, cwd=None, env=None, timeout=600.0, memory_limit_mb=None):
    """``fluo ARGS`` on this process's shared server (started on first use with
    this process's environment and one library thread, stopped at exit);
    ``memory_limit_mb``: the child's RLIMIT_DATA above what the server holds."""
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is None:
            import atexit

            server_env = dict(os.environ)
            for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                      "NUMBA_NUM_THREADS"):
                server_env.setdefault(k, "1")
            _SHARED = Forkserver(env=server_env)
            atexit.register(_SHARED.close)
    return _SHARED.run([str(a) for a in args], cwd=cwd or str(ROOT), env=env, timeout=timeout,
                       memory_limit_mb=memory_limit_mb)
