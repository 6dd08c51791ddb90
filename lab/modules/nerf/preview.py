"""The training preview that follows a camera: while :func:`~lab.modules.nerf.steps.train_nerf` runs, the
viewer hands it the browser's camera and the next preview the training loop renders is seen from there.

The training loops render ``preview.origins`` / ``preview.directions`` in ``preview.shape`` every
``preview_every`` iterations (:class:`~lab.modules.nerf.training.PreviewRays`). A :class:`FollowedPreview`
is such a preview whose rays are those of the camera it was last told to :meth:`~FollowedPreview.follow`
(training view 0 until then; their origins moved along them so that the training's depths ``near .. far``
cover the scene from there, :func:`depth_shift`), at a low resolution while that camera moves and a
sharper one once it has stood still for :data:`STILL_SECONDS` (nerfstudio's viewer does the same: it
renders coarse while the user drags). The rays are made in the training thread when the loop reads
``origins`` (a few thousand rays: cheap); ``directions`` and ``shape`` then belong to the same camera
whatever the viewer's thread does meanwhile. :func:`offering_preview` passes each progress snapshot of
the loop on with the follower in its values (``values["preview_follower"]``), which is how the viewer
finds it; nothing else draws it.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Generator
from typing import TypeVar

import torch

from lab.core import Cameras, Cancelled, InvalidValue, Progress
from lab.modules.nerf.rays import cameras_rays, scaled_cameras
from lab.modules.nerf.training import PreviewRays
from lab.modules.nerf.values import SceneBounds

#: The name a progress snapshot offers the follower under (the viewer's NeRF interaction reads it).
FOLLOWER = "preview_follower"
#: Longest side of the preview while the followed camera moves, and once it stands still.
MOVING_SIDE = 32
STILL_SIDE = 64
#: Seconds without a new camera after which the camera counts as standing still.
STILL_SECONDS = 0.4

R = TypeVar("R")


class FollowedPreview(PreviewRays):
    """Preview rays (``origins``, ``directions`` ``(H * W, 3)``, ``shape`` ``(H, W)``) of the camera last
    given to :meth:`follow`; ``cameras`` (view 0 is used) until the first call. Thread-safe: the viewer's
    thread calls :meth:`follow`, the training thread reads the rays (``origins`` first, as the loops do)."""

    def __init__(self, cameras: Cameras, bounds: SceneBounds, *, device: str = "cpu",
                 still_side: int = STILL_SIDE,
                 moving_side: int = MOVING_SIDE, clock: Callable[[], float] = time.monotonic) -> None:
        # not the frozen dataclass's __init__: the fields are the properties below
        self._lock = threading.Lock()
        self._device = device
        self._bounds = bounds
        self._sides = (moving_side, still_side)
        self._clock = clock
        self._start = self._camera = _one_view(cameras)
        self._moved = -float("inf")
        self._key: tuple[int, int] | None = None  # (id of the camera, side) of the rays made last
        self._rays: tuple[torch.Tensor, torch.Tensor, tuple[int, int]] | None = None
        self.follows = 0  # cameras followed so far

    def follow(self, cameras: Cameras) -> None:
        """Render the next previews from view 0 of ``cameras`` (any size: it is scaled down)."""
        camera = _one_view(cameras)
        with self._lock:
            self._camera = camera
            self._moved = self._clock()
            self.follows += 1

    def reset(self) -> None:
        """Render the next previews from the camera it started with again (training view 0)."""
        with self._lock:
            self._camera = self._start
            self._moved = -float("inf")

    @property
    def side(self) -> int:
        """The preview's longest side now: small while the camera moves, sharper once it stands still."""
        moving, still = self._sides
        return moving if self._clock() - self._moved < STILL_SECONDS else still

    @property
    def origins(self) -> torch.Tensor:
        """Makes the rays of the camera followed now (reading ``directions`` / ``shape`` gives the same)."""
        with self._lock:
            camera, side = self._camera, self.side
            if self._rays is None or self._key != (id(camera), side):
                small = scaled_cameras(camera, min(1.0, side / max(camera.width, camera.height)))
                origins, directions = cameras_rays(small, device=self._device)
                shift = depth_shift(small, self._bounds) if camera is not self._start else 0.0
                self._rays = (origins[0] + shift * directions[0], directions[0], (small.height, small.width))
                self._key = (id(camera), side)
            return self._rays[0]

    @property
    def directions(self) -> torch.Tensor:
        return self._made()[1]

    @property
    def shape(self) -> tuple[int, int]:
        return self._made()[2]

    def _made(self) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        with self._lock:
            rays = self._rays
        if rays is None:
            self.origins  # noqa: B018 - makes them
            return self._made()
        return rays


def depth_shift(camera: Cameras, bounds: SceneBounds) -> float:
    """How far (in depth) to move a camera's ray origins forward so that the training's depths
    ``near .. far`` are centred on the scene's centre: the loops sample every ray between the training
    cameras' near and far, so a camera twice as far away would see nothing. A ray's direction has camera
    z = 1, so ``o + s d`` is ``s`` deeper; ``s >= -near`` keeps every sample in front of the camera."""
    depth = float((camera.R[0] @ bounds.center + camera.t[0])[2])
    return max(depth - (bounds.near + bounds.far) / 2.0, -bounds.near)


def _one_view(cameras: Cameras) -> Cameras:
    if not isinstance(cameras, Cameras) or len(cameras.K) == 0:
        raise InvalidValue("cameras", "the preview follows a Cameras value with at least one view")
    return Cameras(cameras.K[:1], cameras.R[:1], cameras.t[:1], cameras.width, cameras.height)


def offering_preview(loop: Generator[Progress, None, R],
                     follower: FollowedPreview) -> Generator[Progress, None, R]:
    """``loop``'s progress snapshots, each with ``follower`` added to its values under :data:`FOLLOWER`;
    the runner's :class:`~lab.core.Cancelled` is thrown into ``loop`` (which returns what it trained so
    far), and closing this generator closes ``loop``."""
    try:
        while True:
            try:
                progress = next(loop)
            except StopIteration as stop:
                return stop.value
            try:
                yield dataclasses.replace(progress, values={**progress.values, FOLLOWER: follower})
            except Cancelled as cancel:
                try:
                    loop.throw(cancel)
                except StopIteration as stop:
                    return stop.value
                raise  # the loop went on after it was asked to stop: cancelled, as the runner says
    finally:
        loop.close()


__all__ = ["FOLLOWER", "MOVING_SIDE", "STILL_SECONDS", "STILL_SIDE", "FollowedPreview", "depth_shift",
           "offering_preview"]
