"""Epipolar lines and epipoles, and the lines clipped to an image for drawing.

Reference: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
sections 9.1-9.2.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from lab.core import ImageSet, Points2D, Segments2D
from lab.geometry.homogeneous import to_homogeneous
from lab.modules.epipolar._checks import check_matrix


def epipolar_lines(F: np.ndarray, points: np.ndarray, *, image: Literal[1, 2] = 1) -> np.ndarray:
    """Epipolar lines ``(a, b, c)`` ``(N, 3)``, ``a^2 + b^2 = 1`` (so ``a x + b y + c`` is a signed distance).

    Points of image 1 give their lines in image 2, ``l2 = F x1``; points of image 2 (``image=2``)
    give lines in image 1, ``l1 = F^T x2``. Corresponds to ``cv2.computeCorrespondEpilines(points,
    image, F)``. Reference: H&Z section 9.2.1 (result 9.5).
    """
    F = check_matrix(F, "F")
    h = to_homogeneous(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    lines = h @ (F.T if image == 1 else F)
    norm = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return lines / norm[:, None]


def epipoles(F: np.ndarray) -> np.ndarray:
    """The two epipoles as homogeneous unit vectors, ``(2, 3)``: ``e1`` with ``F e1 = 0``, ``e2`` with ``F^T
    e2 = 0``.

    ``e1`` is the image of camera 2's centre in image 1 (where every epipolar line of image 1
    meets) and ``e2`` that of camera 1's centre in image 2: the right and left singular vectors of
    F's smallest singular value. The sign makes the last coordinate non-negative; an epipole at
    infinity (a sideways motion) has last coordinate 0 and stays finite this way.
    Reference: H&Z section 9.2.4 (result 9.8).
    """
    U, _, Vt = np.linalg.svd(check_matrix(F, "F"))
    pair = np.stack([Vt[2], U[:, 2]])
    return pair * np.where(pair[:, 2:] < 0, -1.0, 1.0)


def clip_lines(lines: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip lines ``a x + b y + c = 0`` ``(N, 3)`` to the image ``[0, width - 1] x [0, height - 1]``.

    Returns the segment ends ``(N, 2)`` each and a ``(N,)`` mask of the lines that cross the image.
    """
    lines = np.asarray(lines, dtype=np.float64)
    a, b, c = lines[:, 0], lines[:, 1], lines[:, 2]
    right, bottom = width - 1.0, height - 1.0
    ends = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for x in (0.0, right):  # crossings with the left and right borders
            ends.append(np.stack([np.full_like(a, x), -(a * x + c) / b], axis=-1))
        for y in (0.0, bottom):  # with the top and bottom borders
            ends.append(np.stack([-(b * y + c) / a, np.full_like(a, y)], axis=-1))
    candidates = np.stack(ends, axis=1)  # (N, 4, 2)
    eps = 1e-9 * max(width, height)
    inside = (np.isfinite(candidates).all(axis=2) & (candidates[..., 0] >= -eps)
              & (candidates[..., 0] <= right + eps) & (candidates[..., 1] >= -eps)
              & (candidates[..., 1] <= bottom + eps))
    start = np.zeros((len(lines), 2))
    end = np.zeros((len(lines), 2))
    valid = np.zeros(len(lines), dtype=bool)
    for i in range(len(lines)):
        found = candidates[i][inside[i]]
        if len(found) >= 2:
            distance = np.linalg.norm(found[:, None] - found[None], axis=2)
            j, k = np.unravel_index(np.argmax(distance), distance.shape)
            start[i], end[i], valid[i] = found[j], found[k], distance[j, k] > 0
    return start, end, valid


def line_colors(count: int) -> np.ndarray:
    """``count`` distinct saturated colours ``(count, 3)`` (hues spread around the circle)."""
    import colorsys

    hues = [(0.61803 * i) % 1.0 for i in range(count)]
    return np.array([colorsys.hsv_to_rgb(hue, 0.85, 1.0) for hue in hues]).reshape(-1, 3)



def draw_lines(F: np.ndarray, x1: np.ndarray, x2: np.ndarray,
               images: ImageSet) -> tuple[Segments2D, Points2D]:
    """The epipolar lines of the pairs ``(N, 2)``, clipped to their images, and the pairs themselves, each
    pair and its two lines in one colour (:func:`line_colors`): ``F^T x2`` in image 1 (view 0), ``F x1`` in
    image 2 (view 1); a line that misses its image is left out."""
    colors = line_colors(len(x1))
    starts, ends, views, segment_colors = [], [], [], []
    for view, (lines, image) in enumerate(((epipolar_lines(F, x2, image=2), images[0]),
                                           (epipolar_lines(F, x1, image=1), images[1]))):
        start, end, valid = clip_lines(lines, image.width, image.height)
        starts.append(start[valid])
        ends.append(end[valid])
        views.append(np.full(int(valid.sum()), view))
        segment_colors.append(colors[valid])
    segments = Segments2D(np.concatenate(starts), np.concatenate(ends), view=np.concatenate(views),
                          colors=np.concatenate(segment_colors), image="images")
    points = Points2D(np.concatenate([x1, x2]), view=np.repeat([0, 1], len(x1)),
                      colors=np.concatenate([colors, colors]), image="images")
    return segments, points


def finite_epipoles(pair: np.ndarray) -> Points2D:
    """The epipoles of :func:`epipoles` ``(2, 3)`` that are not at infinity, in pixels (view 0 / 1), white."""
    finite = np.abs(pair[:, 2]) > 1e-12 * np.abs(pair[:, :2]).max(axis=1)
    epipole_xy = pair[finite, :2] / pair[finite, 2:]
    return Points2D(epipole_xy, view=np.flatnonzero(finite), colors=np.ones((int(finite.sum()), 3)),
                    image="images")


__all__ = ["clip_lines", "draw_lines", "epipolar_lines", "epipoles", "finite_epipoles", "line_colors"]
