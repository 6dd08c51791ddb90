"""Interactions of the NeRF module: training follows the browser's camera; a clicked pixel shows its ray.

* **Training preview from your camera.** While ``train_nerf`` runs, every progress snapshot offers the
  run's :class:`~lab.modules.nerf.preview.FollowedPreview` (``Progress.values["preview_follower"]``). This
  interaction hands it the tab's camera when it first sees it and again whenever the browser reports a
  move, so the ``preview`` image the training loop renders (drawn in the Images tab by the generic drawing)
  is the field seen from where the student looks: coarse (32 px) while the camera moves, 64 px once it
  stands still, as nerfstudio's viewer renders. "Follow my camera" off: training view 0 again.

* **A pixel's ray.** A click on a pixel of a held-out view's picture (on its camera frustum, drawn once
  ``render_held_out`` ran: ``held_out_cameras`` carry ``test_renders``) runs the module's ``render_view`` for
  that view and pixel: ``ray_weights`` plots the weights ``w_i`` over the ray's depths (Plots tab) and
  ``ray_samples`` draws the samples in 3D, grey at weight 0 to red at the ray's largest (both drawn by the
  generic renderers).

The camera math is :func:`browser_cameras` (a viser camera as the lab's OpenCV :class:`Cameras`, tested
directly); the click is :class:`~lab.viewer.pixel_click.HeldOutPixelClick`; the classes only wire them to
viser and to the session.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np

from lab.core import Cameras, InvalidValue, Progress
from lab.modules.nerf.preview import FOLLOWER, FollowedPreview
from lab.viewer.interactions import Interaction, InteractionContext
from lab.viewer.pixel_click import HeldOutPixelClick

#: Longest side of the camera handed to the preview (it renders a smaller copy of it).
BROWSER_SIDE = 256


def browser_cameras(position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float, *,
                    side: int = BROWSER_SIDE) -> Cameras:
    """The browser's camera as one OpenCV camera ``X_c = R X_w + t`` of longest side ``side`` px.

    viser reports ``wxyz``, the rotation ``R_wc`` of ``P_world = R_wc p_camera + position`` with the camera's
    frame OpenCV's (x right, y down, z forward), the vertical field of view ``fov`` (radians) and the
    canvas's ``aspect`` (width / height). So ``R = R_wc^T``, ``t = -R position``; square pixels with
    ``f_y = (H / 2) / tan(fov / 2)`` and the principal point at the picture's centre ``((W - 1) / 2,
    (H - 1) / 2)`` (pixel centres at integers).
    """
    if not (0.0 < fov < math.pi) or not (aspect > 0.0 and math.isfinite(aspect)):
        raise InvalidValue("camera", f"expected 0 < fov < pi and a positive aspect, got {fov} and {aspect}")
    import viser.transforms as vtf

    R_wc = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    R = R_wc.T
    t = -R @ np.asarray(position, dtype=np.float64).reshape(3)
    if aspect >= 1.0:
        width, height = side, max(1, round(side / aspect))
    else:
        width, height = max(1, round(side * aspect)), side
    focal = (height / 2.0) / math.tan(fov / 2.0)
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Cameras(K[None], R[None], t[None], width, height)


class TrainingCamera(Interaction):
    """Hands the browser's camera to a running ``train_nerf``'s preview (see the module docstring)."""

    title = "Training preview"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        gui = ctx.gui
        self.follow = self.track(gui.add_checkbox("Follow my camera", initial_value=True))
        self.info = self.track(gui.add_markdown("Run **train_nerf**: its preview is rendered from your "
                                                "camera while it trains."))
        self.follower: FollowedPreview | None = None
        self.closed = False
        self._lock = threading.Lock()
        self.camera = ctx.camera if ctx.is_client else None  # the tab's viser camera handle
        if self.camera is not None:
            self.camera.on_update(ctx.guarded(lambda _camera: self.send()))
        self.follow.on_update(ctx.guarded(lambda _event: self.send()))
        ctx.session.listeners.append(self.on_progress)

    def on_progress(self, step: str, progress: Progress) -> None:
        """A snapshot of a long step (in its thread): a new training run's follower gets the camera now."""
        follower = progress.values.get(FOLLOWER)
        if self.closed or not isinstance(follower, FollowedPreview) or follower is self.follower:
            return
        with self._lock:
            self.follower = follower
        self.ctx.attempt(self.send)

    def send(self) -> bool:
        """Hand the running training's preview the browser's camera now (training view 0 when "Follow my
        camera" is off); False when there is no run or no camera reported yet."""
        with self._lock:
            follower = self.follower
        if self.closed or follower is None:
            return False
        if not self.follow.value:
            follower.reset()
            return True
        view = self.view()
        if view is None:
            return False
        follower.follow(view)
        self.info.content = (f"Previews of **train_nerf** follow your camera ({follower.follows} camera "
                             f"moves so far).")
        return True

    def view(self) -> Cameras | None:
        """The tab's camera as :func:`browser_cameras`, None until the browser has reported it."""
        camera = self.camera
        if camera is None or not getattr(camera, "update_timestamp", 0.0):
            return None
        return browser_cameras(np.asarray(camera.position), np.asarray(camera.wxyz), float(camera.fov),
                               float(camera.aspect))

    def update(self, state: Mapping[str, Any]) -> None:
        """After a refresh: say whether a trained model is there (its preview is training view 0 again)."""
        if self.follower is None and self.ctx.value("model", state) is not None:
            self.info.content = ("A model is trained: run **train_nerf** again to watch its preview from "
                                 "your camera while it trains.")

    def close(self) -> None:
        self.closed = True
        if self.on_progress in self.ctx.session.listeners:
            self.ctx.session.listeners.remove(self.on_progress)
        super().close()


class RayOfPixel(HeldOutPixelClick):
    """Click a held-out view's pixel: run ``render_view`` for it (its ray's samples and weights)."""

    title = "Ray of a pixel"
    text = ("Click a pixel of a held-out view's picture (on its camera, once **render_held_out** ran): "
            "**render_view** shows its ray, the weights w_i = T_i alpha_i over depth (plot *ray_weights*) "
            "and the samples in 3D, grey at weight 0 to red at the largest (*ray_samples*).")

    def clickable(self) -> Cameras | None:
        """The held-out cameras (carrying ``test_renders``) once a model is trained."""
        cameras = self.ctx.value("held_out_cameras")
        return cameras if cameras is not None and self.ctx.value("model") is not None else None


INTERACTIONS: list[type[Interaction]] = [TrainingCamera, RayOfPixel]

__all__ = ["BROWSER_SIDE", "INTERACTIONS", "RayOfPixel", "TrainingCamera", "browser_cameras"]
