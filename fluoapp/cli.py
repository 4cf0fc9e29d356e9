"""The ``fluo`` command line.

Each capability registers its own subcommands from a small ``*_cli`` module
listed in ``CLI_MODULES``; this file only builds the parser, runs the chosen
command and turns errors into one-line messages: bad input (``FluoInputError``)
exit code 2, a device or peer failure (``FluoError``) exit code 1, anything else
is a bug: one line ``fluo: internal error: ...``, exit code 1, and the traceback
only under ``fluo --debug``.

Conventions every subcommand follows:

- ``--json`` prints exactly one JSON object on stdout (progress goes to stderr).
- Bad input raises ``FluoInputError``: one line on stderr, exit code 2.
- A handler returns a dict (the JSON result); without ``--json`` it is printed
  as readable ``key: value`` lines and tables with units (``fluoapp/format.py``).
  ``"_exit_code": 1`` in it (not printed) says the work partly failed (a run with
  failed tasks: they are in its table).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import sys

from fluoguide.errors import FluoCancelled, FluoError, FluoInputError
from fluoguide.jsonable import dumps

# Modules that define ``register(subparsers)``.  Order = order in --help.
CLI_MODULES = [
    "fluoapp.commands.phantom",
    "fluoapp.commands.scene",
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


def main(argv=None):
    from fluoguide.progress import mark_command_start

    mark_command_start()
    parser = build_parser()
    _quiet_vtk()
    args = parser.parse_args(argv)
    try:
        from fluoguide.threads import configure_threads

        configure_threads(args.library_threads)
        result = args.func(args)
    except FluoInputError as exc:
        print(f"fluo: error: {exc}", file=sys.stderr)
        return 2
    except FluoCancelled as exc:
        print(f"fluo: cancelled: {exc}", file=sys.stderr)
        return 130
    except FluoError as exc:
        print(f"fluo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("fluo: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        if exc.errno != errno.ENAMETOOLONG:
            return _internal_error(exc, args)
        # a path typed too long for the file system (any reader's is_file or open):
        # the user's to shorten; the web app refuses it earlier (paths.inside)
        name = str(exc.filename or "")
        shown = name if len(name) <= 80 else f"{name[:60]}... ({len(name)} characters)"
        print(f"fluo: error: {shown}: name too long for the file system", file=sys.stderr)
        return 2
    except Exception as exc:  # the last resort: a bug, not the user's input
        return _internal_error(exc, args)
    if result is None:
        return 0
    # a handler whose work partly failed (a run with failed tasks) returns its
    # result with "_exit_code": printed as usual, then exit 1
    rc = int(result.pop("_exit_code", 0)) if isinstance(result, dict) else 0
    if getattr(args, "json", False):
        print(dumps(result))
    else:
        from fluoapp.format import command_name, format_result

        print(format_result(result, command_name(args)))
    return rc


def _internal_error(exc, args):
    """One line for an unexpected exception (exit 1); the traceback under ``--debug``."""
    if getattr(args, "debug", False):
        import traceback

        traceback.print_exception(exc, file=sys.stderr)
    first = (str(exc).strip().splitlines() or [""])[0][:300]
    hint = "" if getattr(args, "debug", False) else " (fluo --debug ... shows the traceback)"
    print(f"fluo: internal error: {type(exc).__name__}: {first}{hint}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
