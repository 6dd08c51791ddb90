"""The steps of the SfM lesson pipeline, in pipeline order: poses, points, the Jacobian's pattern, the
bundle."""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Cameras, Curve, InvalidControl, InvalidValue, PointCloud, Points2D, Range, metric
from lab.core.step import step_result
from lab.data.reconstruction import SparseModel
from lab.geometry.bundle_adjustment import LOSSES, bundle_adjust, bundle_sparsity
from lab.geometry.camera import as_intrinsics
from lab.geometry.pnp import MIN_CORRESPONDENCES, pnp_dlt, refine_pnp
from lab.geometry.rotations import nearest_rotation
from lab.geometry.triangulation import projection_matrix, refine_points, triangulate_dlt
from lab.modules.sfm_basics._checks import (check_indices, check_observations, check_points, check_poses,
                                           point_count, stacked, view_count, views_and_ids)

#: Parameters per camera in the bundle: axis-angle rotation (3) and translation (3).
CAMERA_PARAMS = 6


def _as_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([R, t[..., None]], axis=-1)


def _reprojection(poses: np.ndarray, X: np.ndarray, observations: Points2D,
                  K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: reprojection error (px) and depth in its camera (no cheirality cut-off)."""
    R, t = poses[:, :, :3], poses[:, :, 3]
    v, n = observations.view, observations.ids
    Xc = np.einsum("mij,mj->mi", R[v], X[n]) + t[v]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
        errors = np.linalg.norm(uv - observations.xy, axis=1)
    return errors, Xc[:, 2]


def _rms(errors: np.ndarray) -> float:
    finite = errors[np.isfinite(errors)]
    return float(np.sqrt(np.mean(finite * finite))) if len(finite) else 0.0


def _cameras(poses: np.ndarray, K: np.ndarray, image_size: Any) -> Cameras:
    width, height = (int(v) for v in np.asarray(image_size).ravel()[:2])
    return Cameras(np.broadcast_to(K, (len(poses), 3, 3)).copy(), poses[:, :, :3], poses[:, :, 3], width,
                   height)


#: The colour of a point of the scene, which has no photos: 0.7 grey, as the SfM module's uncoloured points.
GREY = 178


def _point_errors(errors: np.ndarray, observations: Points2D, count: int) -> np.ndarray:
    """Mean of each point's finite observation errors ``(N,)`` (0 for a point without any)."""
    assert observations.ids is not None
    finite = np.isfinite(errors)
    counts = np.bincount(observations.ids[finite], minlength=count)
    sums = np.bincount(observations.ids[finite], weights=errors[finite], minlength=count)
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


def scene_model(poses: np.ndarray, points: np.ndarray, observations: Points2D, K: np.ndarray,
                image_size: Any) -> SparseModel:
    """The scene as a :class:`SparseModel`: every camera registered, each observation a keypoint whose track
    is its point (``ids``), each point's error its mean reprojection error."""
    assert observations.ids is not None
    views, count = len(poses), len(points)
    errors, _ = _reprojection(poses, points, observations, K)
    return SparseModel(K=np.broadcast_to(K, (views, 3, 3)), poses=poses,
                       registered=np.ones(views, dtype=bool), names=tuple(f"view {v}" for v in range(views)),
                       sizes=np.tile(np.asarray(image_size).ravel()[:2], (views, 1)), keypoints=observations,
                       track_of=observations.ids, observed=np.ones(len(observations), dtype=bool),
                       points=points, point_tracks=np.arange(count), colors=np.full((count, 3), GREY),
                       errors=_point_errors(errors, observations, count))



# ----------------------------------------------------------------------------------------------------
# 1-2. Camera poses: linear PnP, then non-linear
# ----------------------------------------------------------------------------------------------------
def estimate_poses_linear(points3d: np.ndarray, observations: Points2D,
                          K: np.ndarray) -> Annotated[np.ndarray, "poses_linear"]:
    """Linear PnP (DLT) of every camera: ``[R | t]`` from the 2D-3D correspondences it sees.

    For camera ``v`` the correspondences are ``points3d[observations.ids[k]] <-> observations.xy[k]``
    for every ``k`` with ``observations.view[k] == v`` (at least 6, not coplanar). Each is solved by
    :func:`lab.geometry.pnp.pnp_dlt`: normalized coordinates ``K^-1 x``, Hartley's normalization of
    both point sets, the null vector of the ``2n x 12`` system, the normalizations undone, the sign
    chosen so the points have positive depth, ``R`` the nearest rotation to the left ``3 x 3`` block
    (``det R = +1``) and ``t`` the last column divided by that block's mean singular value.

    Args:
        points3d: ``(N, 3)`` known world points.
        observations: ``Points2D``: ``xy`` ``(M, 2)`` pixels, ``view`` ``(M,)`` the camera, ``ids``
            ``(M,)`` the 3D point.
        K: ``(3, 3)`` intrinsics shared by all cameras.

    Returns ``(V, 3, 4)``: ``[R_v | t_v]`` for cameras ``v = 0 .. V-1`` (``X_c = R X + t``).

    No OpenCV flag gives the bare DLT: ``cv2.solvePnP(..., flags=cv2.SOLVEPNP_ITERATIVE)`` starts
    from it and refines. Reference: Hartley & Zisserman (2nd ed.), section 7.1.
    """
    observations = check_observations(observations)
    X = check_points(points3d, "points3d")
    K = as_intrinsics(K)
    point_count(observations, X)
    view, ids = views_and_ids(observations)
    poses = []
    for v in range(view_count(observations)):
        mine = view == v
        if mine.sum() < MIN_CORRESPONDENCES:
            raise InvalidValue("observations",
                               f"camera {v} sees {int(mine.sum())} known points; the linear PnP "
                               f"needs at least {MIN_CORRESPONDENCES}")
        R, t = pnp_dlt(X[ids[mine]], observations.xy[mine], K)
        poses.append(_as_poses(R, t))
    return np.array(poses)


@step_result
class RefinedPoses:
    """:func:`refine_poses`' result: ``poses`` ``(V, 3, 4)``, the ``cameras`` drawn, the stage's errors."""

    poses: np.ndarray
    cameras: Cameras
    rms_linear_px: float = metric("RMS reprojection error of the linear poses", unit="px")
    rms_refined_px: float = metric("RMS reprojection error of the refined poses", unit="px")
    orthonormality_linear: float = metric("largest |R^T R - I| or |det R - 1| of the linear poses' R")
    points_behind_linear: int = metric("observations behind their camera under the linear poses")


def refine_poses(poses_linear: np.ndarray, points3d: np.ndarray, observations: Points2D, K: np.ndarray,
                 image_size: np.ndarray, *,
                 loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
                 f_scale: Annotated[float, Range(0.01, 100.0)] = 1.0) -> RefinedPoses:
    """Non-linear PnP of every camera from its linear pose (:func:`lab.geometry.pnp.refine_pnp`).

    Minimizes each camera's robust reprojection error over its axis-angle rotation and translation
    (``scipy.optimize.least_squares``, trust-region reflective), starting from ``poses_linear`` with
    each ``R`` projected onto the nearest rotation first (so the result is always a proper rotation).
    A refinement that does not lower the error keeps that start.
    The metrics describe the linear poses too: their RMS error, how far their ``R`` are from
    rotations and how many observations lie behind their camera (the cheirality test).

    Args:
        poses_linear: ``(V, 3, 4)`` starting poses.
        points3d, observations, K: as in :func:`estimate_poses_linear`.
        image_size: ``(2,)`` width and height, for the drawn cameras.
        loss: robust loss of ``least_squares``.
        f_scale: its inlier scale, pixels.

    Corresponds to ``cv2.solvePnPRefineLM`` per camera. Reference: H&Z (2nd ed.), section 7.2.
    """
    observations = check_observations(observations)
    X = check_points(points3d, "points3d")
    K = as_intrinsics(K)
    V = view_count(observations)
    start = check_poses(poses_linear, "poses_linear", V)
    point_count(observations, X)
    view, ids = views_and_ids(observations)
    refined = []
    for v in range(V):
        mine = view == v
        R, t = refine_pnp(nearest_rotation(start[v, :, :3]), start[v, :, 3], X[ids[mine]],
                          observations.xy[mine], K, loss=loss, f_scale=f_scale)
        refined.append(_as_poses(np.asarray(R), np.asarray(t)))
    poses = np.array(refined)
    errors_linear, depths_linear = _reprojection(start, X, observations, K)
    errors_refined, _ = _reprojection(poses, X, observations, K)
    R_linear = start[:, :, :3]
    gram = np.abs(np.swapaxes(R_linear, 1, 2) @ R_linear - np.eye(3)).max()
    det = np.abs(np.linalg.det(R_linear) - 1.0).max()
    return RefinedPoses(poses=poses, cameras=_cameras(poses, K, image_size),
                        rms_linear_px=_rms(errors_linear),
                        rms_refined_px=_rms(errors_refined), orthonormality_linear=float(max(gram, det)),
                        points_behind_linear=int(np.sum(~(depths_linear > 0))))


# ----------------------------------------------------------------------------------------------------
# 3-4. Points: linear triangulation, then non-linear
# ----------------------------------------------------------------------------------------------------

def triangulate_points_linear(observations: Points2D, poses: np.ndarray,
                              K: np.ndarray) -> Annotated[np.ndarray, "points_linear"]:
    """Linear (DLT) triangulation of every point from all the cameras that see it.

    With ``P_v = K [R_v | t_v]`` and rows ``p1, p2, p3``, each view seeing the point at pixel
    ``(x, y)`` gives the rows ``x p3 - p1`` and ``y p3 - p2`` of ``A X = 0``; ``X`` is the right
    singular vector of ``A`` with the smallest singular value, de-homogenized
    (:func:`lab.geometry.triangulation.triangulate_dlt`, in pixels, as OpenCV).

    Args:
        observations: ``Points2D`` as in :func:`estimate_poses_linear`; point ``n`` is seen by the
            cameras ``observations.view[k]`` with ``observations.ids[k] == n``.
        poses: ``(V, 3, 4)`` ``[R | t]`` of the cameras.
        K: ``(3, 3)``.

    Returns ``(N, 3)``, row ``n`` the point with id ``n`` (``N = observations.ids.max() + 1``). Two
    views give ``cv2.triangulatePoints(P1, P2, x1.T, x2.T)`` de-homogenized.
    Reference: Hartley & Zisserman (2nd ed.), section 12.2.
    """
    observations = check_observations(observations)
    K = as_intrinsics(K)
    P = check_poses(poses, "poses")
    N = point_count(observations)
    x, mask = stacked(observations, len(P), N)
    return triangulate_dlt(projection_matrix(K, P[:, :, :3], P[:, :, 3]), x, mask)


@step_result
class RefinedPoints:
    """:func:`refine_points_nonlinear`' result: the ``model`` (the cameras and the refined points), the
    ``cloud`` drawn, the stage's errors."""

    model: SparseModel
    cloud: PointCloud
    rms_linear_px: float = metric("RMS reprojection error of the linear points", unit="px")
    rms_refined_px: float = metric("RMS reprojection error of the refined points", unit="px")
    points_behind_linear: int = metric("observations of a linear point that lie behind their camera")


def refine_points_nonlinear(points_linear: np.ndarray, observations: Points2D, poses: np.ndarray,
                            K: np.ndarray, image_size: np.ndarray, *,
                            iterations: Annotated[int, Range(1, 100)] = 10) -> RefinedPoints:
    """Non-linear triangulation: each point moved to minimize its reprojection error, cameras fixed.

    Levenberg-Marquardt on every point's ``3 x 3`` normal equations at once
    (:func:`lab.geometry.triangulation.refine_points`); a point whose error does not fall stays.
    The result is the scene's ``model`` (:func:`scene_model`: the cameras ``poses``, the refined
    points, the observations as tracks), the start of bundle adjustment.

    Args:
        points_linear: ``(N, 3)`` starting points.
        observations, poses, K: as in :func:`triangulate_points_linear`.
        image_size: ``(2,)`` width and height, for the model's cameras.
        iterations: most iterations.

    Reference: Hartley & Zisserman (2nd ed.), sections 12.5 and A6.2.
    """
    observations = check_observations(observations)
    K = as_intrinsics(K)
    P = check_poses(poses, "poses")
    N = point_count(observations)
    X0 = check_points(points_linear, "points_linear", N)
    x, mask = stacked(observations, len(P), N)
    X, _ = refine_points(projection_matrix(K, P[:, :, :3], P[:, :, 3]), x, X0, mask,
                         iterations=int(iterations))
    errors_linear, depths = _reprojection(P, X0, observations, K)
    errors_refined, _ = _reprojection(P, X, observations, K)
    return RefinedPoints(model=scene_model(P, X, observations, K, image_size), cloud=PointCloud(X),
                         rms_linear_px=_rms(errors_linear), rms_refined_px=_rms(errors_refined),
                         points_behind_linear=int(np.sum(~(depths > 0))))


# ----------------------------------------------------------------------------------------------------
# 5-6. Bundle adjustment: the Jacobian's pattern, then the solver that uses it
# ----------------------------------------------------------------------------------------------------

def jacobian_sparsity(camera_indices: np.ndarray, point_indices: np.ndarray, num_cameras: int,
                      num_points: int) -> Annotated[np.ndarray, "sparsity"]:
    """Which entries of the bundle-adjustment Jacobian can be non-zero, as a dense bool array.

    Parameters: 6 per camera (axis-angle rotation, translation; camera ``c`` owns columns ``6 c ..
    6 c + 5``), then 3 per point (point ``p`` owns columns ``6 V + 3 p .. 6 V + 3 p + 2``).
    Observation ``i`` owns residual rows ``2 i`` (u) and ``2 i + 1`` (v), which depend only on its
    camera's 6 and its point's 3 parameters.

    Args:
        camera_indices: ``(M,)`` int, the camera of each observation.
        point_indices: ``(M,)`` int, the point of each observation.
        num_cameras: V.
        num_points: N.

    Returns ``(2 M, 6 V + 3 N)`` bool. :func:`lab.geometry.bundle_adjustment.bundle_sparsity` as a
    dense array (``scipy.sparse``'s ``.toarray()``), the SciPy cookbook's ``bundle_adjustment_sparsity``.
    """
    cameras, points = check_indices(camera_indices, point_indices, num_cameras, num_points)
    pattern = bundle_sparsity(cameras, points, int(num_cameras), int(num_points), camera_params=CAMERA_PARAMS)
    return pattern.toarray().astype(bool)


@step_result
class BundleAdjusted:
    """:func:`bundle_adjust_scene`' result: the adjusted model, cameras and cloud drawn, the costs."""

    adjusted_model: SparseModel
    ba_cameras: Cameras
    ba_cloud: PointCloud
    ba_cost: Curve
    ba_rms_before_px: float = metric("RMS reprojection error before bundle adjustment", unit="px")
    ba_rms_px: float = metric("RMS reprojection error after bundle adjustment", unit="px")
    ba_iterations: int = metric("Jacobian evaluations (trust-region iterations)")
    sparsity_missing: int = metric("entries the Jacobian has that the pattern leaves out")
    sparsity_extra: int = metric("entries the pattern marks that the Jacobian never has")
    ba_improved: bool = metric("whether the solver lowered the error (else the input is kept)")


def bundle_adjust_scene(model: SparseModel, sparsity: np.ndarray, *,
                        loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
                        f_scale: Annotated[float, Range(0.01, 100.0)] = 1.0,
                        max_iterations: Annotated[int, Range(1, 200)] = 30) -> BundleAdjusted:
    """Bundle adjustment with the Jacobian's sparsity pattern from state (finite differences grouped by it).

    Minimizes ``sum_i rho(|pi(K (R_c X_p + t_c)) - x_i|^2)`` over every camera but the first (held:
    it fixes the gauge's rotation and translation) and every point with
    :func:`lab.geometry.bundle_adjustment.bundle_adjust` with ``jacobian="2-point"`` and the state's
    pattern (``scipy.optimize.least_squares(method="trf", jac="2-point", jac_sparsity=...)``). SciPy
    groups columns that share no row of the pattern and perturbs each group at once, and takes every
    entry outside the pattern as zero: a pattern that misses entries leaves those parameters without
    derivatives, one with extra entries costs evaluations (the metrics ``sparsity_missing`` and
    ``sparsity_extra`` count both against :func:`lab.geometry.bundle_adjustment.bundle_sparsity`).
    The result is kept only when the RMS error falls.

    Args:
        model: the scene (:func:`refine_points_nonlinear`): cameras sharing one K, points, and the
            observations, in the order of the pattern's rows.
        sparsity: ``(2 M, 6 V + 3 N)`` bool, from :func:`jacobian_sparsity`.
        loss, f_scale: robust loss and its scale (px).
        max_iterations: most residual evaluations of the solver (``max_nfev``; about one per iteration).

    Returns ``adjusted_model`` (the model with the adjusted cameras and points) and what is drawn.

    Reference: Triggs et al. (1999); H&Z (2nd ed.), appendix A6.3; SciPy cookbook "Large-scale bundle
    adjustment in scipy".
    """
    if not isinstance(model, SparseModel):
        raise InvalidValue("model", f"expected a SparseModel, got {type(model).__name__}")
    if not np.all(model.K[0] == model.K):
        raise InvalidValue("model", "bundle_adjust_scene adjusts cameras that share one K")
    if loss not in LOSSES:
        raise InvalidControl("loss", f"unknown loss {loss!r}; losses are {list(LOSSES)}")
    K, P, X = model.K[0], model.poses, model.points
    V, N = len(P), len(X)
    observed = model.observation_pixels()
    assert observed.view is not None and observed.ids is not None
    M = len(observed)
    pattern = np.asarray(sparsity)
    shape = (2 * M, CAMERA_PARAMS * V + 3 * N)
    if pattern.shape != shape:
        raise InvalidValue("sparsity",
                           f"expected shape {shape} (2 rows per observation, 6 columns per camera "
                           f"and 3 per point), got {pattern.shape}")
    cams, pts, obs = observed.view, observed.ids, observed.xy
    needed = bundle_sparsity(cams, pts, V, N, camera_params=CAMERA_PARAMS).toarray().astype(bool)
    marked = pattern != 0
    missing, extra = int(np.sum(needed & ~marked)), int(np.sum(marked & ~needed))
    result = bundle_adjust(K, P[:, :, :3], P[:, :, 3], X, cams, pts, obs, loss=loss, f_scale=float(f_scale),
                           fixed_cameras=(0,), fix_scale=False, max_iterations=int(max_iterations),
                           jacobian="2-point", sparsity=marked)
    out = _as_poses(result.R, result.t)
    Xp, history = result.points, result.cost_history
    errors, _ = _reprojection(out, Xp, observed, K)
    adjusted = replace(model, poses=out, points=Xp, errors=_point_errors(errors, observed, N))
    cost = Curve(np.arange(len(history)), np.array(history), title="Bundle adjustment", xlabel="iteration",
                 ylabel="RMS reprojection error (px)")
    return BundleAdjusted(adjusted_model=adjusted, ba_cameras=_cameras(out, K, model.sizes[0]),
                          ba_cloud=PointCloud(Xp.copy()), ba_cost=cost, ba_rms_before_px=result.rms_before,
                          ba_rms_px=float(result.rms_after), ba_iterations=result.iterations,
                          ba_improved=result.improved, sparsity_missing=missing, sparsity_extra=extra)
