"""Image quilting: the minimum-error boundary cut against brute force, the blocks joined along it, the
three quilting modes, a periodic texture without seams, texture transfer, the bad inputs."""

import itertools

import numpy as np
import pytest

from lab.core import InvalidControl, InvalidValue, Segments2D
from lab.data.textures import procedural, transfer_target
from lab.modules.texture import (correspondence_map, join_blocks, min_error_cut, path_cost, pick_overlap,
                                 quilt, transfer_texture)

from texture_helpers import drive, small_sample


def brute_force_cut(errors: np.ndarray) -> tuple[float, list[tuple[int, ...]]]:
    """The smallest cost over every 8-connected top-to-bottom path, and every path that reaches it."""
    rows, cols = errors.shape
    best, paths = np.inf, []
    for start in range(cols):
        for moves in itertools.product((-1, 0, 1), repeat=rows - 1):
            path = [start]
            for move in moves:
                path.append(path[-1] + move)
            if min(path) < 0 or max(path) >= cols:
                continue
            cost = float(errors[np.arange(rows), path].sum())
            if cost < best - 1e-12:
                best, paths = cost, [tuple(path)]
            elif abs(cost - best) <= 1e-12:
                paths.append(tuple(path))
    return best, paths


# ----------------------------------------------------------------------------------------------------
# The minimum-error boundary cut and quilting
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape,seed", [((5, 3), 0), ((6, 4), 1), ((4, 5), 2), ((7, 2), 3), ((1, 4), 4)])
def test_min_error_cut_is_the_brute_force_optimum(shape, seed):
    errors = np.random.default_rng(seed).random(shape)
    path = min_error_cut(errors)
    best, optimal = brute_force_cut(errors)
    assert path.shape == (shape[0],) and path.dtype == np.int64
    assert path_cost(errors, path) == pytest.approx(best, abs=1e-12)
    assert tuple(path) in optimal
    assert np.all(np.abs(np.diff(path)) <= 1)


def test_min_error_cut_follows_a_known_valley_and_is_invariant_to_offset_and_scale():
    errors = np.ones((6, 5))
    valley = [0, 1, 2, 3, 3, 4]
    errors[np.arange(6), valley] = 0.0
    assert min_error_cut(errors).tolist() == valley
    rng = np.random.default_rng(0)
    surface = rng.random((8, 6))
    np.testing.assert_array_equal(min_error_cut(surface), min_error_cut(3.0 * surface + 2.0))
    np.testing.assert_array_equal(min_error_cut(surface[:, ::-1]), 5 - min_error_cut(surface))


def test_min_error_cut_errors():
    with pytest.raises(InvalidValue, match="rows, cols"):
        min_error_cut(np.zeros(5))
    with pytest.raises(InvalidValue, match="NaN"):
        min_error_cut(np.array([[0.0, np.nan]]))


def test_join_blocks_uses_the_cut_and_reports_its_cost():
    sample = small_sample(20, seed=8)
    pair = pick_overlap(sample, block=8, overlap=3, rng=np.random.default_rng(0))
    assert pair.overlap_error.shape == (8, 3)
    path = min_error_cut(pair.overlap_error)
    joined = join_blocks(pair.overlap_left, pair.overlap_right, pair.overlap_error, path)
    assert joined.joined.pixels.shape == (8, 13)
    assert joined.cut_cost == pytest.approx(path_cost(pair.overlap_error, path))
    assert joined.cut_cost <= joined.straight_cost + 1e-12 and joined.cut_max_step <= 1
    row = 4
    np.testing.assert_array_equal(joined.joined.pixels[row, 5 + path[row]:8],
                                  pair.overlap_right.pixels[row, path[row]:3])
    with pytest.raises(InvalidValue, match="columns must lie in the overlap"):
        join_blocks(pair.overlap_left, pair.overlap_right, pair.overlap_error, np.full(8, 3))
    with pytest.raises(InvalidValue, match="one column per row"):
        join_blocks(pair.overlap_left, pair.overlap_right, pair.overlap_error, np.zeros(7, int))


def test_quilting_modes_shapes_seams_and_sources():
    sample = small_sample(32, seed=9)
    results = {}
    for mode in ("random", "best_overlap", "min_cut"):
        snapshots, results[mode] = drive(quilt(sample, size=(40, 52), block=12, overlap=3, mode=mode,
                                               rng=np.random.default_rng(0)))
        assert results[mode].quilting.pixels.shape == (40, 52)
        # block origins 9 px apart until a block reaches the edge: 5 rows, 6 columns
        assert snapshots[-1].iteration == snapshots[-1].total == results[mode].blocks == 5 * 6
    assert results["min_cut"].seam_score < results["random"].seam_score
    layout = results["min_cut"].quilting_layout
    assert layout.errors.shape == (30, 12, 12) and layout.new_pixels.shape == (30, 12, 12)
    seams = results["min_cut"].quilting_seams
    assert isinstance(seams, Segments2D) and len(seams) > 0
    assert seams.image == "quilting"
    # the first block is copied whole from where the layout says
    (sy, sx) = layout.sources[0]
    np.testing.assert_array_equal(results["min_cut"].quilting.pixels[:9, :9],
                                  sample.pixels[sy:sy + 9, sx:sx + 9])


def test_quilting_a_periodic_texture_has_no_visible_seams():
    stripes = procedural(pattern="stripes", size=32, period_px=8.0, orientation_deg=0.0).state["sample"]
    result = drive(quilt(stripes, size=(48, 48), block=16, overlap=4, epsilon=0.0,
                         rng=np.random.default_rng(0)))[1]
    columns = result.quilting.pixels
    np.testing.assert_allclose(columns[:, :-8], columns[:, 8:], atol=1e-6)


def test_quilting_bad_input_errors():
    sample = small_sample(16)
    with pytest.raises(InvalidControl, match="smaller than a block"):
        drive(quilt(sample, size=(8, 40), block=12, overlap=2, rng=np.random.default_rng(0)))
    with pytest.raises(InvalidControl, match="larger than the sample"):
        drive(quilt(sample, size=(40, 40), block=20, overlap=2, rng=np.random.default_rng(0)))
    with pytest.raises(InvalidControl, match="smaller than the block"):
        drive(quilt(sample, size=(40, 40), block=8, overlap=8, rng=np.random.default_rng(0)))


def test_texture_transfer_follows_the_target_and_refuses_mixed_kinds():
    sample = small_sample(32, seed=10, pattern="noise")
    target = transfer_target("gradient", 32, colour=False)
    snapshots, result = drive(transfer_texture(sample, target, block=9, iterations=2,
                                               rng=np.random.default_rng(0)))
    assert result.transferred.pixels.shape == (32, 32) and snapshots
    assert snapshots[-1].iteration == snapshots[-1].total  # both passes counted in one progress bar
    sample_map = correspondence_map(sample.pixels[:32, :32])
    random_error = np.mean((sample_map - correspondence_map(target.pixels)) ** 2)
    assert result.correspondence_error < random_error
    colour_target = transfer_target("gradient", 32, colour=True)
    with pytest.raises(InvalidValue, match="grayscale but the target is colour"):
        drive(transfer_texture(sample, colour_target, rng=np.random.default_rng(0)))
    with pytest.raises(InvalidControl, match="smaller than a block"):
        drive(transfer_texture(sample, transfer_target("gradient", 16, colour=False), block=20,
                               rng=np.random.default_rng(0)))


