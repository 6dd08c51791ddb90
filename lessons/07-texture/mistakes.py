"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each takes the step's
parameters and is built from the lab's own step (:mod:`lab.modules.texture`) where the mistake is a
change of its input; the greedy walk, which no input change turns into the cut, is written out.
"""

import numpy as np

from lab.modules import texture


# --- task 1: the masked, Gaussian-weighted SSD --------------------------------------------------------
def distances_ignoring_mask(sample, query_window, query_mask, *, weighting="gaussian", normalize=True):
    """Every pixel of the query compared, the unknown ones too (with whatever value they hold, here 0),
    and the known weight that of the whole window: the lab's distances with every pixel marked known."""
    every_pixel = np.ones(np.shape(query_mask), dtype=bool)
    return texture.window_distances(sample, query_window, every_pixel, weighting=weighting, normalize=normalize)


# --- task 2: the minimum-error boundary cut ----------------------------------------------------------
def cut_each_row_alone(overlap_error):
    """The smallest error of every row on its own (the lab's cut of a one-row surface): the path jumps."""
    rows = np.asarray(overlap_error, dtype=np.float64)
    return np.array([texture.min_error_boundary_cut(row[None, :])[0] for row in rows], dtype=np.int64)


def cut_greedy_from_first_row(overlap_error):
    """Start at the smallest error of the top row and step down, each time to the smallest of the (at
    most three) neighbours below (the leftmost on ties): connected, but not the cheapest path."""
    errors = np.asarray(overlap_error, dtype=np.float64)
    path = [int(np.argmin(errors[0]))]
    for below in errors[1:]:
        first = max(path[-1] - 1, 0)  # the slice stops at the last column by itself
        path.append(first + int(np.argmin(below[first:path[-1] + 2])))
    return np.array(path, dtype=np.int64)
