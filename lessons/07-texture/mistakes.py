"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each takes the step's
parameters and is built from the lab's own step (:mod:`lab.modules.texture`) where the mistake is a
change of its input or output; the greedy walk and the cut that never steps left, which no such
change turns into the cut, are written out. ``vision-lab lesson validate`` also runs each as a
mutant the checks must catch.
"""

import numpy as np

from lab.modules import texture


# --- task 1: the masked, Gaussian-weighted SSD --------------------------------------------------------
def distances_ignoring_mask(sample, query_window, query_mask, *, weighting="gaussian", normalize=True):
    """Every pixel of the query compared, the unknown ones too (with whatever value they hold, here 0),
    and the known weight that of the whole window: the lab's distances with every pixel marked known."""
    every_pixel = np.ones(np.shape(query_mask), dtype=bool)
    return texture.window_distances(sample, query_window, every_pixel, weighting=weighting,
                                    normalize=normalize)


def distances_channels_averaged(sample, query_window, query_mask, *, weighting="gaussian", normalize=True):
    """The squared difference of a colour pixel averaged over its channels instead of summed: the lab's
    distances divided by the number of channels (the same for a gray sample)."""
    distances = texture.window_distances(sample, query_window, query_mask, weighting=weighting,
                                         normalize=normalize)
    pixels = np.asarray(sample.pixels)
    return distances / (pixels.shape[2] if pixels.ndim == 3 else 1)


def distances_divided_by_known_count(sample, query_window, query_mask, *, weighting="gaussian",
                                     normalize=True):
    """Normalized by the number of known pixels, sum m, instead of their total weight, sum g m (the same
    only when every weight is 1): the lab's weighted sums divided by the count."""
    sums = texture.window_distances(sample, query_window, query_mask, weighting=weighting, normalize=False)
    return sums / np.count_nonzero(query_mask) if normalize else sums


def distances_with_unit_sum_gaussian(sample, query_window, query_mask, *, weighting="gaussian",
                                     normalize=True):
    """The Gaussian normalised to sum 1 (``cv2.getGaussianKernel``'s, or ``g / g.sum()``) instead of 1 at the
    centre: the normalized distances do not change, the sums (normalize = false) shrink by sum g."""
    distances = texture.window_distances(sample, query_window, query_mask, weighting=weighting,
                                         normalize=normalize)
    if normalize or weighting != "gaussian":
        return distances
    return distances / texture.gaussian_window(np.shape(query_mask)[0]).sum()


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


def cut_ties_to_the_right(overlap_error):
    """The cut with ties broken the other way (the rightmost of equal totals, at the end and in the trace
    back): the lab's cut of the surface mirrored left to right, mirrored back. The DP is symmetric, so
    this is exactly the reference with every tie resolved to the right."""
    errors = np.asarray(overlap_error, dtype=np.float64)
    return (errors.shape[1] - 1 - texture.min_error_boundary_cut(errors[:, ::-1])).astype(np.int64)


def cut_bottom_to_top(overlap_error):
    """The right cut listed from the bottom row up (the trace back's order, never reversed)."""
    return texture.min_error_boundary_cut(overlap_error)[::-1].copy()


def cut_never_stepping_left(overlap_error):
    """The DP with a slice one short, ``E[i-1, j-1:j+1]``: each pixel reached from above-left or above
    only, so going down the path never moves left; traced back the same way (leftmost on ties)."""
    errors = np.asarray(overlap_error, dtype=np.float64)
    rows, cols = errors.shape
    total = errors.copy()
    for i in range(1, rows):
        for j in range(cols):
            total[i, j] += total[i - 1, max(j - 1, 0):j + 1].min()
    path = np.zeros(rows, dtype=np.int64)
    path[-1] = np.argmin(total[-1])
    for i in range(rows - 2, -1, -1):
        first = max(path[i + 1] - 1, 0)
        path[i] = first + np.argmin(total[i, first:path[i + 1] + 1])
    return path
