"""The epipolar module: every step against exact truth and against OpenCV, run through sessions.

Data: synthetic correspondences (exact truth, controlled noise and outliers), a small rendered
pair of the "room" scene, and OpenCV's leuvenA/B photos with their K
(``../shared/data/opencv-samples``). Sessions are built once per module. The fast kernels against
their readable references are in ``test_epipolar_kernels.py``, the datasets in ``test_epipolar_datasets.py``.
"""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import (Cameras, Curve, InvalidControl, InvalidValue, LabError, PointCloud, Points2D,
                      Segments2D, StepFailed, open_session)
from lab.geometry.rotations import rotation_angle_deg
from lab.modules import get_pipeline
from lab.modules.epipolar import (CANDIDATE_NAMES, PIPELINE, SIFT_OFFSET_PX, VIEWS, CollinearPoints,
                                  CoplanarPoints, DegenerateInput, MissingIntrinsics, TooFewMatches,
                                  ZeroBaseline, clip_lines, compute_epipolar_lines, correspondences,
                                  decompose_essential, detect_features, eight_point, enforce_rank2,
                                  epipolar_distances, epipolar_lines, epipoles, estimate_essential,
                                  estimate_fundamental_8point, estimate_fundamental_ransac,
                                  keypoint_locations, match_features, nearest_neighbours, recover_pose,
                                  refine_points, refine_pose, sampson_distance, sampson_refit,
                                  symmetric_epipolar_distance, triangulate)

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "opencv-samples"
STEPS = [spec.name for spec in PIPELINE.steps]


def unit(F):
    F = np.asarray(F, dtype=np.float64)
    F = F / np.linalg.norm(F)
    return F * np.sign(F.ravel()[np.argmax(np.abs(F))])


def angle_deg(a, b):
    cosine = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))


def ours_pose(x1, x2, K, seed=0):
    ransac = estimate_fundamental_ransac(x1, x2, rng=np.random.default_rng(seed))
    E = estimate_essential(ransac.F, None, K, K)
    pose = recover_pose(E, x1, x2, K, K, ransac.inliers)
    refined = refine_pose(pose, x1, x2, K, K, ransac.inliers)
    return refined.R, refined.t


def opencv_poses(x1, x2, K):
    E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, 1.0)
    _, R_e, t_e, _ = cv2.recoverPose(E[:3], x1, x2, K, mask=mask.copy())
    F, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.99)
    _, R_f, t_f, _ = cv2.recoverPose(K.T @ F[:3] @ K, x1, x2, K, mask=mask.copy())
    return (R_e, t_e.ravel()), (R_f, t_f.ravel())


@pytest.fixture(scope="module")
def clean():
    """Noise-free, outlier-free correspondences: every estimate must be exact."""
    return correspondences(num_points=150, noise_px=0.0, outlier_rate=0.0, seed=11)


@pytest.fixture(scope="module")
def noisy():
    """The correspondences dataset's defaults: 400 points, 0.5 px noise, 30 % outliers."""
    return correspondences(seed=12)


@pytest.fixture(scope="module")
def corr_session():
    """Every step run once ("Run all": the plan of every step whose outputs are missing)."""
    session = open_session(PIPELINE, "correspondences", {"seed": 3}, seed=3)
    session.run_until(None)
    return session


@pytest.fixture(scope="module")
def rendered_session():
    session = open_session(PIPELINE, "rendered", {"width": 400, "height": 300, "seed": 1}, seed=1)
    session.run_until(None)
    return session


@pytest.fixture(scope="module")
def leuven():
    session = open_session(PIPELINE, "photos", {"path": str(SAMPLES), "k_file": "essential_mat_data.txt"})
    session.run("detect_features")
    session.run("match_features")
    return session


# --- the pipeline as a whole ------------------------------------------------------------------------
def test_pipeline_is_registered_with_the_contract_steps():
    assert get_pipeline("epipolar") is PIPELINE
    assert STEPS == ["detect_features", "match_features", "estimate_fundamental_8point",
                     "estimate_fundamental_ransac", "compute_epipolar_lines", "estimate_essential",
                     "decompose_essential", "recover_pose", "refine_pose", "triangulate", "refine_points"]
    assert [d.name for d in PIPELINE.datasets] == ["rendered", "correspondences", "photos"]
    assert PIPELINE.step("detect_features").writes == ("keypoints", "descriptors")
    assert PIPELINE.step("match_features").writes == ("matches", "x1", "x2")
    assert PIPELINE.step("estimate_fundamental_8point").writes == ("F",)
    assert PIPELINE.step("estimate_fundamental_ransac").writes == ("F", "inliers", "ransac_trace")
    assert PIPELINE.step("estimate_fundamental_ransac").runner_args == ("rng",)
    assert PIPELINE.step("compute_epipolar_lines").writes == ("epipolar_lines", "line_points", "epipoles",
                                                              "epipole_points")
    assert PIPELINE.step("estimate_essential").writes == ("E",)
    assert PIPELINE.step("decompose_essential").writes == ("candidates",)
    assert PIPELINE.step("recover_pose").writes == ("pose",)
    assert PIPELINE.step("refine_pose").writes == ("R", "t")
    assert PIPELINE.step("triangulate").writes == ("points3d_dlt",)
    assert PIPELINE.step("refine_points").writes == ("points3d", "cameras", "residuals", "reprojection_cost")
    json.dumps(PIPELINE.describe())  # every schema is JSON


def test_views_are_values_the_pipeline_produces():
    """The names the viewer's interactions read by name are written by a step or seeded by every dataset."""
    assert PIPELINE.views == frozenset(VIEWS)
    written = {name for spec in PIPELINE.steps for name in spec.writes}
    seeded = set(correspondences(num_points=8, outlier_rate=0.0).state)
    assert set(VIEWS) <= written | {"images", "K1", "K2"} and {"images", "K1", "K2"} <= seeded


def test_lesson_steps_take_and_return_plain_arrays():
    spec = PIPELINE.step("estimate_fundamental_8point")
    assert spec.reads == ("x1", "x2") and [c.name for c in spec.controls] == ["normalize"]
    assert PIPELINE.step("recover_pose").reads == ("candidates", "x1", "x2", "K1", "K2", "inliers")
    assert [c.name for c in PIPELINE.step("recover_pose").controls] == ["candidate"]
    assert PIPELINE.step("decompose_essential").reads == ("E",)


def test_done_when_synthetic_benchmark_beats_opencv():
    """Median rotation error <= 0.2 deg, translation direction <= 1 deg, no worse than 1.1 x OpenCV's best."""
    errors = {"ours": [], "cv_e": [], "cv_f": []}
    for seed in range(5):
        loaded = correspondences(seed=seed)
        x1, x2, K, truth = loaded.state["x1"], loaded.state["x2"], loaded.state["K1"], loaded.truth
        (R_e, t_e), (R_f, t_f) = opencv_poses(x1, x2, K)
        poses = (("ours", ours_pose(x1, x2, K, seed)), ("cv_e", (R_e, t_e)), ("cv_f", (R_f, t_f)))
        for name, (R, t) in poses:
            errors[name].append((float(rotation_angle_deg(R, truth["R"])), angle_deg(t, truth["t"])))
    median = {name: np.median(np.array(values), axis=0) for name, values in errors.items()}
    best_cv = np.minimum(median["cv_e"], median["cv_f"])
    assert median["ours"][0] <= 0.2 and median["ours"][1] <= 1.0
    assert median["ours"][0] <= 1.1 * best_cv[0] and median["ours"][1] <= 1.1 * best_cv[1]


def test_done_when_leuven_agrees_with_opencv(leuven):
    """Inlier sets overlap >= 90 %; the Sampson RMS of our inliers <= 1.1 x OpenCV's (FM_RANSAC, 1 px)."""
    x1, x2 = leuven.state["x1"], leuven.state["x2"]
    F_cv, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.99)
    mask = mask.ravel() > 0
    record = leuven.run("estimate_fundamental_ransac")
    ours = leuven.state["inliers"]
    assert (ours & mask).sum() / (ours | mask).sum() >= 0.9
    rms_cv = np.sqrt(np.mean(sampson_distance(F_cv, x1[mask], x2[mask]) ** 2))
    assert record.metrics["sampson_rms_px"] <= 1.1 * rms_cv
    assert record.metrics["rank_of_F"] == 2


def test_whole_pipeline_on_rendered_scene(rendered_session):
    metrics = rendered_session.metrics
    assert metrics["match_features"]["match_precision"] > 0.9
    assert metrics["estimate_fundamental_ransac"]["inlier_precision"] > 0.97
    assert metrics["estimate_fundamental_ransac"]["inlier_recall"] > 0.95
    assert metrics["estimate_fundamental_ransac"]["truth_sampson_rms_px"] < 0.3
    assert metrics["refine_pose"]["rotation_error_deg"] < 0.2
    assert metrics["refine_pose"]["translation_direction_error_deg"] < 1.0
    assert metrics["refine_points"]["point_rel_error_median"] < 0.02
    assert metrics["refine_points"]["reprojection_rms_px"] < 0.5
    assert all(status == "done" for status in rendered_session.step_status().values())


def test_real_photos_have_no_truth_metrics(leuven):
    session = open_session(PIPELINE, "photos", {"path": str(SAMPLES), "k_file": "essential_mat_data.txt",
                                                "max_side": 400})
    session.run_until("refine_points")
    assert "rotation_error_deg" not in session.metrics["refine_pose"]
    assert session.metrics["recover_pose"] == {}
    assert set(session.metrics["estimate_fundamental_ransac"]) == {
        "num_inliers", "inlier_ratio", "iterations", "sampson_rms_px", "rank_of_F"}
    assert session.metrics["refine_points"]["points_behind"] <= 2
    # the camera moved forwards between the leuven photos, as OpenCV's 5-point estimate also says
    x1, x2, K = session.state["x1"], session.state["x2"], session.state["K1"]
    E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, 1.0)
    _, R, t, _ = cv2.recoverPose(E[:3], x1, x2, K, mask=mask)
    assert session.state["t"][2] > 0.95 and angle_deg(session.state["t"], t.ravel()) < 3.0
    assert rotation_angle_deg(session.state["R"], R) < 1.0


def test_a_students_8point_runs_through_the_rest(corr_session):
    """Any step can be replaced: a findFundamentalMat-based 8-point feeds the rest on clean data."""

    def student(x1, x2, *, normalize=True):
        F, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
        return F

    session = open_session(PIPELINE, "correspondences", {"outlier_rate": 0.0, "seed": 4}, seed=4)
    assert session.run("estimate_fundamental_8point", override=student).replaced
    assert session.metrics["estimate_fundamental_8point"]["rank_of_F"] == 2
    for step in ("estimate_essential", "decompose_essential", "recover_pose", "refine_pose"):
        session.run(step)
    assert session.metrics["refine_pose"]["rotation_error_deg"] < 0.2


def test_a_students_pose_with_the_wrong_candidate_shows_in_the_metrics():
    session = open_session(PIPELINE, "correspondences", {"outlier_rate": 0.0, "seed": 5}, seed=5)
    for step in ("estimate_fundamental_8point", "estimate_essential"):
        session.run(step)

    session.run("decompose_essential")

    def student(candidates, x1, x2, K1, K2, inliers=None, *, candidate="cheirality"):
        return _wrong_candidate(candidates, x1, x2, K1, K2, inliers)

    session.run("recover_pose", override=student)
    assert session.metrics["recover_pose"]["rotation_error_deg"] > 90 or \
        session.metrics["recover_pose"]["translation_direction_error_deg"] > 90


def _wrong_candidate(candidates, x1, x2, K1, K2, inliers):
    right = recover_pose(candidates, x1, x2, K1, K2, inliers)
    for candidate in candidates:
        if not np.allclose(candidate, right):
            return candidate
    raise AssertionError("four equal candidates")


def test_a_failed_step_leaves_the_state_alone():
    session = open_session(PIPELINE, "correspondences", {"structure": "plane"})
    session.run("estimate_fundamental_8point")
    before = dict(session.state)
    with pytest.raises(CoplanarPoints):
        session.run("estimate_fundamental_ransac")
    assert session.state.keys() == before.keys() and "inliers" not in session.state
    assert session.history[-1].status == "failed" and "plane" in session.history[-1].error


def test_controls_are_checked():
    session = open_session(PIPELINE, "correspondences", {"num_points": 50})
    with pytest.raises(InvalidControl):
        session.run("estimate_fundamental_ransac", {"threshold_px": 0.0})
    with pytest.raises(InvalidControl):
        session.run("estimate_fundamental_ransac", {"error": "manhattan"})
    with pytest.raises(InvalidControl):
        session.run("match_features", {"ratio": 1.5})


# --- degenerate input: a clear error, never a wrong answer --------------------------------------------
def test_fewer_than_eight_matches():
    loaded = correspondences(num_points=8, outlier_rate=0.0, noise_px=0.0, seed=1)
    x1, x2 = loaded.state["x1"][:7], loaded.state["x2"][:7]
    with pytest.raises(TooFewMatches, match="at least 8"):
        estimate_fundamental_8point(x1, x2)
    with pytest.raises(TooFewMatches, match="at least 8"):
        estimate_fundamental_ransac(x1, x2, rng=np.random.default_rng(0))
    F = estimate_fundamental_8point(loaded.state["x1"], loaded.state["x2"])  # exactly 8 is enough
    np.testing.assert_allclose(unit(F), unit(loaded.truth["F"]), atol=1e-6)


def test_too_few_matches_from_the_matcher_warn_then_fail():
    session = open_session(PIPELINE, "correspondences", {"num_points": 20, "seed": 2})
    record = session.run("match_features", {"ratio": 0.05})
    assert record.metrics["num_matches"] < 8 and "F needs at least 8" in record.warnings[0]
    with pytest.raises(TooFewMatches):
        session.run("estimate_fundamental_ransac")


def test_points_on_one_plane():
    session = open_session(PIPELINE, "correspondences", {"structure": "plane", "seed": 3})
    with pytest.raises(CoplanarPoints, match="one plane"):
        session.run("estimate_fundamental_ransac")
    exact = correspondences(structure="plane", noise_px=0.0, outlier_rate=0.0, seed=3)
    with pytest.raises(CoplanarPoints, match="not unique"):
        estimate_fundamental_8point(exact.state["x1"], exact.state["x2"])


def test_points_on_one_line():
    session = open_session(PIPELINE, "correspondences", {"structure": "line", "seed": 4})
    with pytest.raises(CollinearPoints, match="one line"):
        session.run("estimate_fundamental_ransac")
    exact = correspondences(structure="line", noise_px=0.0, outlier_rate=0.0, seed=4)
    with pytest.raises(CollinearPoints):
        estimate_fundamental_8point(exact.state["x1"], exact.state["x2"])


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_zero_baseline(noise_px):
    loaded = correspondences(baseline=0.0, noise_px=noise_px, seed=5)
    with pytest.raises(ZeroBaseline, match="share their centre"):
        estimate_fundamental_ransac(loaded.state["x1"], loaded.state["x2"], rng=np.random.default_rng(0))


@pytest.mark.parametrize("noise_px", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("threshold_px", [1.0, 2.0])
def test_degenerate_input_is_found_at_realistic_noise(noise_px, threshold_px):
    """One plane or one centre, noise up to twice the threshold, 30 % outliers: the right error (GRIC)."""
    for options, error, words in (({"structure": "plane"}, CoplanarPoints, "one plane"),
                                  ({"baseline": 0.0}, ZeroBaseline, "share their centre")):
        for seed in range(3):
            loaded = correspondences(noise_px=noise_px, seed=seed, **options)
            with pytest.raises(error, match=words):
                estimate_fundamental_ransac(loaded.state["x1"], loaded.state["x2"], threshold_px=threshold_px,
                                            rng=np.random.default_rng(seed))


@pytest.mark.parametrize("noise_px", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("threshold_px", [1.0, 2.0])
def test_general_scenes_are_not_degenerate_at_any_noise(noise_px, threshold_px):
    """Scenes with depth, 30 % outliers, the same noise: never refused (shallow scenes, few points too)."""
    for options in ({}, {"depth_range": 1.0}, {"num_points": 60}, {"baseline": 0.3}):
        for seed in range(3):
            loaded = correspondences(noise_px=noise_px, seed=seed, **options)
            result = estimate_fundamental_ransac(loaded.state["x1"], loaded.state["x2"],
                                                 threshold_px=threshold_px, rng=np.random.default_rng(seed))
            assert result.num_inliers >= 8, (options, seed)


def test_gric_known_answer():
    from lab.modules.epipolar import gric

    n = 50
    exact = np.zeros(n)
    assert gric(exact, 1.0, 3, 7) == pytest.approx(np.log(4) * 3 * n + np.log(4 * n) * 7)
    assert gric(exact, 1.0, 2, 8) == pytest.approx(np.log(4) * 2 * n + np.log(4 * n) * 8)
    # residuals count as (e / sigma)^2, capped at lambda3 (r - d) = 2 (F) or 4 (H); NaN counts as the cap
    residuals = np.array([0.5, 1.0, 10.0, np.nan])
    base = gric(np.zeros(4), 0.5, 3, 7)
    assert gric(residuals, 0.5, 3, 7) - base == pytest.approx(1.0 + 2.0 + 2.0 + 2.0)
    assert gric(residuals, 0.5, 2, 8) - gric(np.zeros(4), 0.5, 2, 8) == pytest.approx(1.0 + 4.0 + 4.0 + 4.0)
    # a plane: H's residuals are twice F's in squares (2 vs 1 degree of freedom), yet H wins by ln 4 per point
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 0.7, (2000, 4))
    assert gric(np.linalg.norm(noise[:, :2], axis=1), 0.7, 2, 8) < gric(np.abs(noise[:, 2]), 0.7, 3, 7)


def test_homography_sampson_distance_known_answer():
    from lab.modules.epipolar import homography_sampson_distance

    x1 = np.array([[10.0, 20.0], [300.0, 40.0], [-5.0, 7.0]])
    move = np.array([[3.0, 4.0], [0.0, 1.0], [-2.0, 0.0]])
    # identity: the smallest move of the pair is half the displacement in each image, |d| / sqrt(2)
    np.testing.assert_allclose(homography_sampson_distance(np.eye(3), x1, x1 + move),
                               np.linalg.norm(move, axis=1) / np.sqrt(2), rtol=1e-12)
    H = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [1e-4, -2e-4, 1.0]])
    exact = cv2.perspectiveTransform(x1[None], H)[0]
    np.testing.assert_allclose(homography_sampson_distance(H, x1, exact), 0.0, atol=1e-9)
    # invariant to the scale of H; a small move in image 2 alone: close to the geometric (gold standard) error
    small = np.array([[0.03, -0.02]] * 3)
    d = homography_sampson_distance(H, x1, exact + small)
    np.testing.assert_allclose(homography_sampson_distance(-3.0 * H, x1, exact + small), d, rtol=1e-12)
    assert np.all(d < np.linalg.norm(small, axis=1)) and np.all(d > 0.5 * np.linalg.norm(small, axis=1))


def test_noise_sigma_is_robust_to_outliers_and_to_the_threshold():
    from lab.modules.epipolar import SIGMA_FLOOR_PX, noise_sigma

    rng = np.random.default_rng(3)
    for sigma in (0.3, 1.0, 2.0):
        inliers = np.abs(rng.normal(0, sigma, 2000))
        outliers = rng.uniform(8 * sigma, 100 * sigma, 900)  # 31 % outliers
        for start in (0.5, 1.0, 2.0):  # the RANSAC threshold it starts from does not matter
            residuals = np.concatenate([inliers, outliers])
            assert noise_sigma(residuals, start_px=start) == pytest.approx(sigma, rel=0.06)
    assert noise_sigma(np.zeros(100)) == SIGMA_FLOOR_PX


def test_zero_baseline_at_the_8point_step():
    exact = correspondences(baseline=0.0, noise_px=0.0, outlier_rate=0.0, seed=5)
    with pytest.raises(ZeroBaseline, match="share their centre"):
        estimate_fundamental_8point(exact.state["x1"], exact.state["x2"])
    session = open_session(PIPELINE, "correspondences",
                           {"baseline": 0.0, "noise_px": 0.0, "outlier_rate": 0.0})
    with pytest.raises(ZeroBaseline):
        session.run("estimate_fundamental_8point")
    assert "F" not in session.state and session.history[-1].status == "failed"


def test_degenerate_errors_are_lab_errors_that_name_the_input():
    """Each degenerate input raises a lab error (HTTP 4xx / CLI exit 2) naming the input and the problem."""
    cases = {"plane": ({"structure": "plane"}, CoplanarPoints, "one plane"),
             "line": ({"structure": "line"}, CollinearPoints, "one line"),
             "rotation": ({"baseline": 0.0}, ZeroBaseline, "zero baseline")}
    for name, (options, error, words) in cases.items():
        session = open_session(PIPELINE, "correspondences", dict(options, seed=8), seed=8)
        with pytest.raises(error, match=words) as raised:
            session.run("estimate_fundamental_ransac")
        assert isinstance(raised.value, LabError) and raised.value.field == "x1", name
    session = open_session(PIPELINE, "correspondences", {"num_points": 8, "outlier_rate": 0.0})
    session.put("x1", session.state["x1"][:7])
    session.put("x2", session.state["x2"][:7])
    with pytest.raises(TooFewMatches, match="7 matches"):
        session.run("estimate_fundamental_8point")


def test_zero_baseline_on_rendered_photos():
    session = open_session(PIPELINE, "rendered", {"width": 240, "height": 180, "baseline": 0.0})
    session.run("detect_features")
    session.run("match_features")
    with pytest.raises(ZeroBaseline):
        session.run("estimate_fundamental_ransac")


def test_small_baseline_warns():
    session = open_session(PIPELINE, "correspondences", {"baseline": 0.05, "seed": 6})
    records = session.run_until("refine_pose")
    assert "parallax" in records[-1].warnings[0]


@pytest.mark.parametrize("step", [estimate_fundamental_8point, estimate_fundamental_ransac])
def test_nans_are_refused(step, noisy):
    x1 = noisy.state["x1"].copy()
    x1[17, 1] = np.nan
    kwargs = {"rng": np.random.default_rng(0)} if step is estimate_fundamental_ransac else {}
    with pytest.raises(InvalidValue, match="NaN") as error:
        step(x1, noisy.state["x2"], **kwargs)
    assert error.value.field == "x1" and "row 17" in error.value.reason


def test_shapes_are_checked(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    with pytest.raises(InvalidValue, match="one per match"):
        estimate_fundamental_8point(x1, x2[:-1])
    with pytest.raises(InvalidValue, match=r"\(M, 2\)"):
        estimate_fundamental_8point(np.column_stack([x1, x1[:, :1]]), x2)
    with pytest.raises(InvalidValue, match="inliers"):
        recover_pose(np.eye(3), x1, x2, noisy.state["K1"], noisy.state["K2"], np.ones(3, dtype=bool))


def test_images_of_different_sizes_without_k(tmp_path):
    shutil.copy(SAMPLES / "leuvenA.jpg", tmp_path / "a.jpg")
    cv2.imwrite(str(tmp_path / "b.png"), cv2.resize(cv2.imread(str(SAMPLES / "leuvenB.jpg")), (600, 450)))
    session = open_session(PIPELINE, "photos", {"path": str(tmp_path)})
    session.run_until("estimate_fundamental_ransac")  # F needs no K
    with pytest.raises(MissingIntrinsics, match="different sizes"):
        session.run("estimate_essential")
    with pytest.raises(LabError):
        session.run("recover_pose")
    assert isinstance(MissingIntrinsics("K1", "x"), InvalidValue)
    assert issubclass(ZeroBaseline, DegenerateInput)
    assert issubclass(DegenerateInput, StepFailed)


# --- 1-2. features and matches ----------------------------------------------------------------------
def test_detect_features_is_opencvs_sift(leuven):
    keypoints = leuven.state["keypoints"]
    assert isinstance(keypoints, Points2D) and keypoints.image == "images"
    gray = np.clip(leuven.state["images"][0].gray() * 255 + 0.5, 0, 255).astype(np.uint8)
    found, descriptors = cv2.SIFT_create(nfeatures=4000).detectAndCompute(gray, None)
    first = keypoints.view == 0
    np.testing.assert_allclose(keypoints.xy[first], np.array([k.pt for k in found]) - SIFT_OFFSET_PX)
    np.testing.assert_array_equal(leuven.state["descriptors"][first], descriptors)
    assert leuven.metrics["detect_features"]["keypoints_image1"] == len(found)


def test_detect_features_finds_a_blob_at_its_true_pixel():
    """Gaussian blobs centred at known pixels (integer and not) are found there within 0.1 px; OpenCV alone
    reports them about SIFT_OFFSET_PX = 0.25 px right of and below."""
    from lab.core import Image, ImageSet

    yy, xx = np.mgrid[0:120, 0:160].astype(np.float64)
    centres = [(40.0, 50.0), (110.3, 70.6), (75.5, 30.25)]
    pixels = sum(np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 3.0**2)) for x, y in centres)
    image = Image(pixels.astype(np.float32))
    found = detect_features(ImageSet((image, image)), contrast_threshold=0.01)
    raw = np.array([k.pt for k in cv2.SIFT_create(contrastThreshold=0.01).detect(
        np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8), None)])
    for view in (0, 1):
        xy = found.keypoints.xy[found.keypoints.view == view]
        for centre in centres:
            assert np.linalg.norm(xy - centre, axis=1).min() < 0.1, (view, centre)
    for centre in centres:  # the bias being removed: OpenCV's own point is ~(0.25, 0.25) off
        offset = raw[np.argmin(np.linalg.norm(raw - centre, axis=1))] - centre
        np.testing.assert_allclose(offset, [SIFT_OFFSET_PX, SIFT_OFFSET_PX], atol=0.1)
    assert SIFT_OFFSET_PX == 0.25


def test_detect_features_controls_change_the_count(leuven):
    fewer = detect_features(leuven.state["images"], max_features=200)
    assert fewer.keypoints_image1 <= 205 and fewer.keypoints_image2 <= 205  # OpenCV keeps ties
    strict = detect_features(leuven.state["images"], contrast_threshold=0.12)
    assert strict.keypoints_image1 < leuven.metrics["detect_features"]["keypoints_image1"]
    with pytest.raises(InvalidValue, match="exactly two"):
        detect_features(type(leuven.state["images"])(leuven.state["images"].images[:1]))


def test_keypoint_locations_name_the_first_keypoint_at_each_pixel():
    xy = np.array([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0], [1.0, 2.0], [3.0, 4.0]])
    view = np.array([0, 0, 0, 1, 1])
    np.testing.assert_array_equal(keypoint_locations(Points2D(xy, view=view)), [0, 1, 0, 3, 4])
    assert keypoint_locations(Points2D(np.zeros((0, 2)), view=np.zeros(0, int))).shape == (0,)


def test_a_location_sift_repeats_is_matched_once():
    """Two keypoints at one pixel (two orientations) whose descriptors both match the two keypoints of one
    pixel in image 2 make one match, between the first keypoints at the two pixels."""
    rng = np.random.default_rng(3)
    d = rng.random((6, 128)).astype(np.float32)
    xy1 = np.array([[10.0, 10.0], [10.0, 10.0], [50.0, 60.0]])
    xy2 = xy1 + np.array([5.0, 0.0])
    keypoints = Points2D(np.concatenate([xy1, xy2]), view=np.repeat([0, 1], 3))
    descriptors = np.concatenate([d[:3], d[:3] + 0.01])
    found = match_features(keypoints, descriptors)
    np.testing.assert_array_equal(found.matches, [[0, 3], [2, 5]])


def test_matching_agrees_with_bf_matcher(leuven):
    keypoints, descriptors = leuven.state["keypoints"], leuven.state["descriptors"]
    d1, d2 = descriptors[keypoints.view == 0], descriptors[keypoints.view == 1]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    knn = matcher.knnMatch(d1, d2, k=2)
    back = {m.queryIdx: m.trainIdx for m in matcher.match(d2, d1)}
    expected = {(m.queryIdx, m.trainIdx) for m, n in knn if m.distance < 0.8 * n.distance
                and back[m.trainIdx] == m.queryIdx}
    offset = int(np.sum(keypoints.view == 0))
    matches = leuven.state["matches"]
    location = keypoint_locations(keypoints)  # a match is made once between two locations
    expected = {(int(location[a]), int(location[b + offset]) - offset) for a, b in expected}
    got = {(int(a), int(b) - offset) for a, b in matches}
    assert len(got ^ expected) <= 0.01 * len(expected)  # float ties aside, the same matches
    np.testing.assert_array_equal(leuven.state["x1"], keypoints.xy[matches[:, 0]])


def test_matching_controls(leuven):
    keypoints, descriptors = leuven.state["keypoints"], leuven.state["descriptors"]
    loose = match_features(keypoints, descriptors, ratio=1.0, mutual=False)
    assert loose.num_matches + loose.repeated == int(np.sum(keypoints.view == 0))
    assert loose.rejected_by_ratio == 0 and loose.repeated > 0  # SIFT repeats locations (orientations)
    mutual_only = match_features(keypoints, descriptors, ratio=1.0, mutual=True)
    assert mutual_only.num_matches < loose.num_matches
    assert (mutual_only.num_matches + mutual_only.repeated + mutual_only.rejected_by_mutual
            == loose.num_matches + loose.repeated)
    strict = match_features(keypoints, descriptors, ratio=0.6)
    assert strict.num_matches < leuven.metrics["match_features"]["num_matches"]


def test_matching_recovers_the_synthetic_matches(noisy):
    result = match_features(noisy.state["keypoints"], noisy.state["descriptors"])
    np.testing.assert_array_equal(result.matches, noisy.state["matches"])


def test_nearest_neighbours_known_answer():
    query = np.array([[0.0, 0.0], [10.0, 0.0]])
    train = np.array([[1.0, 0.0], [0.0, 3.0], [9.0, 0.0]])
    first, d1, d2, back = nearest_neighbours(query, train, chunk=1)
    np.testing.assert_array_equal(first, [0, 2])
    np.testing.assert_allclose(d1, [1.0, 1.0])
    np.testing.assert_allclose(d2, [3.0, 9.0])
    np.testing.assert_array_equal(back, [0, 0, 1])


def test_matching_without_keypoints_in_one_image(leuven):
    keypoints = leuven.state["keypoints"]
    only_first = keypoints.in_view(0)
    result = match_features(only_first, leuven.state["descriptors"][keypoints.view == 0])
    assert result.num_matches == 0 and result.x1.shape == (0, 2) and result.warnings


# --- 3. the 8-point algorithm -----------------------------------------------------------------------
def test_eight_point_exact_on_clean_data(clean):
    F = estimate_fundamental_8point(clean.state["x1"], clean.state["x2"])
    assert F.shape == (3, 3) and np.linalg.norm(F) == pytest.approx(1.0)
    np.testing.assert_allclose(unit(F), unit(clean.truth["F"]), atol=1e-8)
    assert np.linalg.svd(F, compute_uv=False)[2] < 1e-12


def test_eight_point_matches_opencv_fm_8point():
    loaded = correspondences(outlier_rate=0.0, noise_px=1.0, seed=13)
    x1, x2 = loaded.state["x1"], loaded.state["x2"]
    F_cv, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
    np.testing.assert_allclose(unit(estimate_fundamental_8point(x1, x2)), unit(F_cv), atol=1e-7)


def test_normalization_matters_on_noisy_data():
    errors = {True: [], False: []}
    for seed in range(3):
        loaded = correspondences(outlier_rate=0.0, noise_px=1.0, seed=20 + seed)
        truth = loaded.truth
        for normalize in (True, False):
            F = estimate_fundamental_8point(loaded.state["x1"], loaded.state["x2"], normalize=normalize)
            exact = sampson_distance(F, truth["x1_exact"], truth["x2_exact"])
            errors[normalize].append(np.sqrt(np.mean(exact**2)))
    assert np.mean(errors[False]) > 2 * np.mean(errors[True])


def test_normalized_eight_point_is_invariant_to_image_similarities():
    """Move and scale both images: the normalized F maps back to the same epipolar geometry, the plain
    one does not."""
    loaded = correspondences(outlier_rate=0.0, noise_px=1.0, seed=14)
    x1, x2, truth = loaded.state["x1"], loaded.state["x2"], loaded.truth
    S1 = np.array([[2.0, 0.0, 1000.0], [0.0, 2.0, -500.0], [0.0, 0.0, 1.0]])
    S2 = np.array([[0.5, 0.0, 300.0], [0.0, 0.5, 200.0], [0.0, 0.0, 1.0]])
    move = lambda S, x: x @ S[:2, :2].T + S[:2, 2]  # noqa: E731
    change = {}
    for normalize in (True, False):
        F = estimate_fundamental_8point(x1, x2, normalize=normalize)
        F_back = S2.T @ estimate_fundamental_8point(move(S1, x1), move(S2, x2), normalize=normalize) @ S1
        before = sampson_distance(F, truth["x1_exact"], truth["x2_exact"])
        after = sampson_distance(F_back, truth["x1_exact"], truth["x2_exact"])
        change[normalize] = np.abs(after - before).max() / before.max()
    assert change[True] < 1e-8
    assert change[False] > 1e-3


def test_enforce_rank2_is_the_nearest_singular_matrix():
    M = np.random.default_rng(0).normal(size=(3, 3))
    F = enforce_rank2(M)
    U, s, Vt = np.linalg.svd(M)
    np.testing.assert_allclose(F, U[:, :2] * s[:2] @ Vt[:2])
    np.testing.assert_allclose(enforce_rank2(F), F, atol=1e-12)
    assert enforce_rank2(np.stack([M, 2 * M])).shape == (2, 3, 3)


def test_eight_point_batched_equals_one_by_one(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    samples = np.random.default_rng(1).choice(len(x1), (5, 8))
    batched = eight_point(x1[samples], x2[samples])
    for k in range(5):
        one = eight_point(x1[samples[k]], x2[samples[k]])
        np.testing.assert_allclose(unit(batched[k]), unit(one), atol=1e-9)


# --- 4. RANSAC --------------------------------------------------------------------------------------
def test_ransac_finds_the_inliers(corr_session):
    metrics = corr_session.metrics["estimate_fundamental_ransac"]
    assert metrics["inlier_precision"] >= 0.99 and metrics["inlier_recall"] >= 0.9
    assert metrics["rank_of_F"] == 2
    assert metrics["f_error"] < 0.01
    assert 0.3 < metrics["sampson_rms_px"] < 0.6  # the 0.5 px noise, measured
    trace = corr_session.state["ransac_trace"]
    assert isinstance(trace, Curve) and trace.labels == ("best inlier count", "samples needed (N)")
    assert np.all(np.diff(trace.y[0]) >= 0) and np.all(np.diff(trace.y[1]) <= 0)
    assert trace.x[-1] == metrics["iterations"]


def test_ransac_adaptive_count_follows_the_formula(noisy):
    result = estimate_fundamental_ransac(noisy.state["x1"], noisy.state["x2"], rng=np.random.default_rng(0))
    bound = np.log(1 - 0.99) / np.log(1 - result.inlier_ratio**8)
    assert result.iterations <= max(bound, 8) + 256  # stops within one batch of the bound
    fewer = estimate_fundamental_ransac(noisy.state["x1"], noisy.state["x2"], max_iterations=5,
                                        rng=np.random.default_rng(0))
    assert fewer.iterations <= 5


def test_ransac_is_reproducible_and_seeded(noisy):
    a, b = (estimate_fundamental_ransac(noisy.state["x1"], noisy.state["x2"], rng=np.random.default_rng(7))
            for _ in range(2))
    np.testing.assert_array_equal(a.F, b.F)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_ransac_agrees_with_opencv_on_synthetic_data(noisy):
    x1, x2, outliers = noisy.state["x1"], noisy.state["x2"], noisy.truth["outliers"]
    _, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.99)
    mask = mask.ravel() > 0
    ours = estimate_fundamental_ransac(x1, x2, error="epipolar", rng=np.random.default_rng(0))
    assert (ours.inliers & mask).sum() >= 0.9 * mask.sum()  # OpenCV's inliers are (nearly all) ours
    assert ours.num_inliers >= mask.sum()  # and we find more of the right matches
    assert not np.any(ours.inliers & outliers)


def test_ransac_threshold_and_error_controls(noisy):
    x1, x2 = noisy.state["x1"], noisy.state["x2"]
    tight = estimate_fundamental_ransac(x1, x2, threshold_px=0.3, rng=np.random.default_rng(0))
    loose = estimate_fundamental_ransac(x1, x2, threshold_px=2.0, rng=np.random.default_rng(0))
    epipolar = estimate_fundamental_ransac(x1, x2, error="epipolar", rng=np.random.default_rng(0))
    sampson = estimate_fundamental_ransac(x1, x2, error="sampson", rng=np.random.default_rng(0))
    assert tight.num_inliers < sampson.num_inliers < loose.num_inliers
    assert epipolar.num_inliers < sampson.num_inliers  # max(d1, d2) is about sqrt(2) x the Sampson distance
    d1, d2 = epipolar_distances(epipolar.F, x1, x2)
    np.testing.assert_array_equal(epipolar.inliers, np.maximum(d1, d2) <= 1.0)
    np.testing.assert_array_equal(sampson.inliers, sampson_distance(sampson.F, x1, x2) <= 1.0)


def test_ransac_refinement_lowers_the_sampson_error_of_its_inliers():
    for seed in range(5):
        loaded = correspondences(seed=30 + seed)
        x1, x2 = loaded.state["x1"], loaded.state["x2"]
        plain = estimate_fundamental_ransac(x1, x2, refine=False, rng=np.random.default_rng(0))
        a, b = x1[plain.inliers], x2[plain.inliers]
        refit = sampson_refit(plain.F, x1, x2, plain.inliers)
        assert np.sum(sampson_distance(refit, a, b) ** 2) < np.sum(sampson_distance(plain.F, a, b) ** 2)
        assert np.linalg.svd(refit, compute_uv=False)[2] < 1e-12
        assert np.linalg.norm(refit) == pytest.approx(1.0)


# --- distances, lines, epipoles ---------------------------------------------------------------------
def test_sampson_distance_is_the_root_of_cv2_sampson_distance(noisy):
    F, x1, x2 = noisy.truth["F"], noisy.state["x1"][:50], noisy.state["x2"][:50]
    ours = sampson_distance(F, x1, x2)
    theirs = [cv2.sampsonDistance(np.append(a, 1.0), np.append(b, 1.0), F)
              for a, b in zip(x1, x2, strict=True)]
    np.testing.assert_allclose(ours**2, theirs, rtol=1e-9)
    assert sampson_distance(np.stack([F, 2 * F]), x1, x2).shape == (2, 50)
    np.testing.assert_allclose(sampson_distance(3 * F, x1, x2), ours)  # scale-free


def test_point_to_line_distances_known_answer():
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # a pure x translation: y2 = y1
    x1 = np.array([[10.0, 5.0], [3.0, -2.0]])
    x2 = np.array([[50.0, 8.0], [7.0, -2.0]])
    d1, d2 = epipolar_distances(F, x1, x2)
    np.testing.assert_allclose(d1, [3.0, 0.0])
    np.testing.assert_allclose(d2, [3.0, 0.0])
    np.testing.assert_allclose(symmetric_epipolar_distance(F, x1, x2), [np.sqrt(18.0), 0.0])
    np.testing.assert_allclose(sampson_distance(F, x1, x2), [3.0 / np.sqrt(2.0), 0.0])


def test_epipolar_lines_match_compute_correspond_epilines(noisy):
    F, x1, x2 = noisy.truth["F"], noisy.state["x1"], noisy.state["x2"]
    for image, points in ((1, x1), (2, x2)):
        theirs = cv2.computeCorrespondEpilines(points.reshape(-1, 1, 2), image, F).reshape(-1, 3)
        np.testing.assert_allclose(epipolar_lines(F, points, image=image), theirs, atol=1e-6)
    lines = epipolar_lines(F, noisy.truth["x1_exact"], image=1)
    signed = np.sum(lines[:, :2] * noisy.truth["x2_exact"], axis=1) + lines[:, 2]
    np.testing.assert_allclose(signed, 0, atol=1e-9)


def test_epipoles_are_the_images_of_the_camera_centres(clean):
    truth = clean.truth
    e1, e2 = epipoles(truth["F"])
    np.testing.assert_allclose(truth["F"] @ e1, 0, atol=1e-12)
    np.testing.assert_allclose(truth["F"].T @ e2, 0, atol=1e-12)
    centre2 = -truth["R"].T @ truth["t"]  # camera 2's centre in camera 1's frame
    seen = truth["K1"] @ centre2
    np.testing.assert_allclose(e1[:2] / e1[2], seen[:2] / seen[2], rtol=1e-8)
    seen2 = truth["K2"] @ truth["t"]  # camera 1's centre in camera 2
    np.testing.assert_allclose(e2[:2] / e2[2], seen2[:2] / seen2[2], rtol=1e-8)
    sideways = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(np.abs(epipoles(sideways)), [[1, 0, 0], [1, 0, 0]], atol=1e-12)  # at infinity


def test_clip_lines_known_answer():
    lines = np.array([[0.0, 1.0, -10.0], [1.0, 0.0, -5.0], [1.0, 1.0, -1000.0], [1.0, -1.0, 0.0]])
    start, end, valid = clip_lines(lines, 100, 50)
    np.testing.assert_array_equal(valid, [True, True, False, True])
    np.testing.assert_allclose(sorted([start[0][0], end[0][0]]), [0, 99])
    np.testing.assert_allclose([start[0][1], end[0][1]], [10, 10])
    np.testing.assert_allclose(sorted([start[1][1], end[1][1]]), [0, 49])
    np.testing.assert_allclose(sorted([tuple(start[3]), tuple(end[3])]), [(0, 0), (49, 49)])


def test_epipolar_lines_step_values(corr_session):
    state = corr_session.state
    lines, points = state["epipolar_lines"], state["line_points"]
    assert isinstance(lines, Segments2D) and isinstance(points, Points2D)
    assert len(points) == 2 * 30 and corr_session.metrics["compute_epipolar_lines"]["lines_drawn"] == 30
    width, height = state["images"][0].width, state["images"][0].height
    for ends in (lines.start, lines.end):
        assert np.all((ends >= -1e-6) & (ends <= [width - 1 + 1e-6, height - 1 + 1e-6]))
    # each point of image 2 lies near the line of its partner, drawn in image 2 (view 1)
    in_two = lines.view == 1
    direction = lines.end[in_two] - lines.start[in_two]
    offset = points.xy[30:][: int(in_two.sum())] - lines.start[in_two]
    cross = direction[:, 0] * offset[:, 1] - direction[:, 1] * offset[:, 0]
    distance = np.abs(cross) / np.linalg.norm(direction, axis=1)
    assert np.median(distance) < 1.0
    assert state["epipoles"].shape == (2, 3)
    np.testing.assert_allclose(np.linalg.norm(state["epipoles"], axis=1), 1.0)
    metrics = corr_session.metrics["compute_epipolar_lines"]
    assert metrics["symmetric_rms_px"] > metrics["sampson_rms_px"] > 0


def test_epipolar_lines_of_an_arbitrary_matrix_report_its_rank(corr_session):
    state = corr_session.state
    result = compute_epipolar_lines(np.eye(3) + 0.01, state["x1"], state["x2"], state["images"], None,
                                    num_lines=5)
    assert result.rank_of_F == 3 and result.lines_drawn == 5


# --- 6-7. E, its four poses, cheirality -------------------------------------------------------------
def test_essential_from_exact_f(clean):
    E = estimate_essential(clean.truth["F"], clean.state["images"], clean.state["K1"], clean.state["K2"])
    np.testing.assert_allclose(np.linalg.svd(E, compute_uv=False), [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(unit(E), unit(clean.truth["E"]), atol=1e-9)


def test_essential_projection_of_a_noisy_f(corr_session):
    E = corr_session.state["E"]
    np.testing.assert_allclose(np.linalg.svd(E, compute_uv=False), [1.0, 1.0, 0.0], atol=1e-12)
    assert 0.95 < corr_session.metrics["estimate_essential"]["essential_singular_ratio"] <= 1.0
    assert corr_session.metrics["estimate_essential"]["e_error"] < 0.02


def test_essential_needs_k(corr_session):
    with pytest.raises(MissingIntrinsics, match="no camera matrix"):
        estimate_essential(corr_session.state["F"], corr_session.state["images"], None, None)


def test_decomposition_matches_cv2_decompose_essential_mat(corr_session):
    E = corr_session.state["E"]
    candidates = decompose_essential(E)
    assert candidates.shape == (4, 3, 4)
    R1, R2, t = cv2.decomposeEssentialMat(E)
    expected = [np.column_stack([R, s * t.ravel()]) for s in (1, -1) for R in (R1, R2)]
    for want in expected:
        assert min(np.abs(c - want).max() for c in candidates) < 1e-9
    for c in candidates:
        np.testing.assert_allclose(c[:, :3] @ c[:, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(c[:, :3]) == pytest.approx(1.0)
        assert np.linalg.norm(c[:, 3]) == pytest.approx(1.0)
    assert corr_session.metrics["decompose_essential"]["best_candidate_rotation_error_deg"] < 0.5


def test_recover_pose_matches_cv2_recover_pose(corr_session):
    state = corr_session.state
    E, x1, x2, K, inliers = state["E"], state["x1"], state["x2"], state["K1"], state["inliers"]
    pose = recover_pose(E, x1, x2, K, K, inliers)
    _, R, t, _ = cv2.recoverPose(E, x1, x2, K, mask=inliers.astype(np.uint8).reshape(-1, 1))
    np.testing.assert_allclose(pose[:, :3], R, atol=1e-9)
    np.testing.assert_allclose(pose[:, 3], t.ravel(), atol=1e-9)
    np.testing.assert_array_equal(state["pose"], pose)


def test_recover_pose_reads_the_candidates_and_can_be_told_which(corr_session):
    state = corr_session.state
    args = (state["x1"], state["x2"], state["K1"], state["K2"], state["inliers"])
    pose = recover_pose(state["candidates"], *args)
    np.testing.assert_array_equal(pose, recover_pose(state["E"], *args))  # an E is decomposed first
    chosen = [i for i, c in enumerate(state["candidates"]) if np.array_equal(c, pose)]
    assert len(chosen) == 1
    for index, name in enumerate(CANDIDATE_NAMES):
        np.testing.assert_array_equal(recover_pose(state["candidates"], *args, candidate=name),
                                      state["candidates"][index])
    mirror = CANDIDATE_NAMES[(chosen[0] + 2) % 4]  # (R, -t): every point behind both cameras
    session = open_session(PIPELINE, "correspondences", {"seed": 3}, seed=3)
    session.run_until("recover_pose", {"recover_pose": {"candidate": mirror}})
    session.run("refine_pose")
    assert session.metrics["recover_pose"]["translation_direction_error_deg"] > 179
    # Sampson cannot tell t from -t
    assert session.metrics["refine_pose"]["translation_direction_error_deg"] > 179
    with pytest.raises(InvalidValue, match=r"\(4, 3, 4\)"):
        recover_pose(state["candidates"][:3], *args)
    with pytest.raises(InvalidControl):
        session.run("recover_pose", {"candidate": "R3 t"})


def test_recover_pose_exact(clean):
    E = clean.truth["E"]
    pose = recover_pose(E, clean.state["x1"], clean.state["x2"], clean.state["K1"], clean.state["K2"])
    assert rotation_angle_deg(pose[:, :3], clean.truth["R"]) < 1e-6
    np.testing.assert_allclose(pose[:, 3], clean.truth["t"] / np.linalg.norm(clean.truth["t"]), atol=1e-9)


def test_refine_pose_from_a_perturbed_start(clean):
    truth = clean.truth
    from lab.geometry.rotations import rotvec_to_matrix

    start = np.column_stack([rotvec_to_matrix([0.01, -0.02, 0.005]) @ truth["R"],
                             truth["t"] / np.linalg.norm(truth["t"]) + [0.05, -0.03, 0.02]])
    start[:, 3] /= np.linalg.norm(start[:, 3])
    refined = refine_pose(start, clean.state["x1"], clean.state["x2"], clean.state["K1"], clean.state["K2"])
    assert rotation_angle_deg(refined.R, truth["R"]) < 1e-5
    assert angle_deg(refined.t, truth["t"]) < 1e-4
    assert refined.sampson_rms_px < 1e-6 < refined.sampson_rms_start_px
    kept = refine_pose(start, clean.state["x1"], clean.state["x2"], clean.state["K1"], clean.state["K2"],
                       iterations=0)
    np.testing.assert_allclose(kept.R, start[:, :3])


def test_refine_pose_improves_the_pipeline(corr_session):
    metrics = corr_session.metrics
    assert metrics["refine_pose"]["sampson_rms_px"] <= metrics["refine_pose"]["sampson_rms_start_px"]
    assert metrics["refine_pose"]["rotation_error_deg"] < 0.2
    assert metrics["refine_pose"]["translation_direction_error_deg"] < 1.0


# --- 8. triangulation -------------------------------------------------------------------------------
def test_triangulate_matches_cv2_triangulate_points(corr_session):
    state = corr_session.state
    K, R, t, inliers = state["K1"], state["R"], state["t"], state["inliers"]
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K @ np.column_stack([R, t])
    homogeneous = cv2.triangulatePoints(P1, P2, state["x1"][inliers].T, state["x2"][inliers].T)
    np.testing.assert_allclose(state["points3d_dlt"], (homogeneous[:3] / homogeneous[3]).T, rtol=1e-6,
                               atol=1e-9)
    direct = triangulate(state["x1"], state["x2"], R, t, K, K, inliers)
    np.testing.assert_array_equal(direct, state["points3d_dlt"])


def test_refine_points_values(corr_session):
    state, metrics = corr_session.state, corr_session.metrics["refine_points"]
    cloud, cameras, residuals = state["points3d"], state["cameras"], state["residuals"]
    assert isinstance(cloud, PointCloud) and len(cloud) == metrics["points"] == int(state["inliers"].sum())
    assert isinstance(cameras, Cameras) and len(cameras) == 2 and cameras.image == "images"
    np.testing.assert_allclose(cameras.centers[0], 0, atol=1e-12)
    assert np.linalg.norm(cameras.centers[1]) == pytest.approx(1.0)
    assert isinstance(residuals, Segments2D) and len(residuals) == 2 * len(cloud)
    assert metrics["reprojection_rms_px"] <= metrics["reprojection_rms_dlt_px"]
    assert metrics["reprojection_rms_px"] < 0.5 and metrics["points_behind"] == 0
    assert metrics["point_rel_error_median"] < 0.02
    # colours come from image 1 at x1 (the synthetic dots)
    x1 = state["x1"][state["inliers"]]
    image = state["images"][0].pixels
    rows, cols = np.round(x1[:, 1]).astype(int), np.round(x1[:, 0]).astype(int)
    np.testing.assert_allclose(cloud.colors, image[rows, cols], atol=1e-6)
    assert isinstance(state["reprojection_cost"], Curve)


def test_refine_points_checks_its_inputs(corr_session):
    state = corr_session.state
    with pytest.raises(InvalidValue, match="one point per inlier"):
        refine_points(state["points3d_dlt"][:-1], state["x1"], state["x2"], state["R"], state["t"],
                      state["K1"], state["K2"], state["images"], state["inliers"])
    with pytest.raises(InvalidValue, match="rotation"):
        triangulate(state["x1"], state["x2"], 2 * state["R"], state["t"], state["K1"], state["K2"])
