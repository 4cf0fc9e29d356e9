"""``fluo app``: the FluoGuide web application on trame-slicer.

One MRML scene (trame-slicer's ``SlicerApp``), slice views and a 3D view,
trame-slicer's segment editor, and one panel per module.  Each panel is built
over its module's logic class (``<Module>Logic`` on the app's scene), the class the
desktop Slicer widget uses.

Rules the panels follow:

- every callback from the browser goes through :meth:`FluoGuideApp.guarded`, so
  an error becomes a message in the page, never a dead page;
- long work runs through :attr:`jobs` (one background job, progress bar,
  cancel button); its result is applied to the scene on the server's event
  loop by :meth:`poll`, so the UI never freezes and MRML stays single-threaded;
- every path a user types goes through :attr:`workspace` (confined to the
  workspace folder given at launch), and every message through
  :meth:`Workspace.scrub` (no server paths).

Who may connect (a per-launch secret, same-origin pages only, one browser
session at a time) is in :mod:`fluoapp.webapp.security`.
"""

from __future__ import annotations

import asyncio
import functools
import logging

from fluoguide.errors import FluoError

from fluoapp.webapp.jobs import JobRunner
from fluoapp.webapp.security import Workspace

__all__ = ["FluoGuideApp", "create_app"]

log = logging.getLogger("fluoguide.app")


class FluoGuideApp:
    """The server-side application (build with :func:`create_app`)."""

    POLL_S = 0.2

    def __init__(self, server=None, scene_path=None, workspace=None):
        import tempfile

        from fluoguide import mrml_io

        if scene_path:
            mrml_io.load_scene(scene_path)  # a bad scene is refused before the app is built
        from trame.app import get_server
        from trame_slicer import module as trame_slicer_module
        from trame_slicer.app.logic import LayoutButtonLogic
        from trame_slicer.app.logic.segmentation import SegmentEditorLogic
        from trame_slicer.core import SlicerApp
        from trame_slicer.rca_view import register_rca_factories

        self.server = server or get_server(None, client_type="vue3")
        self.server.enable_module(trame_slicer_module)
        self.slicer_app = SlicerApp()
        register_rca_factories(self.slicer_app.view_manager, self.server)
        self.layout_logic = LayoutButtonLogic(self.server, self.slicer_app)
        self.segment_logic = SegmentEditorLogic(self.server, self.slicer_app)
        self.jobs = JobRunner()
        # no workspace given (tests, scripts): a new empty one, never the cwd
        if isinstance(workspace, Workspace):
            self.workspace = workspace
        else:
            self.workspace = Workspace(workspace if workspace is not None
                                       else tempfile.mkdtemp(prefix="fluoguide-workspace-"))
        self.gate = None
        self._form_fields = set()  # the state keys a click may carry (submit)
        self.state.trame__title = "FluoGuide"
        self.state.fluo_message = ""
        self.state.fluo_message_color = "info"
        self.state.fluo_message_visible = False
        self.state.job = self._job_state()
        self.state.ping_count = 0
        # declared before the page is built: a key the client first sees later is
        # not reactive there, and the segment editor's button stayed disabled
        self.state.is_volume_loaded = False
        self.ctrl.fluo_ping = self._ping
        self.ctrl.fluo_cancel_job = self.guarded(self.jobs.cancel)
        self.panels = self._make_panels()
        from fluoapp.webapp.ui import build_ui

        self.ui = build_ui(self)
        self.segment_logic.set_ui(self.ui.tool_registry["segment_editor"])
        self.layout_logic.set_ui(self.ui.layout_button)
        self.ctrl.on_server_ready.add(self._on_ready)
        if scene_path:
            self.load_scene_file(scene_path)

    # -- shorthands ----------------------------------------------------------
    @property
    def state(self):
        return self.server.state

    @property
    def ctrl(self):
        return self.server.controller

    @property
    def scene(self):
        return self.slicer_app.scene

    def _make_panels(self):
        from fluoguide.slicer_compat import import_module_file

        from fluoapp.webapp.calib_panel import CalibPanel
        from fluoapp.webapp.nav_panel import NavPanel
        from fluoapp.webapp.tomo_panel import TomoPanel

        panels = []
        for name, panel in (("FluoCalib", CalibPanel), ("FluoTomo", TomoPanel), ("FluoNav", NavPanel)):
            logic = getattr(import_module_file(name), f"{name}Logic")(self.scene)
            panels.append(panel(self, logic))
        return panels

    # -- messages and guarded callbacks --------------------------------------
    def notify(self, text, color="info"):
        text = self.workspace.scrub(text)
        self.state.fluo_message = text
        self.state.fluo_message_color = color
        self.state.fluo_message_visible = True
        # Pushed even where the server already holds True: the page closes the
        # message itself after its timeout, and a close still on its way when the
        # next message comes would otherwise leave that message hidden.
        self.state.dirty("fluo_message_visible")
        (log.warning if color == "error" else log.info)("%s", text)

    def submit(self, action, fields):
        """A button's ``click`` that carries the form fields its panel's actions read.

        The browser pushes typed values only while no request is in flight, but sends
        a click at once: a click right after typing (during a render, say) would run
        the action on the values from before. So the values travel with the click and
        :meth:`guarded` applies them before the action runs.

        Parameters
        ----------
        action : str
            The controller function's name (``app.ctrl.<action>``).
        fields : sequence of str
            State keys bound to the panel's inputs.
        """
        self._form_fields.update(fields)
        form = ", ".join(f"{k}: {k}" for k in fields)
        return (getattr(self.ctrl, action), "[]", "{fluo_form: {" + form + "}}")

    def guarded(self, fn):
        """Wrap a UI callback: errors become a red message, the page lives on. A
        ``fluo_form`` argument (from :meth:`submit`) is applied to the state first."""

        @functools.wraps(fn)
        def wrapper(*args, fluo_form=None, **kwargs):
            try:
                if fluo_form:
                    self.state.update({k: v for k, v in fluo_form.items()
                                       if k in self._form_fields})
                return fn(*args, **kwargs)
            except FluoError as exc:
                self.notify(str(exc), "error")
            except Exception as exc:  # unexpected: keep the page alive, show the type
                log.exception("callback %s failed", getattr(fn, "__name__", fn))
                self.notify(f"{type(exc).__name__}: {exc}", "error")
            return None

        return wrapper

    def start_job(self, name, work, on_done=None, owner=None):
        """Run ``work(progress, cancel)`` in the background; ``on_done(result)`` later
        on the event loop.  Errors and cancellation end up as messages. ``owner``:
        the panel that started it (FluoCalib, FluoNav, FluoTomo): only that panel
        shows the job's name, progress and outcome."""

        def on_error(kind, text):
            if kind == "cancelled":
                self.notify(f"{name}: cancelled", "warning")
            else:
                self.notify(f"{name} failed: {text}", "error")

        self.jobs.start(name, work, on_done=on_done, on_error=on_error)
        self._job_owner = owner
        self.state.job = self._job_state()

    def _job_state(self):
        job = self.jobs.state.as_dict()
        job["owner"] = getattr(self, "_job_owner", None)
        job["message"], job["error"] = (self.workspace.scrub(job["message"]),
                                        self.workspace.scrub(job["error"]))
        return job

    def _ping(self):
        # The browser tests time this round trip while a job runs.
        self.state.ping_count = int(self.state.ping_count or 0) + 1

    # -- event loop ----------------------------------------------------------
    def _on_ready(self, **_):
        asyncio.get_event_loop().create_task(self._poll_loop())

    async def _poll_loop(self):
        while True:
            try:
                self.poll()
            except Exception:  # never let the poller die
                log.exception("poll failed")
            await asyncio.sleep(self.POLL_S)

    def poll(self):
        """Apply finished jobs and publish job progress to the browser."""
        with self.state:
            self.jobs.poll()
            self.state.job = self._job_state()
            for panel in self.panels:
                hook = getattr(panel, "on_poll", None)
                if hook is not None:
                    hook()

    # -- scene ---------------------------------------------------------------
    def load_scene_file(self, path):
        from fluoguide import mrml_io
        from fluoguide.errors import FluoInputError

        loaded = mrml_io.load_scene(path)  # validates and names bad files
        self.scene.Clear(0)
        ok = self.slicer_app.io_manager.load_scene(str(path))
        if not ok:
            raise FluoInputError("scene could not be loaded into the app", file=path)
        del loaded
        self.show_cbct()

    def show_cbct(self, reset=True):
        from fluoguide import mrml_io

        vol = mrml_io.get_node(self.scene, "CBCT", required=False)
        if vol is None:
            return None
        self.slicer_app.display_manager.show_volume(vol, vr_preset="CT-AAA", do_reset_views=reset)
        vr = self.slicer_app.volume_rendering.get_vr_display_node(vol)
        if vr is not None:
            vr.SetVisibility(False)  # slices + surface models read better than a CT render here
        self.segment_logic.on_volume_changed(vol)
        self.state.is_volume_loaded = True
        return vol

    def show_volume(self, volume_node, reset=True):
        """Any volume (a user's label map) as the slices' background."""
        self.slicer_app.display_manager.show_volume(volume_node, do_reset_views=reset)
        vr = self.slicer_app.volume_rendering.get_vr_display_node(volume_node)
        if vr is not None:
            vr.SetVisibility(False)
        self.segment_logic.on_volume_changed(volume_node)
        self.state.is_volume_loaded = True
        return volume_node

    def show_in_3d(self, node):
        self.slicer_app.display_manager.set_node_visible_in_group(node)

    def show_foreground(self, volume_node, opacity=0.7):
        for view in self.slicer_app.view_manager.get_slice_views():
            view.set_foreground_volume_id(volume_node.GetID() if volume_node else None)
            view.set_foreground_opacity(opacity)

    def render_all(self, reset_3d=False):
        if reset_3d:
            for view in self.slicer_app.view_manager.get_threed_views():
                view.reset_camera()
        for view in self.slicer_app.view_manager.get_views():
            view.schedule_render()

    def start(self, port=8080, host="127.0.0.1", secret=None, allow_origins=(), announce=print,
              **kwargs):
        """Serve the app (blocking) to the holder of ``secret`` (default: a new one).

        ``announce`` receives the address with the secret, the one line a user
        needs (``fluo app`` prints it).
        """
        from trame_server.protocol import CoreServer

        from fluoapp.webapp.security import SessionGate, new_secret, origin_middleware

        secret = secret or new_secret()
        self.gate = SessionGate(secret)
        # wslink compares the hello's secret with this one unless a link protocol
        # decides (the gate does: right secret and no other session)
        self.server.cli.set_defaults(authKey=secret)
        CoreServer.authentication_token = secret
        self.server.add_protocol_to_configure(
            lambda protocol: protocol.registerLinkProtocol(self.gate.protocol))
        middleware = origin_middleware(self.gate, host, allow_origins)
        self.server.controller.on_server_bind.add(
            lambda wslink_server: wslink_server.app.middlewares.append(middleware))

        def ready(**_):
            shown = f"[{host}]" if ":" in host else host
            announce(f"FluoGuide app: http://{shown}:{self.server.port}/?secret={secret}")
            announce(f"workspace: {self.workspace.root} (the UI reads and writes only here)")

        self.ctrl.on_server_ready.add(ready)
        return self.server.start(port=port, host=host, open_browser=False,
                                 show_connection_info=False, **kwargs)


def create_app(server=None, scene_path=None, workspace=None):
    return FluoGuideApp(server=server, scene_path=scene_path, workspace=workspace)
