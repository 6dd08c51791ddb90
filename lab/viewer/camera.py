"""Framing a tab's 3D camera: point it at the session's 3D content the first time there is some.

The content is the state's 3D values (point clouds, cameras, meshes ...: what
:func:`lab.viewer.renderers.viewpoint` measures), else what the module's interactions draw (e.g. the
two cameras of an epipolar pair before anything is triangulated: :meth:`Interaction.bounds`). The
tab frames once per session, so a student's own camera moves are never undone by a redraw.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from lab.core.values import PointCloud
from lab.viewer.interactions import Interaction
from lab.viewer.renderers import viewpoint

log = logging.getLogger("lab.viewer")


def framing(state: Mapping[str, Any],
            interactions: Iterable[Interaction] = ()) -> tuple[np.ndarray, np.ndarray] | None:
    """``(eye, look_at)`` for a tab's camera: the state's 3D values, else what ``interactions`` draw;
    None when there is nothing in 3D yet."""
    view = viewpoint(state.values())
    if view is None:
        boxes = [b for b in (i.bounds() for i in interactions) if b is not None]
        view = viewpoint([PointCloud(np.concatenate(boxes))]) if boxes else None
    return view


class CameraFramer:
    """Frames the camera of one browser tab (``target``: a viser ``ClientHandle``) once per session."""

    def __init__(self, target: Any, *, is_client: bool) -> None:
        self.target = target
        self.is_client = is_client
        self.framed = False

    def reset(self) -> None:
        """A new session is shown: frame its content when it has some."""
        self.framed = False

    def frame(self, state: Mapping[str, Any], interactions: Iterable[Interaction]) -> None:
        """Point the camera at the 3D content the first time there is some (y down: the OpenCV convention)."""
        if self.framed or not self.is_client:
            return
        self.fit(state, interactions)

    def fit(self, state: Mapping[str, Any], interactions: Iterable[Interaction]) -> None:
        """Point the camera at all the 3D content now (the "Fit view" button), whatever was done before."""
        if not self.is_client:
            return
        view = framing(state, interactions)
        if view is None:
            return
        self.framed = True
        position, look_at = view
        try:
            camera = self.target.camera
            camera.up_direction = (0.0, -1.0, 0.0)
            camera.position = tuple(position)
            camera.look_at = tuple(look_at)  # after the position, which drags look_at along
        except Exception as exc:  # cosmetic
            log.info("could not frame the camera: %s", exc)


__all__ = ["CameraFramer", "framing"]
