"""The epipolar module's fast functions against their readable references
(``lab.modules.epipolar.reference``).

Each compiled function ``x`` is compared with ``x_reference`` (NumPy), RANSAC as a whole with its run on
the references (``RANSAC_REFERENCE``), and every kernel with itself run by the interpreter (a child process
with ``NUMBA_DISABLE_JIT=1``: what numba compiles is what the Python says).
"""

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import open_session
from lab.geometry.homogeneous import hartley_normalization
from lab.modules.epipolar import (PIPELINE, RANSAC_REFERENCE, correspondences, design_matrix,
                                  keypoint_locations, distance_from_best_line,
                                  distance_from_best_line_reference, eight_point,
                                  enforce_rank2, estimate_fundamental_ransac, fixed_samples,
                                  homographies_4point, homography_share, homography_share_reference,
                                  inlier_counts, inlier_counts_reference, inlier_mask, inlier_mask_reference,
                                  local_optimization, local_optimization_reference, match_features,
                                  minimal_fundamentals, minimal_fundamentals_reference, nearest_neighbours,
                                  nearest_neighbours_reference, noise_sigma, noise_sigma_reference,
                                  normal_equations, normal_equations_reference, ransac_fundamental, refit,
                                  refit_reference, sampson_distance, sampson_distances, sampson_refit,
                                  sampson_refit_reference, two_nearest_scan, two_nearest_scan_reference)

REPO = Path(__file__).resolve().parents[2]


def unit(F):
    F = np.asarray(F, dtype=np.float64)
    F = F / np.linalg.norm(F)
    return F * np.sign(F.ravel()[np.argmax(np.abs(F))])


@pytest.fixture(scope="module")
def noisy():
    """The correspondences dataset's defaults: 400 points, 0.5 px noise, 30 % outliers."""
    return correspondences(seed=12)


@pytest.fixture(scope="module")
def rendered_session():
    session = open_session(PIPELINE, "rendered", {"width": 400, "height": 300, "seed": 1}, seed=1)
    session.run_until("match_features")
    return session


# --- RANSAC's parts --------------------------------------------------------------------------------
def _slow_sampson_weighted_refit(F, x1, x2, iterations=3):
    """An independent oracle of the Sampson refit: Hartley's T, its inverse, homogeneous lines."""
    T1, n1 = hartley_normalization(x1)
    T2, n2 = hartley_normalization(x2)
    Fn = np.linalg.inv(T2).T @ F @ np.linalg.inv(T1)
    A = design_matrix(n1, n2)
    h1, h2 = np.column_stack([n1, np.ones(len(n1))]), np.column_stack([n2, np.ones(len(n2))])
    for _ in range(iterations):
        Fx1, Ftx2 = h1 @ Fn.T, h2 @ Fn
        gradient = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
        weighted = A / gradient[:, None]
        Fn = enforce_rank2(np.linalg.eigh(weighted.T @ weighted)[1][:, 0].reshape(3, 3))
    F = T2.T @ Fn @ T1
    return F / np.linalg.norm(F)


def test_minimal_solver_is_the_eight_point_algorithm_of_each_sample(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    samples = np.random.default_rng(3).permutation(len(x1))[:8 * 40].reshape(40, 8)
    compiled = minimal_fundamentals(x1, x2, samples)
    reference = minimal_fundamentals_reference(x1, x2, samples)
    np.testing.assert_allclose(compiled, reference, atol=1e-9)  # the same sign too
    for a, b, c in zip(compiled, reference, eight_point(x1[samples], x2[samples]), strict=True):
        np.testing.assert_allclose(unit(a), unit(c), atol=1e-9)
        np.testing.assert_allclose(unit(b), unit(c), atol=1e-9)
    coincident = np.zeros((1, 8), dtype=np.int64)  # one point eight times: no F, NaN (RANSAC scores it -1)
    assert np.all(np.isnan(minimal_fundamentals(x1, x2, coincident)))
    assert np.all(np.isnan(minimal_fundamentals_reference(x1, x2, coincident)))


def test_normal_equations_and_refits_equal_their_references(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    inliers = ~noisy.truth["outliers"]
    a, b = x1[inliers], x2[inliers]
    # unweighted: A^T A of the design matrix of the Hartley-normalized selection, and its normalization
    T1, n1 = hartley_normalization(a)
    T2, n2 = hartley_normalization(b)
    A = design_matrix(n1, n2)
    M, n = normal_equations(x1, x2, inliers, np.zeros((3, 3)))
    np.testing.assert_allclose(M, A.T @ A, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(n, [T1[0, 0], *a.mean(axis=0), T2[0, 0], *b.mean(axis=0)], rtol=1e-12)
    for F in (np.zeros((3, 3)), noisy.truth["F"]):
        M, n = normal_equations(x1, x2, inliers, F)
        M_ref, n_ref = normal_equations_reference(x1, x2, inliers, F)
        np.testing.assert_allclose(M, M_ref, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(n, n_ref, rtol=1e-12)
    # the refits: unweighted = the 8-point algorithm of the selection, weighted = the readable Sampson refit
    np.testing.assert_allclose(unit(refit(x1, x2, inliers, np.zeros((3, 3)))[0]), unit(eight_point(a, b)),
                               atol=1e-10)
    for weights in (np.zeros((3, 3)), refit_reference(x1, x2, inliers, np.zeros((3, 3)))[1]):
        F_ref, Fn_ref, n_ref = refit_reference(x1, x2, inliers, weights)
        F_fast, Fn_fast, n_fast = refit(x1, x2, inliers, weights)
        np.testing.assert_allclose(unit(F_fast), unit(F_ref), atol=1e-10)
        np.testing.assert_allclose(unit(Fn_fast), unit(Fn_ref), atol=1e-10)
        np.testing.assert_allclose(n_fast, n_ref, rtol=1e-12)
        assert np.linalg.svd(Fn_fast, compute_uv=False)[2] < 1e-12  # rank 2
    start = eight_point(a, b)
    slow = _slow_sampson_weighted_refit(start, a, b)
    np.testing.assert_allclose(unit(sampson_refit(start, x1, x2, inliers, 3)), unit(slow), atol=1e-10)
    reference = sampson_refit_reference(start, x1, x2, inliers, 3)
    np.testing.assert_allclose(unit(reference), unit(slow), atol=1e-10)


def test_the_inlier_test_has_one_fast_path_equal_to_its_reference(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    guesses = [noisy.truth["F"], eight_point(x1, x2), np.random.default_rng(5).normal(size=(3, 3))]
    for F in guesses:
        for error in ("sampson", "epipolar"):
            for threshold in (0.5, 1.0, 3.0):
                expected = inlier_mask_reference(F, x1, x2, threshold, error)
                np.testing.assert_array_equal(inlier_mask(F, x1, x2, threshold, error), expected)
        np.testing.assert_array_equal(inlier_mask(F, x1, x2, 1.0), sampson_distance(F, x1, x2) <= 1.0)
        np.testing.assert_allclose(sampson_distances(F, x1, x2), sampson_distance(F, x1, x2), rtol=1e-10)
    batch = np.stack([*guesses, np.full((3, 3), np.nan)])
    for error in ("sampson", "epipolar"):
        expected = np.append(inlier_mask_reference(batch[:-1], x1, x2, 1.5, error).sum(axis=1), -1)  # NaN: -1
        np.testing.assert_array_equal(inlier_counts(batch, x1, x2, 1.5, error), expected)
        np.testing.assert_array_equal(inlier_counts_reference(batch, x1, x2, 1.5, error), expected)
    # Sampson distances where the gradient vanishes: NumPy's 0/0 = nan and r/0 = inf
    zero = np.zeros((3, 3))
    zero[2, 2] = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        np.testing.assert_array_equal(sampson_distances(zero, x1[:3], x2[:3]),
                                      sampson_distance(zero, x1[:3], x2[:3]))


def test_local_optimization_equals_its_reference(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    sample = np.flatnonzero(~noisy.truth["outliers"])[:8]
    F0 = eight_point(x1[sample], x2[sample])
    for error in ("sampson", "epipolar"):
        F_ref, mask_ref = local_optimization_reference(F0, x1, x2, 1.0, error)
        F_lo, mask_lo = local_optimization(F0, x1, x2, 1.0, error)
        np.testing.assert_array_equal(mask_lo, mask_ref)
        np.testing.assert_allclose(unit(F_lo), unit(F_ref), atol=1e-10)
        assert mask_lo.sum() >= inlier_mask(F0, x1, x2, 1.0, error).sum()  # a refit never loses inliers


def test_ransac_gives_the_same_answer_through_the_references(noisy, rendered_session):
    """The whole search on the readable references (RANSAC_REFERENCE): the same inliers, iterations and F."""
    rendered = rendered_session.state
    pairs = [(noisy.state["x1"], noisy.state["x2"]), (rendered["x1"], rendered["x2"])]
    for a, b in pairs:
        fast = estimate_fundamental_ransac(a, b, rng=np.random.default_rng(4))
        slow = ransac_fundamental(a, b, threshold_px=1.0, confidence=0.99, max_iterations=5000,
                                  error="sampson", refine=True, rng=np.random.default_rng(4),
                                  kernels=RANSAC_REFERENCE)
        np.testing.assert_array_equal(fast.inliers, slow.inliers)
        assert fast.iterations == slow.drawn
        np.testing.assert_allclose(unit(fast.F), unit(slow.F), atol=1e-9)
        slow_rms = np.sqrt(np.mean(slow.distances[slow.inliers] ** 2))
        assert fast.sampson_rms_px == pytest.approx(slow_rms, rel=1e-9)
        np.testing.assert_array_equal(fast.ransac_trace.x, slow.trace[0])


# --- the degeneracy check's screens -------------------------------------------------------------------
def test_homography_screen_against_opencv():
    """The fast 4-point screen in front of cv2.findHomography: high on one plane or one centre, low on a
    volume."""
    x = np.random.default_rng(0).uniform(0, 600, (4, 4, 2))
    y = x + np.random.default_rng(1).normal(0, 20, x.shape)
    for a, b, H in zip(x, y, homographies_4point(x, y), strict=True):
        expected = cv2.getPerspectiveTransform(a.astype(np.float32), b.astype(np.float32))
        np.testing.assert_allclose(H / H[2, 2], expected, rtol=1e-4, atol=1e-6)
    for options, low, high in (({"structure": "plane"}, 0.9, 1.0), ({"baseline": 0.0}, 0.9, 1.0),
                               ({"structure": "plane", "noise_px": 1.0}, 0.7, 1.0), ({}, 0.0, 0.3),
                               ({"noise_px": 2.0}, 0.0, 0.3)):
        loaded = correspondences(outlier_rate=0.0, **options, seed=21)
        p, q = loaded.state["x1"][:200], loaded.state["x2"][:200]
        picks = fixed_samples(len(p), 4, 20)
        share = homography_share_reference(p, q, picks, 4.0)
        assert low <= share <= high, options
        assert homography_share(p, q, picks, 4.0) == pytest.approx(share, abs=0.011)
    # one plane, no noise: one homography maps every pair
    exact = correspondences(structure="plane", noise_px=0.0, outlier_rate=0.0, seed=21)
    p, q = exact.state["x1"][:200], exact.state["x2"][:200]
    assert homography_share(p, q, fixed_samples(200, 4, 20), 1e-6) == 1.0
    assert homography_share_reference(p, q, fixed_samples(200, 4, 20), 1e-6) == 1.0
    # a singular sample: the fast screen answers with the reference's null vectors
    repeated = np.array([[0, 0, 1, 2]])
    assert homography_share(p, q, repeated, 4.0) == homography_share_reference(p, q, repeated, 4.0)


def test_noise_scale_and_collinearity_screen_equal_their_references(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    with np.errstate(divide="ignore", invalid="ignore"):
        distances = sampson_distance(noisy.truth["F"], x1, x2)
    for start_px in (0.1, 1.0, 5.0):
        assert noise_sigma(distances, start_px=start_px) == \
            pytest.approx(noise_sigma_reference(distances, start_px=start_px), rel=1e-9)
    rng = np.random.default_rng(5)
    for off_line in (0.0, 0.01, 1.0, 30.0):  # the RMS distance from the best line, as the SVD says
        t = rng.uniform(-300, 300, 200)
        points = np.column_stack([320 + t * 0.8, 240 + t * 0.6])
        points += np.outer(rng.normal(size=200), [-0.6, 0.8]) * off_line
        mask = rng.random(200) < 0.7
        centred = points[mask] - points[mask].mean(axis=0)
        expected = np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(mask.sum())
        assert distance_from_best_line(points, mask) == pytest.approx(expected, rel=1e-6, abs=1e-5)
        reference = distance_from_best_line_reference(points, mask)
        assert reference == pytest.approx(expected, rel=1e-12, abs=1e-12)


# --- the fast matcher against its float64 reference ---------------------------------------------------
def _assert_same_neighbours(query, train, chunk=1024):
    first, d1, d2, back = nearest_neighbours(query, train, chunk=chunk)
    first_ref, d1_ref, d2_ref, back_ref = nearest_neighbours_reference(query, train, chunk=chunk)
    np.testing.assert_array_equal(first, first_ref)
    np.testing.assert_array_equal(back, back_ref)
    # both compute |q|^2 + |t|^2 - 2 q.t in float64: equal within its rounding, ~1e-16 (|q|^2 + |t|^2)
    qq = np.sum(np.asarray(query, np.float64) ** 2, axis=1)
    scale = qq + np.max(np.sum(np.asarray(train, np.float64) ** 2, axis=1))
    np.testing.assert_array_less(np.abs(d1**2 - d1_ref**2), 1e-13 * scale)
    finite = np.isfinite(d2_ref)
    np.testing.assert_array_equal(np.isfinite(d2), finite)
    np.testing.assert_array_less(np.abs(d2[finite]**2 - d2_ref[finite]**2), 1e-13 * scale[finite])
    return first, d1, d2, back


def test_fast_matcher_equals_the_float64_reference_on_sift(rendered_session):
    """SIFT descriptors of a rendered pair: the float32 matcher gives the float64 reference's neighbours and
    distances, so match_features keeps exactly the same matches."""
    keypoints, descriptors = rendered_session.state["keypoints"], rendered_session.state["descriptors"]
    query, train = descriptors[keypoints.view == 0], descriptors[keypoints.view == 1]
    assert len(query) > 500 and len(train) > 500
    for chunk in (1024, 97):
        first, d1, d2, _ = _assert_same_neighbours(query, train, chunk)
    _, d1_ref, d2_ref, back_ref = nearest_neighbours_reference(query, train)
    for ratio in (0.6, 0.8, 0.95):
        np.testing.assert_array_equal(d1 < ratio * d2, d1_ref < ratio * d2_ref)
    result = match_features(keypoints, descriptors)
    np.testing.assert_array_equal(result.matches, rendered_session.state["matches"])
    index1, index2 = np.flatnonzero(keypoints.view == 0), np.flatnonzero(keypoints.view == 1)
    keep = (d1_ref < 0.8 * d2_ref) & (back_ref[first] == np.arange(len(query)))
    nearest = np.column_stack([index1[keep], index2[first[keep]]])  # then once per pair of locations
    np.testing.assert_array_equal(result.matches, np.unique(keypoint_locations(keypoints)[nearest], axis=0))


def test_fast_matcher_on_adversarial_near_ties():
    """Near-ties that float32 cannot separate (relative gaps of 1e-9, far below its 6e-8 resolution) but
    float64
    can: the float32 pass must hand them to the float64 re-check, for the nearest, the second and the back
    match."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 200, (60, 128))  # |q|^2 ~ 1.7e6: float32 distances off by ~0.1, float64 by ~1e-9

    def shell(centre, gaps):
        """Points around ``centre`` at squared distances ``400 + gaps`` (gaps ~1e-3: float32 ties them)."""
        directions = rng.normal(size=(len(gaps), 128))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        return centre + directions * np.sqrt(400.0 + gaps)[:, None]

    # each query: 40 train rows at nearly the same distance; the nearest and second are known (the smallest
    # gaps)
    queries, train, nearest, runner_up = base[:8], [], [], []
    for i, q in enumerate(queries):
        gaps = rng.permutation(np.linspace(1e-3, 4e-2, 40))
        train.append(shell(q, gaps))
        nearest.append(40 * i + int(np.argmin(gaps)))
        runner_up.append(40 * i + int(np.argsort(gaps)[1]))
    train = np.concatenate(train)
    first, d1, d2, back = _assert_same_neighbours(queries, train)
    np.testing.assert_array_equal(first, nearest)
    assert np.all(d2 - d1 < 1e-4)  # really near-ties: 1e-3 in squared distance
    for chunk in (3, 1):  # the same across blocks
        _assert_same_neighbours(queries, train, chunk)
    # each train row: 30 queries at nearly the same distance (the back match of the mutual check)
    rows = base[8:12]
    crowd = np.concatenate([shell(t, rng.permutation(np.linspace(1e-3, 3e-2, 30))) for t in rows])
    _, _, _, back = _assert_same_neighbours(crowd, rows, chunk=7)
    distances = np.sum((crowd[:, None, :] - rows[None, :, :]) ** 2, axis=2)
    np.testing.assert_array_equal(back, np.argmin(distances, axis=0))
    # the ratio test right at its boundary: float64 distances decide, as in the reference
    query3 = np.zeros((1, 4))
    train3 = np.array([[8.0, 0, 0, 0], [0, 10.0 * (1 + 1e-12), 0, 0], [0, 0, 0, 50.0]])
    first, d1, d2, _ = _assert_same_neighbours(query3, train3)
    assert first[0] == 0 and bool(d1[0] < 0.8 * d2[0])
    # exact duplicates in float64: lowest index first, like the reference's back matches
    dup = np.concatenate([base[:5], base[:5]])
    first, _, _, back = nearest_neighbours(base[:5], dup)
    np.testing.assert_array_equal(first, np.arange(5))
    _assert_same_neighbours(dup, base[:5])


def _scan_blocks(scan, dots, qq, tt):
    """``scan`` over two blocks of rows (the column state carried over); its six outputs."""
    rows, columns = dots.shape
    out = [np.empty(rows, np.int64), np.empty(rows, np.int64), np.empty(rows, bool), np.full(columns, np.inf),
           np.zeros(columns, np.int64), np.full(columns, np.inf)]
    for start, stop in ((0, 10), (10, rows)):
        scan(dots[start:stop], qq[start:stop], tt, start, 1e-3, out[0][start:stop], out[1][start:stop],
             out[2][start:stop], *out[3:])
    return out


def _scan_input():
    rng = np.random.default_rng(2)
    dots = rng.normal(size=(23, 31)).astype(np.float32)
    dots[3, 7] = dots[3, 8]  # an exact tie
    return dots, rng.uniform(5, 6, 23), rng.uniform(5, 6, 31)


def test_two_nearest_scan_equals_its_reference():
    dots, qq, tt = _scan_input()
    fast = _scan_blocks(two_nearest_scan, dots, qq, tt)
    slow = _scan_blocks(two_nearest_scan_reference, dots, qq, tt)
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(a, b)
    squared = qq[:, None] + tt[None, :] - 2.0 * dots.astype(np.float64)
    np.testing.assert_array_equal(fast[0], np.argmin(squared, axis=1))
    np.testing.assert_array_equal(fast[4], np.argmin(squared, axis=0))
    np.testing.assert_array_equal(fast[3], squared.min(axis=0))


# --- what numba compiles is what the Python says -------------------------------------------------------
def kernel_outputs():
    """Every fast function on small fixed inputs, by name: run compiled here, and interpreted in a child."""
    noisy = correspondences(seed=12)
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    inliers = ~noisy.truth["outliers"]
    few = slice(0, 40)  # the interpreted loops are slow: a few pairs where they run per pair and hypothesis
    samples = np.random.default_rng(3).permutation(len(x1))[:8 * 3].reshape(3, 8)
    guesses = np.stack([noisy.truth["F"], eight_point(x1, x2), np.random.default_rng(5).normal(size=(3, 3)),
                        np.full((3, 3), np.nan)])
    out = {"minimal": minimal_fundamentals(x1, x2, samples)}
    for error in ("sampson", "epipolar"):
        out[f"counts_{error}"] = inlier_counts(guesses, x1[few], x2[few], 1.5, error)
        out[f"mask_{error}"] = inlier_mask(guesses[0], x1[few], x2[few], 1.0, error)
        F, mask = local_optimization(eight_point(x1[inliers][:8], x2[inliers][:8]), x1, x2, 1.0, error)
        out[f"lo_F_{error}"], out[f"lo_mask_{error}"] = unit(F), mask
    out["sampson_distances"] = sampson_distances(guesses[1], x1[few], x2[few])
    for k, weights in enumerate((np.zeros((3, 3)), noisy.truth["F"])):
        out[f"normal_M_{k}"], out[f"normal_n_{k}"] = normal_equations(x1, x2, inliers, weights)
        F, Fn, n = refit(x1, x2, inliers, weights)
        out[f"refit_F_{k}"], out[f"refit_Fn_{k}"], out[f"refit_n_{k}"] = unit(F), unit(Fn), n
    out["sampson_refit"] = unit(sampson_refit(eight_point(x1[inliers], x2[inliers]), x1, x2, inliers, 3))
    plane = correspondences(structure="plane", outlier_rate=0.0, seed=21)
    p, q = plane.state["x1"][:30], plane.state["x2"][:30]
    out["homography_share"] = np.array([homography_share(p, q, fixed_samples(30, 4, 20), 4.0)])
    with np.errstate(divide="ignore", invalid="ignore"):
        distances = sampson_distance(noisy.truth["F"], x1, x2)
    out["noise_sigma"] = np.array([noise_sigma(distances, start_px=s) for s in (0.1, 1.0, 5.0)])
    out["line_distance"] = np.array([distance_from_best_line(x1, inliers),
                                     distance_from_best_line(x2, ~inliers)])
    for name, value in zip(("first", "second", "unsure", "column_best", "column_index", "column_second"),
                           _scan_blocks(two_nearest_scan, *_scan_input()), strict=True):
        out[f"scan_{name}"] = value
    return out


def test_compiled_kernels_equal_the_interpreted_python(tmp_path):
    compiled = kernel_outputs()
    script = ("import runpy, sys, numpy as np; found = runpy.run_path(sys.argv[1])['kernel_outputs'](); "
              "np.savez(sys.argv[2], **found)")
    env = dict(os.environ, NUMBA_DISABLE_JIT="1", PYTHONPATH=str(REPO))
    done = subprocess.run([sys.executable, "-c", script, __file__, str(tmp_path / "interpreted.npz")],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    interpreted = np.load(tmp_path / "interpreted.npz")
    assert sorted(interpreted.files) == sorted(compiled)
    for name, value in compiled.items():
        if value.dtype.kind in "biu" or name.startswith(("homography", "scan")):
            np.testing.assert_array_equal(interpreted[name], value, err_msg=name)
        elif name.startswith(("refit_F", "refit_Fn", "lo_F", "sampson_refit")):  # eigh through numba or NumPy
            np.testing.assert_allclose(interpreted[name], value, atol=1e-10, err_msg=name)
        elif name == "noise_sigma":
            np.testing.assert_allclose(interpreted[name], value, rtol=1e-9, err_msg=name)
        else:
            np.testing.assert_allclose(interpreted[name], value, rtol=1e-12, atol=1e-12, err_msg=name)
