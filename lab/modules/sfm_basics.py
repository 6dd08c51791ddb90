"""The building blocks of structure from motion, one small step each: the teaching pipeline of lesson 04.

The incremental reconstruction of :mod:`lab.modules.sfm` registers images one at a time inside one
generator step. This pipeline lays its building blocks out flat on a small scene made exactly (no
rendering, no matching), so each can be run, inspected and replaced by a student's function:

1. :func:`estimate_poses_linear` - linear PnP (DLT) of every camera from known 3D points
   (:func:`lab.geometry.pnp.pnp_dlt`; lesson task 1);
2. :func:`refine_poses` - non-linear PnP (:func:`lab.geometry.pnp.refine_pnp`);
3. :func:`triangulate_points_linear` - linear triangulation (DLT) of every point from all views that
   see it (:func:`lab.geometry.triangulation.triangulate_dlt`; lesson task 2);
4. :func:`refine_points_nonlinear` - non-linear triangulation (:func:`lab.geometry.triangulation.refine_points`);
5. :func:`jacobian_sparsity` - which entries of the bundle-adjustment Jacobian can be non-zero
   (:func:`lab.geometry.bundle_adjustment.bundle_sparsity`; lesson task 3);
6. :func:`bundle_adjust_scene` - bundle adjustment by ``scipy.optimize.least_squares`` with
   finite differences grouped by *that* pattern, so a wrong pattern shows in the final error.

It is not a registered module (the lesson names it ``lab.modules.sfm_basics:PIPELINE``).

State names (float64 unless said):
    K              (3, 3)        the intrinsics of every camera (dataset)
    image_size     (2,) int      width, height in pixels (dataset)
    points3d       (N, 3)        known 3D points ("the map so far"), world frame (dataset)
    observations   Points2D      M pixels: ``view`` the camera, ``ids`` the 3D point (dataset)
    camera_indices (M,) int      = observations.view (dataset)
    point_indices  (M,) int      = observations.ids (dataset)
    num_cameras, num_points int  V and N (dataset)
    poses_linear   (V, 3, 4)     [R | t] of each camera from the linear PnP
    poses          (V, 3, 4)     refined by non-linear PnP;  cameras: Cameras (drawn)
    points_linear  (N, 3)        linear triangulation from ``poses``
    points         (N, 3)        refined points;  cloud: PointCloud (drawn)
    sparsity       (2M, 6V + 3N) bool, the Jacobian's pattern
    ba_poses, ba_points, ba_cameras, ba_cloud, ba_cost   after bundle adjustment

Conventions (DESIGN.md section 3): OpenCV cameras, ``X_c = R X_w + t``, pixel (0, 0) the centre of
the top-left pixel. Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), sections 7.1
(DLT for P), 12.2 (linear triangulation), A6.3 (sparse Levenberg-Marquardt); Triggs et al.,
"Bundle adjustment - a modern synthesis" (1999); the SciPy cookbook "Large-scale bundle adjustment
in scipy".
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np

from lab.core.step import step_result
from lab.core import (Cameras, Curve, InvalidControl, InvalidValue, Loaded, Pipeline, PointCloud, Points2D, Range,
                      metric)
from lab.data.scenes.cameras import intrinsics, orbit_cameras
from lab.geometry.bundle_adjustment import LOSSES, bundle_adjust, bundle_sparsity
from lab.geometry.camera import as_intrinsics
from lab.geometry.pnp import MIN_CORRESPONDENCES, pnp_dlt, refine_pnp
from lab.geometry.rotations import nearest_rotation, rotation_angle_deg
from lab.geometry.triangulation import projection_matrix, refine_points, triangulate_dlt

#: Parameters per camera in the bundle: axis-angle rotation (3) and translation (3).
CAMERA_PARAMS = 6


# ----------------------------------------------------------------------------------------------------
# The dataset
# ----------------------------------------------------------------------------------------------------
def synthetic(*, num_points: Annotated[int, Range(6, 2000)] = 60, num_views: Annotated[int, Range(2, 30)] = 6,
              noise_px: Annotated[float, Range(0.0, 20.0)] = 1.0,
              map_noise: Annotated[float, Range(0.0, 1.0)] = 0.05,
              visibility: Annotated[float, Range(0.3, 1.0)] = 0.8,
              outlier_rate: Annotated[float, Range(0.0, 0.5)] = 0.0,
              seed: int = 0) -> Loaded:
    """Random 3D points in a box seen by cameras on an orbit, projected exactly, plus pixel noise.

    The points are uniform in a 2 m cube centred at ``(8, 5, 1)`` (the world origin is a corner
    of the site, about 9 m away, behind some of the cameras); ``num_views`` cameras (640 x 480, 60 degree field of view)
    sit on a circle of radius 4.5 m, 1.5 m up, around the cube's centre and look at it, each eye
    and look-at point jittered by 0.1 m. Each camera sees each point with probability
    ``visibility`` (every point is seen by at least two cameras and every camera sees at least 12
    points). Pixels are the exact projections plus Gaussian noise of ``noise_px``; a share
    ``outlier_rate`` of the observations is replaced by uniform random pixels.

    Args:
        num_points: 3D points N.
        num_views: cameras V.
        noise_px: standard deviation of the pixel noise.
        map_noise: standard deviation (metres) of the noise on the known 3D points ``points3d``
            given to the PnP step (the "map" an incremental reconstruction has so far).
        visibility: probability that a camera sees a point.
        outlier_rate: share of observations replaced by random pixels.
        seed: the random seed.

    Truth: ``R`` (V, 3, 3), ``t`` (V, 3), ``X`` (N, 3) (the exact points), ``pixels`` (M, 2) (the
    exact projections of the observations).
    """
    rng = np.random.default_rng(seed)
    center = np.array([8.0, 5.0, 1.0])
    X = center + rng.uniform(-1.0, 1.0, size=(num_points, 3))
    width, height = 640, 480
    K = intrinsics(width=width, height=height)
    cameras = orbit_cameras(center, num_views=num_views, radius=4.5, elevation=1.5,
                            start_deg=float(rng.uniform(0.0, 360.0)), K=K, width=width, height=height,
                            jitter=0.1, seed=int(rng.integers(2**31)))
    R, t = cameras.R, cameras.t
    seen = rng.random((num_views, num_points)) < visibility
    for n in np.flatnonzero(seen.sum(axis=0) < 2):  # every point in at least two views
        seen[rng.choice(num_views, size=2, replace=False), n] = True
    for v in np.flatnonzero(seen.sum(axis=1) < 12):  # every camera sees enough points for PnP
        seen[v, rng.choice(num_points, size=min(12, num_points), replace=False)] = True
    view, ids = np.nonzero(seen)  # ordered by camera, then point
    Xc = np.einsum("mij,mj->mi", R[view], X[ids]) + t[view]
    exact = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    pixels = exact + rng.normal(0.0, noise_px, size=exact.shape)
    outliers = rng.random(len(pixels)) < outlier_rate
    pixels[outliers] = rng.uniform((0.0, 0.0), (width - 1.0, height - 1.0), size=(int(outliers.sum()), 2))
    observations = Points2D(pixels, view=view, ids=ids, image="")
    state = {
        "K": K, "image_size": np.array([width, height]),
        "points3d": X + rng.normal(0.0, map_noise, size=X.shape),
        "observations": observations, "camera_indices": view.astype(np.int64), "point_indices": ids.astype(np.int64),
        "num_cameras": int(num_views), "num_points": int(num_points),
    }
    truth = {"R": R, "t": t, "X": X, "pixels": exact}
    return Loaded(state, truth, description=f"{num_points} points, {num_views} cameras on an orbit, "
                                            f"{len(view)} observations, {noise_px:g} px noise")


# ----------------------------------------------------------------------------------------------------
# Checks of the inputs
# ----------------------------------------------------------------------------------------------------
def _observations(observations: Any) -> Points2D:
    if not isinstance(observations, Points2D):
        raise InvalidValue("observations", f"expected Points2D, got {type(observations).__name__}")
    if observations.view is None or observations.ids is None:
        raise InvalidValue("observations", "needs view (the camera) and ids (the 3D point) of every pixel")
    if len(observations) == 0:
        raise InvalidValue("observations", "there are no observations")
    if observations.view.min() < 0 or observations.ids.min() < 0:
        raise InvalidValue("observations", "view and ids must be non-negative indices")
    return observations


def _points(points: Any, name: str, count: int | None = None) -> np.ndarray:
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or (count is not None and len(X) != count):
        want = "(N, 3)" if count is None else f"({count}, 3)"
        raise InvalidValue(name, f"expected {want} points, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return X


def _poses(poses: Any, name: str, count: int | None = None) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4) or (count is not None and len(P) != count):
        want = "(V, 3, 4)" if count is None else f"({count}, 3, 4)"
        raise InvalidValue(name, f"expected {want} [R | t] matrices, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return P


def _views(observations: Points2D) -> int:
    views = np.unique(observations.view)
    if not np.array_equal(views, np.arange(len(views))):
        raise InvalidValue("observations", f"cameras must be numbered 0 .. V-1 without gaps, "
                                           f"got views {views.tolist()}")
    return len(views)


def _point_count(observations: Points2D, points: np.ndarray | None = None) -> int:
    count = int(observations.ids.max()) + 1
    if points is not None:
        if len(points) < count:
            raise InvalidValue("observations", f"ids go up to {count - 1} but there are {len(points)} 3D points")
        count = len(points)
    return count


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
    return Cameras(np.broadcast_to(K, (len(poses), 3, 3)).copy(), poses[:, :, :3], poses[:, :, 3], width, height)


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
    observations = _observations(observations)
    X = _points(points3d, "points3d")
    K = as_intrinsics(K)
    _point_count(observations, X)
    poses = []
    for v in range(_views(observations)):
        mine = observations.view == v
        if mine.sum() < MIN_CORRESPONDENCES:
            raise InvalidValue("observations", f"camera {v} sees {int(mine.sum())} known points; the linear PnP "
                                               f"needs at least {MIN_CORRESPONDENCES}")
        R, t = pnp_dlt(X[observations.ids[mine]], observations.xy[mine], K)
        poses.append(_as_poses(R, t))
    return np.array(poses)


@step_result
class RefinedPoses:
    """:func:`refine_poses`' result: ``poses`` ``(V, 3, 4)``, the ``cameras`` drawn, and the stage's errors."""

    poses: np.ndarray
    cameras: Cameras
    rms_linear_px: float = metric("RMS reprojection error of the linear poses", unit="px")
    rms_refined_px: float = metric("RMS reprojection error of the refined poses", unit="px")
    orthonormality_linear: float = metric("largest |R^T R - I| or |det R - 1| of the linear poses' R")
    points_behind_linear: int = metric("observations behind their camera under the linear poses")


def refine_poses(poses_linear: np.ndarray, points3d: np.ndarray, observations: Points2D, K: np.ndarray,
                 image_size: np.ndarray, *, loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
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
    observations = _observations(observations)
    X = _points(points3d, "points3d")
    K = as_intrinsics(K)
    V = _views(observations)
    start = _poses(poses_linear, "poses_linear", V)
    _point_count(observations, X)
    refined = []
    for v in range(V):
        mine = observations.view == v
        R, t = refine_pnp(nearest_rotation(start[v, :, :3]), start[v, :, 3], X[observations.ids[mine]],
                          observations.xy[mine], K, loss=loss, f_scale=f_scale)
        refined.append(_as_poses(np.asarray(R), np.asarray(t)))
    poses = np.array(refined)
    errors_linear, depths_linear = _reprojection(start, X, observations, K)
    errors_refined, _ = _reprojection(poses, X, observations, K)
    R_linear = start[:, :, :3]
    gram = np.abs(np.swapaxes(R_linear, 1, 2) @ R_linear - np.eye(3)).max()
    det = np.abs(np.linalg.det(R_linear) - 1.0).max()
    return RefinedPoses(poses=poses, cameras=_cameras(poses, K, image_size), rms_linear_px=_rms(errors_linear),
                        rms_refined_px=_rms(errors_refined), orthonormality_linear=float(max(gram, det)),
                        points_behind_linear=int(np.sum(~(depths_linear > 0))))


# ----------------------------------------------------------------------------------------------------
# 3-4. Points: linear triangulation, then non-linear
# ----------------------------------------------------------------------------------------------------
def _stacked(observations: Points2D, V: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    """Observations as ``(V, N, 2)`` pixels and a ``(V, N)`` mask (a camera sees a point at most once)."""
    x = np.zeros((V, N, 2))
    mask = np.zeros((V, N), dtype=bool)
    if np.any(observations.view >= V):
        raise InvalidValue("observations", f"a view index is {int(observations.view.max())} but there are {V} poses")
    flat = observations.view * N + observations.ids
    if len(np.unique(flat)) != len(flat):
        raise InvalidValue("observations", "a camera observes the same point twice")
    x[observations.view, observations.ids] = observations.xy
    mask[observations.view, observations.ids] = True
    seen = mask.sum(axis=0)
    if np.any(seen < 2):
        raise InvalidValue("observations", f"point {int(np.flatnonzero(seen < 2)[0])} is seen by fewer than two "
                                           "cameras: it cannot be triangulated")
    return x, mask


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
    observations = _observations(observations)
    K = as_intrinsics(K)
    P = _poses(poses, "poses")
    N = _point_count(observations)
    x, mask = _stacked(observations, len(P), N)
    return triangulate_dlt(projection_matrix(K, P[:, :, :3], P[:, :, 3]), x, mask)


@step_result
class RefinedPoints:
    """:func:`refine_points_nonlinear`' result: ``points`` ``(N, 3)``, the ``cloud`` drawn, the stage's errors."""

    points: np.ndarray
    cloud: PointCloud
    rms_linear_px: float = metric("RMS reprojection error of the linear points", unit="px")
    rms_refined_px: float = metric("RMS reprojection error of the refined points", unit="px")
    points_behind_linear: int = metric("observations of a linear point that lie behind their camera")


def refine_points_nonlinear(points_linear: np.ndarray, observations: Points2D, poses: np.ndarray, K: np.ndarray, *,
                            iterations: Annotated[int, Range(1, 100)] = 10) -> RefinedPoints:
    """Non-linear triangulation: each point moved to minimize its reprojection error, cameras fixed.

    Levenberg-Marquardt on every point's ``3 x 3`` normal equations at once
    (:func:`lab.geometry.triangulation.refine_points`); a point whose error does not fall stays.

    Args:
        points_linear: ``(N, 3)`` starting points.
        observations, poses, K: as in :func:`triangulate_points_linear`.
        iterations: most iterations.

    Reference: Hartley & Zisserman (2nd ed.), sections 12.5 and A6.2.
    """
    observations = _observations(observations)
    K = as_intrinsics(K)
    P = _poses(poses, "poses")
    N = _point_count(observations)
    X0 = _points(points_linear, "points_linear", N)
    x, mask = _stacked(observations, len(P), N)
    X, _ = refine_points(projection_matrix(K, P[:, :, :3], P[:, :, 3]), x, X0, mask, iterations=int(iterations))
    errors_linear, depths = _reprojection(P, X0, observations, K)
    errors_refined, _ = _reprojection(P, X, observations, K)
    return RefinedPoints(points=X, cloud=PointCloud(X), rms_linear_px=_rms(errors_linear),
                         rms_refined_px=_rms(errors_refined), points_behind_linear=int(np.sum(~(depths > 0))))


# ----------------------------------------------------------------------------------------------------
# 5-6. Bundle adjustment: the Jacobian's pattern, then the solver that uses it
# ----------------------------------------------------------------------------------------------------
def _indices(camera_indices: Any, point_indices: Any, num_cameras: Any, num_points: Any) -> tuple[np.ndarray, ...]:
    cameras = np.asarray(camera_indices)
    points = np.asarray(point_indices)
    if cameras.ndim != 1 or points.shape != cameras.shape or len(cameras) == 0:
        raise InvalidValue("camera_indices", f"camera and point indices must be two non-empty (M,) arrays of the same "
                                             f"length, got {cameras.shape} and {points.shape}")
    if not (np.issubdtype(cameras.dtype, np.integer) and np.issubdtype(points.dtype, np.integer)):
        raise InvalidValue("camera_indices", "indices must be integers")
    for name, value in (("num_cameras", num_cameras), ("num_points", num_points)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InvalidValue(name, f"must be a positive integer, got {value!r}")
    return cameras.astype(np.int64), points.astype(np.int64)


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
    cameras, points = _indices(camera_indices, point_indices, num_cameras, num_points)
    pattern = bundle_sparsity(cameras, points, int(num_cameras), int(num_points), camera_params=CAMERA_PARAMS)
    return pattern.toarray().astype(bool)


@step_result
class BundleAdjusted:
    """:func:`bundle_adjust_scene`' result: poses and points, drawn cameras and cloud, the cost per iteration."""

    ba_poses: np.ndarray
    ba_points: np.ndarray
    ba_cameras: Cameras
    ba_cloud: PointCloud
    ba_cost: Curve
    ba_rms_before_px: float = metric("RMS reprojection error before bundle adjustment", unit="px")
    ba_rms_px: float = metric("RMS reprojection error after bundle adjustment", unit="px")
    ba_iterations: int = metric("Jacobian evaluations (trust-region iterations)")
    sparsity_missing: int = metric("entries the Jacobian has that the pattern leaves out")
    sparsity_extra: int = metric("entries the pattern marks that the Jacobian never has")
    ba_improved: bool = metric("whether the solver lowered the error (else the input is kept)")


def bundle_adjust_scene(poses: np.ndarray, points: np.ndarray, observations: Points2D, K: np.ndarray,
                        sparsity: np.ndarray, image_size: np.ndarray, *,
                        loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "huber",
                        f_scale: Annotated[float, Range(0.01, 100.0)] = 1.0,
                        max_iterations: Annotated[int, Range(1, 200)] = 30) -> BundleAdjusted:
    """Bundle adjustment with the Jacobian's sparsity pattern from state (finite differences grouped by it).

    Minimizes ``sum_i rho(|pi(K (R_c X_p + t_c)) - x_i|^2)`` over every camera but the first (held:
    it fixes the gauge's rotation and translation) and every point with
    :func:`lab.geometry.bundle_adjustment.bundle_adjust` with ``jacobian="2-point"`` and the state's
    pattern (``scipy.optimize.least_squares(method="trf", jac="2-point", jac_sparsity=...)``). SciPy groups
    columns that share no row of the pattern and perturbs each group at once, and takes every entry
    outside the pattern as zero: a pattern that misses entries leaves those parameters without
    derivatives, one with extra entries costs evaluations (the metrics ``sparsity_missing`` and
    ``sparsity_extra`` count both against :func:`lab.geometry.bundle_adjustment.bundle_sparsity`).
    The result is kept only when the RMS error falls.

    Args:
        poses: ``(V, 3, 4)``; points: ``(N, 3)``; observations, K: as above.
        sparsity: ``(2 M, 6 V + 3 N)`` bool, from :func:`jacobian_sparsity`.
        image_size: ``(2,)``, for the drawn cameras.
        loss, f_scale: robust loss and its scale (px).
        max_iterations: most residual evaluations of the solver (``max_nfev``; about one per iteration).

    Reference: Triggs et al. (1999); H&Z (2nd ed.), appendix A6.3; SciPy cookbook "Large-scale bundle
    adjustment in scipy".
    """
    observations = _observations(observations)
    K = as_intrinsics(K)
    P = _poses(poses, "poses")
    V = len(P)
    N = _point_count(observations)
    X = _points(points, "points", N)
    _stacked(observations, V, N)  # checks view indices
    if loss not in LOSSES:
        raise InvalidControl("loss", f"unknown loss {loss!r}; losses are {list(LOSSES)}")
    M = len(observations)
    pattern = np.asarray(sparsity)
    shape = (2 * M, CAMERA_PARAMS * V + 3 * N)
    if pattern.shape != shape:
        raise InvalidValue("sparsity", f"expected shape {shape} (2 rows per observation, 6 columns per camera and 3 "
                                       f"per point), got {pattern.shape}")
    cams, pts, obs = observations.view.astype(np.int64), observations.ids.astype(np.int64), observations.xy
    needed = bundle_sparsity(cams, pts, V, N, camera_params=CAMERA_PARAMS).toarray().astype(bool)
    marked = pattern != 0
    missing, extra = int(np.sum(needed & ~marked)), int(np.sum(marked & ~needed))
    result = bundle_adjust(K, P[:, :, :3], P[:, :, 3], X, cams, pts, obs, loss=loss, f_scale=float(f_scale),
                           fixed_cameras=(0,), fix_scale=False, max_iterations=int(max_iterations),
                           jacobian="2-point", sparsity=marked)
    out = _as_poses(result.R, result.t)
    Xp, history = result.points, result.cost_history
    rms_before, rms_after, evaluations, improved = result.rms_before, result.rms_after, result.iterations, result.improved
    cost = Curve(np.arange(len(history)), np.array(history), title="Bundle adjustment", xlabel="iteration",
                 ylabel="RMS reprojection error (px)")
    return BundleAdjusted(ba_poses=out, ba_points=Xp.copy(), ba_cameras=_cameras(out, K, image_size),
                          ba_cloud=PointCloud(Xp.copy()), ba_cost=cost, ba_rms_before_px=rms_before,
                          ba_rms_px=float(rms_after), ba_iterations=evaluations, ba_improved=improved,
                          sparsity_missing=missing, sparsity_extra=extra)


# ----------------------------------------------------------------------------------------------------
# Evaluations against the truth
# ----------------------------------------------------------------------------------------------------
def _pose_errors(poses: np.ndarray, truth: dict[str, Any], prefix: str = "") -> dict[str, float]:
    if "R" not in truth or np.shape(poses)[0] != len(truth["R"]):
        return {}
    poses = np.asarray(poses, dtype=np.float64)
    R_true, t_true = np.asarray(truth["R"]), np.asarray(truth["t"])
    angles = rotation_angle_deg(nearest_rotation(poses[:, :, :3]), R_true)
    centers = -np.einsum("vji,vj->vi", poses[:, :, :3], poses[:, :, 3])
    centers_true = -np.einsum("vji,vj->vi", R_true, t_true)
    center_errors = np.linalg.norm(centers - centers_true, axis=1)
    return {f"{prefix}rotation_error_deg": float(angles.max()), f"{prefix}center_error_m": float(center_errors.max())}


def evaluate_poses_linear(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest rotation angle (deg) and camera-centre distance (m) of the linear poses from the truth."""
    return _pose_errors(state["poses_linear"], truth, "linear_")


def evaluate_poses(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest rotation angle (deg) and camera-centre distance (m) of the refined poses from the truth."""
    return _pose_errors(state["poses"], truth)


def _point_error(points: np.ndarray, truth: dict[str, Any], name: str) -> dict[str, float]:
    if "X" not in truth or np.shape(points) != np.shape(truth["X"]):
        return {}
    return {name: float(np.sqrt(np.mean(np.sum((np.asarray(points) - truth["X"]) ** 2, axis=1))))}


def evaluate_points_linear(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """RMS distance (m) of the linear points from the true points."""
    return _point_error(state["points_linear"], truth, "linear_point_error_m")


def evaluate_points(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """RMS distance (m) of the refined points from the true points."""
    return _point_error(state["points"], truth, "point_error_m")


def evaluate_bundle(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Rotation and centre errors of the adjusted cameras (the first is held, so the frame is the world's
    up to a small scale drift); RMS distance of the adjusted points from the truth."""
    metrics = _pose_errors(state["ba_poses"], truth, "ba_")
    metrics.update(_point_error(state["ba_points"], truth, "ba_point_error_m"))
    return metrics


PIPELINE = Pipeline.build(
    name="sfm_basics",
    title="Structure from motion: the building blocks",
    summary="Linear and non-linear PnP, linear and non-linear triangulation, and bundle adjustment with the "
            "Jacobian's sparsity pattern, each a step, on a small exact multi-view scene.",
    steps=[estimate_poses_linear, refine_poses, triangulate_points_linear, refine_points_nonlinear, jacobian_sparsity,
           bundle_adjust_scene],
    datasets=[synthetic],
    evaluations={"estimate_poses_linear": evaluate_poses_linear, "refine_poses": evaluate_poses,
                 "triangulate_points_linear": evaluate_points_linear, "refine_points_nonlinear": evaluate_points,
                 "bundle_adjust_scene": evaluate_bundle},
)

__all__ = ["PIPELINE", "synthetic", "estimate_poses_linear", "refine_poses", "triangulate_points_linear",
           "refine_points_nonlinear", "jacobian_sparsity", "bundle_adjust_scene", "CAMERA_PARAMS"]
