"""Who may drive the web app, and which files its users may name.

The app binds 127.0.0.1, but any local process, and any web page open in the
same browser, can reach a port on 127.0.0.1. So:

- **Per-launch secret.** ``fluo app`` prints ``http://HOST:PORT/?secret=TOKEN``;
  trame's client sends the token in wslink's hello (and removes it from the
  address bar). A websocket without it is refused every call.
- **Origin.** A websocket handshake from a page of another origin (another
  site open in the same browser, a DNS-rebinding page) is refused with HTTP
  403 before any message is read.
- **One user.** trame keeps one state per server process: one form, one job
  slot, one message line. Two browser sessions would see each other's typing
  and cancel each other's jobs, so the app serves one session at a time: while
  one is connected, another page gets a page that says so (HTTP 409) and
  another websocket is refused at hello. When the first closes, the next may
  connect. A second user starts a second ``fluo app`` on another port.
- **Workspace.** Every path typed in the UI is resolved inside the workspace
  folder given at launch (links followed); the bundled example data can be
  read as ``bundled:NAME``. Messages show workspace-relative paths, never the
  server's own.
"""

from __future__ import annotations

import glob
import hmac
import logging
import re
import secrets
import time
from pathlib import Path

from fluoguide.errors import FluoInputError
from fluoguide.paths import inside

__all__ = ["Workspace", "SessionGate", "new_secret", "origin_middleware", "BUNDLED_PREFIX"]

log = logging.getLogger("fluoguide.app")

BUNDLED_PREFIX = "bundled:"
BUNDLED_ROOT = Path(__file__).resolve().parents[2] / "FluoCalib" / "Resources" / "TestData"


def new_secret():
    """A fresh token for one launch (URL-safe, 192 bits)."""
    return secrets.token_urlsafe(24)


class Workspace:
    """The folder the UI's paths are confined to.

    Parameters
    ----------
    root : path
        The workspace folder (not the file-system root).
    create : bool
        Create it now if missing (else :meth:`create` does, when the app starts).
    """

    def __init__(self, root, create=True):
        root = Path(root).expanduser().resolve()
        if root == Path(root.anchor):
            raise FluoInputError("the workspace cannot be the file-system root", field="--workspace",
                                 value=str(root))
        if root.exists() and not root.is_dir():
            raise FluoInputError("workspace is not a folder", file=root, field="--workspace")
        self.root = root
        if create:
            self.create()
        else:  # refuse now what create() would refuse later
            from fluoguide import atomic

            atomic.check_writable(root, "--workspace", folder=True)

    def create(self):
        """Create the workspace folder if it is missing."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FluoInputError(f"cannot create the workspace ({exc.strerror})", file=self.root,
                                 field="--workspace") from None
        return self

    def path(self, text, field, what="file", must_exist=False, writable=False):
        """The resolved path of a UI entry ``text`` (relative to the workspace).

        ``bundled:NAME`` names the bundled example data (read-only). Refused:
        anything outside the workspace, a missing path when ``must_exist``.
        """
        text = str(text or "").strip()
        if text.startswith(BUNDLED_PREFIX):
            if writable:
                raise FluoInputError("bundled data is read-only", field=field, value=text)
            p = inside(BUNDLED_ROOT, text[len(BUNDLED_PREFIX):] or ".", field=field, what=what,
                       root_name="the bundled data")
        else:
            p = inside(self.root, text, field=field, what=what, root_name="the workspace")
        if must_exist:
            ok = p.is_dir() if what == "folder" else p.is_file()
            if not ok:
                raise FluoInputError(f"{what} not found", field=field, value=text)
        return p

    def glob(self, pattern, field):
        """Files matching a UI glob ``pattern``, all inside the workspace (or bundled data)."""
        pattern = str(pattern or "").strip()
        bundled = pattern.startswith(BUNDLED_PREFIX)
        root = BUNDLED_ROOT if bundled else self.root
        rel = pattern[len(BUNDLED_PREFIX):] if bundled else pattern
        if not rel or Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise FluoInputError("pattern must be relative to the workspace (no '..')", field=field,
                                 value=pattern)
        files = sorted(glob.glob(str(root / rel)))
        # a link inside may still point outside: keep only files that resolve inside
        return [f for f in files if Path(f).is_file() and _is_inside(Path(f), root)]

    def shown(self, path):
        """How ``path`` is shown to the user: relative to the workspace (or ``bundled:``)."""
        p = Path(path)
        for root, prefix in ((self.root, ""), (BUNDLED_ROOT, BUNDLED_PREFIX)):
            try:
                rel = p.resolve().relative_to(root)
            except ValueError:
                continue
            return prefix + (str(rel) if str(rel) != "." else ".")
        return p.name

    # a "/" after "<" closes a tag in a name ("<b>x</b>"), it starts no server path
    _ABS = re.compile(r"(?<![\w.~<-])/(?:[^\s/:'\"(),;]+/)*[^\s/:'\"(),;]*")

    def scrub(self, text):
        """``text`` with server paths made workspace-relative (others cut to their name)."""
        text = str(text)
        for root, prefix in ((self.root, ""), (BUNDLED_ROOT, BUNDLED_PREFIX)):
            text = text.replace(str(root) + "/", prefix).replace(str(root), prefix or ".")
        return self._ABS.sub(lambda m: "…/" + m.group(0).rstrip("/").rsplit("/", 1)[-1]
                             if m.group(0) != "/" else "/", text)


def _is_inside(path, root):
    try:
        path.resolve().relative_to(root.resolve())
        return True
    except ValueError:
        return False


class SessionGate:
    """One browser session at a time, and only with the launch's secret.

    A wslink link protocol: wslink asks ``validateToken`` at each hello (and,
    because one is defined, no longer compares the secret itself).
    """

    def __init__(self, secret):
        from wslink.websocket import LinkProtocol

        self.secret = str(secret)
        self.owner = None
        self.owner_since = None
        self.refused = 0

        gate = self

        class _Protocol(LinkProtocol):
            async def validateToken(self, token, client_id):  # noqa: N802 (wslink's name)
                return gate.admit(token, client_id)

            def onClose(self, client_id):  # noqa: N802
                gate.release(client_id)

        self.protocol = _Protocol()

    def admit(self, token, client_id):
        """True for the launch's secret when no other session holds the app."""
        if not isinstance(token, str) or not hmac.compare_digest(token.encode(), self.secret.encode()):
            self.refused += 1
            log.warning("websocket refused: wrong or missing secret")
            return False
        if self.owner is not None and self.owner != client_id:
            self.refused += 1
            log.warning("websocket refused: a session is already open (single-user app)")
            return False
        self.owner, self.owner_since = client_id, time.time()
        return True

    def release(self, client_id):
        if client_id == self.owner:
            self.owner = self.owner_since = None

    @property
    def busy(self):
        return self.owner is not None


BUSY_PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>FluoGuide: in use</title>
<meta http-equiv="refresh" content="5">
<style>body{{font-family:sans-serif;max-width:40em;margin:4em auto;color:#222}}</style></head>
<body id="fluo-single-user"><h1>FluoGuide is open in another browser session</h1>
<p>This app serves one session at a time (since {since}): two sessions would share one form,
one job and one message line. Close the other tab or window, then reload this page; or start a
second app for a second user: <code>fluo app --port OTHER_PORT</code>. This page tries again
every 5 seconds.</p></body></html>
"""


def origin_middleware(gate, host, extra_origins=()):
    """aiohttp middleware: foreign websocket Origins get 403; a second page gets 409."""
    from aiohttp import web

    wildcard = host in ("", "0.0.0.0", "::")

    def allowed(request):
        sock = request.transport.get_extra_info("sockname") if request.transport else None
        port = sock[1] if sock else None
        names = {"127.0.0.1", "localhost", "[::1]"}
        if not wildcard:
            names.add(f"[{host}]" if ":" in host else host)
        return {f"{scheme}://{n}:{port}" for n in names for scheme in ("http", "https")} | set(
            extra_origins)

    @web.middleware
    async def guard(request, handler):
        if request.headers.get("Upgrade", "").lower() == "websocket":
            origin = request.headers.get("Origin")
            # browsers always send Origin on a websocket; scripts need the secret anyway
            if origin is not None and origin not in allowed(request):
                gate.refused += 1
                log.warning("websocket refused: foreign origin %r", origin[:100])
                return web.Response(status=403, text="foreign origin refused\n")
        elif request.method == "GET" and request.path in ("/", "/index.html") and gate.busy:
            since = time.strftime("%H:%M:%S", time.localtime(gate.owner_since or time.time()))
            return web.Response(status=409, content_type="text/html",
                                text=BUSY_PAGE.format(since=since))
        return await handler(request)

    return guard
