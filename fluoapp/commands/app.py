"""``fluo app``: serve the web application."""

from __future__ import annotations

from pathlib import Path

from fluoguide.errors import FluoInputError


def _app(args):
    import logging

    from fluoapp.webapp.app import create_app

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("fluoguide").setLevel(logging.INFO)
    if args.scene and not Path(args.scene).is_file():
        raise FluoInputError("scene file not found", file=args.scene, field="--scene")
    if not 0 < args.port < 65536:
        raise FluoInputError("port must be within 1..65535", field="--port", value=args.port)
    app = create_app(scene_path=args.scene)
    print(f"FluoGuide app: http://{args.host}:{args.port}/", flush=True)
    app.start(port=args.port, host=args.host)
    return {"stopped": True}


def register(subparsers):
    p = subparsers.add_parser("app", help="web application (trame-slicer) on the shared MRML scene",
                              description="Serve the FluoGuide web app: slice and 3D views, the "
                              "segment editor and one panel per module.")
    p.add_argument("--scene", help="MRML scene to open (.mrml; default: an empty scene)")
    p.add_argument("--port", type=int, default=8080,
                   help="TCP port to serve on (default %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only)")
    p.set_defaults(func=_app)
