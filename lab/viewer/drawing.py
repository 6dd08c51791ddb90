"""Drawing helpers the module interactions share, beside the per-type renderers (:mod:`lab.viewer.renderers`).

The renderers draw each state value by its type; an interaction draws what is special to its module,
and these are the pieces more than one of them needs: 2D overlays drawn thick into a picture (a single
epipolar line or a picked pixel must stay visible on a scene plane), a frustum as line segments
(a camera drawn with its image plane at the depth the interaction chooses), and two images side by
side with their matches joined. No viser calls: each returns an array the interaction hands to viser.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from lab.core.values import Image, Points2D, Segments2D
from lab.viewer.renderers import overlay_view, to_rgb8

#: Colours (RGB, 0-255) of matches: RANSAC's inliers, its outliers, matches not classified yet.
INLIER_COLOR = (30, 200, 60)
OUTLIER_COLOR = (235, 40, 40)
UNCLASSIFIED_COLOR = (255, 210, 0)
#: Most match lines drawn on an image pair.
MAX_MATCH_LINES = 400


def draw_overlays(image: Image, overlays: Sequence[Points2D | Segments2D], *, max_side: int | None = None,
                  min_side: int | None = None,
                  thickness: int = 2, base: np.ndarray | None = None) -> np.ndarray:
    """``image`` with ``overlays`` (Points2D / Segments2D, ``view`` None) drawn thick, ``(H', W', 3)`` uint8.

    The size is :func:`lab.viewer.renderers.overlay_view`'s (shrunk to ``max_side`` or enlarged to
    ``min_side``); points are discs' outlines and segments lines ``thickness`` pixels wide, so that a
    single epipolar line stays visible on a scene plane or a panel image. ``base``: that resized
    image already made (``overlay_view(image, [], ...)``, kept by the caller: a click redraws fast).
    """
    rgb = (overlay_view(image, [], max_side=max_side, min_side=min_side) if base is None else base).copy()
    scale_x, scale_y = rgb.shape[1] / image.width, rgb.shape[0] / image.height
    shift = 4
    one = 1 << shift

    def fixed(xy: np.ndarray) -> tuple[int, int]:
        return (round(((xy[0] + 0.5) * scale_x - 0.5) * one),
                round(((xy[1] + 0.5) * scale_y - 0.5) * one))

    radius = round(max(4.0, min(rgb.shape[:2]) / 60.0) * one)
    for overlay in overlays:
        colors = overlay.colors if overlay.colors is not None else np.ones((len(overlay), 3))
        for i in range(len(overlay)):
            color = tuple(int(c) for c in np.clip(colors[i], 0, 1) * 255 + 0.5)
            if isinstance(overlay, Segments2D):
                cv2.line(rgb, fixed(overlay.start[i]), fixed(overlay.end[i]), color, thickness, cv2.LINE_AA,
                         shift)
            else:
                cv2.circle(rgb, fixed(overlay.xy[i]), radius, color, thickness, cv2.LINE_AA, shift)
    return rgb


def match_pair_image(image1: Image, image2: Image, x1: np.ndarray, x2: np.ndarray,
                     inliers: np.ndarray | None, *,
                     height: int = 360, max_lines: int = MAX_MATCH_LINES) -> np.ndarray:
    """The two images side by side ``(height, W1' + W2', 3)`` uint8, each match joined by a line: inliers
    green, outliers red, all matches yellow when ``inliers`` is None (RANSAC has not run).

    Both images are scaled to ``height`` (pixel centres stay centres); at most ``max_lines`` matches
    are joined (evenly spread over the list, outliers and inliers alike), every match gets its two dots.
    """
    halves, scales = [], []
    for image in (image1, image2):
        rgb = to_rgb8(image.pixels)
        scale = height / rgb.shape[0]
        size = (max(1, round(rgb.shape[1] * scale)), height)
        halves.append(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR))
        scales.append((size[0] / rgb.shape[1], height / rgb.shape[0]))
    canvas = np.ascontiguousarray(np.concatenate(halves, axis=1))
    offset = halves[0].shape[1]
    shift = 4
    one = 1 << shift

    def fixed(xy: np.ndarray, index: int, dx: float) -> np.ndarray:
        sx, sy = scales[index]
        out = np.column_stack([(xy[:, 0] + 0.5) * sx - 0.5 + dx, (xy[:, 1] + 0.5) * sy - 0.5])
        return np.round(out * one).astype(np.int64)

    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    a, b = fixed(x1, 0, 0.0), fixed(x2, 1, float(offset))
    if inliers is None:
        colors = [UNCLASSIFIED_COLOR] * len(x1)
    else:
        colors = [INLIER_COLOR if keep else OUTLIER_COLOR for keep in np.asarray(inliers, dtype=bool)]
    joined: np.ndarray = np.unique(np.linspace(0, len(x1) - 1, min(len(x1), max_lines)).round().astype(int)) \
        if len(x1) else np.zeros(0, int)
    for i in joined:
        cv2.line(canvas, tuple(int(v) for v in a[i]), tuple(int(v) for v in b[i]), colors[i], 1, cv2.LINE_AA,
                 shift)
    radius = round(2.5 * one)
    for i in range(len(x1)):
        cv2.circle(canvas, tuple(int(v) for v in a[i]), radius, colors[i], -1, cv2.LINE_AA, shift)
        cv2.circle(canvas, tuple(int(v) for v in b[i]), radius, colors[i], -1, cv2.LINE_AA, shift)
    return canvas


def frustum_segments(centre: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Line segments ``(8, 2, 3)`` of a frustum: centre to each corner, and the image's outline."""
    spokes = np.stack([np.repeat(centre[None], 4, axis=0), corners], axis=1)
    outline = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    return np.concatenate([spokes, outline]).astype(np.float32)


__all__ = ["INLIER_COLOR", "MAX_MATCH_LINES", "OUTLIER_COLOR", "UNCLASSIFIED_COLOR", "draw_overlays",
           "frustum_segments", "match_pair_image"]
