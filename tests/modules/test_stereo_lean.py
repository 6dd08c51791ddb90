"""Issue 19: stereo at full resolution in bounded memory (lab.modules.stereo.lean) and the automatic range.

The row-wise path is checked against the full-volume path, its oracle, bit for bit: the same census
costs, the same integer scale, rounding and path updates, so every winner and cost it keeps must be
equal, not close. Small pairs are forced onto it by lowering the volume kept whole
(``_checks.MAX_VOLUME_ENTRIES``) and the band size (``lean.BAND_ENTRIES``: many bands, the last one
short). Peak memory at full size is measured by benchmarks/bench_stereo.py, not here.
"""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import CapacityExceeded, Image, InvalidControl, InvalidValue, Points2D, budgets, open_session
from lab.modules.stereo import (PIPELINE, CensusRows, RowWinners, aggregate_costs, best_two_costs,
                                block_matching_rows, census_rows, cost_volume, costs_around,
                                estimate_disparity_range, estimate_max_disparity, match_range_features,
                                refine_subpixel, right_disparity, semi_global_matching_rows, synthetic)
from lab.modules.stereo import _checks, lean


@pytest.fixture(scope="module")
def pair() -> tuple[Image, Image]:
    loaded = synthetic(width=96, height=70, baseline=0.2)
    return loaded.state["left_raw"], loaded.state["right_raw"]


@pytest.fixture
def small_bands(monkeypatch):
    monkeypatch.setattr(lean, "BAND_ENTRIES", 2**12)  # 8 rows a band: 9 bands of 70 rows, the last of 6


def assert_same_winners(rows: RowWinners, volume: np.ndarray) -> None:
    D = volume.shape[2]
    winner = np.argmin(volume, axis=2)
    np.testing.assert_array_equal(rows.winner, winner)
    np.testing.assert_array_equal(rows.right, right_disparity(volume))
    np.testing.assert_array_equal(rows.around, costs_around(volume, np.clip(winner, 1, D - 2)))
    best, second = best_two_costs(volume)
    np.testing.assert_array_equal(rows.best, best)
    np.testing.assert_array_equal(rows.second, second)


def test_census_rows_give_the_rows_of_the_volume(pair):
    left, right = pair
    volume = cost_volume(left, right, max_disparity=23)
    rows = census_rows(left.gray(), right.gray(), 24, 5)
    assert rows.shape == volume.shape and np.shape(rows) == volume.shape
    for y0, y1 in ((0, 70), (0, 1), (33, 41), (64, 70)):
        np.testing.assert_array_equal(rows.band(y0, y1), volume[y0:y1])


@pytest.mark.parametrize("paths", [8, 4])
def test_sgm_by_rows_keeps_exactly_what_the_steps_read_of_the_full_volume(pair, small_bands, paths):
    left, right = pair
    volume = cost_volume(left, right, max_disparity=23)
    rows = census_rows(left.gray(), right.gray(), 24, 5)
    assert_same_winners(semi_global_matching_rows(rows, P1=0.05, P2=1.0, paths=paths),
                        aggregate_costs(volume, paths=paths))
    assert_same_winners(semi_global_matching_rows(rows, P1=0.2, P2=0.6, paths=paths),
                        aggregate_costs(volume, P1=0.2, P2=0.6, paths=paths))


def test_block_matching_by_rows_keeps_the_winners_of_the_costs(pair, small_bands):
    left, right = pair
    volume = cost_volume(left, right, max_disparity=23)
    assert_same_winners(block_matching_rows(census_rows(left.gray(), right.gray(), 24, 5)), volume)


def test_a_session_aggregated_by_rows_ends_with_the_same_disparities(monkeypatch, small_bands):
    def run() -> dict:
        session = open_session(PIPELINE, "motorcycle", {"downsample": 4})
        session.run_until("reconstruct_points", {"cost_volume": {"max_disparity": 20}})
        return session.state

    full = run()
    monkeypatch.setattr(_checks, "MAX_VOLUME_ENTRIES", 1000)
    rows = run()
    assert isinstance(full["cost_volume"], np.ndarray) and isinstance(rows["cost_volume"], CensusRows)
    assert isinstance(rows["aggregated_cost"], RowWinners)
    for name in ("disparity_wta", "consistent", "disparity_subpixel", "disparity", "depth"):
        np.testing.assert_array_equal(rows[name], full[name], err_msg=name)
    assert rows["disparity"].min() == -1 and (rows["disparity"] >= 0).mean() > 0.5


def test_rows_refine_only_their_own_winners(pair, monkeypatch):
    left, right = pair
    monkeypatch.setattr(_checks, "MAX_VOLUME_ENTRIES", 1000)
    aggregated = aggregate_costs(cost_volume(left, right, max_disparity=23))
    assert isinstance(aggregated, RowWinners)
    refine_subpixel(aggregated, aggregated.winner)
    with pytest.raises(InvalidValue, match="its own winners") as caught:
        refine_subpixel(aggregated, np.maximum(aggregated.winner - 1, 0))
    assert caught.value.field == "disparity_wta"


def test_a_pair_over_the_memory_budget_names_the_memory_and_downsample(pair, monkeypatch):
    left, right = pair
    monkeypatch.setattr(_checks, "MAX_VOLUME_ENTRIES", 1000)
    monkeypatch.setattr(budgets, "MAX_STEREO_BYTES", 100_000)
    with pytest.raises(CapacityExceeded) as caught:
        cost_volume(left, right, max_disparity=23)
    reason = caught.value.reason
    assert caught.value.field == "max_disparity" and "MiB" in reason and "downsample" in reason
    assert f"{lean.lean_memory_bytes(70, 96, 24, 5) / 2**20:,.0f} MiB" in reason
    with pytest.raises(InvalidControl, match="census"):
        cost_volume(left, right, cost="ssd", max_disparity=23)


def test_the_memory_of_rows_is_about_two_bytes_a_cost():
    """A 1.5-megapixel pair with 256 disparities fits the default budget, well under 1.5 GB."""
    need = lean.lean_memory_bytes(1110, 1282, 257, 5)
    assert 1110 * 1282 * 257 * 2 < need < 1.2 * 1110 * 1282 * 257 * 2
    assert need < budgets.MAX_STEREO_BYTES < 1.5e9


# ----------------------------------------------------------------------------------------------------
# The automatic range
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scene,baseline", [("table", 0.3), ("room", 0.25)])
def test_the_estimated_range_covers_the_true_disparities(scene, baseline):
    loaded = synthetic(scene=scene, width=320, height=256, baseline=baseline)
    left, right, truth = loaded.state["left_raw"], loaded.state["right_raw"], loaded.truth["disparity"]
    top, note = estimate_max_disparity(match_range_features(left, right), left.width)
    assert top % 16 == 0 and "matched features" in note
    assert truth.max() <= top <= truth.max() + 48, (top, truth.max())
    volume = cost_volume(left, right, max_disparity=0)
    assert volume.shape[2] == top + 1


def test_matched_features_are_drawn_on_both_images_with_their_disparity():
    loaded = synthetic(width=320, height=256, baseline=0.3)
    result = estimate_disparity_range(loaded.state["left_raw"], loaded.state["right_raw"])
    drawn, other = result.disparity_features, result.disparity_features_right
    assert isinstance(drawn, Points2D) and (drawn.image, other.image) == ("left", "right")
    assert len(drawn) == len(other) == result.range_matches >= 10
    np.testing.assert_array_equal(drawn.ids, other.ids)
    np.testing.assert_allclose(drawn.xy[:, 1], other.xy[:, 1], atol=2.0)  # one row
    truth = loaded.truth["disparity"]
    at = np.rint(drawn.xy).astype(int)
    found = drawn.xy[:, 0] - other.xy[:, 0]
    assert np.median(np.abs(found - truth[at[:, 1], at[:, 0]])) < 1.0
    near, far = np.argmax(found), np.argmin(found)
    assert not np.allclose(drawn.colors[near], drawn.colors[far])  # coloured by disparity
    assert result.feature_disparity_high <= result.auto_max_disparity and result.warnings == ()


def test_a_pair_without_matches_says_to_set_max_disparity():
    flat = Image(np.full((64, 96), 0.5, np.float32))
    result = estimate_disparity_range(flat, flat)
    assert result.auto_max_disparity == -1 and result.range_matches == 0
    assert "set max_disparity" in result.warnings[0]
    with pytest.raises(InvalidControl, match="set max_disparity") as caught:
        cost_volume(flat, flat, max_disparity=0)
    assert caught.value.field == "max_disparity"
