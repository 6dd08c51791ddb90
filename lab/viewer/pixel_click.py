"""A click on a pixel of a held-out view's picture runs the module's step for that view and pixel.

NeRF and Gaussian splatting both draw their held-out cameras carrying their renders (``test_renders``) and
answer "what is this pixel made of" by a step with ``view``, ``pixel_u`` and ``pixel_v`` controls
(``render_view``): NeRF's ray samples and weights, splatting's Gaussians. :class:`HeldOutPixelClick` is that
interaction once; a module's interactions file subclasses it with its names and text.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from lab.core import Cameras
from lab.viewer.interactions import Interaction, InteractionContext


def clicked_pixel(pixel: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """The pixel ``(column, row)`` holding a click at picture coordinates ``pixel`` ``(u, v)`` (0 at the
    picture's left and top edges, ``width`` and ``height`` at the others), clamped into the image."""
    u, v = float(pixel[0]), float(pixel[1])
    return min(max(math.floor(u), 0), width - 1), min(max(math.floor(v), 0), height - 1)


class HeldOutPixelClick(Interaction):
    """Click a pixel of a picture of image set :attr:`image`: when :meth:`clickable` gives the cameras that
    carry it (there is a model to ask), run :attr:`step` with that ``view``, ``pixel_u``, ``pixel_v``.
    Subclasses set the title and :attr:`text` (what the folder says) and read the session's values in
    :meth:`clickable` (by name, so the views contract sees what they read)."""

    image: ClassVar[str] = "test_renders"
    step: ClassVar[str] = "render_view"
    text: ClassVar[str] = ""

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        self.track(ctx.gui.add_markdown(self.text))
        self.last: tuple[int, int, int] | None = None

    def clickable(self) -> Cameras | None:
        """The cameras carrying :attr:`image` when a click can be answered now, else None."""
        raise NotImplementedError

    def pixel_clicked(self, image_name: str, view: int, pixel: np.ndarray) -> bool:
        """Take clicks on :attr:`image` while :meth:`clickable`; other clicks select the view as usual."""
        if image_name != self.image:
            return False
        cameras = self.clickable()
        if cameras is None:
            return False
        u, v = clicked_pixel(pixel, cameras.width, cameras.height)
        self.last = (view, u, v)
        self.ctx.run(self.step, {"view": view, "pixel_u": u, "pixel_v": v})
        return True


__all__ = ["HeldOutPixelClick", "clicked_pixel"]
