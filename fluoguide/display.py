"""How FluoGuide's result volumes look in slice views: pure MRML display
settings, the same in desktop Slicer (the FluoTomo panel) and in the web app's
trame-slicer views (``fluoapp.webapp.scene_display``)."""

from __future__ import annotations

import numpy as np

from fluoguide import mrml_io

__all__ = ["YIELD_COLORMAP", "yield_color_node_id", "style_yield_volume"]

# Slicer's "Iron" table (black - purple - red - yellow - white): monotonic in
# lightness, so a brighter colour always means more yield, and it is in
# slicer-core's built-in colours (the file-based Inferno/Viridis are not).
YIELD_COLORMAP = "vtkMRMLColorTableNodeIron"


def yield_color_node_id(scene, preferred=YIELD_COLORMAP):
    """ID of the yield colour table in ``scene`` (Iron, else Rainbow; None if neither)."""
    for cid in (preferred, "vtkMRMLColorTableNodeRainbow"):
        if scene.GetNodeByID(cid) is not None:
            return cid
    return None


def style_yield_volume(scene, node, threshold_fraction=0.2):
    """Colour map, window over [0, max] and a lower threshold at a fraction of the max.

    Returns ``(vmin, vmax, threshold)`` in the volume's units [1/mm].
    """
    arr = mrml_io.volume_array(node)
    vmax = float(np.nanmax(arr)) if arr.size else 0.0
    vmax = vmax if vmax > 0 else 1.0
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    disp = node.GetDisplayNode()
    cid = yield_color_node_id(scene)
    if cid:
        disp.SetAndObserveColorNodeID(cid)
    disp.SetAutoWindowLevel(0)
    disp.SetWindowLevelMinMax(0.0, vmax)
    thr = float(threshold_fraction) * vmax
    disp.SetAutoThreshold(0)
    disp.SetApplyThreshold(1)
    disp.SetThreshold(thr, vmax * 1.0001)
    return 0.0, vmax, thr
