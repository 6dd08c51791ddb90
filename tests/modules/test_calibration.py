"""The calibration module: every step against exact truth and against OpenCV, run through sessions.

Datasets are built once per module: the default synthetic set (15 views, 0.2 px corner noise) and
OpenCV's 13 sample photos (``../shared/data/opencv-samples/left*.jpg``).
"""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core import (Cameras, Curve, Image, ImageSet, InvalidControl, InvalidValue, LabError, Mesh, Points2D,
                      MissingInput, Progress, Segments2D, StepFailed, open_session)
from lab.geometry.camera import optimal_new_camera_matrix, project_points, undistort_pixels, undistortion_map
from lab.geometry.homogeneous import apply_homography
from lab.geometry.rotations import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix
from lab.data.exports import read_opencv_calibration
from lab.modules import get_pipeline
from lab.modules.calibration import (PIPELINE, Checkerboard, detect_corners, estimate_distortion,
                                     estimate_extrinsics, estimate_homographies, estimate_intrinsics,
                                     refine_calibration, refine_corners, synthetic, undistort_image)

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "opencv-samples"
STEPS = [spec.name for spec in PIPELINE.steps]
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)


def run(generator):
    """Drive a generator step to its result, collecting its progress."""
    progress = []
    try:
        while True:
            progress.append(next(generator))
    except StopIteration as stop:
        return stop.value, progress


def opencv_calibration(corners: Points2D, board_points: np.ndarray, size=(640, 480), flags=0):
    views = np.unique(corners.view)
    object_points = [board_points[corners.ids[corners.view == v]].astype(np.float32) for v in views]
    image_points = [corners.xy[corners.view == v].astype(np.float32) for v in views]
    return cv2.calibrateCameraExtended(object_points, image_points, size, None, None, flags=flags)


@pytest.fixture(scope="module")
def synthetic_session():
    session = open_session(PIPELINE, seed=0)  # the default dataset: synthetic, 15 views, noise 0.2 px
    session.run_until("refine_calibration")
    return session


@pytest.fixture(scope="module")
def real_session():
    session = open_session(PIPELINE, "folder", {"path": str(SAMPLES), "pattern": "left*.jpg"})
    session.run_until("refine_calibration")
    return session


@pytest.fixture(scope="module")
def real_opencv(real_session):
    return opencv_calibration(real_session.state["corners"], real_session.state["board_points"])


@pytest.fixture(scope="module")
def exact(synthetic_session):
    """Exact homographies, poses and projections of the synthetic truth (no noise, no image)."""
    truth = synthetic_session.truth
    K, R, t = truth["K"], truth["rotations"], truth["translations"]
    H = K @ np.stack([R[:, :, 0], R[:, :, 1], t], axis=-1)
    board_points = Checkerboard().object_points()
    n, v = len(board_points), len(R)
    ideal = project_points(board_points[None], K, None, R, t).reshape(-1, 2)
    corners = Points2D(ideal, view=np.repeat(np.arange(v), n), ids=np.tile(np.arange(n), v))
    return dict(K=K, R=R, t=t, H=H / H[:, 2:3, 2:3], board_points=board_points, corners=corners)


# --- the pipeline as a whole ------------------------------------------------------------------------
def test_pipeline_is_registered_with_the_contract_steps():
    assert get_pipeline("calibration") is PIPELINE
    assert STEPS == ["detect_corners", "estimate_homographies", "estimate_intrinsics", "estimate_extrinsics",
                     "estimate_distortion", "refine_calibration", "undistort_image"]
    assert [d.name for d in PIPELINE.datasets] == ["synthetic", "folder"]
    assert PIPELINE.step("refine_calibration").is_generator
    assert PIPELINE.step("estimate_homographies").writes == ("homographies",)
    assert PIPELINE.step("detect_corners").writes == ("corners", "board_points", "views")


def test_done_when_synthetic_recovers_the_truth(synthetic_session):
    """Default synthetic data (noise 0.2 px): fx, fy, cx, cy within 0.2 %, k1 within 0.01."""
    metrics = synthetic_session.metrics["refine_calibration"]
    for name in ("fx", "fy", "cx", "cy"):
        assert metrics[f"{name}_rel_error"] < 0.002, name
    assert metrics["k1_abs_error"] < 0.01
    assert metrics["rotation_error_deg"] < 0.2
    assert metrics["truth_rms_px"] < 0.15  # the fitted model lies closer to the exact corners than the noise
    assert 0.2 < metrics["rms_px"] < 0.35  # the residual is the corner noise, sqrt(2) x 0.2 px
    status = synthetic_session.step_status()
    assert all(status[name] == "done" for name in STEPS[:6])


def test_done_when_real_photos_match_opencv(real_session, real_opencv):
    """13 real photos: RMS within 1 % of OpenCV's on the same corners, fx within 0.2 %."""
    rms, K_cv = real_opencv[0], real_opencv[1]
    metrics = real_session.metrics["refine_calibration"]
    assert metrics["rms_px"] == pytest.approx(rms, rel=0.01)
    assert metrics["fx"] == pytest.approx(K_cv[0, 0], rel=0.002)
    assert metrics["fy"] == pytest.approx(K_cv[1, 1], rel=0.002)
    assert real_session.metrics["detect_corners"] == {"views_found": 13, "views_total": 13}


def test_history_records_every_step(synthetic_session):
    steps = [record.step for record in synthetic_session.history if record.status == "ok"]
    assert steps[:6] == STEPS[:6]
    assert "transfer_rms_px" in synthetic_session.metrics["estimate_homographies"]
    assert "fx_rel_error" in synthetic_session.metrics["estimate_intrinsics"]
    assert "rotation_error_deg" in synthetic_session.metrics["estimate_extrinsics"]
    assert "k1_abs_error" in synthetic_session.metrics["estimate_distortion"]


def test_real_data_has_no_truth_metrics(real_session):
    assert "fx_rel_error" not in real_session.metrics["refine_calibration"]
    assert real_session.metrics["estimate_intrinsics"] == {}
    assert real_session.metrics["estimate_homographies"]["transfer_rms_px"] > 0


def test_folder_names_the_photos_without_a_board(tmp_path):
    for name in ("left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg", "leuvenA.jpg"):
        shutil.copy(SAMPLES / name, tmp_path / name)
    session = open_session(PIPELINE, "folder", {"path": str(tmp_path)})
    record = session.run("detect_corners")
    assert record.warnings == ("leuvenA.jpg: no 9x6 board found",)
    assert record.metrics == {"views_found": 4, "views_total": 5}
    np.testing.assert_array_equal(session.state["views"], [0, 1, 2, 3])
    session.run_until("refine_calibration")
    photos = ("left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg")
    assert session.state["per_view_rms"].categories == photos


def test_a_students_homographies_run_through_the_rest(real_session):
    """Any step can be replaced: a findHomography-based estimate feeds the closed form."""

    def student(corners, board_points, *, normalize=True):
        out = []
        for v in np.unique(corners.view):
            keep = corners.view == v
            H, _ = cv2.findHomography(board_points[corners.ids[keep], :2], corners.xy[keep], 0)
            out.append(H / H[2, 2])
        return np.array(out)

    session = open_session(PIPELINE, "folder", {"path": str(SAMPLES), "pattern": "left0[1-6].jpg"})
    session.run("detect_corners")
    assert session.run("estimate_homographies", override=student).replaced
    session.run("estimate_intrinsics")
    assert session.state["K_init"][0, 0] == pytest.approx(real_session.state["K"][0, 0], rel=0.1)


def test_a_failed_step_leaves_the_state_alone(real_session):
    session = open_session(PIPELINE, "folder", {"path": str(SAMPLES), "pattern": "left01.jpg"})
    session.run("detect_corners")
    session.run("estimate_homographies")
    with pytest.raises(LabError):
        session.run("estimate_intrinsics")  # one view is not enough
    assert "K_init" not in session.state and session.history[-1].status == "failed"


# --- 1. detect_corners ----------------------------------------------------------------------------
def test_detect_corners_on_synthetic_matches_the_truth(synthetic_session):
    corners, truth = synthetic_session.state["corners"], synthetic_session.truth["corners"]
    assert corners.image == "images" and len(corners) == 15 * 54
    np.testing.assert_array_equal(synthetic_session.state["views"], np.arange(15))
    assert synthetic_session.state["board_points"].shape == (54, 3)
    errors = corners.xy - truth.xy  # same order: view by view, ids 0..53
    np.testing.assert_array_equal(corners.ids, truth.ids)
    assert np.sqrt(np.mean(errors**2)) < 0.3  # the 0.2 px corner noise plus a little detection error


def test_detect_corners_orders_the_board_the_same_way_when_the_photo_is_turned(synthetic_session):
    images, board = synthetic_session.state["images"], synthetic_session.state["board"]
    turned = ImageSet(tuple(Image(np.ascontiguousarray(im.pixels[::-1, ::-1]), im.name)
                            for im in images.images[:3]))
    result = detect_corners(turned, board)
    h, w = images[0].height, images[0].width
    expected = np.array([w - 1, h - 1]) - synthetic_session.truth["corners"].xy[: 3 * 54]
    assert np.abs(result.corners.xy - expected).max() < 1.5  # corner 0 is the same board corner


def test_subpixel_refinement_improves_the_corners():
    clean = synthetic(num_views=3, noise_px=0.0)  # no corner noise: what is left is detection error
    images, board, truth = clean.state["images"], clean.state["board"], clean.truth["corners"].xy
    coarse = detect_corners(images, board, subpixel=False).corners.xy
    fine = detect_corners(images, board, subpixel=True).corners.xy
    assert np.sqrt(np.mean((fine - truth) ** 2)) < 0.6 * np.sqrt(np.mean((coarse - truth) ** 2))
    assert np.sqrt(np.mean((fine - truth) ** 2)) < 0.05


def test_detect_corners_errors():
    board = Checkerboard()
    blank = ImageSet((Image(np.full((60, 80), 0.5, dtype=np.float32), "blank.png"),))
    with pytest.raises(StepFailed, match="no board"):
        detect_corners(blank, board)
    photo = Image(cv2.imread(str(SAMPLES / "left01.jpg"), cv2.IMREAD_GRAYSCALE), "left01.jpg")
    larger = Image(cv2.resize(photo.pixels, (800, 600)), "larger.jpg")
    with pytest.raises(InvalidValue, match="same size"):
        detect_corners(ImageSet((photo, larger)), board)
    with pytest.raises(InvalidValue):
        detect_corners(ImageSet(()), board)


def test_refine_corners_matches_cv2_corner_subpix(real_session):
    """The hand-written Förstner iteration against cv2.cornerSubPix on real photos."""
    images = real_session.state["images"]
    grays = [images[i].gray() for i in range(3)]
    starts, views = [], []
    for index, gray in enumerate(grays):
        found, xy = cv2.findChessboardCorners(np.clip(gray * 255 + 0.5, 0, 255).astype(np.uint8), (9, 6))
        assert found
        starts.append(xy.reshape(-1, 2))
        views.append(np.full(54, index))
    start = np.concatenate(starts)
    for window in (3, 5, 8):
        ours = refine_corners(np.stack(grays), start, np.concatenate(views), window=window)
        expected = np.concatenate([
            cv2.cornerSubPix(g, s.astype(np.float32).reshape(-1, 1, 2).copy(), (window, window), (-1, -1),
                             SUBPIX_CRITERIA).reshape(-1, 2)
            for g, s in zip(grays, starts, strict=True)])
        assert np.abs(ours - expected).max() < 5e-3, window


def test_refine_corners_converges_to_a_known_corner():
    """A checker corner at (20.3, 19.6), area-sampled (20 x 20 samples per pixel) and blurred."""
    corner = np.array([20.3, 19.6])
    offsets = (np.arange(20) + 0.5) / 20 - 0.5
    fine = np.arange(41)[:, None] + offsets[None, :]  # (pixel, sample) coordinates along one axis
    above_x = (fine > corner[0]).astype(np.float32)  # (41, 20)
    above_y = (fine > corner[1]).astype(np.float32)
    # mean over the pixel's samples of (x above) xor (y above)
    fx, fy = above_x.mean(axis=1), above_y.mean(axis=1)
    image = (fy[:, None] * (1 - fx[None, :]) + (1 - fy[:, None]) * fx[None, :]).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    start = np.array([[21.4, 18.7], [19.5, 20.5]])
    found = refine_corners(image, start, window=5)
    np.testing.assert_allclose(found, np.repeat(corner[None], 2, axis=0), atol=0.05)  # the method's own bias
    expected = cv2.cornerSubPix(image, start.astype(np.float32)[:, None].copy(), (5, 5), (-1, -1),
                                SUBPIX_CRITERIA)
    np.testing.assert_allclose(found, expected[:, 0], atol=2e-3)


def test_refine_corners_rejects_bad_input():
    with pytest.raises(InvalidValue):
        refine_corners(np.zeros(5), np.zeros((1, 2)))
    with pytest.raises(InvalidValue):
        refine_corners(np.zeros((10, 10)), np.zeros((2, 2)), view=np.array([0, 3]))


# --- 2. estimate_homographies -----------------------------------------------------------------------
def test_homographies_known_answer(exact):
    H = estimate_homographies(exact["corners"], exact["board_points"])
    assert H.shape == (15, 3, 3)
    np.testing.assert_allclose(H[:, 2, 2], 1.0)
    np.testing.assert_allclose(H, exact["H"], rtol=1e-7, atol=1e-7 * np.abs(exact["H"]).max())


def test_homographies_match_cv2_find_homography(real_session):
    corners, board_points = real_session.state["corners"], real_session.state["board_points"]
    ours = real_session.state["homographies"]
    for m, view in enumerate(real_session.state["views"]):
        keep = corners.view == view
        src, dst = board_points[corners.ids[keep], :2], corners.xy[keep]
        H_cv, _ = cv2.findHomography(src, dst, 0)  # least squares, refined on the geometric error
        err_ours = np.sqrt(np.mean(np.sum((apply_homography(ours[m], src) - dst) ** 2, axis=1)))
        err_cv = np.sqrt(np.mean(np.sum((apply_homography(H_cv, src) - dst) ** 2, axis=1)))
        assert err_ours == pytest.approx(err_cv, rel=0.05)


def test_homographies_do_not_depend_on_corner_order_or_view_numbers(exact):
    corners = exact["corners"]
    order = np.random.default_rng(0).permutation(len(corners))
    shuffled = Points2D(corners.xy[order], view=corners.view[order] * 3 + 10, ids=corners.ids[order])
    np.testing.assert_allclose(estimate_homographies(shuffled, exact["board_points"]),
                               estimate_homographies(corners, exact["board_points"]), rtol=1e-9, atol=1e-6)


def test_homographies_of_views_with_different_point_counts(exact):
    corners = exact["corners"]
    keep = ~((corners.view == 1) & (corners.ids >= 20))  # view 1 keeps only 20 corners
    partial = Points2D(corners.xy[keep], view=corners.view[keep], ids=corners.ids[keep])
    H = estimate_homographies(partial, exact["board_points"])
    np.testing.assert_allclose(H[:3], exact["H"][:3], rtol=1e-7, atol=1e-7 * np.abs(exact["H"]).max())


def test_normalization_makes_the_dlt_independent_of_the_image_coordinates(real_session):
    """H&Z 4.4.2: move the image origin and scale, and only the normalized DLT follows exactly."""
    corners, board_points = real_session.state["corners"], real_session.state["board_points"]
    S = np.array([[10.0, 0.0, 5000.0], [0.0, 10.0, -3000.0], [0.0, 0.0, 1.0]])
    moved = Points2D(apply_homography(S, corners.xy), view=corners.view, ids=corners.ids)
    src = board_points[:, :2]
    for normalize, tolerance in ((True, 1e-8), (False, None)):
        H = estimate_homographies(corners, board_points, normalize=normalize)
        back = np.linalg.solve(S, estimate_homographies(moved, board_points, normalize=normalize))
        change = np.abs(apply_homography(back[:, None], src[None])
                        - apply_homography(H[:, None], src[None])).max()
        if normalize:
            assert change < tolerance
        else:
            assert change > 1e-4  # the unnormalized DLT's answer depends on the coordinate frame


def test_homographies_errors(exact):
    corners, board_points = exact["corners"], exact["board_points"]
    few = Points2D(corners.xy[:3], view=corners.view[:3], ids=corners.ids[:3])
    with pytest.raises(InvalidValue, match="at least 4"):
        estimate_homographies(few, board_points)
    # one row of the board: collinear
    line = Points2D(corners.xy[:9], view=np.zeros(9, int), ids=np.arange(9))
    with pytest.raises(InvalidValue, match="collinear"):
        estimate_homographies(line, board_points)
    with pytest.raises(InvalidValue, match="ids"):
        estimate_homographies(Points2D(corners.xy), board_points)
    with pytest.raises(InvalidValue):
        estimate_homographies(Points2D(corners.xy[:5], ids=np.arange(5) + 100), board_points)


# --- 3. estimate_intrinsics -------------------------------------------------------------------------
def test_intrinsics_known_answer(exact):
    np.testing.assert_allclose(estimate_intrinsics(exact["H"]), exact["K"], rtol=1e-7, atol=1e-6)
    K = estimate_intrinsics(exact["H"], zero_skew=True)
    assert K[0, 1] == 0.0
    np.testing.assert_allclose(K, exact["K"], rtol=1e-7, atol=1e-6)


def test_intrinsics_are_invariant_to_the_scale_of_each_homography(exact):
    scales = np.linspace(-3.0, 5.0, 15)
    scales[scales == 0] = 1.0
    np.testing.assert_allclose(estimate_intrinsics(exact["H"] * scales[:, None, None]), exact["K"], rtol=1e-7,
                               atol=1e-8)


def test_intrinsics_from_two_views_need_zero_skew(exact):
    with pytest.raises(InvalidValue, match="at least 3"):
        estimate_intrinsics(exact["H"][:2])
    np.testing.assert_allclose(estimate_intrinsics(exact["H"][:2], zero_skew=True), exact["K"], rtol=1e-6)


def test_intrinsics_reject_parallel_views(exact):
    with pytest.raises(InvalidValue):
        estimate_intrinsics(np.repeat(exact["H"][:1], 4, axis=0))
    with pytest.raises(InvalidValue):
        estimate_intrinsics(np.zeros((3, 3, 2)))


def test_closed_form_on_noisy_photos_is_close(synthetic_session):
    # Zhang's closed form ignores distortion (a strong barrel here shrinks f): a rough start that
    # the refinement then fixes
    assert synthetic_session.metrics["estimate_intrinsics"]["fx_rel_error"] < 0.3
    assert synthetic_session.metrics["refine_calibration"]["fx_rel_error"] < \
        synthetic_session.metrics["estimate_intrinsics"]["fx_rel_error"]


# --- 4. estimate_extrinsics -------------------------------------------------------------------------
def test_extrinsics_known_answer(exact):
    result = estimate_extrinsics(exact["H"], exact["K"])
    assert rotation_angle_deg(result.R_init, exact["R"]).max() < 1e-6
    np.testing.assert_allclose(result.t_init, exact["t"], rtol=1e-7)


def test_extrinsics_put_the_board_in_front_and_are_rotations(exact):
    noisy = exact["H"] * (1 + 1e-3 * np.random.default_rng(1).normal(size=exact["H"].shape))
    result = estimate_extrinsics(-noisy, exact["K"])  # the sign of H is arbitrary
    assert np.all(result.t_init[:, 2] > 0)
    R = result.R_init
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)


def test_extrinsics_errors(exact):
    with pytest.raises(InvalidValue):
        estimate_extrinsics(exact["H"], np.eye(4))
    with pytest.raises(InvalidValue):
        estimate_extrinsics(exact["H"][:, :2], exact["K"])


# --- 5. estimate_distortion -------------------------------------------------------------------------
def test_linear_distortion_known_answer(exact):
    """Zhang 3.3 is exact for a purely radial (k1, k2) lens with known K and poses."""
    truth = np.array([-0.21, 0.07, 0.0, 0.0, 0.0])
    corners = exact["corners"]
    observed = project_points(exact["board_points"][None], exact["K"], truth, exact["R"],
                              exact["t"]).reshape(-1, 2)
    distorted = Points2D(observed, view=corners.view, ids=corners.ids)
    dist = estimate_distortion(distorted, exact["board_points"], exact["K"], exact["R"], exact["t"])
    np.testing.assert_allclose(dist, truth, atol=1e-9)
    zero = estimate_distortion(corners, exact["board_points"], exact["K"], exact["R"], exact["t"])
    np.testing.assert_allclose(zero, 0.0, atol=1e-9)


def test_linear_distortion_on_rendered_corners_with_the_true_camera(synthetic_session):
    """With the right K and poses, the linear fit finds the lens's k1 from detected corners."""
    state, truth = synthetic_session.state, synthetic_session.truth
    assert state["dist_init"].shape == (5,)
    np.testing.assert_array_equal(state["dist_init"][2:], 0.0)
    dist = estimate_distortion(state["corners"], state["board_points"], truth["K"], truth["rotations"],
                               truth["translations"])
    assert dist[0] == pytest.approx(truth["dist"][0], abs=0.02)


def test_linear_distortion_errors(exact):
    with pytest.raises(InvalidValue, match="poses"):
        estimate_distortion(exact["corners"], exact["board_points"], exact["K"], exact["R"][:3],
                            exact["t"][:3])
    behind = -exact["t"]
    with pytest.raises(InvalidValue, match="behind"):
        estimate_distortion(exact["corners"], exact["board_points"], exact["K"], exact["R"], behind)


# --- 6. refine_calibration --------------------------------------------------------------------------
def test_refinement_matches_opencv_on_real_photos(real_session, real_opencv):
    _, K_cv, dist_cv, _, _, std_cv, _, per_view_cv = real_opencv
    state = real_session.state
    np.testing.assert_allclose(state["K"], K_cv, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(state["dist"], dist_cv.ravel(), rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(real_session.metrics["refine_calibration"]["per_view_rms_px"],
                               per_view_cv.ravel(), rtol=1e-3)
    # standard deviations: OpenCV's order is fx fy cx cy k1 k2 p1 p2 k3; ours puts the skew after cy
    ours = np.delete(state["std_intrinsics"], 4)
    np.testing.assert_allclose(ours, std_cv.ravel()[:9], rtol=1e-2)
    assert state["std_intrinsics"][4] == 0.0  # the skew is held at 0


@pytest.mark.parametrize("controls, flags", [(dict(fix_k3=True), cv2.CALIB_FIX_K3),
                                             (dict(fix_tangential=True), cv2.CALIB_ZERO_TANGENT_DIST)])
def test_refinement_controls_match_opencv_flags(real_session, controls, flags):
    state = real_session.state
    result, _ = run(refine_calibration(state["corners"], state["board_points"], state["K_init"],
                                       state["dist_init"], state["R_init"], state["t_init"], **controls))
    rms, K_cv, dist_cv, *_ = opencv_calibration(state["corners"], state["board_points"], flags=flags)
    assert result.rms_px == pytest.approx(rms, rel=1e-4)
    np.testing.assert_allclose(result.K, K_cv, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(result.dist, dist_cv.ravel(), atol=1e-4)
    if "fix_k3" in controls:
        assert result.dist[4] == 0.0 and result.k3_std == 0.0
    else:
        assert result.dist[2] == result.dist[3] == 0.0 and result.p1_std == 0.0


def test_refinement_with_skew_lowers_the_cost(real_session):
    state = real_session.state
    result, _ = run(refine_calibration(state["corners"], state["board_points"], state["K_init"],
                                       state["dist_init"], state["R_init"], state["t_init"],
                                       estimate_skew=True))
    assert result.rms_px <= real_session.metrics["refine_calibration"]["rms_px"] + 1e-9
    assert result.skew_std > 0 and abs(result.skew) < 3 * result.skew_std + 1.0


def test_refinement_yields_progress_and_a_falling_cost(real_session):
    state = real_session.state
    result, progress = run(refine_calibration(state["corners"], state["board_points"], state["K_init"],
                                              state["dist_init"], state["R_init"], state["t_init"]))
    assert progress and all(isinstance(p, Progress) for p in progress)
    assert [p.iteration for p in progress] == list(range(1, len(progress) + 1))
    assert result.iterations == len(progress)
    costs = result.cost.y[0]
    assert len(costs) == len(progress) + 1 and np.all(np.diff(costs) <= 1e-12)
    assert costs[-1] == pytest.approx(result.rms_px)
    assert progress[-1].loss == pytest.approx(result.rms_px)
    preview = progress[-1].values["reprojected"]  # the viewer animates the reprojected corners
    assert isinstance(preview, Points2D) and len(preview) == len(state["corners"])
    np.testing.assert_allclose(preview.xy, result.reprojected.xy)


def test_refinement_stops_at_max_iterations(real_session):
    state = real_session.state
    result, progress = run(refine_calibration(state["corners"], state["board_points"], state["K_init"],
                                              state["dist_init"], state["R_init"], state["t_init"],
                                              max_iterations=2))
    assert len(progress) == 2 and result.iterations == 2


def test_refinement_values_for_the_viewer(real_session):
    state, metrics = real_session.state, real_session.metrics["refine_calibration"]
    views = state["views"]
    cameras = state["cameras"]
    assert isinstance(cameras, Cameras) and len(cameras) == 13 and cameras.image == "images"
    np.testing.assert_array_equal(cameras.views, views)
    assert (cameras.width, cameras.height) == (640, 480)
    np.testing.assert_allclose(cameras.K[0], state["K"])
    assert np.all(cameras.centers[:, 2] < 0)  # the cameras look at the board from its -Z side
    per_view = np.array(metrics["per_view_rms_px"])
    worst = int(np.argmax(per_view))
    assert metrics["worst_view"] == views[worst]
    assert cameras.colors[worst, 0] == cameras.colors[:, 0].max()  # the worst view is the reddest
    curve = state["per_view_rms"]
    assert isinstance(curve, Curve) and curve.kind == "bar"
    assert curve.categories == tuple(real_session.state["images"].names[i] for i in views)
    assert curve.categories[worst] in curve.title
    np.testing.assert_allclose(curve.y[0], per_view)
    assert isinstance(state["board_mesh"], Mesh) and len(state["board_mesh"].faces) == 2 * 10 * 7
    reprojected, corners = state["reprojected"], state["corners"]
    assert isinstance(reprojected, Points2D) and len(reprojected) == len(corners)
    residuals = state["residuals"]
    assert isinstance(residuals, Segments2D) and len(residuals) == len(corners)
    np.testing.assert_allclose(residuals.end - residuals.start, 100.0 * (reprojected.xy - residuals.start))
    rms = np.sqrt(np.mean(np.sum((reprojected.xy - corners.xy) ** 2, axis=1)))
    assert rms == pytest.approx(metrics["rms_px"])
    expected = project_points(state["board_points"][None], state["K"], state["dist"], state["rotations"],
                              state["translations"])
    np.testing.assert_allclose(reprojected.xy, expected.reshape(-1, 2), atol=1e-9)
    assert state["std_intrinsics"].shape == (10,)
    assert {"fx_std", "k1_std", "iterations"} <= set(metrics)


def test_refinement_errors(exact):
    corners = Points2D(exact["corners"].xy[:54 * 2], view=exact["corners"].view[:108],
                       ids=exact["corners"].ids[:108])
    few = Points2D(corners.xy[::11], view=corners.view[::11], ids=corners.ids[::11])  # 10 corners, 21 params
    with pytest.raises(InvalidValue, match="not enough"):
        run(refine_calibration(few, exact["board_points"], exact["K"], np.zeros(5), exact["R"][:2],
                               exact["t"][:2]))
    with pytest.raises(InvalidValue):
        run(refine_calibration(corners, exact["board_points"], exact["K"], np.zeros(5), exact["R"],
                               exact["t"]))


def test_refinement_recovers_exact_parameters_from_a_perturbed_start(exact):
    truth_dist = np.array([-0.2, 0.05, 0.001, -0.0005, 0.01])
    corners = exact["corners"]
    observed = project_points(exact["board_points"][None], exact["K"], truth_dist, exact["R"], exact["t"])
    data = Points2D(observed.reshape(-1, 2), view=corners.view, ids=corners.ids)
    K0 = exact["K"] * np.array([[1.03, 0, 1.02], [0, 0.98, 0.99], [0, 0, 1]])
    R0 = rotvec_to_matrix(matrix_to_rotvec(exact["R"]) + 0.01)
    result, _ = run(refine_calibration(data, exact["board_points"], K0, np.zeros(5), R0, exact["t"] * 1.02))
    np.testing.assert_allclose(result.K, exact["K"], rtol=1e-8, atol=1e-7)
    np.testing.assert_allclose(result.dist, truth_dist, atol=1e-9)
    assert result.rms_px < 1e-8


# --- 7. undistort_image -----------------------------------------------------------------------------
@pytest.mark.parametrize("alpha", [0.0, 1.0])
def test_undistort_image_matches_cv2_undistort(real_session, alpha):
    state = real_session.state
    K, dist = state["K"], state["dist"]
    out = undistort_image(state["images"], K, dist, view=2, alpha=alpha)
    assert isinstance(out, Image) and out.pixels.shape == (480, 640) and "left03.jpg" in out.name
    K_new = optimal_new_camera_matrix(K, dist, (640, 480), alpha=alpha)
    K_cv, _ = cv2.getOptimalNewCameraMatrix(K, dist, (640, 480), alpha)
    np.testing.assert_allclose(K_new, K_cv, rtol=0.01)  # OpenCV undistorts its grid less exactly
    expected = cv2.undistort(state["images"][2].pixels, K, dist, None, K_new)
    inner = (slice(10, -10), slice(10, -10))
    assert np.abs(out.pixels[inner] - expected[inner]).mean() < 2e-3


def test_undistorted_photo_has_straight_board_rows(real_session):
    """After undistortion the corners of a board row lie on a line (far straighter than before)."""
    state = real_session.state
    K, dist = state["K"], state["dist"]
    K_new = optimal_new_camera_matrix(K, dist, (640, 480), alpha=0.0)
    corners = state["corners"].in_view(0).xy.reshape(6, 9, 2)
    mapping = undistortion_map(K, dist, (640, 480), K_new=K_new)
    straight = undistort_pixels(corners, K, dist, K_new)
    np.testing.assert_allclose(mapping[round(straight[0, 0, 1]), round(straight[0, 0, 0])],
                               corners[0, 0], atol=1.5)

    def bend(rows):
        out = []
        for row in rows:
            centred = row - row.mean(axis=0)
            out.append(np.linalg.svd(centred, compute_uv=False)[1])
        return max(out)

    assert bend(straight) < 0.2 * bend(corners)


def test_undistort_image_errors(real_session):
    state = real_session.state
    with pytest.raises(InvalidControl):
        undistort_image(state["images"], state["K"], state["dist"], view=13)
    with pytest.raises(InvalidValue):
        undistort_image(state["images"], state["K"], np.zeros(3))
    session = open_session(PIPELINE, "folder", {"path": str(SAMPLES), "pattern": "left01.jpg"})
    session.state["K"], session.state["dist"] = state["K"], state["dist"]
    with pytest.raises(InvalidControl):
        session.run("undistort_image", {"view": -1})
    record = session.run("undistort_image", {"view": 0, "alpha": 0.5})
    assert record.status == "ok" and isinstance(session.state["undistorted"], Image)


# --- the pipeline's declarations: exports and views -------------------------------------------------
def test_views_and_export_reads_are_values_of_the_pipeline():
    """Every name the viewer or an export reads is written by a step or given by every dataset."""
    written = {name for spec in PIPELINE.steps for name in spec.writes}
    given = {"images", "board"}  # what both datasets put in the state
    assert set(synthetic().state) == given
    assert PIPELINE.views <= written | given
    export = PIPELINE.export("opencv-yaml")
    assert set(export.reads) <= written | given and {"K", "dist"} <= set(export.reads)


def test_opencv_yaml_export_reads_back(real_session, tmp_path):
    state, metrics = real_session.state, real_session.metrics
    written = PIPELINE.export("opencv-yaml").write(state, metrics, tmp_path / "calib" / "camera.yaml")
    assert written == tmp_path / "calib" / "camera.yaml"
    back = read_opencv_calibration(written)
    np.testing.assert_allclose(back.K, state["K"])
    np.testing.assert_allclose(back.dist, state["dist"])
    assert (back.image_width, back.image_height) == (640, 480)
    assert back.avg_reprojection_error == pytest.approx(metrics["refine_calibration"]["rms_px"])
    storage = cv2.FileStorage(str(written), cv2.FILE_STORAGE_READ)
    try:
        assert storage.getNode("nframes").real() == 13
        assert (storage.getNode("board_width").real(), storage.getNode("board_height").real()) == (9, 6)
        assert storage.getNode("square_size").real() == pytest.approx(0.025)
        np.testing.assert_allclose(storage.getNode("per_view_reprojection_errors").mat().ravel(),
                                   metrics["refine_calibration"]["per_view_rms_px"])
        extrinsics = storage.getNode("extrinsic_parameters").mat()
        assert extrinsics.shape == (13, 6)
        np.testing.assert_allclose(extrinsics[:, 3:], state["translations"])
        np.testing.assert_allclose(extrinsics[:, :3], matrix_to_rotvec(state["rotations"]), atol=1e-9)
    finally:
        storage.release()


def test_opencv_yaml_export_needs_a_camera(real_session, tmp_path):
    write = PIPELINE.export("opencv-yaml").write
    with pytest.raises(MissingInput, match="refine_calibration"):
        write({"images": real_session.state["images"]}, {}, tmp_path / "a.yaml")
    state = {"K": real_session.state["K"], "dist": real_session.state["dist"]}
    with pytest.raises(InvalidValue, match="image size"):
        write(state, {}, tmp_path / "b.yaml")
    written = write({**state, "images": real_session.state["images"]}, {}, tmp_path / "c.yaml")
    back = read_opencv_calibration(written)  # no refinement metrics: no RMS, still a valid file
    assert back.avg_reprojection_error is None and (back.image_width, back.image_height) == (640, 480)
    assert not (tmp_path / "a.yaml").exists() and not (tmp_path / "b.yaml").exists()
