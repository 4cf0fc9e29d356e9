"""Page layout of the FluoGuide app: app bar, a tool strip on the left (one
button per module panel plus the segment editor and layouts), the panel
drawer, the view grid, and a message bar."""

from __future__ import annotations

__all__ = ["build_ui"]


class _UI:
    def __init__(self):
        self.tool_registry = {}
        self.layout = None
        self.layout_button = None


def build_ui(app):
    from trame.widgets import html
    from trame.widgets.vuetify3 import VBtn, VSnackbar, VSpacer, VDivider
    from trame_slicer.app.ui import ViewerLayout
    from trame_slicer.app.ui.control_button import ControlButton
    from trame_slicer.app.ui.layout_button import LayoutButton
    from trame_slicer.app.ui.segmentation import (SegmentEditorToolbarUI, SegmentEditorUI,
                                                  SegmentEditorUndoRedoUI)

    ui = _UI()
    state = app.state
    state.active_tool = state.active_tool or "FluoTomo"
    state.is_drawer_visible = True

    def active(key):
        return f"active_tool === '{key}'"

    def toggle(key):
        def fn():
            show = not state.is_drawer_visible or state.active_tool != key
            state.is_drawer_visible = show
            state.active_tool = key if show else None

        return fn

    with ViewerLayout(app.server, title="FluoGuide", is_drawer_visible=True) as layout:
        ui.layout = layout
        layout.title.set_text("FluoGuide")
        with layout.appbar:
            VSpacer()
            html.Span("{{ job.running ? (job.name + ': ' + job.message) : '' }}",
                      classes="text-caption mr-4", id="fluo-job-status")
            # A server round trip anyone can trigger; the browser tests time it
            # while a reconstruction runs (UI latency).
            with VBtn(click=app.ctrl.fluo_ping, variant="text", size="small", id="fluo-ping",
                      title="Check that the server answers"):
                html.Span("server {{ ping_count }}", id="fluo-ping-count",
                          classes="text-caption")
        with layout.drawer:
            for panel in app.panels:
                with html.Div(v_if=(active(panel.key),), classes="pa-2", id=f"panel-{panel.key}"):
                    panel.build_ui()
            editor = SegmentEditorUI(v_if=(active("segment_editor"),))
            ui.tool_registry["segment_editor"] = editor
        with layout.toolbar:
            for panel in app.panels:
                ControlButton(name=panel.title, icon=panel.icon, click=toggle(panel.key),
                              active=(active(panel.key),), classes="mt-1",
                              id=f"tool-{panel.key}")
            VDivider(classes="my-1")
            ControlButton(name="Segment editor (paint, erase, islands, smoothing)",
                          icon="mdi-brush", click=toggle("segment_editor"),
                          active=(active("segment_editor"),), classes="mt-1",
                          disabled=("!is_volume_loaded",), id="tool-segment-editor")
            SegmentEditorToolbarUI(editor_ui=editor)
            ui.layout_button = LayoutButton(classes="mt-1")
        with layout.undo_redo:
            SegmentEditorUndoRedoUI(editor_ui=editor, v_if=(active("segment_editor"),))
        with layout.content:
            app.layout_logic.layout_manager.initialize_layout_grid(layout)
        with VSnackbar(v_model=("fluo_message_visible",), color=("fluo_message_color",),
                       timeout=8000, location="top", multi_line=True, id="fluo-message"):
            html.Span("{{ fluo_message }}")
            with VBtn(variant="text", click="fluo_message_visible = false", size="small"):
                html.Span("close")
    return ui
