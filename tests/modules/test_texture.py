"""The texture module: the fast Efros–Leung against the slow reference (identical output for a seed), the
minimum-error cut against brute force, the lesson's window distance against a per-window loop, the pyramid
and histogram matching, quilting and transfer, the mesh, the metrics, the datasets and the bad inputs.

Everything runs on small images (a 16 x 16 sample, 7 x 7 windows) so that the file takes seconds.
"""

import itertools

import numpy as np
import pytest

from lab.core import Image, InvalidControl, InvalidValue, LabError, Mesh, Points2D, Segments2D, open_session
from lab.data.textures import brick, grass, gravel, image_file, procedural, procedural_pixels, transfer_target
from lab.modules import MODULES, get_pipeline
from lab.modules import texture as T
from lab.modules.texture import (PIPELINE, build_pyramid, candidates_within, collapse_pyramid, efros_leung,
                                 efros_leung_pixel_matches, efros_leung_reference, gaussian_window, join_blocks,
                                 match_histogram, match_window, min_error_boundary_cut, min_error_cut,
                                 onion_layer, parametric_surface, path_cost, pick_overlap, pick_query_window, quilt,
                                 sample_texture, seam_score, synthesize_efros_leung, synthesize_parametric,
                                 texture_statistics_distance, textured_trimesh, transfer_texture, window_distances,
                                 wrap_on_mesh)

STEPS = [spec.name for spec in PIPELINE.steps]


def small_sample(size: int = 16, *, colour: bool = False, seed: int = 0, pattern: str = "blobs") -> Image:
    return procedural(pattern=pattern, size=size, colour=colour, seed=seed).state["sample"]


def drive(generator):
    """Run a generator step to its end: (progress snapshots, result)."""
    snapshots = []
    while True:
        try:
            snapshots.append(next(generator))
        except StopIteration as stop:
            return snapshots, stop.value


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


def loop_window_distances(sample: np.ndarray, query: np.ndarray, mask: np.ndarray, weights: np.ndarray) -> np.ndarray:
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
# Registration and the pipeline
# ----------------------------------------------------------------------------------------------------
def test_module_is_registered_with_its_steps_and_datasets():
    assert "texture" in MODULES and get_pipeline("texture") is PIPELINE
    assert STEPS[:6] == ["pick_query_window", "window_distances", "match_window", "pick_overlap", "min_error_cut",
                         "join_blocks"]
    assert {"synthesize_parametric", "synthesize_efros_leung", "quilt", "transfer_texture",
            "wrap_on_mesh"} <= set(STEPS)
    assert [d.name for d in PIPELINE.datasets] == ["brick", "grass", "gravel", "procedural", "image_file"]
    for name in ("synthesize_parametric", "synthesize_efros_leung", "quilt", "transfer_texture"):
        assert PIPELINE.step(name).is_generator
    window = PIPELINE.step("synthesize_efros_leung").control("window")
    assert (window.minimum, window.maximum, window.default) == (3, 31, 11)
    assert PIPELINE.step("quilt").control("mode").choices == ("random", "best_overlap", "min_cut")
    assert PIPELINE.dataset("image_file").takes_path


def test_every_step_runs_on_a_small_procedural_sample():
    session = open_session(PIPELINE, "procedural", {"size": 24, "colour": True, "target_size": 24}, seed=3)
    params = {"synthesize_parametric": {"size": (24, 24), "levels": 2}, "synthesize_efros_leung": {"size": (12, 12),
              "window": 5}, "quilt": {"size": (32, 32), "block": 12, "overlap": 3},
              "transfer_texture": {"block": 9}, "wrap_on_mesh": {"resolution": 8}}
    for name in STEPS:
        record = session.run(name, params.get(name))
        assert record.status == "ok"
    assert session.state["parametric"].pixels.shape == (24, 24, 3)
    assert session.state["efros_leung"].pixels.shape == (12, 12, 3)
    assert session.state["quilting"].pixels.shape == (32, 32, 3)
    assert session.state["transferred"].pixels.shape == (24, 24, 3)
    assert isinstance(session.state["textured_mesh"], Mesh)
    assert session.metrics["match_window"]["match_error_px"] == 0.0
    for name in ("synthesize_parametric", "synthesize_efros_leung", "quilt"):
        assert 0.0 <= session.metrics[name]["stat_distance"] < 2.0
        assert abs(session.metrics[name]["mean_error"]) < 0.1  # procedural truth: mean 0.5


@pytest.mark.parametrize("loader", [brick, grass, gravel])
def test_skimage_textures_load_offline_as_gray_samples(loader):
    loaded = loader(size=32, downsample=4, target_size=24)
    assert loaded.state["sample"].pixels.shape == (32, 32)
    assert loaded.state["transfer_target"].pixels.shape == (24, 24)
    assert 0.05 < loaded.state["sample"].pixels.std() < 0.5


@pytest.mark.parametrize("pattern", ["noise", "blobs", "stripes", "dots"])
def test_procedural_textures_have_their_known_statistics(pattern):
    pixels, truth = procedural_pixels(pattern, 256, np.random.default_rng(1))
    assert abs(pixels.mean() - truth["mean"]) < 0.03
    assert abs(pixels.std() / truth["std"] - 1.0) < 0.12


def test_image_file_dataset_reads_shrinks_and_matches_the_target_kind(tmp_path):
    import cv2

    rgb = (np.random.default_rng(0).random((40, 60, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "t.png"), rgb)
    loaded = image_file(path=str(tmp_path / "t.png"), max_size=30)
    assert loaded.state["sample"].pixels.shape == (20, 30, 3)
    assert loaded.state["transfer_target"].pixels.ndim == 3
    with pytest.raises(InvalidValue, match="no image file"):
        image_file(path=str(tmp_path / "missing.png"))
    assert transfer_target("rings", 16, colour=False).pixels.shape == (16, 16)


# ----------------------------------------------------------------------------------------------------
# The lesson's window distance
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
    uniform = window_distances(sample, query.query_window, query.query_mask, weighting="uniform", normalize=False)
    np.testing.assert_allclose(uniform, loop_window_distances(sample.pixels.astype(np.float64), query.query_window,
                                                              query.query_mask, np.ones((5, 5)))
                               * query.query_mask.sum(), rtol=1e-9, atol=1e-12)


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
    fast, fast_trace = efros_leung(sample, size=size, window=window, epsilon=0.1, rng=np.random.default_rng(seed))
    slow, slow_trace = efros_leung_reference(sample, size=size, window=window, epsilon=0.1,
                                             rng=np.random.default_rng(seed))
    assert fast.shape == size + ((3,) if colour else ())
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(fast_trace.fill_order, slow_trace.fill_order)
    np.testing.assert_array_equal(fast_trace.source, slow_trace.source)
    other, _ = efros_leung(sample, size=size, window=window, rng=np.random.default_rng(seed + 100))
    assert not np.array_equal(fast, other)


def test_efros_leung_copies_sample_pixels_and_fills_in_onion_order():
    sample = small_sample(12, seed=3)
    texture, trace = efros_leung(sample, size=(13, 13), window=5, rng=np.random.default_rng(0))
    levels = T.sample_levels(sample.pixels)[:, :, 0]
    assert np.array_equal(np.rint(texture * 255), levels[trace.source[..., 0], trace.source[..., 1]])
    assert sorted(trace.fill_order.ravel()) == list(range(13 * 13))
    assert trace.fill_order[6, 6] < 9  # the 3 x 3 seed sits in the middle and comes first
    assert trace.fill_order[0, 0] > trace.fill_order[3, 3] > trace.fill_order[5, 5]  # grows outwards


def test_efros_leung_with_a_whole_window_seed_reproduces_a_periodic_texture():
    stripes = procedural(pattern="stripes", size=16, period_px=4.0, orientation_deg=0.0, seed=0).state["sample"]
    texture, trace = efros_leung(stripes, size=(12, 20), window=5, epsilon=0.0, rng=np.random.default_rng(0))
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
    snapshots, result = drive(synthesize_efros_leung(sample, size=(10, 10), window=5, rng=np.random.default_rng(1)))
    assert snapshots[-1].iteration == 100 and snapshots[-1].total == 100
    assert [s.iteration for s in snapshots] == sorted(s.iteration for s in snapshots)
    assert "efros_leung" in snapshots[0].values
    assert result.layers == len(snapshots) and 0 <= result.stat_distance and result.seam_score >= 0
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
    assert isinstance(results["min_cut"].quilting_seams, Segments2D) and len(results["min_cut"].quilting_seams) > 0
    assert results["min_cut"].quilting_seams.image == "quilting"
    # the first block is copied whole from where the layout says
    (sy, sx) = layout.sources[0]
    np.testing.assert_array_equal(results["min_cut"].quilting.pixels[:9, :9], sample.pixels[sy:sy + 9, sx:sx + 9])


def test_quilting_a_periodic_texture_has_no_visible_seams():
    stripes = procedural(pattern="stripes", size=32, period_px=8.0, orientation_deg=0.0).state["sample"]
    result = drive(quilt(stripes, size=(48, 48), block=16, overlap=4, epsilon=0.0, rng=np.random.default_rng(0)))[1]
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
    snapshots, result = drive(transfer_texture(sample, target, block=9, iterations=2, rng=np.random.default_rng(0)))
    assert result.transferred.pixels.shape == (32, 32) and snapshots
    assert snapshots[-1].iteration == snapshots[-1].total  # both passes counted in one progress bar
    random_error = np.mean((T.correspondence_map(sample.pixels[:32, :32]) - T.correspondence_map(target.pixels)) ** 2)
    assert result.correspondence_error < random_error
    colour_target = transfer_target("gradient", 32, colour=True)
    with pytest.raises(InvalidValue, match="grayscale but the target is colour"):
        drive(transfer_texture(sample, colour_target, rng=np.random.default_rng(0)))
    with pytest.raises(InvalidControl, match="smaller than a block"):
        drive(transfer_texture(sample, transfer_target("gradient", 16, colour=False), block=20,
                               rng=np.random.default_rng(0)))


# ----------------------------------------------------------------------------------------------------
# Heeger–Bergen
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("orientations", [1, 4])
def test_pyramid_collapses_back_to_the_image(orientations):
    image = np.random.default_rng(0).random((23, 30))
    bands = build_pyramid(image, levels=3, orientations=orientations)
    assert len(bands) == 3 * orientations + 1 and bands[-1].shape == (3, 4)
    np.testing.assert_allclose(collapse_pyramid(bands, orientations=orientations), image, atol=1e-10)


def test_oriented_bands_separate_orientations():
    yy, xx = np.mgrid[0:32, 0:32]
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


# ----------------------------------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------------------------------
def test_statistics_distance_is_small_for_the_same_process_and_large_for_another():
    a = procedural_pixels("stripes", 64, np.random.default_rng(0))[0]
    b = procedural_pixels("stripes", 64, np.random.default_rng(1))[0]
    noise = procedural_pixels("noise", 64, np.random.default_rng(2))[0]
    assert texture_statistics_distance(a, a) == pytest.approx(0.0, abs=1e-12)
    assert texture_statistics_distance(b, a) < 0.25 * texture_statistics_distance(noise, a)
    shifted = np.roll(a, (5, 7), axis=(0, 1))  # translation invariant (statistics, not pixels)
    assert texture_statistics_distance(shifted, a) < 0.1
    with pytest.raises(InvalidValue, match="channel"):
        texture_statistics_distance(np.zeros((16, 16, 3)), a)


def test_seam_score_sees_pasted_edges():
    rng = np.random.default_rng(0)
    sample = procedural_pixels("blobs", 32, rng)[0]
    rows, cols = np.mgrid[0:16, 0:16]
    whole = np.stack([rows + 4, cols + 4], axis=2)
    assert seam_score(sample[4:20, 4:20], whole, sample) == 1.0  # one copy: no seam at all
    halves = whole.copy()
    halves[:, 8:, 0] += 10  # the right half comes from elsewhere
    pasted = sample[halves[..., 0], halves[..., 1]]
    pasted[:, 8:] = 1.0 - pasted[:, 8:]  # and does not agree at all
    assert seam_score(pasted, halves, sample) > 3.0


# ----------------------------------------------------------------------------------------------------
# The mesh
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", ["plane", "cylinder", "torus"])
def test_parametric_surfaces_have_uvs_and_closed_seams(shape):
    vertices, faces, uv = parametric_surface(shape, 8)
    assert vertices.shape == (81, 3) and faces.shape == (128, 3) and uv.shape == (81, 2)
    assert uv.min() == 0.0 and uv.max() == 1.0
    grid = vertices.reshape(9, 9, 3)
    if shape != "plane":  # u = 0 and u = 1 meet
        np.testing.assert_allclose(grid[:, 0], grid[:, -1], atol=1e-12)
    if shape == "torus":
        np.testing.assert_allclose(grid[0], grid[-1], atol=1e-12)
        radii = np.hypot(vertices[:, 0], vertices[:, 1])
        assert radii.min() == pytest.approx(0.6) and radii.max() == pytest.approx(1.4)


def test_wrap_on_mesh_colours_vertices_from_the_texture():
    checker = np.kron([[0.0, 1.0], [1.0, 0.0]], np.ones((8, 8))).astype(np.float32)
    result = wrap_on_mesh(Image(checker), texture="sample", shape="plane", repeats=1, resolution=4)
    colours = result.textured_mesh.vertex_colors.reshape(5, 5, 3)
    assert colours[1, 1, 0] == pytest.approx(0.0) and colours[1, 3, 0] == pytest.approx(1.0)
    np.testing.assert_allclose(sample_texture(checker, np.array([[0.75, 0.25]])), [[1.0, 1.0, 1.0]])
    with pytest.raises(InvalidValue, match="run step 'quilt' first"):
        wrap_on_mesh(Image(checker), texture="quilting")
    with pytest.raises(InvalidValue, match="run step 'transfer_texture' first"):
        wrap_on_mesh(Image(checker), texture="transferred")
    mesh = textured_trimesh(result.textured_mesh, result.mesh_uv, checker)
    assert len(mesh.visual.uv) == 25 and mesh.visual.material.image.size == (16, 16)
