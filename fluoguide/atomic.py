"""Writes that a crash cannot leave half done.

One file: write a temporary sibling, flush it to disk, ``os.replace`` it onto the
final name (:func:`atomic_path`). A reader sees the old file or the new one.

Several files that belong together (a scene's ``.mrml`` and its data files, a
phantom folder): they are written into a staging folder on the same file system,
then moved in by :func:`commit_files`, which first writes a journal naming every
move. A crash before the journal leaves the old state (plus a hidden staging
folder); a crash after it is rolled forward by :func:`recover`, which every
loader and every later commit calls first, so a reader sees the old set or the
new set, never a mix.

A set of files written as a whole (:func:`staged_folder`: a phantom, a synthetic
data set) is staged beside a new folder and appears with one rename
(:func:`stage_beside`, :func:`publish_folder`), or is committed into an existing
folder as above.

A kill -9 cannot run cleanup code, so it leaves hidden debris (a ``.NAME.tmp-PID-*``
file, a ``.NAME.stage-PID-*`` folder), never a damaged final name; the next
write to the same name removes debris whose process is gone.

Errors the user can fix (the output is a folder, its parent is a file, no
permission, read-only file system) are ``FluoInputError`` naming the path.

Crash points (for tests of the promises above): with ``FLUO_CRASH_AT`` set to
``POINT``, ``POINT:N``, ``POINT@NAME`` or ``POINT@NAME:N`` in the environment, the
process prints one line to stderr (``fluo: crash point POINT reached
(FLUO_CRASH_AT=...): PATH``), flushes it and kills itself with SIGKILL the N-th
time (default 1) it reaches that named step of a write (with ``@NAME``: a step
on a path that ends in NAME, one or more whole components, e.g.
``atomic.before_replace@table.csv`` or ``commit.moved@demo/CBCT.nrrd``), so a
test interrupts exactly the step it means to, not a random moment. The points
are :data:`CRASH_POINTS`; a POINT that is not one of them, or an N that is not a
positive integer, is a ``ValueError`` at the first point reached, never a run
that is silently not killed. Without the variable a point costs one environment
look-up.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from fluoguide.errors import FluoInputError

#: The named steps where ``FLUO_CRASH_AT`` kills the process, in the order a
#: write reaches them (see the module docstring), and the path each names
#: (what ``@NAME`` matches the end of):
#:
#: ``atomic.before_replace`` (the final file)
#:     :func:`atomic_path`: the temporary file is complete and on disk, not yet
#:     renamed onto the final name (every single-file write, the journal too).
#: ``folder.before_publish`` (the new folder)
#:     :func:`publish_folder`: a new folder is complete in its staging folder
#:     beside the final name, before the one rename.
#: ``commit.before_journal`` (the folder committed into)
#:     :func:`commit_files`: every file is staged inside the folder; no journal.
#: ``commit.journal_written`` (the folder)
#:     :func:`commit_files`: the journal is on disk; nothing moved yet.
#: ``commit.moved`` (the file just moved in)
#:     the roll forward (of a commit, or of :func:`recover`): after each file
#:     moved in (``commit.moved:1`` is after the first of several moves).
#: ``commit.before_cleanup`` (the folder)
#:     the roll forward: every file moved and the journal removed, the
#:     staging folder not yet removed.
CRASH_POINTS = ("atomic.before_replace", "folder.before_publish", "commit.before_journal",
                "commit.journal_written", "commit.moved", "commit.before_cleanup")
CRASH_ENV = "FLUO_CRASH_AT"
_crash_hits = {}             # FLUO_CRASH_AT value -> times its point was reached in this process
_crash_lock = threading.Lock()

JOURNAL = ".fluo-commit.json"
STAGING_PREFIX = ".fluo-stage-"
# errors that the user can fix by choosing another output path
_USER_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR,
                errno.EEXIST, errno.ENOENT, errno.ENAMETOOLONG, errno.ELOOP, errno.ENOTEMPTY}


def output_error(exc, path, field=None):
    """``FluoInputError`` for an OSError the user can fix, else the OSError itself.

    A full disk or an I/O error is not bad input: it stays an OSError (the CLI
    reports it on one line with exit code 1).
    """
    if isinstance(exc, OSError) and exc.errno in _USER_ERRNOS:
        return FluoInputError(f"cannot write here ({exc.strerror})", file=path, field=field)
    return exc


def make_folder(path, field="--out"):
    """``path`` created with its parents (an existing one is fine) and returned as a
    Path; a folder the user cannot create there is one ``FluoInputError`` naming
    it and ``field`` (:func:`output_error`)."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(exc, out, field) from None
    return out


def crash_point(name, path=None):
    """Die here (SIGKILL) when ``FLUO_CRASH_AT`` names this point and hit.

    Parameters
    ----------
    name : str
        One of :data:`CRASH_POINTS`.
    path : path, optional
        What is being written: named in the stderr line, and matched by the
        ``@NAME`` of ``FLUO_CRASH_AT``.

    Raises
    ------
    ValueError
        When ``FLUO_CRASH_AT`` is set but names no crash point or has a bad
        count, or ``name`` is not a crash point (a test must not pass because
        nothing was killed).
    """
    spec = os.environ.get(CRASH_ENV)
    if not spec:
        return
    head, colon, nth = spec.rpartition(":")
    if not colon:
        head, nth = spec, "1"
    point, at, target = head.partition("@")
    if (point not in CRASH_POINTS or not nth.isdigit() or int(nth) < 1
            or (at and not target)):
        raise ValueError(f"{CRASH_ENV}={spec!r}: expected POINT, POINT:N, POINT@NAME or "
                         f"POINT@NAME:N (N >= 1), POINT one of {', '.join(CRASH_POINTS)}")
    if name not in CRASH_POINTS:
        raise ValueError(f"crash point {name!r} is not in atomic.CRASH_POINTS")
    if point != name:
        return
    if at:
        want = Path(target).parts
        if path is None or Path(path).parts[-len(want):] != want:
            return
    with _crash_lock:        # writers in threads (the web app) count each hit once
        hits = _crash_hits[spec] = _crash_hits.get(spec, 0) + 1
        if hits != int(nth):
            return
        with contextlib.suppress(Exception):
            sys.stderr.flush()                # what was printed before stays before
        line = f"fluo: crash point {name} reached ({CRASH_ENV}={spec})"
        # straight to fd 2: sys.stderr may be a progress bar's or a captured stream
        os.write(2, (line + (f": {path}" if path is not None else "") + "\n").encode())
        os.kill(os.getpid(), signal.SIGKILL)


def _pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def _remove_debris(folder, prefix, max_age_s=86400.0):
    """Remove ``folder/prefix<pid>-*`` entries of processes that are gone (or a day old)."""
    now = time.time()
    with contextlib.suppress(OSError):
        for entry in Path(folder).glob(glob.escape(prefix) + "*"):
            pid = entry.name[len(prefix):].split("-", 1)[0]
            try:
                stale = (not pid.isdigit() or not _pid_alive(int(pid))
                         or now - entry.lstat().st_mtime > max_age_s)
            except OSError:
                continue
            if stale:
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    with contextlib.suppress(OSError):
                        entry.unlink()


def _check_target(path, field=None):
    """Refuse a final name that is a folder; create the parent folder."""
    path = Path(path)
    if path.is_dir():
        raise FluoInputError("is a folder, expected a file name", file=path, field=field)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(exc, path, field) from None


def _fsync_dir(folder):
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path, field=None):
    """Yield a temporary path beside ``path``; on success it becomes ``path``.

    The temporary name keeps the suffix, so writers that choose the format from
    the extension (matplotlib, VTK, SimpleITK) behave as for ``path``. On an
    exception the temporary file is removed and ``path`` is untouched. The
    writer must create the temporary file (a missing one is an error).
    """
    path = Path(path)
    _check_target(path, field)
    prefix = f".{path.name}.tmp-"
    _remove_debris(path.parent, prefix)
    tmp = path.with_name(f"{prefix}{os.getpid()}-{time.monotonic_ns()}{''.join(path.suffixes)}")
    try:
        try:
            yield tmp
        except OSError as exc:
            # the writer could not create the temporary file: a folder that refuses
            # writes (EACCES/EPERM/EROFS, root included) although check_writable
            # passed (os.access trusts root); an error about another file is the
            # writer's own and goes up as it is
            if str(exc.filename) != str(tmp):
                raise
            raise output_error(exc, path, field) from None
        if not tmp.is_file():
            raise FluoInputError("the writer produced no file", file=path, field=field)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        crash_point("atomic.before_replace", path)
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise output_error(exc, path, field) from None
        _fsync_dir(path.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def check_writable(path, field=None, folder=False):
    """Refuse an output path that cannot be written, before any work or writing.

    The path (a file, or a folder when ``folder``) may exist or not; the
    nearest existing ancestor must be a writable folder. Nothing is created.
    """
    path = Path(path)
    if path.exists():
        if folder and not path.is_dir():
            raise FluoInputError("output exists and is not a folder", file=path, field=field)
        if not folder and path.is_dir():
            raise FluoInputError("is a folder, expected a file name", file=path, field=field)
    up = path if folder and path.exists() else path.parent
    while not up.exists() and up != up.parent:
        up = up.parent
    if not up.is_dir():
        raise FluoInputError("cannot write here (a file where a folder is needed)", file=path,
                             field=field, value=str(up))
    if not os.access(up, os.W_OK | os.X_OK):
        raise FluoInputError("cannot write here (no permission)", file=path, field=field)
    return path


def write_bytes(path, data, field=None):
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path, field) as tmp:
        try:
            Path(tmp).write_bytes(data)
        except OSError as exc:
            raise output_error(exc, path, field) from None
    return Path(path)


def write_text(path, text, field=None):
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    return write_bytes(path, text.encode("utf-8"), field)


def save_figure(fig, path, field=None, **savefig_kwargs):
    """``fig.savefig(path)`` atomically (the format follows the suffix); returns the path."""
    with atomic_path(path, field) as tmp:
        fig.savefig(tmp, **savefig_kwargs)
    return Path(path)


def save_npy(path, array, field=None):
    """``numpy.save`` to exactly ``path`` (no ``.npy`` appended), atomically."""
    import numpy as np

    with atomic_path(path, field) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, array)
    return Path(path)


def stage_beside(folder):
    """A new hidden staging folder beside ``folder`` (same file system), for
    :func:`publish_folder`; debris of killed writers is removed first."""
    folder = Path(folder)
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(exc, folder) from None
    prefix = f".{folder.name}.stage-"
    _remove_debris(folder.parent, prefix)
    stage = folder.with_name(f"{prefix}{os.getpid()}-{time.monotonic_ns()}")
    try:
        stage.mkdir()  # not mkdtemp: its 0700 mode would follow the folder into place
    except OSError as exc:
        raise output_error(exc, folder) from None
    return stage


def publish_folder(stage, folder):
    """Rename the complete ``stage`` to ``folder`` (which must not exist): one step."""
    stage, folder = Path(stage), Path(folder)
    crash_point("folder.before_publish", folder)
    try:
        os.rename(stage, folder)
    except OSError as exc:
        if folder.exists():
            raise FluoInputError("the output folder appeared while it was being written",
                                 file=folder) from None
        raise output_error(exc, folder) from None
    _fsync_dir(folder.parent)
    return folder


def staging_folder(out_dir):
    """A new hidden staging folder inside ``out_dir`` (created)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    recover(out_dir)
    stage = out_dir / f"{STAGING_PREFIX}{os.getpid()}-{time.monotonic_ns()}"
    stage.mkdir()
    return stage


@contextlib.contextmanager
def staged_folder(out_dir, last=()):
    """Yield a staging folder whose files become ``out_dir``'s as one step.

    A new ``out_dir`` is staged beside its final name and appears with one
    rename; over an existing folder the files are staged inside it and moved
    in as a journaled transaction (:func:`commit_files`), ``last`` (the files
    readers open first: a manifest, the ``.mrml``) last. Flat folders only.
    On an exception nothing of the new set is left behind.
    """
    given = Path(out_dir)          # messages name the folder as the user gave it
    out_dir = given.resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise FluoInputError("output exists and is not a folder", file=given)
    fresh = not out_dir.exists()
    if fresh:
        stage = stage_beside(out_dir)
    else:
        try:
            stage = staging_folder(out_dir)
        except OSError as exc:
            raise output_error(exc, given) from None
    try:
        yield stage
        if fresh:
            publish_folder(stage, out_dir)
        else:
            names = sorted(f.name for f in stage.iterdir() if f.name not in last)
            commit_files(stage, out_dir, names + [n for n in last if (stage / n).exists()])
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def commit_files(stage, out_dir, names):
    """Move ``names`` from ``stage`` into ``out_dir`` as one transaction.

    ``names`` are moved in order, so put the file that readers open first (the
    ``.mrml``) last. ``stage`` is removed afterwards.
    """
    stage, out_dir = Path(stage), Path(out_dir)
    journal = {"stage": os.path.relpath(stage, out_dir), "files": list(names)}
    crash_point("commit.before_journal", out_dir)
    write_text(out_dir / JOURNAL, json.dumps(journal))
    crash_point("commit.journal_written", out_dir)
    _roll_forward(out_dir, journal)


def _roll_forward(out_dir, journal):
    stage = (out_dir / journal["stage"]).resolve()
    for name in journal["files"]:
        src = stage / name
        if src.exists():  # moved already when a crash interrupted the last roll
            try:
                os.replace(src, out_dir / name)
            except FileNotFoundError:
                continue  # a reader's recover() rolling the same journal moved it first
            crash_point("commit.moved", out_dir / name)
    _fsync_dir(out_dir)
    with contextlib.suppress(FileNotFoundError):
        (out_dir / JOURNAL).unlink()
    _fsync_dir(out_dir)
    crash_point("commit.before_cleanup", out_dir)
    shutil.rmtree(stage, ignore_errors=True)


def recover(out_dir, stale_after_s=600.0):
    """Finish a commit that a crash interrupted in ``out_dir``; drop stale staging folders.

    Returns True when a commit was rolled forward.
    """
    out_dir = Path(out_dir)
    rolled = False
    journal_path = out_dir / JOURNAL
    if journal_path.is_file():
        try:
            journal = json.loads(journal_path.read_text())
            files, stage = journal["files"], journal["stage"]
            # a hostile folder's journal must not move files in from elsewhere or
            # delete a folder outside (the roll ends by removing the stage)
            ok = (isinstance(files, list) and all(isinstance(f, str) and "/" not in f
                                                  and f not in ("", ".", "..") for f in files)
                  and isinstance(stage, str) and stage.startswith(STAGING_PREFIX)
                  and "/" not in stage and ".." not in stage
                  and (out_dir / stage).is_dir() and not (out_dir / stage).is_symlink())
        except (ValueError, KeyError, TypeError, OSError):
            ok = False
        if ok:
            _roll_forward(out_dir, journal)
            rolled = True
        else:  # the journal is written atomically: unreadable means not ours
            journal_path.unlink(missing_ok=True)
    # another process may be staging right now: only a dead writer's (or an
    # old) staging folder is debris
    _remove_debris(out_dir, STAGING_PREFIX, max_age_s=stale_after_s)
    return rolled
