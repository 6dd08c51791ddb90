"""The viser front end (DESIGN.md section 4): a GUI generated from any pipeline, one renderer per
value type, and :func:`export_scene_html` for headless reports.

    from lab.viewer import ViewerApp
    viewer = ViewerApp(store, port=8080).start()   # one session per browser tab

The server is :mod:`lab.viewer.app`; one tab is :class:`lab.viewer.view.ClientView`.
"""

from __future__ import annotations

from lab.viewer.app import ClientView, ModuleCatalog, ViewerApp
from lab.viewer.export import export_scene_html
from lab.viewer.renderers import RENDERERS, Canvas, StateDrawer, curve_image, overlay_view

__all__ = ["RENDERERS", "Canvas", "ClientView", "ModuleCatalog", "StateDrawer", "ViewerApp", "curve_image",
           "export_scene_html", "overlay_view"]
