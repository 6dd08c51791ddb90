"""The winners of a cost volume: checked, the right image's, the costs around them, the best two.

Helpers of the steps :func:`~lab.modules.stereo.winner_take_all` (:func:`check_winners`),
:func:`~lab.modules.stereo.left_right_check` (:func:`right_disparity`),
:func:`~lab.modules.stereo.refine_subpixel` (:func:`costs_around`) and
:func:`~lab.modules.stereo.filter_disparity`'s uniqueness test (:func:`best_two_costs`); each fast
function's oracle is in :mod:`.reference`.
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidValue
from lab.core.kernels import bands, in_parallel
from lab.modules.stereo._checks import check_volume
from lab.modules.stereo._kernels import _best_two_costs_kernel, _costs_around_kernel, _right_disparity_kernel


def check_winners(volume: np.ndarray, winner: np.ndarray) -> None:
    """NaN anywhere in a pixel's costs makes it the argmin (NumPy's rule), so checking the winners' costs
    finds every NaN, and any infinite minimum, without another pass over the volume."""
    H, W, D = volume.shape
    chosen = volume.reshape(-1)[np.arange(H * W) * D + winner.reshape(-1)]
    if not np.all(np.isfinite(chosen)):
        raise InvalidValue("aggregated_cost", "contains NaN or infinite costs")


def right_disparity(volume: np.ndarray) -> np.ndarray:
    """Winner-take-all disparity of the *right* image from the left image's volume, ``(H, W)`` int64.

    Right pixel ``(x, y)`` matches left pixel ``(x + d, y)``, so ``d_R(x, y) = argmin_d S(y, x + d, d)``
    over ``x + d < W`` (Hirschmüller 2008, section 3.4: no second matching needed). Fast kernel;
    :func:`right_disparity_reference` is the oracle.
    """
    volume = check_volume(volume, "aggregated_cost", finite=False)
    out = np.empty(volume.shape[:2], np.int64)
    in_parallel(_right_disparity_kernel, [(volume, out, y0, y1) for y0, y1 in bands(volume.shape[0])])
    return out


def costs_around(volume: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` float64: ``C(d - 1)``, ``C(d)``, ``C(d + 1)`` of every pixel, ``d = centre`` in
    ``[1, D - 2]``.

    ``np.take_along_axis(volume, centre[..., None] + [-1, 0, 1], axis=2)``, in a kernel: NumPy's
    fancy indexing builds index arrays for all three axes and takes several times as long. Bands
    of rows run on the thread pool (each pixel's read is a cache miss)."""
    out = np.empty((3, *centre.shape), np.float64)
    centre = np.ascontiguousarray(centre, dtype=np.int64)
    in_parallel(_costs_around_kernel, [(volume, centre, out, y0, y1) for y0, y1 in bands(centre.shape[0])])
    return out


def best_two_costs(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's lowest cost and the lowest cost at least two disparities away from the winner,
    ``(H, W)`` float32 each (``inf`` when the range has no such disparity). Fast kernel; the oracle
    is :func:`best_two_costs_reference`."""
    volume = check_volume(volume, "aggregated_cost", finite=False)
    best = np.empty(volume.shape[:2], np.float32)
    second = np.empty(volume.shape[:2], np.float32)
    in_parallel(_best_two_costs_kernel, [(volume, best, second, y0, y1) for y0, y1 in bands(volume.shape[0])])
    return best, second
