"""Lesson 03, stereo matching: fill in the three functions, then run

    vision-lab grade 03-stereo starter.py

You may import numpy, scipy and cv2 (not the lab's own implementation). Keep the signatures.

Conventions: the pair is rectified; left pixel (x, y) is seen at (x - d, y) in the right image,
d = 0 .. max_disparity. A cost volume is (H, W, D) with D = max_disparity + 1.
"""

import numpy as np


def cost_volume(left, right, *, cost, window=5, max_disparity):
    """The matching cost of every left pixel at every disparity, averaged over a square window.

    Args:
        left, right: lab.core.Image, the rectified pair. ``left.gray()`` is the (H, W) float32
            gray image in [0, 1] (``left.pixels`` the (H, W, 3) colour one); match in gray.
        cost: "ssd" or "ncc" (the checks ask for nothing else).
        window: odd side of the square window in pixels.
        max_disparity: the largest disparity searched.

    Returns:
        (H, W, max_disparity + 1) float32 (or float64) with, for a = the left window around (x, y)
        and b = the right window around (x - d, y), n = window * window:

        - "ssd": (1/n) sum (a - b)^2;
        - "ncc": 1 - NCC, NCC = sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 sum (b - mean b)^2),
          NCC = 0 where either window's variance is below 1e-10 (a flat window).

        Borders are replicated: the right image at a column x - d < 0 is its column 0, and a
        window reaching over any border repeats the edge pixels (shift first, then average each
        disparity slice with a box filter whose border mode replicates the edge).
    """
    raise NotImplementedError


def winner_take_all(aggregated_cost):
    """Each pixel's disparity: the one with the lowest cost (the first one where costs are equal).

    Args:
        aggregated_cost: (H, W, D) float32 cost volume.

    Returns:
        (H, W) integer disparities in 0 .. D - 1.
    """
    raise NotImplementedError


def left_right_check(aggregated_cost, disparity_wta, *, max_difference=1):
    """Keep a pixel when the right image's own winner-take-all disparity points back to it.

    Args:
        aggregated_cost: (H, W, D) float32, the left image's cost volume: right pixel (x_r, y)
            and left pixel (x_r + d, y) are matched with cost ``aggregated_cost[y, x_r + d, d]``
            (only where x_r + d < W).
        disparity_wta: (H, W) integer, the left image's winner-take-all disparities d_L.
        max_difference: largest |d_L(x) - d_R(x - d_L(x))| kept.

    Returns:
        (H, W) bool, True where consistent; False where x - d_L(x) < 0 (the match would lie
        left of the right image).
    """
    raise NotImplementedError
