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
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from pathlib import Path

JOURNAL = ".fluo-commit.json"
STAGING_PREFIX = ".fluo-stage-"


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
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success it becomes ``path``.

    The temporary name keeps the suffix, so writers that choose the format from
    the extension (matplotlib, VTK, SimpleITK) behave as for ``path``. On an
    exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{time.monotonic_ns()}{''.join(path.suffixes)}")
    try:
        yield tmp
        if tmp.exists():
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return Path(path)


def staging_folder(out_dir):
    """A new hidden staging folder inside ``out_dir`` (created)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    recover(out_dir)
    stage = out_dir / f"{STAGING_PREFIX}{os.getpid()}-{time.monotonic_ns()}"
    stage.mkdir()
    return stage


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
            files = journal["files"]
            ok = isinstance(files, list) and all(isinstance(f, str) and "/" not in f for f in files)
        except (ValueError, KeyError, TypeError, OSError):
            ok = False
        if ok:
            _roll_forward(out_dir, journal)
            rolled = True
        else:  # the journal is written atomically: unreadable means not ours
            journal_path.unlink(missing_ok=True)
    now = time.time()
    with contextlib.suppress(OSError):
        for stage in out_dir.glob(f"{STAGING_PREFIX}*"):
            # another process may be staging right now: only old ones are debris
            if stage.is_dir() and now - stage.stat().st_mtime > stale_after_s:
                shutil.rmtree(stage, ignore_errors=True)
    return rolled
