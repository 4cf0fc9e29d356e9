"""FluoNav panel: the tissue surface from the segmented CBCT, shown in 3D."""

from __future__ import annotations

from fluoguide import mrml_io

__all__ = ["NavPanel"]


class NavPanel:
    key = "FluoNav"
    title = "FluoNav: surface and navigation"
    icon = "mdi-crosshairs-gps"

    def __init__(self, app, logic):
        self.app = app
        self.logic = logic
        s = app.state
        s.nav_target_triangles = 62000
        s.nav_surface_info = ""
        app.ctrl.nav_build_surface = app.guarded(self.build_surface)

    def build_surface(self):
        s = self.app.state
        target = int(s.nav_target_triangles) if s.nav_target_triangles else None
        model = self.logic.buildSurface(targetTriangles=target)
        model.GetDisplayNode().SetOpacity(0.6)
        self.app.show_in_3d(model)
        poly = model.GetPolyData()
        s.nav_surface_info = (f"TissueSurface: {poly.GetNumberOfCells()} triangles, "
                              f"{poly.GetNumberOfPoints()} points")
        self.app.render_all()
        self.app.notify(s.nav_surface_info, "success")

    def build_ui(self):
        from trame.widgets import html
        from trame.widgets import vuetify3 as v

        html.Div("FluoNav", classes="text-h6")
        html.Div("Tissue surface (for per-pixel ray casting)", classes="text-subtitle-2 mt-2")
        v.VTextField(v_model_number=("nav_target_triangles",), type="number",
                     label="Target triangles (0 = keep all)", density="compact", hide_details=True,
                     id="nav-triangles")
        v.VBtn("Surface from CBCTLabels", click=self.app.ctrl.nav_build_surface, block=True,
               classes="mt-2", disabled=("job.running",), id="nav-surface")
        html.Div("{{ nav_surface_info }}", classes="text-caption", id="nav-surface-info")
