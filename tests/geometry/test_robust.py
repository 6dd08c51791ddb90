"""lab.geometry.robust: the adaptive RANSAC count and the minimal samples."""

import math

import numpy as np
import pytest

from lab.core import InvalidValue
from lab.geometry.robust import random_samples, ransac_iterations


@pytest.mark.parametrize("w, s, p", [(0.5, 8, 0.99), (0.7, 8, 0.99), (0.5, 7, 0.999), (0.9, 4, 0.95), (0.3, 2, 0.5)])
def test_ransac_iterations_known_answer(w, s, p):
    expected = math.ceil(math.log(1 - p) / math.log(1 - w**s))
    assert ransac_iterations(w, s, p, 10**9) == expected


def test_ransac_iterations_table_of_hartley_zisserman():
    """H&Z table 4.3 (p = 0.99): s = 8 needs 1177 samples at 50 % outliers and 78 at 30 %, s = 7 needs 588."""
    assert ransac_iterations(0.5, 8, 0.99, 10**6) == 1177
    assert ransac_iterations(0.7, 8, 0.99, 10**6) == 78
    assert ransac_iterations(0.5, 7, 0.99, 10**6) == 588


def test_ransac_iterations_limits():
    assert ransac_iterations(1.0, 8, 0.99, 500) == 1  # all inliers: one sample
    assert ransac_iterations(0.0, 8, 0.99, 500) == 500  # no inliers: the cap
    assert ransac_iterations(0.01, 8, 0.99, 500) == 500  # 1 - w^s rounds to 1
    assert ransac_iterations(0.5, 8, 0.99, 100) == 100
    assert ransac_iterations(1.5, 8, 0.99, 500) == 1  # clipped to [0, 1]


def test_ransac_iterations_grow_with_confidence_and_sample_size():
    counts = [ransac_iterations(0.6, s, p, 10**9) for s, p in ((4, 0.9), (4, 0.99), (8, 0.99), (8, 0.999))]
    assert counts == sorted(counts) and len(set(counts)) == 4


@pytest.mark.parametrize("confidence", [0.0, 1.0, -0.1, 1.5])
def test_ransac_iterations_rejects_bad_confidence(confidence):
    with pytest.raises(InvalidValue, match="confidence"):
        ransac_iterations(0.5, 8, confidence, 100)


@pytest.mark.parametrize("population", [8, 20, 127, 128, 1000])
def test_random_samples_are_distinct_and_in_range(population):
    samples = random_samples(np.random.default_rng(0), population, 8, 300)
    assert samples.shape == (300, 8) and samples.dtype.kind == "i"
    assert samples.min() >= 0 and samples.max() < population
    assert all(len(set(row)) == 8 for row in samples.tolist())


@pytest.mark.parametrize("population", [20, 1000])
def test_random_samples_cover_the_population_uniformly(population):
    samples = random_samples(np.random.default_rng(1), population, 8, 4000)
    counts = np.bincount(samples.ravel(), minlength=population)
    expected = 4000 * 8 / population
    assert np.all(np.abs(counts - expected) < 6 * np.sqrt(expected))


def test_random_samples_follow_the_generator():
    a = random_samples(np.random.default_rng(5), 500, 8, 10)
    b = random_samples(np.random.default_rng(5), 500, 8, 10)
    np.testing.assert_array_equal(a, b)


def test_random_samples_errors():
    with pytest.raises(InvalidValue, match="distinct"):
        random_samples(np.random.default_rng(0), 7, 8, 1)
    assert random_samples(np.random.default_rng(0), 8, 8, 3).shape == (3, 8)  # the whole population
