"""Gaussian splatting's interaction: a click on a pixel of a held-out view's picture (on its camera frustum,
drawn once ``render_held_out`` ran) lists the Gaussians that pixel is made of.

The list is the module's :func:`~lab.modules.splatting.render_view` run for that view and pixel: the chart
``pixel_gaussians`` gives each Gaussian's alpha, the transmittance it meets and its weight, front to back,
and ``pixel_splats`` draws their centres (both drawn by the generic renderers, named in the legend).
"""

from __future__ import annotations

import math

import numpy as np

from lab.viewer.interactions import Interaction, InteractionContext


def clicked_pixel(pixel: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """The pixel ``(column, row)`` holding a click at picture coordinates ``pixel`` ``(u, v)`` (0 at the
    picture's left and top edges, ``width`` and ``height`` at the others), clamped into the image."""
    u, v = float(pixel[0]), float(pixel[1])
    return min(max(math.floor(u), 0), width - 1), min(max(math.floor(v), 0), height - 1)


class PixelGaussians(Interaction):
    """Click a held-out view's pixel: run ``render_view`` for it (the Gaussians it is made of)."""

    title = "Gaussians of a pixel"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        self.track(ctx.gui.add_markdown(
            "Click a pixel of a held-out view's picture (on its camera, once **render_held_out** ran): "
            "**render_view** lists the Gaussians it is made of, front to back, with their alpha, the "
            "transmittance they meet and their weight (chart *pixel_gaussians*; their centres are "
            "*pixel_splats*)."))
        self.last: tuple[int, int, int] | None = None

    def pixel_clicked(self, image_name: str, view: int, pixel: np.ndarray) -> bool:
        """Take clicks on ``test_renders`` (the held-out cameras' pictures) once there is a model."""
        cameras = self.ctx.value("held_out_cameras")
        if image_name != "test_renders" or cameras is None or self.ctx.value("model") is None:
            return False
        u, v = clicked_pixel(pixel, cameras.width, cameras.height)
        self.last = (view, u, v)
        self.ctx.run("render_view", {"view": view, "pixel_u": u, "pixel_v": v})
        return True


INTERACTIONS: list[type[Interaction]] = [PixelGaussians]

__all__ = ["INTERACTIONS", "PixelGaussians", "clicked_pixel"]
