"""``fluo app``: serve the web application."""

from __future__ import annotations

import functools
import os
from pathlib import Path

from fluoguide.errors import FluoInputError


def _check_host(host):
    """The address must resolve here: a typo fails now with one line, not inside the server."""
    import socket

    try:
        socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, ValueError) as exc:
        raise FluoInputError(f"address does not resolve ({exc})", field="--host",
                             value=host) from None


def _app(args):
    import logging

    if args.scene and not Path(args.scene).is_file():
        raise FluoInputError("scene file not found", file=args.scene, field="--scene")
    if not 0 <= args.port < 65536:
        raise FluoInputError("port must be within 0..65535 (0: any free port)", field="--port",
                             value=args.port)
    _check_host(args.host)
    for origin in args.allow_origin or []:
        if not origin.startswith(("http://", "https://")) or origin.endswith("/"):
            raise FluoInputError("expected scheme://host:port", field="--allow-origin",
                                 value=origin)
    from fluoapp.webapp.app import create_app
    from fluoapp.webapp.security import Workspace

    workspace = Workspace(args.workspace or os.getcwd(), create=False)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("fluoguide").setLevel(logging.INFO)
    app = create_app(scene_path=args.scene, workspace=workspace)
    workspace.create()       # only once everything given was accepted
    app.start(port=args.port, host=args.host, allow_origins=tuple(args.allow_origin or []),
              announce=functools.partial(print, flush=True))
    return {"stopped": True}


def register(subparsers):
    p = subparsers.add_parser("app", help="web application (trame-slicer) on the shared MRML scene",
                              description="Serve the FluoGuide web app: slice and 3D views, the "
                              "segment editor and one panel per module. It prints the address to "
                              "open, with this launch's secret; it serves one browser session at "
                              "a time, and the paths typed in it stay inside --workspace.")
    p.add_argument("--scene", help="MRML scene to open (.mrml; default: an empty scene)")
    p.add_argument("--port", type=int, default=8080,
                   help="TCP port to serve on (default %(default)s; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--workspace", default=None,
                   help="folder the UI may read and write (default: the current folder)")
    p.add_argument("--allow-origin", action="append", default=None, metavar="ORIGIN",
                   help="also accept pages from this origin (scheme://host:port), e.g. behind a "
                   "proxy; repeatable (default: none; only the app's own address)")
    p.set_defaults(func=_app, serves=True)   # its warnings: its log, as they come (cli.py)
