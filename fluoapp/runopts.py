"""Command-line options of every command that runs many tasks on the run engine
(``fluo study`` and ``fluo tomo batch``; Monte Carlo photon budgets next).

``--workers [N|auto]`` runs on an embedded local Dask cluster (``auto``, the
default when the option has no value: as many workers as the machine has cores
for ``--threads``); ``--scheduler ADDRESS`` (or ``$FLUO_SCHEDULER``) sends the
same tasks to a running Dask cluster; neither runs serially in this process.
``--resume`` reuses the finished tasks of a killed run in ``--out``.

A scheduler that does not answer within ``$FLUO_SCHEDULER_TIMEOUT`` seconds
(default 30; the connection, the handshake, its workers, and a sign of life
whenever no result came for that long during the run) ends the run with one
line and exit code 1 (:mod:`fluoguide.runs.cluster`).
"""

from __future__ import annotations

import sys

from fluoguide.errors import FluoInputError


def add_run_options(p, threads_default="1"):
    """The options on parser ``p``; ``threads_default=None``: --threads defaults to the
    process's library threads (``fluo --threads``) serially and 1 on workers (fluo demo)."""
    g = p.add_argument_group("running many tasks (Dask)")
    g.add_argument("--workers", nargs="?", const="auto", default=None, metavar="N|auto",
                   help="run on a local Dask cluster of N worker processes (auto, the default "
                   "value: one per core); without it (and without --scheduler) tasks run serially")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="tcp://HOST:PORT of a running Dask scheduler (default: $FLUO_SCHEDULER): "
                   "the same tasks on a real cluster; its workers need FluoGuide installed. "
                   "Each answer it owes is awaited at most $FLUO_SCHEDULER_TIMEOUT seconds "
                   "(default 30), then the run ends with an error")
    default_text = ("1: one task per core, no oversubscription" if threads_default == "1" else
                    "the process's (fluo --threads) serially, 1 per task on workers")
    g.add_argument("--threads", default=threads_default, metavar="N",
                   help=f"BLAS/OpenMP/numba threads per task (default {default_text}); "
                   "'none' leaves the libraries' own defaults")
    g.add_argument("--resume", action="store_true",
                   help="reuse the finished tasks of an earlier (killed) run in --out")
    g.add_argument("--no-dashboard", action="store_true",
                   help="start the local cluster without its web dashboard")


def threads_from(args):
    """--threads as an int, or None for 'none'."""
    text = str(args.threads).strip().lower()
    if text == "none":
        return None
    from fluoguide.runs.grid import convert

    n = convert(text, "--threads", int)
    if not 1 <= n <= 4096:
        raise FluoInputError("threads per task must be 1 to 4096 (or none)", field="--threads",
                             value=args.threads)
    return n


def check_run_options(args):
    """Validate the options before any work starts (one-line errors, exit 2)."""
    from fluoguide.runs.cluster import local_workers, scheduler_address, scheduler_timeout

    threads = threads_from(args)
    if args.resume and not getattr(args, "out", None):
        raise FluoInputError("--resume needs the run folder --out", field="--resume")
    if args.workers is not None:
        local_workers(args.workers, threads)
    if scheduler_address(args.scheduler) is not None or args.workers is not None:
        scheduler_timeout()   # a bad $FLUO_SCHEDULER_TIMEOUT: refused before any work
    return threads


def executor_for(args, threads):
    """Context manager: the executor the options ask for (the cluster is announced on stderr)."""
    from fluoguide.runs.cluster import executor

    return executor(workers=args.workers, scheduler=args.scheduler, threads=threads,
                    log=sys.stderr, dashboard=not args.no_dashboard)
