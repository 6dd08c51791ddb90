"""The stereo module's matching costs and fast kernels: every cost against a slow per-pixel definition and
OpenCV's matchTemplate, known answers on shifted textures, and each fast kernel
(lab.modules.stereo._kernels) against its readable reference (lab.modules.stereo.reference), on one thread
and on many bands."""

import cv2
import numpy as np
import pytest
from stereo_pairs import shifted_pair

from lab.core import CapacityExceeded, Image, InvalidControl, InvalidValue, kernels
from lab.modules.stereo import (COSTS, MAX_VOLUME_ENTRIES, aggregate_costs, best_two_costs,
                                best_two_costs_reference, block_match_realtime,
                                block_match_realtime_reference, box_mean, box_mean_reference, census_costs,
                                census_transform, census_transform_reference, cost_volume, costs_around,
                                hamming_costs, hamming_costs_reference, quantize_costs, rank_transform,
                                refine_subpixel, right_disparity, right_disparity_reference,
                                semi_global_matching, sgm_inputs, sgm_reference, volume_range,
                                winner_take_all)

RNG = np.random.default_rng(5)


# ----------------------------------------------------------------------------------------------------
# Helpers: the slow per-pixel definition of every cost
# ----------------------------------------------------------------------------------------------------
def _clamp(value: int, size: int) -> int:
    return min(max(value, 0), size - 1)


def _census_code(image: np.ndarray, y: int, x: int, r: int) -> list[bool]:
    H, W = image.shape
    return [image[_clamp(y + dy, H), _clamp(x + dx, W)] < image[y, x]
            for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy or dx]


def _local_mean(image: np.ndarray, y: int, x: int, r: int) -> float:
    H, W = image.shape
    return float(np.mean([image[_clamp(y + dy, H), _clamp(x + dx, W)] for dy in range(-r, r + 1)
                          for dx in range(-r, r + 1)]))


def slow_cost(cost: str, a: np.ndarray, b: np.ndarray, y: int, x: int, d: int, window: int) -> float:
    """The cost of left pixel (x, y) at disparity d, by its definition: a loop over the window's pixels.

    Window pixels are clamped to the image; the right pixel of a left pixel q is (q_y, max(q_x - d, 0)).
    """
    H, W = a.shape
    r = window // 2
    n = window * window
    positions = [(_clamp(y + dy, H), _clamp(x + dx, W)) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    A = np.array([a[qy, qx] for qy, qx in positions], dtype=np.float64)
    B = np.array([b[qy, max(qx - d, 0)] for qy, qx in positions], dtype=np.float64)
    if cost == "ssd":
        return float(np.sum((A - B) ** 2) / n)
    if cost == "sad":
        return float(np.sum(np.abs(A - B)) / n)
    if cost == "nssd":
        return float(np.sum((A - B) ** 2) / max(np.sqrt(np.sum(A * A) * np.sum(B * B)), 1e-12))
    if cost == "ncc":
        za, zb = A - A.mean(), B - B.mean()
        denominator = np.sqrt(np.sum(za * za) * np.sum(zb * zb))
        return 1.0 if denominator < 1e-10 * n else float(1.0 - np.sum(za * zb) / denominator)
    if cost == "zsad":
        terms = [abs((a[qy, qx] - _local_mean(a, qy, qx, r))
                     - (b[qy, max(qx - d, 0)] - _local_mean(b, qy, max(qx - d, 0), r)))
                 for qy, qx in positions]
        return float(np.sum(terms) / n)
    if cost == "rank":
        def rank(image, qy, qx):
            return sum(_census_code(image, qy, qx, r))
        return float(sum(abs(rank(a, qy, qx) - rank(b, qy, max(qx - d, 0))) for qy, qx in positions)
                     / n / (n - 1))
    if cost == "census":
        return float(sum(sum(p != q for p, q in zip(_census_code(a, qy, qx, r),
                                                    _census_code(b, qy, max(qx - d, 0), r), strict=True))
                         for qy, qx in positions) / n / (n - 1))
    raise AssertionError(cost)


@pytest.fixture(scope="module")
def tiny_pair():
    rng = np.random.default_rng(3)
    left = rng.random((7, 10)).astype(np.float32)
    right = np.roll(left, -2, axis=1) * 0.9 + 0.05 * rng.random((7, 10)).astype(np.float32)
    return Image(left), Image(right)



# ----------------------------------------------------------------------------------------------------
# Matching costs
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cost", COSTS)
@pytest.mark.parametrize("window", [3, 5])
def test_each_cost_matches_its_per_pixel_definition(tiny_pair, cost, window):
    left, right = tiny_pair
    volume = cost_volume(left, right, cost=cost, window=window, max_disparity=3)
    assert volume.shape == (7, 10, 4) and volume.dtype == np.float32 and volume.flags.c_contiguous
    expected = np.array([[[slow_cost(cost, left.pixels, right.pixels, y, x, d, window) for d in range(4)]
                          for x in range(10)] for y in range(7)])
    np.testing.assert_allclose(volume, expected, rtol=2e-4, atol=2e-5)


@pytest.mark.parametrize("cost,method,transform", [("ssd", cv2.TM_SQDIFF, lambda v, n: v / n),
                                                   ("nssd", cv2.TM_SQDIFF_NORMED, lambda v, n: v),
                                                   ("ncc", cv2.TM_CCOEFF_NORMED, lambda v, n: 1.0 - v)])
def test_window_costs_match_opencv_match_template(cost, method, transform):
    left, right = shifted_pair(3.0, height=20, width=40)
    volume = cost_volume(left, right, cost=cost, window=5, max_disparity=6)
    y, x = 10, 25
    template = left.pixels[y - 2:y + 3, x - 2:x + 3]
    for d in range(7):
        patch = right.pixels[y - 2:y + 3, x - d - 2:x - d + 3]
        expected = transform(float(cv2.matchTemplate(patch, template, method)[0, 0]), 25)
        assert volume[y, x, d] == pytest.approx(expected, rel=1e-3, abs=1e-5)


@pytest.mark.parametrize("cost", COSTS)
def test_integer_shift_is_found_by_every_cost(cost):
    left, right = shifted_pair(5.0)
    winners = winner_take_all(cost_volume(left, right, cost=cost, window=5, max_disparity=12))
    assert np.all(winners[:, 20:-5] == 5)  # away from the borders, where windows are clamped


@pytest.mark.parametrize("cost", COSTS)
@pytest.mark.parametrize("disparity", [3.25, 3.5, 3.75])
def test_subpixel_shift_by_parabola(cost, disparity):
    left, right = shifted_pair(disparity)
    volume = cost_volume(left, right, cost=cost, window=5, max_disparity=12)
    refined = refine_subpixel(volume, winner_take_all(volume))[5:-5, 20:-5]
    assert abs(np.median(refined) - disparity) < 0.12  # the parabola's pixel-locking bias stays below 0.12 px
    assert np.mean(np.abs(refined - disparity)) < 0.15


def test_cost_volume_is_invariant_to_a_brightness_offset_for_zero_mean_costs():
    left, right = shifted_pair(4.0)
    brighter = Image(np.clip(right.pixels * 0.8 + 0.1, 0, 1))
    for cost in ("zsad", "ncc", "census", "rank"):
        winners = winner_take_all(cost_volume(left, brighter, cost=cost, window=5, max_disparity=10))
        assert np.mean(winners[:, 20:] == 4) > 0.99, cost


def test_color_images_are_matched_in_gray():
    left, right = shifted_pair(4.0)
    colour = [Image(np.repeat(image.pixels[:, :, None], 3, axis=2)) for image in (left, right)]
    np.testing.assert_allclose(cost_volume(*colour, max_disparity=8),
                               cost_volume(left, right, max_disparity=8), atol=1e-6)


def test_cost_volume_errors():
    left, right = shifted_pair(2.0, height=20, width=30)
    smaller = Image(right.pixels[:, :20])
    with pytest.raises(InvalidValue, match="differ in size"):
        cost_volume(left, smaller)
    with pytest.raises(InvalidControl, match="larger than the image"):
        cost_volume(left, right, max_disparity=30)
    with pytest.raises(InvalidControl, match="odd"):
        cost_volume(left, right, window=4, max_disparity=5)
    with pytest.raises(InvalidControl, match="at least 3"):
        cost_volume(left, right, cost="census", window=1, max_disparity=5)
    with pytest.raises(InvalidControl, match="one of"):
        cost_volume(left, right, cost="mutual_information", max_disparity=5)
    with pytest.raises(InvalidValue, match="Image"):
        cost_volume(left.pixels, right, max_disparity=5)


def test_cost_volume_refuses_a_volume_too_large():
    """Refused before any cost is computed: 512 x 1024 pixels at 1001 disparities is 8 times the volume kept
    whole; census costs would be aggregated by rows, but their 16-bit sums alone need 1001 MiB, over the
    memory budget; other costs are never aggregated by rows."""
    image = Image(np.zeros((512, 1024), np.float32))
    assert MAX_VOLUME_ENTRIES < 512 * 1024 * 1001
    with pytest.raises(CapacityExceeded, match="max_disparity") as caught:
        cost_volume(image, image, max_disparity=1000)
    assert "MAX_STEREO_BYTES" in caught.value.reason and "downsample=2 needs about" in caught.value.reason
    assert caught.value.field == "max_disparity" and caught.value.status == 413
    with pytest.raises(InvalidControl, match="max_disparity") as caught:
        cost_volume(image, image, cost="sad", max_disparity=1000)
    assert f"{MAX_VOLUME_ENTRIES:,} allowed whole" in caught.value.reason and "census" in caught.value.reason


# ----------------------------------------------------------------------------------------------------
# Fast kernels against their references
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [1, 3, 5, 9])
def test_box_mean_matches_summed_area_table_and_opencv(window):
    volume = RNG.random((13, 17, 4)).astype(np.float32)
    ours = box_mean(volume, window)
    np.testing.assert_allclose(ours, box_mean_reference(volume, window), rtol=1e-5, atol=1e-6)
    for d in range(4):
        expected = cv2.boxFilter(volume[:, :, d], -1, (window, window), normalize=True,
                                 borderType=cv2.BORDER_REPLICATE)
        np.testing.assert_allclose(ours[:, :, d], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(box_mean(volume[:, :, 0], window), ours[:, :, 0])


def test_box_mean_with_a_window_larger_than_the_image():
    image = RNG.random((4, 6)).astype(np.float32)
    np.testing.assert_allclose(box_mean(image, 11), box_mean_reference(image, 11), rtol=1e-5)


@pytest.mark.parametrize("window", [3, 5, 9, 11])
def test_census_kernel_matches_reference(window):  # 9 and 11 need two 64-bit words
    image = RNG.random((12, 15)).astype(np.float32)
    codes = census_transform(image, window)
    assert codes.shape == (12, 15, -(-(window * window - 1) // 64)) and codes.dtype == np.uint64
    np.testing.assert_array_equal(codes, census_transform_reference(image, window))


def test_hamming_kernel_matches_reference():
    a, b = RNG.random((9, 14)).astype(np.float32), RNG.random((9, 14)).astype(np.float32)
    codes_a, codes_b = census_transform(a, 9), census_transform(b, 9)
    np.testing.assert_array_equal(hamming_costs(codes_a, codes_b, 6),
                                  hamming_costs_reference(codes_a, codes_b, 6))


@pytest.mark.parametrize("window", [3, 5, 9])
@pytest.mark.parametrize("shape", [(13, 17), (3, 20), (1, 6)])  # windows taller than the image too
def test_fused_census_kernel_equals_hamming_then_box_mean_bit_for_bit(window, shape, monkeypatch):
    a, b = RNG.random(shape).astype(np.float32), RNG.random(shape).astype(np.float32)
    disparities = min(6, shape[1])
    hamming = hamming_costs_reference(census_transform_reference(a, window),
                                      census_transform_reference(b, window), disparities)
    per_bit = hamming.astype(np.float64) / (window * window - 1)
    expected = box_mean_reference(per_bit, window).astype(np.float32)
    fused = census_costs(a, b, disparities, window)
    np.testing.assert_allclose(fused, expected, rtol=1e-6, atol=0)
    separate = box_mean(hamming, window) * np.float32(1.0 / (window * window - 1))
    np.testing.assert_allclose(fused, separate, rtol=1e-6, atol=0)
    monkeypatch.setattr(kernels, "workers", lambda: 1)  # one band: the same numbers
    np.testing.assert_array_equal(census_costs(a, b, disparities, window), fused)
    monkeypatch.setattr(kernels, "workers", lambda: 5)  # many thin bands
    np.testing.assert_array_equal(census_costs(a, b, disparities, window), fused)


def test_rank_transform_known_answer():
    image = np.arange(9, dtype=np.float32).reshape(3, 3)
    assert rank_transform(image, 3)[1, 1] == 4  # four of the eight neighbours are darker than the centre


@pytest.mark.parametrize("paths", [4, 8])
@pytest.mark.parametrize("P1,P2", [(3.0, 20.0), (50.0, 5000.0)])  # a large P2 coarsens the integer costs
def test_sgm_kernel_equals_reference_on_integer_costs(paths, P1, P2):
    costs = RNG.integers(0, 40, (11, 14, 7)).astype(np.float32)
    volume, scale, p1, p2 = sgm_inputs(costs, P1, P2, paths)
    assert (volume.max() + P2) * scale < 2**14  # the kernel's int16 path costs cannot overflow
    expected = sgm_reference(quantize_costs(volume, scale), p1, p2, paths=paths) / scale
    np.testing.assert_array_equal(semi_global_matching(costs, P1=P1, P2=P2, paths=paths), expected)


@pytest.mark.parametrize("paths", [4, 8])
def test_sgm_kernel_equals_reference_on_real_costs(paths):
    left, right = shifted_pair(3.0, height=16, width=24)
    volume = cost_volume(left, right, cost="sad", window=3, max_disparity=6)
    checked, scale, p1, p2 = sgm_inputs(volume, 0.01, 0.1, paths)
    expected = sgm_reference(quantize_costs(checked, scale), p1, p2, paths=paths) / scale
    np.testing.assert_array_equal(semi_global_matching(volume, P1=0.01, P2=0.1, paths=paths), expected)


def test_sgm_kernel_runs_on_one_thread_too(monkeypatch):
    costs = RNG.integers(0, 40, (9, 12, 5)).astype(np.float32)
    expected = semi_global_matching(costs, P1=2.0, P2=9.0, paths=8)
    monkeypatch.setattr(kernels, "workers", lambda: 1)
    np.testing.assert_array_equal(semi_global_matching(costs, P1=2.0, P2=9.0, paths=8), expected)


def test_sgm_reference_known_answer_on_one_row():
    """One row, one path (left to right): L = C at the first pixel, then the recursion by hand."""
    costs = np.array([[[0, 5], [5, 0]]])  # (1, 2, 2)
    L = sgm_reference(costs, 1, 3, paths=1)
    # pixel 1: d=0: 5 + min(0, 5 + 1, 0 + 3) - 0 = 5; d=1: 0 + min(5, 0 + 1, 0 + 3) - 0 = 1
    np.testing.assert_array_equal(L, [[[0, 5], [5, 1]]])


def test_sgm_is_invariant_to_a_constant_cost_offset():
    left, right = shifted_pair(4.0, height=24, width=40)
    volume = cost_volume(left, right, max_disparity=8)
    a = winner_take_all(semi_global_matching(volume, P1=0.05, P2=1.0))
    b = winner_take_all(semi_global_matching(volume + 0.5, P1=0.05, P2=1.0))
    c = winner_take_all(semi_global_matching(volume - 0.25, P1=0.05, P2=1.0))  # negative costs are shifted
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)


def test_sgm_smooths_a_noisy_cost_volume():
    """Known answer: a constant disparity hidden under noise: SGM recovers it where winner-take-all does
    not."""
    rng = np.random.default_rng(2)
    volume = rng.random((30, 40, 9)).astype(np.float32)
    volume[:, :, 4] -= 0.3
    raw = np.mean(winner_take_all(volume) == 4)
    aggregated = np.mean(winner_take_all(aggregate_costs(volume, P1=1.0, P2=2.0)) == 4)
    assert raw < 0.5 and aggregated > 0.98


def test_aggregate_costs_none_and_errors():
    volume = RNG.random((5, 6, 3)).astype(np.float32)
    assert aggregate_costs(volume, method="none") is volume
    with pytest.raises(InvalidControl, match="P1 <= P2"):
        aggregate_costs(volume, P1=2.0, P2=1.0)
    with pytest.raises(InvalidControl, match="4 or 8"):
        semi_global_matching(volume, P1=0.1, P2=1.0, paths=6)
    broken = volume.copy()
    broken[1, 2, 0] = np.nan
    with pytest.raises(InvalidValue, match="NaN"):
        aggregate_costs(broken)
    with pytest.raises(InvalidValue, match="NaN"):
        winner_take_all(broken)
    with pytest.raises(InvalidValue, match=r"\(H, W, D\)"):
        aggregate_costs(volume[0])


def test_volume_range_and_costs_around_match_numpy():
    volume = RNG.random((9, 13, 7)).astype(np.float32) - 0.25
    assert volume_range(volume) == (float(volume.min()), float(volume.max()))
    broken = volume.copy()
    broken[8, 12, 6] = np.nan  # in the last band
    assert all(np.isnan(volume_range(broken)))
    centre = RNG.integers(1, 6, (9, 13))
    expected = np.take_along_axis(volume, centre[:, :, None] + np.arange(-1, 2), axis=2).transpose(2, 0, 1)
    np.testing.assert_array_equal(costs_around(volume, centre), expected)


def test_right_disparity_and_best_two_match_references():
    volume = RNG.random((8, 12, 6)).astype(np.float32)
    np.testing.assert_array_equal(right_disparity(volume), right_disparity_reference(volume))
    best, second = best_two_costs(volume)
    expected_best, expected_second = best_two_costs_reference(volume)
    np.testing.assert_array_equal(best, expected_best)
    np.testing.assert_array_equal(second, expected_second)



# ----------------------------------------------------------------------------------------------------
# Real-time block matching (issue 19 item 3): integer SAD by running sums against its reference
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("block,max_disparity", [(9, 31), (5, 7), (3, 1), (1, 4), (7, 40)])
def test_realtime_block_matching_equals_its_reference_on_random_pairs(block, max_disparity, monkeypatch):
    """Integer SADs on 8-bit levels: the running-sum kernel and the whole-slice reference agree exactly,
    ties (frequent on these levels) included, on one band and on many thin ones."""
    left = RNG.integers(0, 256, (37, 90), dtype=np.uint8)
    right = np.roll(left, -5, axis=1) // 2 + RNG.integers(0, 128, (37, 90), dtype=np.uint8)
    expected = block_match_realtime_reference(left, right, max_disparity=max_disparity, block=block)
    assert np.array_equal(block_match_realtime(left, right, max_disparity=max_disparity, block=block,
                                               parallel=False), expected)
    monkeypatch.setattr(kernels, "workers", lambda: 7)  # many thin bands
    assert np.array_equal(block_match_realtime(left, right, max_disparity=max_disparity, block=block),
                          expected)
    r = block // 2
    valid = expected >= 0
    assert valid[r:37 - r, r + max_disparity:90 - r].all()
    assert valid.sum() == (37 - 2 * r) * (90 - 2 * r - max_disparity)


def test_realtime_block_matching_equals_its_reference_on_the_synthetic_rig():
    from lab.modules.stereo import synthetic

    loaded = synthetic(width=160, height=120)
    left, right = (loaded.state[name].gray() for name in ("left_raw", "right_raw"))  # floats in [0, 1]
    fast = block_match_realtime(left, right, max_disparity=31, block=9)
    assert np.array_equal(fast, block_match_realtime_reference(left, right, max_disparity=31, block=9))
    to8 = [np.rint(image * 255.0).astype(np.uint8) for image in (left, right)]
    assert np.array_equal(fast, block_match_realtime(*to8, max_disparity=31, block=9))  # floats: 8-bit levels
    truth = loaded.truth["disparity"]
    inside = (fast >= 0) & (truth >= 0)
    assert np.mean(np.abs(fast[inside] - truth[inside]) <= 1.0) > 0.8  # a sanity check of the matches


@pytest.mark.parametrize("disparity", [0, 6, 19])
def test_realtime_block_matching_finds_a_constant_shift(disparity):
    """A texture seen ``d`` px further left in the right image: every valid pixel gets ``d`` (SAD 0), every
    pixel whose window leaves the image is -1, and the pipeline's SAD block matching agrees inside."""
    left, right = shifted_pair(disparity, height=30, width=70, seed=3)
    found = block_match_realtime(left.gray(), right.gray(), max_disparity=24, block=5)
    assert np.all(found[2:28, 26:68] == disparity)
    assert np.all(found[:2] == -1) and np.all(found[28:] == -1) and np.all(found[:, :26] == -1)
    assert np.all(found[:, 68:] == -1)
    volume = cost_volume(left, right, cost="sad", window=5, max_disparity=24)
    pipeline = winner_take_all(aggregate_costs(volume, method="none"))
    assert np.array_equal(pipeline[2:28, 26:68], found[2:28, 26:68])


def test_realtime_block_matching_refuses_bad_input():
    gray = np.zeros((20, 40), np.uint8)
    with pytest.raises(InvalidControl, match="odd"):
        block_match_realtime(gray, gray, block=4)
    with pytest.raises(InvalidValue, match="differ in size"):
        block_match_realtime(gray, gray[:, :30])
    with pytest.raises(InvalidValue, match="grey image"):
        block_match_realtime(np.zeros((20, 40, 3), np.uint8), gray)
    with pytest.raises(InvalidValue, match=r"\[0, 1\]"):
        block_match_realtime(np.full((20, 40), 2.0), gray)
    with pytest.raises(InvalidControl, match="at least"):
        block_match_realtime(gray, gray, max_disparity=31, block=11)
