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
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import shutil
import time
from pathlib import Path

from fluoguide.errors import FluoInputError

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
        yield tmp
        if not tmp.is_file():
            raise FluoInputError("the writer produced no file", file=path, field=field)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
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
    out_dir = Path(out_dir).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise FluoInputError("output exists and is not a folder", file=out_dir)
    fresh = not out_dir.exists()
    if fresh:
        stage = stage_beside(out_dir)
    else:
        try:
            stage = staging_folder(out_dir)
        except OSError as exc:
            raise output_error(exc, out_dir) from None
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
    write_text(out_dir / JOURNAL, json.dumps(journal))
    _roll_forward(out_dir, journal)


def _roll_forward(out_dir, journal):
    stage = (out_dir / journal["stage"]).resolve()
    for name in journal["files"]:
        src = stage / name
        if src.exists():  # moved already when a crash interrupted the last roll
            os.replace(src, out_dir / name)
    _fsync_dir(out_dir)
    with contextlib.suppress(FileNotFoundError):
        (out_dir / JOURNAL).unlink()
    _fsync_dir(out_dir)
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
