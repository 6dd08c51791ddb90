"""Robust estimation helpers shared by every RANSAC: the adaptive iteration count and minimal samples.

RANSAC (Fischler and Bolles, 1981) draws minimal samples of ``s`` correspondences, fits a model to
each and keeps the one with the most inliers. If a fraction ``w`` of the data are inliers, a sample
is all inliers with probability ``w^s``, so ``N`` samples contain at least one clean sample with
probability ``1 - (1 - w^s)^N``. Asking for confidence ``p`` gives the adaptive count

    N = log(1 - p) / log(1 - w^s)

re-evaluated whenever a better model raises the inlier ratio ``w`` (Hartley & Zisserman, Multiple
View Geometry, 2nd ed., section 4.7.1, algorithm 4.5; OpenCV's ``RANSACUpdateNumIters``).
"""

from __future__ import annotations

import math

import numpy as np

from lab.core.errors import InvalidValue


def ransac_iterations(inlier_ratio: float, sample_size: int, confidence: float, max_iterations: int) -> int:
    """Samples needed to draw one all-inlier sample with probability ``confidence``:
    ``log(1-p) / log(1-w^s)``.

    Args:
        inlier_ratio: ``w``, the fraction of inliers of the best model so far, in [0, 1].
        sample_size: ``s``, correspondences per minimal sample (8 for the 8-point algorithm).
        confidence: ``p`` in (0, 1).
        max_iterations: the cap (returned when ``w`` is so low that the count explodes).

    Returns the count, rounded up, at least 1 and at most ``max_iterations``. Corresponds to OpenCV's
    ``RANSACUpdateNumIters(p, 1 - w, s, max_iterations)`` (calib3d/src/ptsetreg.cpp).

    Reference: Hartley & Zisserman (2nd ed.), section 4.7.1, eq. (4.18).
    """
    if not 0.0 < confidence < 1.0:
        raise InvalidValue("confidence", f"must lie strictly between 0 and 1, got {confidence}")
    if sample_size < 1 or max_iterations < 1:
        raise InvalidValue("sample_size", "sample size and iteration cap must be positive")
    w = min(max(float(inlier_ratio), 0.0), 1.0)
    clean = w ** sample_size  # probability that one sample is all inliers
    if clean <= 0.0:
        return int(max_iterations)
    if clean >= 1.0:
        return 1
    denominator = math.log1p(-clean)
    if denominator > -1e-300:  # 1 - w^s rounds to 1: practically hopeless
        return int(max_iterations)
    count = math.log1p(-confidence) / denominator
    return int(min(max(math.ceil(count), 1), max_iterations))


def random_samples(rng: np.random.Generator, population: int, size: int, count: int) -> np.ndarray:
    """``count`` random samples of ``size`` distinct indices from ``range(population)``:
    ``(count, size)`` int.

    Each row is uniform over the ``size``-subsets (in random order); rows are independent. Large
    populations draw with replacement and redraw the rare rows with a repeat; small ones rank
    random keys (``argpartition``), which is exact for any size.
    """
    if size > population:
        raise InvalidValue("population", f"cannot draw {size} distinct indices from {population}")
    if population >= 2 * size * size:  # P(row has a repeat) <= s^2 / (2 n) <= 1/4
        samples = rng.integers(0, population, size=(count, size))
        while True:
            ordered = np.sort(samples, axis=1)
            repeated = np.any(ordered[:, 1:] == ordered[:, :-1], axis=1)
            if not repeated.any():
                return samples
            samples[repeated] = rng.integers(0, population, size=(int(repeated.sum()), size))
    keys = rng.random((count, population))
    if size < population:
        return np.argpartition(keys, size - 1, axis=1)[:, :size]
    return np.argsort(keys, axis=1)


__all__ = ["random_samples", "ransac_iterations"]
