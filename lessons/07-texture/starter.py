"""Lesson 07, texture synthesis: fill in both functions, then run

    vision-lab grade 07-texture starter.py

You may import numpy, scipy and cv2 (not the lab's own implementation). Keep the signatures.
"""

import numpy as np


def window_distances(sample, query_window, query_mask, *, weighting="gaussian", normalize=True):
    """Efros-Leung's distance of a partly known window to every window of the sample.

    Args:
        sample: lab.core.Image. ``sample.pixels`` is (h, ws) or (h, ws, C) float32 in [0, 1].
        query_window: (w, w) or (w, w, C) float64, w odd; its unknown pixels hold 0 (ignore them).
        query_mask: (w, w) bool, True where the query's pixel is known.
        weighting: "gaussian": weigh offset (dy, dx) from the centre by
            g = exp(-(dx^2 + dy^2) / (2 sigma^2)), sigma = w / 6.4; "uniform": every weight 1.
        normalize: divide each sum by the total weight of the known pixels, sum(g * mask).

    Returns:
        (h - w + 1, ws - w + 1) float64: entry (i, j) compares the query with the sample window whose
        top-left pixel is (i, j): sum over offsets of g * mask * (squared difference summed over the
        colour channels), divided by sum(g * mask) when normalize.
    """
    raise NotImplementedError


def min_error_cut(overlap_error):
    """The minimum-error boundary cut through a vertical overlap (Efros & Freeman 2001, section 2.1).

    Args:
        overlap_error: (rows, cols) float64, the squared difference of the two blocks in their overlap.

    Returns:
        (rows,) int64 np.ndarray: the column of the cut in every row, from the top row to the bottom one,
        moving at most one column between neighbouring rows, with the smallest summed error. Build
        E[i, j] = e[i, j] + min(E[i-1, j-1], E[i-1, j], E[i-1, j+1]) row by row, start at the smallest
        E of the last row and trace back; on ties take the leftmost column.
    """
    raise NotImplementedError
