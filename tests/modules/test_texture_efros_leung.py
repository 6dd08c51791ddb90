"""Efros–Leung: the lesson's window distance against a per-window loop, the match, and the fast exact
synthesis against the slow readable reference (identical output for a seed, layer by layer and whole),
the onion order, a pixel's choice replayed, the bad inputs. Small images (a 16 x 16 sample, 5 x 5 and
7 x 7 windows) so that the file takes seconds.
"""

import numpy as np
import pytest

from lab.core import Image, InvalidControl, InvalidValue, LabError, Points2D, open_session
from lab.data.textures import procedural
from lab.modules.texture import (PIPELINE, candidates_within, efros_leung, efros_leung_pixel_matches,
                                 efros_leung_reference, fill_layer, fill_layer_reference, gaussian_window,
                                 integer_gaussian, match_window, onion_layer, pick_query_window,
                                 sample_levels, synthesize_efros_leung, window_distances)

from texture_helpers import drive, small_sample


def loop_window_distances(sample: np.ndarray, query: np.ndarray, mask: np.ndarray,
                          weights: np.ndarray) -> np.ndarray:
    """The definition, one window at a time."""
    s = sample if sample.ndim == 3 else sample[:, :, None]
    q = query if query.ndim == 3 else query[:, :, None]
    w = q.shape[0]
    out = np.zeros((s.shape[0] - w + 1, s.shape[1] - w + 1))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            d = ((q - s[i:i + w, j:j + w]) ** 2).sum(axis=2)
            out[i, j] = (weights * mask * d).sum() / (weights * mask).sum()
    return out


# ----------------------------------------------------------------------------------------------------
# The lesson's window distance and the match
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("colour", [False, True])
def test_window_distances_match_the_per_window_definition(colour):
    sample = small_sample(12, colour=colour, seed=2)
    query = pick_query_window(sample, window=5, known_fraction=0.6, rng=np.random.default_rng(0))
    got = window_distances(sample, query.query_window, query.query_mask)
    expected = loop_window_distances(sample.pixels.astype(np.float64), query.query_window, query.query_mask,
                                     gaussian_window(5))
    assert got.shape == (8, 8)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
    uniform = window_distances(sample, query.query_window, query.query_mask, weighting="uniform",
                               normalize=False)
    loop = loop_window_distances(sample.pixels.astype(np.float64), query.query_window, query.query_mask,
                                 np.ones((5, 5)))
    np.testing.assert_allclose(uniform, loop * query.query_mask.sum(), rtol=1e-9, atol=1e-12)


def test_window_distance_is_zero_where_the_query_was_cut_and_ignores_unknown_pixels():
    sample = small_sample(16, seed=4, pattern="noise")
    query = pick_query_window(sample, window=7, known_fraction=0.5, rng=np.random.default_rng(1))
    distances = window_distances(sample, query.query_window, query.query_mask)
    top, left = query.query_origin
    assert distances[top, left] == pytest.approx(0.0, abs=1e-12)
    assert np.unravel_index(np.argmin(distances), distances.shape) == (top, left)
    scrambled = np.where(query.query_mask, query.query_window, 0.77)  # unknown pixels take any value
    np.testing.assert_allclose(window_distances(sample, scrambled, query.query_mask), distances, atol=1e-12)


def test_window_distance_is_invariant_to_the_scale_of_the_mask_weights_by_normalization():
    sample = small_sample(12, seed=5)
    query = pick_query_window(sample, window=5, known_fraction=0.9, rng=np.random.default_rng(2))
    gauss = window_distances(sample, query.query_window, query.query_mask)
    raw = window_distances(sample, query.query_window, query.query_mask, normalize=False)
    ratio = raw / np.maximum(gauss, 1e-300)
    np.testing.assert_allclose(ratio[gauss > 1e-9], (gaussian_window(5) * query.query_mask).sum(), rtol=1e-9)


def test_window_distance_errors_name_the_problem():
    sample = small_sample(8)
    with pytest.raises(InvalidValue, match="odd side"):
        window_distances(sample, np.zeros((4, 4)), np.ones((4, 4), bool))
    with pytest.raises(InvalidValue, match="larger than the sample"):
        window_distances(sample, np.zeros((9, 9)), np.ones((9, 9), bool))
    with pytest.raises(InvalidValue, match="no pixel of the window is known"):
        window_distances(sample, np.zeros((3, 3)), np.zeros((3, 3), bool))
    with pytest.raises(InvalidValue, match="grayscale and colour"):
        window_distances(sample, np.zeros((3, 3, 3)), np.ones((3, 3), bool))
    with pytest.raises(InvalidValue, match="boolean"):
        window_distances(sample, np.zeros((3, 3)), np.ones((3, 3)))


def test_match_window_keeps_the_candidates_within_epsilon_and_draws_one():
    sample = small_sample(10, seed=1)
    distances = np.full((4, 4), 10.0)
    distances[1, 2], distances[3, 0], distances[0, 0] = 1.0, 1.05, 1.2
    result = match_window(sample, distances, epsilon=0.1, rng=np.random.default_rng(0))
    assert isinstance(result.match_candidates, Points2D) and result.candidates == 2
    assert sorted(map(tuple, result.match_candidates.xy - 3)) == [(0.0, 3.0), (2.0, 1.0)]  # centres (x, y)
    assert tuple(result.chosen_match) in {(1, 2), (3, 0)}
    assert candidates_within(distances, 0.0).tolist() == [6]


# ----------------------------------------------------------------------------------------------------
# Efros–Leung: fast == reference, growth order, bad input
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("colour,size,window,seed", [(False, (14, 14), 5, 0), (False, (11, 17), 7, 1),
                                                     (True, (12, 12), 5, 2)])
def test_fast_efros_leung_equals_the_reference_for_the_same_seed(colour, size, window, seed):
    sample = small_sample(14, colour=colour, seed=seed)
    fast, fast_trace = efros_leung(sample, size=size, window=window, epsilon=0.1,
                                   rng=np.random.default_rng(seed))
    slow, slow_trace = efros_leung_reference(sample, size=size, window=window, epsilon=0.1,
                                             rng=np.random.default_rng(seed))
    assert fast.shape == size + ((3,) if colour else ())
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(fast_trace.fill_order, slow_trace.fill_order)
    np.testing.assert_array_equal(fast_trace.source, slow_trace.source)
    other, _ = efros_leung(sample, size=size, window=window, rng=np.random.default_rng(seed + 100))
    assert not np.array_equal(fast, other)


@pytest.mark.parametrize("colour,chunk", [(False, 256), (False, 3), (True, 2)])
def test_fill_layer_equals_its_reference_on_one_onion_layer(colour, chunk):
    sample = small_sample(12, colour=colour, seed=5)
    levels = sample_levels(sample.pixels)
    window, rng = 5, np.random.default_rng(3)
    height, width, channels = 11, 13, levels.shape[2]
    filled = np.zeros((height, width), bool)
    filled[3:8, 4:9] = True  # a grown patch: its frontier is the layer, some pixels know more than others
    filled[3, 4] = filled[7, 8] = False
    out = np.where(filled[:, :, None], rng.integers(0, 256, (height, width, channels)), 0)
    order = np.where(filled, np.cumsum(filled).reshape(height, width) - 1, -1)
    source = np.where(filled[:, :, None], rng.integers(2, 8, (height, width, 2)), -1)
    pixels = onion_layer(filled, window, rng)
    uniforms = rng.random(len(pixels))
    start = int(filled.sum())
    fast = [a.copy() for a in (out, filled, order, source)]
    slow = [a.copy() for a in (out, filled, order, source)]
    weights = integer_gaussian(window)
    fast_counter = fill_layer(levels, *fast, pixels, weights, 0.1, uniforms, start, chunk=chunk)
    slow_counter = fill_layer_reference(levels, *slow, pixels, weights, 0.1, uniforms, start)
    assert fast_counter == slow_counter == start + len(pixels)
    for got, expected in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(got, expected)
    assert slow[1][pixels[:, 0], pixels[:, 1]].all()  # the layer is filled, in the order given
    assert slow[2][pixels[:, 0], pixels[:, 1]].tolist() == list(range(start, start + len(pixels)))


def test_efros_leung_copies_sample_pixels_and_fills_in_onion_order():
    sample = small_sample(12, seed=3)
    texture, trace = efros_leung(sample, size=(13, 13), window=5, rng=np.random.default_rng(0))
    levels = sample_levels(sample.pixels)[:, :, 0]
    assert np.array_equal(np.rint(texture * 255), levels[trace.source[..., 0], trace.source[..., 1]])
    assert sorted(trace.fill_order.ravel()) == list(range(13 * 13))
    assert trace.fill_order[6, 6] < 9  # the 3 x 3 seed sits in the middle and comes first
    assert trace.fill_order[0, 0] > trace.fill_order[3, 3] > trace.fill_order[5, 5]  # grows outwards


def test_efros_leung_with_a_whole_window_seed_reproduces_a_periodic_texture():
    loaded = procedural(pattern="stripes", size=16, period_px=4.0, orientation_deg=0.0, seed=0)
    texture, _ = efros_leung(loaded.state["sample"], size=(12, 20), window=5, epsilon=0.0,
                             rng=np.random.default_rng(0))
    columns = np.rint(texture * 255)
    np.testing.assert_array_equal(columns[:, :-4], columns[:, 4:])  # the period survives
    assert np.all(np.ptp(columns, axis=0) == 0)  # vertical stripes stay vertical


def test_onion_layer_lists_the_frontier_most_known_first():
    filled = np.zeros((7, 7), bool)
    filled[2:5, 2:5] = True
    layer = onion_layer(filled, 3, np.random.default_rng(0))
    assert len(layer) == 16 and not filled[layer[:, 0], layer[:, 1]].any()
    counts = [filled[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].sum() for r, c in layer]
    assert counts == sorted(counts, reverse=True) and counts[0] == 3 and counts[-1] == 1


def test_synthesize_efros_leung_yields_growing_previews_and_metrics():
    sample = small_sample(14, seed=6)
    snapshots, result = drive(synthesize_efros_leung(sample, size=(10, 10), window=5,
                                                     rng=np.random.default_rng(1)))
    assert snapshots[-1].iteration == 100 and snapshots[-1].total == 100
    assert [s.iteration for s in snapshots] == sorted(s.iteration for s in snapshots)
    assert "efros_leung" in snapshots[0].values
    assert result.layers == len(snapshots) and result.stat_distance >= 0 and result.seam_score >= 0
    reference = drive(synthesize_efros_leung(sample, size=(10, 10), window=5, implementation="reference",
                                             rng=np.random.default_rng(1)))[1]
    np.testing.assert_array_equal(reference.efros_leung.pixels, result.efros_leung.pixels)


def test_pixel_matches_replay_the_choice_made_during_synthesis():
    sample = small_sample(12, seed=7)
    texture, trace = efros_leung(sample, size=(12, 12), window=5, rng=np.random.default_rng(4))
    matches = efros_leung_pixel_matches(sample, Image(texture), trace, 0, 11)
    assert matches.known.any() and not matches.known[2, 2]
    assert matches.distances.shape == (8, 8)
    assert any(np.array_equal(c, matches.chosen) for c in matches.candidates)
    assert np.array_equal(matches.chosen + 2, trace.source[0, 11])
    seed_row, seed_col = np.argwhere(trace.fill_order == 4)[0]  # the middle of the 3 x 3 seed: not matched
    seed = efros_leung_pixel_matches(sample, Image(texture), trace, seed_row, seed_col)
    assert trace.seed_pixels == 9 and not seed.known.any() and np.array_equal(seed.candidates, [seed.chosen])
    with pytest.raises(InvalidValue, match="outside"):
        efros_leung_pixel_matches(sample, Image(texture), trace, 12, 0)


def test_efros_leung_bad_input_errors():
    sample = small_sample(8)
    with pytest.raises(InvalidControl, match="larger than the sample"):
        efros_leung(sample, size=(10, 10), window=9, rng=np.random.default_rng(0))
    with pytest.raises(InvalidControl, match="must be odd"):
        efros_leung(sample, size=(10, 10), window=4, rng=np.random.default_rng(0))
    with pytest.raises(InvalidControl, match="smaller than the seed"):
        efros_leung(sample, size=(2, 10), window=3, rng=np.random.default_rng(0))
    session = open_session(PIPELINE, "procedural", {"size": 8})
    with pytest.raises(LabError) as caught:
        session.run("synthesize_efros_leung", {"window": 6})
    assert caught.value.field == "window" and "odd" in caught.value.reason
    assert "efros_leung" not in session.state


