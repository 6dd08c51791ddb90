"""The disparity range of a rectified pair, estimated from sparse matched features.

A user's own pair comes without a known range: too short a range cuts the near surfaces off, too
long a one costs memory and time in proportion. Sparse features tell it cheaply: SIFT keypoints of
both images (``cv2.SIFT_create``; D. Lowe, "Distinctive image features from scale-invariant
keypoints", IJCV 60, 2004), matched by their nearest descriptor with Lowe's ratio test (section 7.1:
the nearest closer than 0.75 times the second nearest) and kept when the two rows agree, as they
must on a rectified pair (within :data:`ROW_TOLERANCE_PX`), and the disparity is not negative.
Their disparities' :data:`RANGE_PERCENTILE` th percentile (robust to the odd wrong match) plus a
margin of :data:`RANGE_MARGIN_PX` px and :data:`RANGE_MARGIN_SHARE` of it, rounded up to a multiple
of 16 (OpenCV's ``numDisparities`` rule), is the largest disparity searched.

Pairs above :data:`RANGE_PIXELS` are matched at a smaller scale (the disparities scaled back), which
costs a pixel or two of precision that the margin covers. Fewer than :data:`MIN_RANGE_MATCHES`
matches give no estimate (:func:`estimate_max_disparity` returns -1 and says why).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core import Image

#: Largest vertical offset (pixels, at the matching scale) between the two ends of a kept match.
ROW_TOLERANCE_PX = 1.5
#: Lowe's ratio: the nearest descriptor must be closer than this times the second nearest.
RANGE_RATIO = 0.75
#: Percentile of the matched disparities taken as the top of the range.
RANGE_PERCENTILE = 99.0
#: Margin added to that percentile: a fixed part in pixels and a share of it.
RANGE_MARGIN_PX = 8.0
RANGE_MARGIN_SHARE = 0.05
#: Matches needed for an estimate.
MIN_RANGE_MATCHES = 10
#: Pixels of one image above which the pair is matched at a smaller scale.
RANGE_PIXELS = 600_000


@dataclass(frozen=True, eq=False)
class RangeMatches:
    """Matched features of a rectified pair: ``left``, ``right`` ``(N, 2)`` pixels (full scale),
    ``disparity`` ``(N,)`` = ``x_left - x_right`` (at least 0)."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray


def _gray8(image: Image, scale: float) -> np.ndarray:
    import cv2

    gray = np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if scale == 1.0:
        return gray
    return cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def match_range_features(left: Image, right: Image) -> RangeMatches:
    """SIFT features of both images matched with the ratio test and the row constraint (module docstring)."""
    import cv2

    scale = min(1.0, float(np.sqrt(RANGE_PIXELS / (left.width * left.height))))
    sift = cv2.SIFT.create()
    found = [sift.detectAndCompute(_gray8(image, scale), None) for image in (left, right)]
    (points_l, descriptors_l), (points_r, descriptors_r) = found
    empty = RangeMatches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    if descriptors_l is None or descriptors_r is None or len(descriptors_r) < 2:
        return empty
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(descriptors_l, descriptors_r, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < RANGE_RATIO * m[1].distance]
    if not good:
        return empty
    xy_l = np.array([points_l[m.queryIdx].pt for m in good], np.float64)
    xy_r = np.array([points_r[m.trainIdx].pt for m in good], np.float64)
    disparity = xy_l[:, 0] - xy_r[:, 0]
    keep = (np.abs(xy_l[:, 1] - xy_r[:, 1]) <= ROW_TOLERANCE_PX) & (disparity >= -ROW_TOLERANCE_PX)
    # keypoints at pixel centres of the smaller image: (x + 0.5) / scale - 0.5 at full scale
    to_full = lambda xy: (xy[keep] + 0.5) / scale - 0.5  # noqa: E731
    return RangeMatches(to_full(xy_l), to_full(xy_r), np.maximum(disparity[keep] / scale, 0.0))


def estimate_max_disparity(matches: RangeMatches, width: int) -> tuple[int, str]:
    """``(max_disparity, note)``: the top of the range from the matches, a multiple of 16 below ``width``
    (module docstring); ``(-1, why)`` with fewer than :data:`MIN_RANGE_MATCHES` matches."""
    count = len(matches.disparity)
    if count < MIN_RANGE_MATCHES:
        return -1, (f"only {count} SIFT features matched along the rows (at least {MIN_RANGE_MATCHES} are "
                    "needed to estimate the disparity range): the pair has too little texture, or is not "
                    "rectified; set max_disparity to the largest disparity you expect")
    top = float(np.percentile(matches.disparity, RANGE_PERCENTILE))
    wanted = int(16 * np.ceil((top * (1.0 + RANGE_MARGIN_SHARE) + RANGE_MARGIN_PX) / 16.0))
    usable = max(1, int(width) - 1)
    chosen = max(16, min(wanted, usable))
    note = (f"{count} matched features, {RANGE_PERCENTILE:g}th percentile of their disparities "
            f"{top:.1f} px")
    if wanted > usable:
        note += f"; {wanted} px would be wider than the image, {chosen} px is searched"
    return min(chosen, usable), note
