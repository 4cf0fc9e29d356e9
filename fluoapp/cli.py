"""The ``fluo`` command line.

Each capability registers its own subcommands from a small ``*_cli`` module
listed in ``CLI_MODULES``; this file only builds the parser, runs the chosen
command and turns errors into one-line messages: bad input (``FluoInputError``)
exit code 2, a device or peer failure (``FluoError``) exit code 1, anything else
is a bug: one line ``fluo: internal error: ...``, exit code 1, and the traceback
only under ``fluo --debug``.

Conventions every subcommand follows:

- ``--json`` prints exactly one JSON object on stdout (progress goes to stderr).
- Bad input raises ``FluoInputError``: one line on stderr, exit code 2. Every
  line the CLI prints is one line whatever a path or value holds (control
  characters escaped: ``fluoguide.errors.one_line``).
- Python warnings raised during a command (a physics caveat, numpy's
  ``overflow encountered``) never print on stderr before the result or the
  error: they go in the result's ``warnings`` list (the command succeeded) or
  the log (it failed; ``--debug`` shows them). A command that serves until
  stopped (``set_defaults(serves=True)``: ``fluo app``) keeps Python's own
  printing, in its log.
- A handler returns a dict (the JSON result); without ``--json`` it is printed
  as readable ``key: value`` lines and tables with units (``fluoapp/format.py``).
  ``"_exit_code": 1`` in it (not printed) says the work partly failed (a run with
  failed tasks: they are in its table).
- The long commands (:data:`MEMORY_REPORTED`) add ``peak_memory_gb`` to their
  result: this process's peak resident memory (Dask workers are other
  processes; the run engine's table has their own).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import sys
import warnings
from pathlib import Path

from fluoguide.errors import FluoCancelled, FluoError, FluoInputError, one_line
from fluoguide.jsonable import dumps

log = logging.getLogger("fluoguide.cli")

# Warnings about the code, not about the user's data: the log, never the result
_CODE_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, FutureWarning, ImportWarning,
                  ResourceWarning)
# a warning raised from the project's own code is said by its message alone
_PROJECT_ROOT = str(Path(__file__).resolve().parents[1])

# Modules that define ``register(subparsers)``.  Order = order in --help.
CLI_MODULES = [
    "fluoapp.commands.phantom",
    "fluoapp.commands.scene",
    "fluoapp.commands.segment",
    "fluoapp.commands.demo",
    "fluoapp.commands.app",
    "fluoapp.commands.fem",
    "fluoapp.commands.study",
    "fluoapp.commands.validate",
    "fluoapp.commands.mesh",
    "fluoapp.commands.tomo",
    "fluoapp.commands.calib_geometry",
    "fluoapp.commands.calib_light",
    "fluoapp.commands.devices",
    "fluoapp.commands.nav",
]


def cli_group(subparsers, name, help_text):
    """Return the sub-subparsers of group ``name`` (``fluo calib ...``), creating it once.

    Several modules add commands to one group (``calib camera`` and
    ``calib radiometry`` live in different files).
    """
    groups = subparsers.__dict__.setdefault("_fluo_groups", {})
    if name not in groups:
        p = subparsers.add_parser(name, help=help_text, description=help_text)
        groups[name] = p.add_subparsers(dest=f"{name}_command", metavar="COMMAND")
        groups[name].required = True
    return groups[name]


def add_json_flag(parser):
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def build_parser():
    parser = argparse.ArgumentParser(
        prog="fluo",
        description="FluoGuide: image-guided fluorescence quantification "
        "(calibration, navigation, tomography).",
    )
    from fluoguide import __version__

    parser.add_argument("--version", action="version", version=f"fluo {__version__}")
    # dest differs from `fluo mesh --threads` (fTetWild's own threads), which
    # would otherwise overwrite it in the namespace
    parser.add_argument("--threads", default=None, metavar="N", dest="library_threads",
                        help="threads of the numerical libraries (BLAS, MKL/PARDISO, numba): a "
                        "count, 'auto' (every core) or 'system' (the libraries' own defaults); "
                        "default: $FLUO_THREADS, else 1 (docs/performance.md)")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an unexpected error (default: one line)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in CLI_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def _quiet_vtk():
    """VTK/MRML log to stderr on their own; the CLI reports errors itself."""
    try:
        import vtk

        vtk.vtkObject.GlobalWarningDisplayOff()
        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    except (ImportError, AttributeError):
        pass


#: commands (or command groups) whose result says the process's peak memory
MEMORY_REPORTED = ("demo", "study", "forward", "mesh", "tomo", "validate", "phantom")


def main(argv=None):
    from fluoguide.memory import hand_back_large_blocks
    from fluoguide.progress import mark_command_start

    mark_command_start()
    hand_back_large_blocks()       # before the work's first large arrays
    parser = build_parser()
    _quiet_vtk()
    args = parser.parse_args(argv)
    # FluoError's text is one line already (FluoError.__str__); one_line again costs nothing
    with warnings.catch_warnings(record=True) as caught:
        if getattr(args, "serves", False):
            warnings.showwarning = _shown_warning    # a server's warnings: its log, as they come
        try:
            from fluoguide.threads import configure_threads

            configure_threads(args.library_threads)
            result = args.func(args)
        except FluoInputError as exc:
            _failed_warnings(caught, args)
            print(f"fluo: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except FluoCancelled as exc:
            _failed_warnings(caught, args)
            print(f"fluo: cancelled: {one_line(exc)}", file=sys.stderr)
            return 130
        except FluoError as exc:
            _failed_warnings(caught, args)
            print(f"fluo: error: {one_line(exc)}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print("fluo: interrupted", file=sys.stderr)
            return 130
        except OSError as exc:
            _failed_warnings(caught, args)
            if exc.errno != errno.ENAMETOOLONG:
                return _internal_error(exc, args)
            # a path typed too long for the file system (any reader's is_file or open):
            # the user's to shorten; the web app refuses it earlier (paths.inside)
            name = one_line(exc.filename or "")
            shown = name if len(name) <= 80 else f"{name[:60]}... ({len(name)} characters)"
            print(f"fluo: error: {shown}: name too long for the file system", file=sys.stderr)
            return 2
        except Exception as exc:  # the last resort: a bug, not the user's input
            _failed_warnings(caught, args)
            return _internal_error(exc, args)
    said = _warning_texts(caught)
    if said and isinstance(result, dict):
        old = result.get("warnings")
        old = [] if old is None else list(old) if isinstance(old, (list, tuple)) else [old]
        result["warnings"] = old + [w for w in said if w not in old]
    elif said:             # no result to carry them (nothing printed): one line each
        for w in said:
            print(f"fluo: warning: {w}", file=sys.stderr)
    if result is None:
        return 0
    # a handler whose work partly failed (a run with failed tasks) returns its
    # result with "_exit_code": printed as usual, then exit 1
    rc = int(result.pop("_exit_code", 0)) if isinstance(result, dict) else 0
    from fluoapp.format import command_name

    if isinstance(result, dict) and command_name(args).split(" ")[0] in MEMORY_REPORTED:
        from fluoguide.memory import peak_resident_bytes

        peak = peak_resident_bytes()
        if peak is not None:
            result.setdefault("peak_memory_gb", round(peak / 1e9, 2))
    if getattr(args, "json", False):
        text = dumps(result)
    else:
        from fluoapp.format import format_result

        text = format_result(result, command_name(args))
    return _print_stdout(text, rc)


def _print_stdout(text, rc):
    """Print the result; a reader that closed the pipe early (``fluo ... | head``)
    ends the command quietly with exit 1, not a traceback (Python's documented
    way: stdout pointed at /dev/null so the interpreter's final flush is quiet)."""
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    return rc


def _warning_texts(caught):
    """The caught warnings about the user's data or the numbers, one line each, in
    order, once each: a project warning by its message, another (numpy's) with its
    category (``RuntimeWarning: overflow encountered in exp``). Warnings about the
    code (deprecations) are logged instead."""
    out = []
    for w in caught:
        if issubclass(w.category, _CODE_WARNINGS):
            log.debug("%s: %s (%s:%s)", w.category.__name__, w.message, w.filename, w.lineno)
            continue
        text = str(w.message).strip()
        if not (issubclass(w.category, UserWarning) and str(w.filename).startswith(_PROJECT_ROOT)):
            text = f"{w.category.__name__}: {text}"
        text = one_line(text, limit=300)
        if text not in out:
            out.append(text)
    return out


def _failed_warnings(caught, args):
    """A failed command's warnings: the log, and stderr under ``--debug`` (before the
    error line, which stays last)."""
    for text in _warning_texts(caught):
        log.info("warning of a failed command: %s", text)
        if getattr(args, "debug", False):
            print(f"fluo: debug: warning: {text}", file=sys.stderr)


def _shown_warning(message, category, filename, lineno, file=None, line=None):
    """How a serving command shows a Python warning: one line in its log."""
    log.warning("%s", one_line(f"{category.__name__}: {message} ({filename}:{lineno})"))


def _internal_error(exc, args):
    """One line for an unexpected exception (exit 1); the traceback under ``--debug``.

    The message is the exception's, escaped to one line and without a C++
    library's internals (a SimpleITK or OpenCV error names its build's source
    files: ``fluoguide.library_errors.scrub``).
    """
    if getattr(args, "debug", False):
        import traceback

        traceback.print_exception(exc, file=sys.stderr)
    from fluoguide.library_errors import scrub

    first = scrub(str(exc).strip(), limit=300)
    hint = "" if getattr(args, "debug", False) else " (fluo --debug ... shows the traceback)"
    print(f"fluo: internal error: {type(exc).__name__}: {first}{hint}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
