"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each takes the step's
parameters and is built from the lab's own correct step, so it is exact by construction.
"""

import dataclasses

import numpy as np

from lab.modules import stereo


def _mirrored(image):
    """The image flipped left to right."""
    return dataclasses.replace(image, pixels=np.ascontiguousarray(image.pixels[:, ::-1]))


def cost_volume_shifted_right(left, right, *, cost="ssd", window=5, max_disparity=64):
    """Left pixel ``x`` compared with right pixel ``x + d`` (the right image shifted the wrong way).

    Mirroring both images turns ``x + d`` into ``x' - d``, so this is the lab's volume of the
    mirrored pair, mirrored back (the border column repeated is then the last one).
    """
    volume = stereo.cost_volume(_mirrored(left), _mirrored(right), cost=cost, window=window,
                                max_disparity=max_disparity)
    return np.ascontiguousarray(volume[:, ::-1])


def winner_take_all_argmax(aggregated_cost):
    """The disparity of the *highest* cost."""
    return np.argmax(aggregated_cost, axis=2)


def left_right_check_looks_right(aggregated_cost, disparity_wta, *, max_difference=1):
    """The right image's disparity read at ``x + d_L`` instead of ``x - d_L``."""
    width = aggregated_cost.shape[1]
    d_right = stereo.right_disparity(aggregated_cost)
    d_left = np.asarray(disparity_wta, dtype=np.int64)
    columns = np.arange(width)[None, :] + d_left
    inside = columns < width
    back = np.take_along_axis(d_right, np.clip(columns, 0, width - 1), axis=1)
    return inside & (np.abs(d_left - back) <= max_difference)
