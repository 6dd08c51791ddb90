"""Heeger–Bergen: the oriented pyramid collapses back to the image and separates orientations, histogram
matching is exact, the synthesis matches the histograms and yields every iteration."""

import numpy as np
import pytest

from lab.core import InvalidControl
from lab.modules.texture import (build_pyramid, collapse_pyramid, match_histogram, synthesize_parametric,
                                 texture_statistics_distance)

from texture_helpers import drive, small_sample


@pytest.mark.parametrize("orientations", [1, 4])
def test_pyramid_collapses_back_to_the_image(orientations):
    image = np.random.default_rng(0).random((23, 30))
    bands = build_pyramid(image, levels=3, orientations=orientations)
    assert len(bands) == 3 * orientations + 1 and bands[-1].shape == (3, 4)
    np.testing.assert_allclose(collapse_pyramid(bands, orientations=orientations), image, atol=1e-10)


def test_oriented_bands_separate_orientations():
    _, xx = np.mgrid[0:32, 0:32]
    vertical_stripes = np.sin(2 * np.pi * xx / 4.0)
    bands = build_pyramid(vertical_stripes, levels=1, orientations=4)
    energy = [float((b ** 2).sum()) for b in bands[:4]]
    assert int(np.argmax(energy)) == 0 and energy[0] > 10 * energy[2]


def test_match_histogram_is_exact_and_order_preserving():
    rng = np.random.default_rng(0)
    values, reference = rng.random((10, 10)), rng.standard_normal(100)
    matched = match_histogram(values, reference)
    np.testing.assert_allclose(np.sort(matched.ravel()), np.sort(reference))
    assert np.array_equal(np.argsort(matched.ravel()), np.argsort(values.ravel()))
    assert match_histogram(rng.random(37), reference).shape == (37,)


def test_heeger_bergen_matches_the_histograms_and_yields_each_iteration():
    sample = small_sample(32, seed=11, pattern="dots", colour=True)
    snapshots, result = drive(synthesize_parametric(sample, size=(32, 40), levels=2, iterations=3,
                                                    rng=np.random.default_rng(0)))
    assert [s.iteration for s in snapshots] == [1, 2, 3] and "parametric" in snapshots[0].values
    assert result.parametric.pixels.shape == (32, 40, 3)
    gray = drive(synthesize_parametric(small_sample(32, seed=11), size=(32, 32), levels=2, iterations=3,
                                       rng=np.random.default_rng(0)))[1]
    assert gray.histogram_error < 0.01  # a gray sample: the pixel histogram is matched last, exactly
    noise = np.random.default_rng(1).random((32, 40, 3)).astype(np.float32)
    assert result.stat_distance < texture_statistics_distance(noise, sample.pixels)
    with pytest.raises(InvalidControl, match="levels"):
        drive(synthesize_parametric(sample, size=(32, 32), levels=5, rng=np.random.default_rng(0)))


