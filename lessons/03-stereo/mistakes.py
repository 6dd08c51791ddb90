"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each takes the step's
parameters and is built from the lab's own correct step where the mistake is a change of its input
or output, so it is exact by construction; the window sums with another border rule, which no such
change gives, are computed with SciPy from the lab's own per-pixel terms. ``vision-lab lesson
validate`` also runs each as a mutant the checks must catch.
"""

import dataclasses

import numpy as np
from scipy import ndimage

from lab.modules import stereo


def _mirrored(image):
    """The image flipped left to right."""
    return dataclasses.replace(image, pixels=np.ascontiguousarray(image.pixels[:, ::-1]))


# --- task 1: the cost volume ---------------------------------------------------------------------------
def cost_volume_shifted_right(left, right, *, cost="ssd", window=5, max_disparity=64):
    """Left pixel ``x`` compared with right pixel ``x + d`` (the right image shifted the wrong way).

    Mirroring both images turns ``x + d`` into ``x' - d``, so this is the lab's volume of the
    mirrored pair, mirrored back (the border column repeated is then the last one).
    """
    volume = stereo.cost_volume(_mirrored(left), _mirrored(right), cost=cost, window=window,
                                max_disparity=max_disparity)
    return np.ascontiguousarray(volume[:, ::-1])


def _window_costs(left, right, cost, window, max_disparity, *, mode="nearest", roll=False):
    """SSD or 1 - NCC with the window means taken by ``scipy.ndimage.uniform_filter(mode=mode)`` (float64)
    and the right image shifted by :func:`lab.modules.stereo.shifted_right` (column 0 repeated) or, with
    ``roll``, by ``np.roll`` (wrapping around); the lab's own volume for another cost."""
    if cost not in ("ssd", "ncc"):
        return stereo.cost_volume(left, right, cost=cost, window=window, max_disparity=max_disparity)
    a = left.gray().astype(np.float64)
    gray = right.gray().astype(np.float64)
    if roll:
        b = np.stack([np.roll(gray, d, axis=1) for d in range(max_disparity + 1)], axis=2)
    else:
        b = stereo.shifted_right(gray, max_disparity + 1)

    def box(values):
        return ndimage.uniform_filter(values, size=(window, window) + (1,) * (values.ndim - 2), mode=mode)

    if cost == "ssd":
        return box((a[:, :, None] - b) ** 2)
    mean_a, mean_b = box(a)[:, :, None], box(b)
    var_a = np.maximum(box(a * a)[:, :, None] - mean_a ** 2, 0.0)
    var_b = np.maximum(box(b * b) - mean_b ** 2, 0.0)
    covariance = box(a[:, :, None] * b) - mean_a * mean_b
    flat = (var_a < stereo.NCC_FLAT_VARIANCE) | (var_b < stereo.NCC_FLAT_VARIANCE)
    ncc = np.where(flat, 0.0, covariance / np.sqrt(np.where(flat, 1.0, var_a * var_b)))
    return 1.0 - np.clip(ncc, -1.0, 1.0)


def cost_volume_borders_reflected(left, right, *, cost="ssd", window=5, max_disparity=64):
    """The window means with the image reflected at its borders (``scipy.ndimage.uniform_filter``'s
    default ``mode="reflect"``, cv2's BORDER_REFLECT) instead of its edge pixels repeated."""
    return _window_costs(left, right, cost, window, max_disparity, mode="reflect")


def cost_volume_borders_mirrored(left, right, *, cost="ssd", window=5, max_disparity=64):
    """The window means with the image mirrored about its edge pixels (``cv2.boxFilter``'s default
    BORDER_REFLECT_101, SciPy's ``mode="mirror"``) instead of its edge pixels repeated."""
    return _window_costs(left, right, cost, window, max_disparity, mode="mirror")


def cost_volume_shift_wraps_around(left, right, *, cost="ssd", window=5, max_disparity=64):
    """The right image shifted with ``np.roll``: where ``x - d < 0`` left pixel ``x`` is compared with the
    right image's column ``W + x - d`` (its right edge) instead of its column 0 repeated."""
    return _window_costs(left, right, cost, window, max_disparity, roll=True)


def cost_volume_one_disparity_short(left, right, *, cost="ssd", window=5, max_disparity=64):
    """Disparities ``0 .. max_disparity - 1`` (``range(max_disparity)``): the last slice is missing."""
    volume = stereo.cost_volume(left, right, cost=cost, window=window, max_disparity=max_disparity)
    return np.ascontiguousarray(volume[:, :, :-1])


def ncc_similarity_not_cost(left, right, *, cost="ssd", window=5, max_disparity=64):
    """NCC itself returned for ``cost = "ncc"``, a similarity (1 for a perfect match), not the cost
    1 - NCC."""
    volume = stereo.cost_volume(left, right, cost=cost, window=window, max_disparity=max_disparity)
    return 1.0 - volume.astype(np.float64) if cost == "ncc" else volume


# --- task 2: winner-take-all ---------------------------------------------------------------------------
def winner_take_all_argmax(aggregated_cost):
    """The disparity of the *highest* cost."""
    return np.argmax(aggregated_cost, axis=2)


def winner_take_all_last_of_ties(aggregated_cost):
    """The *last* of equal lowest costs (a loop comparing with ``<=``): the lab's winners of the volume with
    its disparities reversed, counted back."""
    volume = np.asarray(aggregated_cost)
    return volume.shape[2] - 1 - stereo.winner_take_all(np.ascontiguousarray(volume[:, :, ::-1]))


# --- task 3: the left-right check ----------------------------------------------------------------------
def left_right_check_looks_right(aggregated_cost, disparity_wta, *, max_difference=1):
    """The right image's disparity read at ``x + d_L`` instead of ``x - d_L``."""
    width = aggregated_cost.shape[1]
    d_right = stereo.right_disparity(aggregated_cost)
    d_left = np.asarray(disparity_wta, dtype=np.int64)
    columns = np.arange(width)[None, :] + d_left
    inside = columns < width
    back = np.take_along_axis(d_right, np.clip(columns, 0, width - 1), axis=1)
    return inside & (np.abs(d_left - back) <= max_difference)


def left_right_check_with_left_disparity(aggregated_cost, disparity_wta, *, max_difference=1):
    """``d_L(x)`` compared with the *left* image's disparity at ``x - d_L(x)``, not the right image's own
    winner-take-all ``d_R``: the lab's check with the left disparities standing in for the right ones."""
    width = np.shape(disparity_wta)[1]
    d_left = np.asarray(disparity_wta, dtype=np.int64)
    columns = np.arange(width)[None, :] - d_left
    back = np.take_along_axis(d_left, np.clip(columns, 0, width - 1), axis=1)
    return (columns >= 0) & (np.abs(d_left - back) <= max_difference)


def left_right_check_keeps_outside(aggregated_cost, disparity_wta, *, max_difference=1):
    """Matches that land left of the right image (``x - d_L < 0``) compared with its column 0 instead of
    failing: the lab's test without the ``x - d_L >= 0`` condition."""
    width = aggregated_cost.shape[1]
    d_right = stereo.right_disparity(aggregated_cost)
    d_left = np.asarray(disparity_wta, dtype=np.int64)
    columns = np.clip(np.arange(width)[None, :] - d_left, 0, width - 1)
    return np.abs(d_left - np.take_along_axis(d_right, columns, axis=1)) <= max_difference
