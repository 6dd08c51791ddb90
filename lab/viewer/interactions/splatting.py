"""Gaussian splatting's interaction: a click on a pixel of a held-out view's picture (on its camera frustum,
drawn once ``render_held_out`` ran) lists the Gaussians that pixel is made of.

The list is the module's :func:`~lab.modules.splatting.render_view` run for that view and pixel: the chart
``pixel_gaussians`` gives each Gaussian's alpha, the transmittance it meets and its weight, front to back,
and ``pixel_splats`` draws their centres (both drawn by the generic renderers, named in the legend). The
click is :class:`~lab.viewer.pixel_click.HeldOutPixelClick` (NeRF's ray click is the same).
"""

from __future__ import annotations

from lab.core import Cameras
from lab.viewer.interactions import Interaction
from lab.viewer.pixel_click import HeldOutPixelClick, clicked_pixel


class PixelGaussians(HeldOutPixelClick):
    """Click a held-out view's pixel: run ``render_view`` for it (the Gaussians it is made of)."""

    title = "Gaussians of a pixel"
    text = ("Click a pixel of a held-out view's picture (on its camera, once **render_held_out** ran): "
            "**render_view** lists the Gaussians it is made of, front to back, with their alpha, the "
            "transmittance they meet and their weight (chart *pixel_gaussians*; their centres are "
            "*pixel_splats*).")

    def clickable(self) -> Cameras | None:
        """The held-out cameras (carrying ``test_renders``) once a model is trained."""
        cameras = self.ctx.value("held_out_cameras")
        return cameras if cameras is not None and self.ctx.value("model") is not None else None


INTERACTIONS: list[type[Interaction]] = [PixelGaussians]

__all__ = ["INTERACTIONS", "PixelGaussians", "clicked_pixel"]
