"""Paths named inside data files and typed by users, confined to a folder.

A manifest (``stack.json``, ``illumination.json``, an MRML scene) names its
data files relative to its own folder; a hostile one could name
``../../etc/passwd`` or an absolute path and make a loader read it. The web
app confines every path its users type to a workspace folder. Both go through
:func:`inside`, which resolves symbolic links before it decides.
"""

from __future__ import annotations

import os
from pathlib import Path

from fluoguide.errors import FluoInputError

__all__ = ["inside", "is_inside"]


def is_inside(path, root):
    """True when ``path`` (resolved, links followed) is ``root`` or below it."""
    path, root = Path(path).resolve(), Path(root).resolve()
    return path == root or root in path.parents


def _check_length(path, root, name, file, field, what):
    """Refuse a path the file system cannot hold: every later ``is_file`` or
    ``open`` would raise ENAMETOOLONG (pathlib's ``is_dir`` does not swallow it),
    a traceback in the web app's log for a 5,000-character folder name."""
    try:
        name_max = os.pathconf(root, "PC_NAME_MAX")
        path_max = os.pathconf(root, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096          # Linux's limits
    longest = max((len(os.fsencode(part)) for part in path.parts), default=0)
    if longest > name_max or len(os.fsencode(str(path))) >= path_max:
        text = str(name)
        raise FluoInputError(f"{what} name too long (at most {name_max} bytes a name, "
                             f"{path_max - 1} a path)", file=file, field=field,
                             value=f"{text[:40]}... ({len(text)} characters)")


def inside(root, name, file=None, field=None, what="file", root_name="its folder", given=False):
    """``root / name`` resolved, refused unless it stays inside ``root``.

    Parameters
    ----------
    root : path
        The folder the name is relative to.
    name : str or path
        A relative name (an absolute one must still lie inside ``root``).
    file : path, optional
        The manifest the name came from, for the message.
    field : str, optional
        The field or UI input the name came from.
    what : str
        "file" or "folder", for the message.
    root_name : str
        What ``root`` is, for the message ("its folder", "the workspace").
    given : bool
        Return ``root / name`` as given (``acq/data.csv`` for a folder typed
        ``acq``) rather than resolved, for the messages of the reader that
        opens it: they name files as the user gave them, never the absolute
        form (docs/reliability.md). The check is the same.

    Returns
    -------
    Path
        The resolved path, or with ``given`` the path as given (not checked
        for existence).
    """
    if not isinstance(name, (str, Path)) or not str(name).strip() or "\x00" in str(name):
        raise FluoInputError(f"expected a {what} name", file=file, field=field, value=name)
    shown = Path(root) / str(name).strip()
    root = Path(root).resolve()
    path = (root / str(name).strip()).resolve()
    _check_length(path, root, name, file, field, what)
    if not (path == root or root in path.parents):
        # the value as given, never the resolved server path
        raise FluoInputError(f"{what} must be inside {root_name}", file=file, field=field,
                             value=str(name))
    return shown if given else path
