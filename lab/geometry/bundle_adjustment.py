"""Sparse bundle adjustment: cameras and points refined together by minimizing the reprojection error.

Unknowns, in this order in the parameter vector ``x``:

* per camera ``camera_params`` numbers: the axis-angle rotation ``w`` (3), the translation ``t``
  (3) of ``X_c = R(w) X + t``, and, when every camera has its own refined intrinsics, its
  ``(fx, fy, cx, cy)`` (4, so ``camera_params = 10``);
* ``intrinsic_params`` shared numbers: ``(fx, fy, cx, cy)`` of one ``K`` used by every camera when
  it is refined (4), else none;
* per point its three coordinates.

Residuals: for observation ``i`` (camera ``c_i`` sees point ``p_i`` at pixel ``x_i``) the two rows
``2 i`` and ``2 i + 1`` hold ``pi(K_c (R_c X_p + t_c)) - x_i``. Row ``2 i`` depends only on camera
``c_i``'s parameters, the shared intrinsics and point ``p_i``'s coordinates, so the Jacobian is
sparse with a fixed pattern (:func:`bundle_sparsity`) that ``scipy.optimize.least_squares`` uses
for its sparse trust-region solver and, with finite differences, to perturb many columns at once.

Reference: B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment - a modern
synthesis" (1999); Hartley & Zisserman (2nd ed.), appendix A6.3 (sparse Levenberg-Marquardt);
the SciPy cookbook "Large-scale bundle adjustment in scipy"
(https://scipy-cookbook.readthedocs.io/items/bundle_adjustment.html).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
import scipy.sparse
from scipy.optimize import OptimizeResult, least_squares
from scipy.spatial.transform import Rotation

from lab.core.errors import InvalidControl, InvalidValue
from lab.geometry.rotations import matrix_to_rotvec, skew, so3_left_jacobian

#: Robust losses ``least_squares`` knows.
LOSSES = ("linear", "huber", "soft_l1", "cauchy", "arctan")


def robust_loss(name: str):
    """``least_squares``' robust loss ``name`` as a callable without the second-order correction.

    SciPy scales the Jacobian by ``sqrt(rho' + 2 rho'' f^2)`` (Triggs et al. 1999, section 4.3).
    For every loss here ``rho'' < 0`` in the robust region, and for Huber that factor is exactly 0
    beyond ``f_scale``: residuals larger than ``f_scale`` lose all curvature, and a bundle started
    a few pixels off stalls after a handful of iterations. Ceres' ``Corrector`` drops the
    correction whenever ``rho'' <= 0``, which leaves iteratively-reweighted Gauss-Newton
    (Jacobian and residual scaled by ``sqrt(rho')``); this does the same by reporting ``rho'' =
    0``. The cost minimized is unchanged. Returns ``"linear"`` for ``"linear"``.
    """
    if name not in LOSSES:
        raise InvalidControl("loss", f"unknown loss {name!r}; losses are {list(LOSSES)}")
    if name == "linear":
        return "linear"

    def loss(z: np.ndarray) -> np.ndarray:
        rho = np.empty((3, z.size))
        if name == "huber":
            large = z > 1.0
            root = np.sqrt(np.where(large, z, 1.0))
            rho[0] = np.where(large, 2.0 * root - 1.0, z)
            rho[1] = np.where(large, 1.0 / root, 1.0)
        elif name == "soft_l1":
            root = np.sqrt(1.0 + z)
            rho[0], rho[1] = 2.0 * (root - 1.0), 1.0 / root
        elif name == "cauchy":
            rho[0], rho[1] = np.log1p(z), 1.0 / (1.0 + z)
        else:  # arctan
            rho[0], rho[1] = np.arctan(z), 1.0 / (1.0 + z * z)
        rho[2] = 0.0
        return rho

    return loss


# --- the sparsity pattern (the lesson task) -------------------------------------------------------
def _jacobian_coordinates(camera_indices: np.ndarray, point_indices: np.ndarray, num_cameras: int,
                          *, camera_params: int, intrinsic_params: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of every structurally non-zero Jacobian entry, ``(M, 2, width)`` each.

    ``width = camera_params + intrinsic_params + 3``: entry ``[i, k, j]`` is residual row
    ``2 i + k`` against the ``j``-th parameter observation ``i`` depends on (its camera's block,
    then the shared intrinsics, then its point's block). The analytic Jacobian fills values in the
    same order.
    """
    m = len(camera_indices)
    camera_cols = camera_indices[:, None] * camera_params + np.arange(camera_params)  # (M, cp)
    intrinsic_cols = np.broadcast_to(num_cameras * camera_params + np.arange(intrinsic_params),
                                     (m, intrinsic_params))
    point_cols = (num_cameras * camera_params + intrinsic_params + 3 * point_indices[:, None]
                  + np.arange(3))  # (M, 3)
    cols = np.concatenate([camera_cols, intrinsic_cols, point_cols], axis=1)  # (M, width)
    cols = np.broadcast_to(cols[:, None, :], (m, 2, cols.shape[1]))
    rows = np.broadcast_to((2 * np.arange(m)[:, None] + np.arange(2))[:, :, None], cols.shape)
    return rows, cols


def bundle_sparsity(camera_indices: np.ndarray, point_indices: np.ndarray, num_cameras: int,
                    num_points: int, *, camera_params: int = 6,
                    intrinsic_params: int = 0) -> scipy.sparse.csr_matrix:
    """Which entries of the bundle-adjustment Jacobian can be non-zero: a ``(2M, n)`` 0/1 sparse matrix.

    ``n = num_cameras * camera_params + intrinsic_params + 3 * num_points``. Observation ``i``
    (camera ``camera_indices[i]`` sees point ``point_indices[i]``) owns residual rows ``2 i`` (u)
    and ``2 i + 1`` (v). Its pixel depends on exactly three groups of parameters, so each of its
    two rows has ones in three blocks and zeros elsewhere::

        columns:  | camera 0 | camera 1 | ... | shared K | point 0 | point 1 | ... |
        row 2i:   |          | 1 1 .. 1 |     | 1 1 1 1  |         |  1 1 1  |     |   (c_i = 1, p_i = 1)
        row 2i+1: |          | 1 1 .. 1 |     | 1 1 1 1  |         |  1 1 1  |     |

    - the ``camera_params`` columns of its camera (rotation, translation [, intrinsics]) starting
      at ``camera_indices[i] * camera_params``;
    - all ``intrinsic_params`` shared columns (one ``K`` for every camera), if any;
    - the 3 columns of its point starting at ``num_cameras * camera_params + intrinsic_params +
      3 * point_indices[i]``.

    A camera's columns are thus non-zero only in the rows of its own observations, a point's only
    in the rows of its track: with thousands of points the matrix is more than 99 % zeros, and the
    normal equations have the arrow shape that the Schur complement exploits.

    Args:
        camera_indices: ``(M,)`` int, the camera of each observation, in ``[0, num_cameras)``.
        point_indices: ``(M,)`` int, the point of each observation, in ``[0, num_points)``.
        num_cameras, num_points: how many of each.
        camera_params: parameters per camera (6: axis-angle and translation; 10 with its own
            ``fx, fy, cx, cy``).
        intrinsic_params: parameters shared by all cameras (4 for one refined ``K``; 0 if none).

    Returns a ``scipy.sparse.csr_matrix`` of int (0/1) to pass as ``least_squares(...,
    jac_sparsity=...)``. Written after the SciPy cookbook's ``bundle_adjustment_sparsity``
    (which fills a ``lil_matrix`` per parameter; here all entries are built at once).
    """
    cameras = np.asarray(camera_indices)
    points = np.asarray(point_indices)
    if cameras.ndim != 1 or points.shape != cameras.shape:
        raise InvalidValue("camera_indices", "camera and point indices must be two (M,) arrays of the same "
                                             f"length, got {cameras.shape} and {points.shape}")
    if cameras.size and not (np.issubdtype(cameras.dtype, np.integer)
                             and np.issubdtype(points.dtype, np.integer)):
        raise InvalidValue("camera_indices", "indices must be integers")
    if cameras.size and (cameras.min() < 0 or cameras.max() >= num_cameras):
        raise InvalidValue("camera_indices", f"must lie in [0, {num_cameras})")
    if points.size and (points.min() < 0 or points.max() >= num_points):
        raise InvalidValue("point_indices", f"must lie in [0, {num_points})")
    if camera_params < 0 or intrinsic_params < 0:
        raise InvalidValue("camera_params", "parameter counts must be non-negative")
    rows, cols = _jacobian_coordinates(cameras.astype(np.int64), points.astype(np.int64), int(num_cameras),
                                       camera_params=int(camera_params),
                                       intrinsic_params=int(intrinsic_params))
    shape = (2 * len(cameras),
             int(num_cameras) * int(camera_params) + int(intrinsic_params) + 3 * int(num_points))
    ones = np.ones(rows.size, dtype=np.int8)
    return scipy.sparse.csr_matrix((ones, (rows.ravel(), cols.ravel())), shape=shape)


# --- projection and its analytic derivatives (shared with lab.geometry.pnp) -------------------------
@overload
def project_with_jacobians(rotvecs: np.ndarray, translations: np.ndarray, points: np.ndarray,
                           intrinsics: np.ndarray, skews: np.ndarray, *, cameras: np.ndarray | None = None,
                           jacobians: Literal[True] = True) -> tuple[np.ndarray, dict[str, np.ndarray]]: ...


@overload
def project_with_jacobians(rotvecs: np.ndarray, translations: np.ndarray, points: np.ndarray,
                           intrinsics: np.ndarray, skews: np.ndarray, *, cameras: np.ndarray | None = None,
                           jacobians: Literal[False]) -> tuple[np.ndarray, None]: ...


def project_with_jacobians(rotvecs: np.ndarray, translations: np.ndarray, points: np.ndarray,
                           intrinsics: np.ndarray, skews: np.ndarray, *, cameras: np.ndarray | None = None,
                           jacobians: bool = True) -> tuple[np.ndarray, dict[str, np.ndarray] | None]:
    """Pixels of ``M`` (camera, point) pairs and the derivatives of each pixel, analytic.

    Args:
        rotvecs: ``(M, 3)`` axis-angle rotation of the camera of each pair, or ``(C, 3)`` one
            per camera when ``cameras`` is given.
        translations: ``(M, 3)``, or ``(C, 3)`` with ``cameras``.
        points: ``(M, 3)`` world points.
        intrinsics: ``(M, 4)`` ``(fx, fy, cx, cy)``.
        skews: ``(M,)`` ``K[0, 1]`` (held fixed).
        cameras: ``(M,)`` int, the camera of each pair (rotations and their Jacobians are then
            computed once per camera).

    Returns ``uv`` ``(M, 2)`` and, with ``jacobians``, a dict of ``(M, 2, k)`` blocks: ``rotvec``,
    ``t``, ``point`` and ``intrinsics``. With ``Y = R(w) X + t``, ``x = Y_1 / Y_3``, ``y = Y_2 /
    Y_3``, ``u = fx x + s y + cx``, ``v = fy y + cy``: ``dY/dw = -[R X]_x J_l(w)``
    (:func:`lab.geometry.rotations.so3_left_jacobian`), ``dY/dt = I``, ``dY/dX = R``. These are
    the derivatives ``cv2.projectPoints`` returns (without distortion).
    """
    rotvecs = np.ascontiguousarray(rotvecs, dtype=np.float64).reshape(-1, 3)
    translations = np.asarray(translations, dtype=np.float64)
    pick = np.arange(len(points)) if cameras is None else np.asarray(cameras)
    R_each = Rotation.from_rotvec(rotvecs).as_matrix()  # (C, 3, 3)
    R = R_each[pick]  # (M, 3, 3)
    rotated = np.einsum("mij,mj->mi", R, points)
    Y = rotated + (translations if cameras is None else translations[pick])
    z = Y[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = Y[:, 0] / z, Y[:, 1] / z
    fx, fy, cx, cy = intrinsics.T
    uv = np.stack([fx * x + skews * y + cx, fy * y + cy], axis=1)
    if not jacobians:
        return uv, None
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
    zeros = np.zeros_like(z)
    d_normalized = np.stack([np.stack([inv_z, zeros, -x * inv_z], axis=1),
                             np.stack([zeros, inv_z, -y * inv_z], axis=1)], axis=1)  # (M, 2, 3) d(x, y)/dY
    d_pixel = np.stack([np.stack([fx, skews], axis=1), np.stack([zeros, fy], axis=1)], axis=1)  # (M, 2, 2)
    dY = d_pixel @ d_normalized  # (M, 2, 3) d(u, v)/dY
    d_rot = dY @ (-skew(rotated) @ so3_left_jacobian(rotvecs)[pick])
    ones = np.ones_like(z)
    d_intrinsics = np.stack([np.stack([x, zeros, ones, zeros], axis=1),
                             np.stack([zeros, y, zeros, ones], axis=1)], axis=1)
    return uv, {"rotvec": d_rot, "t": dY, "point": dY @ R, "intrinsics": d_intrinsics}


# --- the solver -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BundleResult:
    """Cameras and points after bundle adjustment.

    ``R`` ``(N, 3, 3)``, ``t`` ``(N, 3)`` (world to camera), ``points`` ``(P, 3)``, ``K`` of the
    shape given (``(N, 3, 3)`` or ``(3, 3)``). ``rms_before`` / ``rms_after``: RMS reprojection
    error in pixels, ``sqrt(mean_i |pi(...) - x_i|^2)`` over the observations. ``cost_history``:
    that RMS before the first and after every iteration (what ``on_iteration`` reported).
    ``iterations``: trust-region iterations run. ``improved``: False when the optimiser did not
    lower the RMS (or the robust cost, see ``guard``) and the input came back unchanged
    (``rms_after == rms_before``; ``cost_history`` still shows the rejected run).
    """

    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    K: np.ndarray
    rms_before: float
    rms_after: float
    cost_history: np.ndarray
    iterations: int
    improved: bool = True


def _rms(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.sum(residuals * residuals) / max(len(residuals) // 2, 1)))


def _robust_cost(residuals: np.ndarray, loss: str, f_scale: float) -> float:
    """``0.5 sum f^2 rho(r^2 / f^2)``: the cost ``least_squares`` minimizes with this loss."""
    function = robust_loss(loss)
    z = residuals * residuals / f_scale**2
    values = z if function == "linear" else function(z)[0]
    return float(0.5 * f_scale**2 * np.sum(values))


def _check_inputs(K, R, t, points, camera_indices, point_indices, observations):
    R = np.asarray(R, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or len(R) < 1:
        raise InvalidValue("R", f"expected (N, 3, 3) rotations, got shape {R.shape}")
    n = len(R)
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (n, 3):
        raise InvalidValue("t", f"expected ({n}, 3) translations, got shape {t.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape not in ((3, 3), (n, 3, 3)):
        raise InvalidValue("K", f"expected (3, 3) or ({n}, 3, 3), got shape {K.shape}")
    Ks = np.broadcast_to(K, (n, 3, 3))
    if not np.allclose(Ks[:, 2], (0.0, 0.0, 1.0)) or np.any(Ks[:, 1, 0] != 0) or np.any(Ks[:, 0, 0] == 0) \
            or np.any(Ks[:, 1, 1] == 0):
        raise InvalidValue("K", "a camera matrix is [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                                "with non-zero focal lengths")
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InvalidValue("points", f"expected (P, 3) points, got shape {X.shape}")
    cameras = np.asarray(camera_indices)
    point_ids = np.asarray(point_indices)
    x = np.asarray(observations, dtype=np.float64)
    if cameras.ndim != 1 or point_ids.shape != cameras.shape or x.shape != (len(cameras), 2):
        raise InvalidValue("observations", "expected camera_indices (M,), point_indices (M,) and "
                                           f"observations (M, 2); got {cameras.shape}, {point_ids.shape} "
                                           f"and {x.shape}")
    if len(cameras) == 0:
        raise InvalidValue("observations", "there are no observations to adjust")
    if not (np.issubdtype(cameras.dtype, np.integer) and np.issubdtype(point_ids.dtype, np.integer)):
        raise InvalidValue("camera_indices", "camera and point indices must be integers")
    if cameras.min() < 0 or cameras.max() >= n:
        raise InvalidValue("camera_indices", f"must lie in [0, {n})")
    if point_ids.min() < 0 or point_ids.max() >= len(X):
        raise InvalidValue("point_indices", f"must lie in [0, {len(X)})")
    for name, value in (("K", K), ("R", R), ("t", t), ("points", X), ("observations", x)):
        if not np.all(np.isfinite(value)):
            raise InvalidValue(name, "contains NaN or infinite entries")
    return K, R, t, X, cameras.astype(np.int64), point_ids.astype(np.int64), x


def _scale_gauge_column(R: np.ndarray, t: np.ndarray, anchor: int, cameras_seen: np.ndarray,
                        camera_params: int) -> int | None:
    """The translation entry that fixes the scale: of the camera farthest from the anchor camera.

    Holding camera ``a`` fixed leaves a scaling about its centre ``C_a``, under which another
    camera's ``t_j + R_j C_a = R_j (C_a - C_j)`` (the baseline in camera ``j``'s frame) scales with
    the world. :func:`bundle_adjust` passes the ``t`` of the world centred on ``C_a``, where that
    baseline *is* ``t_j``: holding its largest component fixes the scale.
    """
    centers = -np.einsum("nji,nj->ni", R, t)
    baselines = np.einsum("nij,nj->ni", R, centers[anchor] - centers)  # R_j (C_a - C_j)
    candidates = [j for j in np.unique(cameras_seen) if j != anchor]
    if not candidates:
        return None
    j = max(candidates, key=lambda c: np.linalg.norm(baselines[c]))
    if np.linalg.norm(baselines[j]) <= 1e-12 * max(1.0, float(np.linalg.norm(centers[anchor]))):
        return None
    k = int(np.argmax(np.abs(baselines[j])))
    return int(j * camera_params + 3 + k)


# --- the solver's parts, in the order bundle_adjust uses them ---------------------------------------
def _check_controls(loss: str, f_scale: float, max_iterations: int, guard: str, jacobian: str) -> None:
    if loss not in LOSSES:
        raise InvalidControl("loss", f"unknown loss {loss!r}; losses are {list(LOSSES)}")
    if not float(f_scale) > 0:
        raise InvalidControl("f_scale", f"must be positive, got {f_scale}")
    if int(max_iterations) < 1:
        raise InvalidControl("max_iterations", f"must be at least 1, got {max_iterations}")
    if guard not in ("rms", "robust_cost"):
        raise InvalidControl("guard", f"must be 'rms' or 'robust_cost', got {guard!r}")
    if jacobian not in ("analytic", "2-point"):
        raise InvalidControl("jacobian", f"must be 'analytic' or '2-point', got {jacobian!r}")


def _check_fixed(fixed_cameras: tuple[int, ...], cameras: int) -> list[int]:
    """The held cameras, sorted and without repeats."""
    fixed = sorted({int(c) for c in fixed_cameras})
    if any(c < 0 or c >= cameras for c in fixed):
        raise InvalidControl("fixed_cameras",
                             f"camera indices must lie in [0, {cameras}), got {tuple(fixed_cameras)}")
    return fixed


@dataclass(frozen=True)
class _Parameters:
    """The parameter vector ``x`` of the module docstring, and which of its entries the solver moves.

    ``full`` holds every unknown in the solver's world, the input's translated by ``-origin`` (the
    first held camera's centre); ``free`` indexes the entries that move, the others (held poses,
    the scale-gauge entry) keep their value in ``full``. ``intrinsics`` ``(N, 4)`` are the input's
    ``(fx, fy, cx, cy)``, used as they are when not refined.
    """

    cameras: int
    points: int
    camera_params: int  # 6, or 10 with per-camera intrinsics
    intrinsic_params: int  # 4 for one shared refined K, else 0
    intrinsics: np.ndarray
    origin: np.ndarray
    full: np.ndarray
    free: np.ndarray

    @property
    def per_camera_intrinsics(self) -> bool:
        return self.camera_params == 10

    def expand(self, x_free: np.ndarray) -> np.ndarray:
        """The full vector with the free entries ``x_free``."""
        full = self.full.copy()
        full[self.free] = x_free
        return full

    def camera_block(self, full: np.ndarray) -> np.ndarray:
        """``(N, camera_params)``: rotation vector, translation [, fx, fy, cx, cy] per camera."""
        return full[: self.cameras * self.camera_params].reshape(self.cameras, self.camera_params)

    def shared_intrinsics(self, full: np.ndarray) -> np.ndarray:
        """``(4,)`` the refined shared ``(fx, fy, cx, cy)`` (with ``intrinsic_params == 4``)."""
        start = self.cameras * self.camera_params
        return full[start: start + 4]

    def point_block(self, full: np.ndarray) -> np.ndarray:
        """``(P, 3)`` the points, in the solver's world."""
        return full[self.cameras * self.camera_params + self.intrinsic_params:].reshape(self.points, 3)

    def observed_intrinsics(self, full: np.ndarray, cams: np.ndarray) -> np.ndarray:
        """``(M, 4)`` the ``(fx, fy, cx, cy)`` of the camera of each observation."""
        if self.per_camera_intrinsics:
            return self.camera_block(full)[:, 6:][cams]
        if self.intrinsic_params:
            return np.broadcast_to(self.shared_intrinsics(full), (len(cams), 4))
        return self.intrinsics[cams]


def _pack_parameters(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, cams: np.ndarray,
                     fixed: list[int], *, refine_intrinsics: bool, fix_scale: bool) -> _Parameters:
    """The starting parameter vector and its free entries: every pose but the held cameras', every
    point, the intrinsics when refined, less the scale-gauge entry (see :func:`bundle_adjust`)."""
    n = len(R)
    shared_K = K.ndim == 2
    Ks = np.broadcast_to(K, (n, 3, 3))
    per_camera_intrinsics = refine_intrinsics and not shared_K
    cp = 10 if per_camera_intrinsics else 6
    ip = 4 if (refine_intrinsics and shared_K) else 0
    camera_block = np.zeros((n, cp))
    camera_block[:, :3] = matrix_to_rotvec(R)
    # Work in a world centred on the first held camera: X~ = X - c, t~ = t + R c. The scaling left
    # by holding that camera is then about the origin, under which every t~ scales exactly, so
    # holding one entry of a t~ fixes the scale whatever the rotations do (and the result does not
    # depend on where the world's origin is). Better conditioned, too.
    origin = -R[fixed[0]].T @ t[fixed[0]] if fixed else np.zeros(3)
    camera_block[:, 3:6] = t + R @ origin
    intrinsics = np.stack([Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]], axis=1)  # (N, 4)
    if per_camera_intrinsics:
        camera_block[:, 6:] = intrinsics
    shared_block = intrinsics[0].copy() if ip else np.zeros(0)
    full = np.concatenate([camera_block.ravel(), shared_block, (X - origin).ravel()])
    free = np.ones(full.size, dtype=bool)
    for c in fixed:
        free[c * cp: c * cp + 6] = False
    if fix_scale and len(fixed) == 1:
        column = _scale_gauge_column(R, camera_block[:, 3:6], fixed[0], cams, cp)
        if column is not None:
            free[column] = False
    return _Parameters(cameras=n, points=len(X), camera_params=cp, intrinsic_params=ip,
                       intrinsics=intrinsics, origin=origin, full=full, free=np.flatnonzero(free))


class _Reprojection:
    """The residuals of the free parameters and their sparse analytic Jacobian.

    Residual rows ``2 i``, ``2 i + 1`` are ``pi(K_c (R_c X_p + t_c)) - x_i`` of observation ``i``.
    The Jacobian's pattern is :func:`_jacobian_coordinates`' without the held parameters' columns;
    its CSR layout is built once, and each evaluation only refills the values.
    """

    def __init__(self, parameters: _Parameters, K: np.ndarray, cams: np.ndarray, pts: np.ndarray,
                 obs: np.ndarray) -> None:
        self.parameters = parameters
        self.cams, self.pts, self.obs = cams, pts, obs
        self.skews = np.broadcast_to(K, (parameters.cameras, 3, 3))[:, 0, 1][cams]
        free = parameters.free
        column_map = np.full(parameters.full.size, -1)
        column_map[free] = np.arange(len(free))
        rows, cols = _jacobian_coordinates(cams, pts, parameters.cameras,
                                           camera_params=parameters.camera_params,
                                           intrinsic_params=parameters.intrinsic_params)
        self.keep = column_map[cols] >= 0
        self.rows, self.cols = rows[self.keep], column_map[cols[self.keep]]
        self.shape = (2 * len(cams), len(free))
        layout = scipy.sparse.csr_matrix((np.arange(1, len(self.rows) + 1), (self.rows, self.cols)),
                                         shape=self.shape)
        self._csr_order, self._csr_indices, self._csr_indptr = layout.data - 1, layout.indices, layout.indptr

    def _projection_inputs(self, x_free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per camera its rotation vector and translation; per observation its point and the
        ``(fx, fy, cx, cy)`` of its camera."""
        parameters = self.parameters
        full = parameters.expand(x_free)
        block = parameters.camera_block(full)
        return (block[:, :3], block[:, 3:6], parameters.point_block(full)[self.pts],
                parameters.observed_intrinsics(full, self.cams))

    def residuals(self, x_free: np.ndarray) -> np.ndarray:
        """``(2M,)`` the reprojection errors, u and v of each observation in turn."""
        rotvecs, translations, points, intrinsics = self._projection_inputs(x_free)
        uv, _ = project_with_jacobians(rotvecs, translations, points, intrinsics, self.skews,
                                       cameras=self.cams, jacobians=False)
        return (uv - self.obs).ravel()

    def jacobian(self, x_free: np.ndarray) -> scipy.sparse.csr_matrix:
        """``(2M, free)`` d residuals / d free parameters, analytic, in the pattern."""
        rotvecs, translations, points, intrinsics = self._projection_inputs(x_free)
        _, J = project_with_jacobians(rotvecs, translations, points, intrinsics, self.skews,
                                      cameras=self.cams)
        parts = [J["rotvec"], J["t"]]
        if self.parameters.per_camera_intrinsics:
            parts.append(J["intrinsics"])
        if self.parameters.intrinsic_params:
            parts.append(J["intrinsics"])
        parts.append(J["point"])
        values = np.concatenate(parts, axis=2)  # (M, 2, width), the order of _jacobian_coordinates
        return scipy.sparse.csr_matrix((values[self.keep][self._csr_order], self._csr_indices,
                                        self._csr_indptr), shape=self.shape)

    def pattern(self, sparsity: np.ndarray | scipy.sparse.spmatrix | None) -> scipy.sparse.csr_matrix:
        """The 0/1 pattern over the free columns that finite differences are grouped by: the
        Jacobian's, or the given one over all parameters with the held columns dropped."""
        if sparsity is None:
            return scipy.sparse.csr_matrix((np.ones(len(self.rows), dtype=np.int8), (self.rows, self.cols)),
                                           shape=self.shape)
        given = scipy.sparse.csr_matrix(sparsity)
        expected = (self.shape[0], self.parameters.full.size)
        if given.shape != expected:
            raise InvalidValue("sparsity", f"expected shape {expected} "
                                           "(2 rows per observation, a column per parameter), "
                                           f"got {given.shape}")
        return (given[:, self.parameters.free] != 0).astype(np.int8)


class _IterationLog:
    """The solver's callback: the RMS reprojection error after every iteration (after ``rms_before``
    in ``history``), reported to ``on_iteration``; stops the solver after ``max_iterations``."""

    def __init__(self, problem: _Reprojection, rms_before: float, max_iterations: int,
                 on_iteration: Callable[[int, float], None] | None) -> None:
        self.problem = problem
        self.max_iterations = max_iterations
        self.on_iteration = on_iteration
        self.history = [rms_before]
        self.iterations = 0

    # least_squares passes the OptimizeResult to a callback whose one parameter has this name
    def __call__(self, intermediate_result: OptimizeResult) -> None:
        self.iterations += 1
        rms = _rms(self.problem.residuals(intermediate_result.x))
        self.history.append(rms)
        if self.on_iteration is not None:
            self.on_iteration(self.iterations, rms)
        if self.iterations >= self.max_iterations:
            raise StopIteration


def _solve(problem: _Reprojection, x0: np.ndarray, log: _IterationLog, *, loss: str, f_scale: float,
           max_iterations: int, jacobian: str,
           sparsity: np.ndarray | scipy.sparse.spmatrix | None) -> np.ndarray:
    """The free parameters after ``least_squares``' sparse trust region (``x0`` when none is free)."""
    if len(x0) == 0:
        return x0
    pattern = problem.pattern(sparsity)
    analytic = jacobian == "analytic"
    result = least_squares(problem.residuals, x0, jac=problem.jacobian if analytic else "2-point",
                           jac_sparsity=None if analytic else pattern,
                           method="trf", x_scale="jac", loss=robust_loss(loss), f_scale=float(f_scale),
                           tr_solver="lsmr",
                           max_nfev=4 * int(max_iterations) + 10, callback=log)
    return result.x


def _improved(r0: np.ndarray, r1: np.ndarray, rms_before: float, rms_after: float, *, guard: str,
              loss: str, f_scale: float) -> bool:
    """Whether the solve lowered what ``guard`` names: the RMS, or the robust cost minimized."""
    if guard == "rms":
        return rms_after < rms_before
    return bool(np.all(np.isfinite(r1))
                and _robust_cost(r1, loss, float(f_scale)) < _robust_cost(r0, loss, float(f_scale)))


def _unpack_solution(parameters: _Parameters, solution: np.ndarray, K: np.ndarray, R: np.ndarray,
                     t: np.ndarray,
                     fixed: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(R, t, points, K)`` of the solution, back in the input's world; the held cameras' poses are
    the input's, bit for bit."""
    full = parameters.expand(solution)
    block = parameters.camera_block(full)
    K_out = K.copy()
    if parameters.per_camera_intrinsics:
        K_out[:, 0, 0], K_out[:, 1, 1], K_out[:, 0, 2], K_out[:, 1, 2] = block[:, 6:].T
    elif parameters.intrinsic_params:
        K_out[0, 0], K_out[1, 1], K_out[0, 2], K_out[1, 2] = parameters.shared_intrinsics(full)
    R_out = Rotation.from_rotvec(block[:, :3]).as_matrix()
    t_out = block[:, 3:6] - R_out @ parameters.origin
    R_out[fixed], t_out[fixed] = R[fixed], t[fixed]
    return R_out, t_out, parameters.point_block(full) + parameters.origin, K_out


def bundle_adjust(K: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray,
                  camera_indices: np.ndarray, point_indices: np.ndarray, observations: np.ndarray, *,
                  loss: str = "huber", f_scale: float = 1.0, refine_intrinsics: bool = False,
                  fixed_cameras: tuple[int, ...] = (0,), fix_scale: bool = True,
                  max_iterations: int = 50, jacobian: str = "analytic", guard: str = "rms",
                  sparsity: np.ndarray | scipy.sparse.spmatrix | None = None,
                  on_iteration: Callable[[int, float], None] | None = None) -> BundleResult:
    """Refine all cameras and points by minimizing the robust reprojection error (sparse trust region).

    Minimizes ``sum_i rho(|pi(K_c (R_c X_p + t_c)) - x_i|^2)`` over the free parameters (module
    docstring) with ``scipy.optimize.least_squares(method="trf", x_scale="jac")``: the Jacobian is
    analytic (``jacobian="analytic"``, a sparse matrix in the pattern of :func:`bundle_sparsity`)
    or finite differences grouped by that pattern (``jacobian="2-point"``, the SciPy cookbook's
    way); the trust-region subproblems are solved by LSMR on the sparse Jacobian.

    Gauge: the reprojection error does not change when the whole scene moves by a similarity (7
    degrees of freedom: rotation, translation, scale), so the minimum is not unique. The cameras
    in ``fixed_cameras`` keep their pose (the first one removes rotation and translation); with
    exactly one fixed camera and ``fix_scale``, one translation entry of the camera farthest from
    it is held too (its largest baseline component in its own frame, see
    ``_scale_gauge_column``), which removes the scale. The solver works in the world translated
    to the first held camera's centre, where that entry scales with the world whatever the
    rotations do, so the gauge (and the result) moves with any similarity of the input. Fixed
    cameras' intrinsics are still refined with ``refine_intrinsics``.

    Args:
        K: ``(3, 3)`` shared by all cameras, or ``(N, 3, 3)`` one per camera (skew is kept).
        R: ``(N, 3, 3)`` world-to-camera rotations; ``t`` ``(N, 3)``.
        points: ``(P, 3)``.
        camera_indices, point_indices: ``(M,)`` int, observation ``i`` is point
            ``point_indices[i]`` seen by camera ``camera_indices[i]`` ...
        observations: ``(M, 2)`` ... at this pixel (undistorted, OpenCV pixel convention).
        loss, f_scale: robust loss of ``least_squares`` and its inlier scale in pixels.
        refine_intrinsics: also refine ``fx, fy, cx, cy`` (shared when ``K`` is ``(3, 3)``).
        fixed_cameras: cameras whose pose is held.
        fix_scale: hold the scale as described above.
        max_iterations: most trust-region iterations.
        jacobian: ``"analytic"`` or ``"2-point"`` (finite differences with ``jac_sparsity``).
        sparsity: with ``jacobian="2-point"``, the pattern the finite differences are grouped by,
            over all parameters (``(2M, N*cp + ip + 3P)`` as :func:`bundle_sparsity` lays it out;
            the held parameters' columns are dropped here). Default: :func:`bundle_sparsity`'s.
            Entries it leaves out get no derivative: a wrong pattern slows or stalls the solver
            (what lesson 04 lets a student see).
        guard: what must fall for the result to be kept: ``"rms"`` (the RMS reprojection error
            over all observations) or ``"robust_cost"`` (the cost minimized: with outliers among
            the observations a robust loss may rightly let their errors, and the RMS, grow).
        on_iteration: called as ``on_iteration(iteration, rms_px)`` after every iteration (the
            RMS reprojection error in pixels), for live progress.

    Returns a :class:`BundleResult`. If the optimiser does not lower the RMS reprojection error
    (or the robust cost, see ``guard``) the input comes back unchanged (``improved=False``):
    never a worse reconstruction.

    Reference: Triggs et al., "Bundle adjustment - a modern synthesis" (1999); H&Z appendix A6.3.
    """
    _check_controls(loss, f_scale, max_iterations, guard, jacobian)
    K, R, t, X, cams, pts, obs = _check_inputs(K, R, t, points, camera_indices, point_indices, observations)
    fixed = _check_fixed(fixed_cameras, len(R))
    parameters = _pack_parameters(K, R, t, X, cams, fixed, refine_intrinsics=refine_intrinsics,
                                  fix_scale=fix_scale)
    problem = _Reprojection(parameters, K, cams, pts, obs)
    x0 = parameters.full[parameters.free]
    r0 = problem.residuals(x0)
    if not np.all(np.isfinite(r0)):
        raise InvalidValue("points", "some points project to infinity (they lie in a camera's focal plane)")
    rms_before = _rms(r0)
    log = _IterationLog(problem, rms_before, int(max_iterations), on_iteration)
    solution = _solve(problem, x0, log, loss=loss, f_scale=f_scale, max_iterations=max_iterations,
                      jacobian=jacobian, sparsity=sparsity)
    r1 = problem.residuals(solution)
    rms_after = _rms(r1) if np.all(np.isfinite(r1)) else np.inf
    if not _improved(r0, r1, rms_before, rms_after, guard=guard, loss=loss, f_scale=f_scale):
        return BundleResult(R=R.copy(), t=t.copy(), points=X.copy(), K=K.copy(), rms_before=rms_before,
                            rms_after=rms_before, cost_history=np.array(log.history),
                            iterations=log.iterations, improved=False)
    R_out, t_out, X_out, K_out = _unpack_solution(parameters, solution, K, R, t, fixed)
    return BundleResult(R=R_out, t=t_out, points=X_out, K=K_out, rms_before=rms_before, rms_after=rms_after,
                        cost_history=np.array(log.history), iterations=log.iterations, improved=True)


def bundle_adjust_progress(*args, **kwargs) -> Generator[tuple[int, float], None, BundleResult]:
    """:func:`bundle_adjust` as a generator: yields ``(iteration, rms_px)`` live, returns the
    :class:`BundleResult`.

    For generator steps (DESIGN.md section 1: long steps yield progress snapshots): the solver runs
    in a worker thread and reports each iteration through a queue, so a step can do
    ``result = yield from bundle_adjust_progress(K, R, t, ...)`` and wrap each pair in its own
    snapshot. Closing the generator cancels the solver at its next iteration (the partial result
    is discarded); an error in the solver is raised here. Takes the arguments of
    :func:`bundle_adjust` (except ``on_iteration``).
    """
    if "on_iteration" in kwargs:
        raise InvalidControl("on_iteration", "bundle_adjust_progress reports iterations itself")
    reports: queue.Queue = queue.Queue()
    cancelled = threading.Event()

    def on_iteration(iteration: int, rms: float) -> None:
        if cancelled.is_set():
            raise StopIteration
        reports.put(("iteration", (iteration, rms)))

    def work() -> None:
        try:
            reports.put(("done", bundle_adjust(*args, on_iteration=on_iteration, **kwargs)))
        except BaseException as exc:  # handed to the consumer
            reports.put(("error", exc))

    worker = threading.Thread(target=work, name="bundle-adjust", daemon=True)
    worker.start()
    try:
        while True:
            kind, payload = reports.get()
            if kind == "iteration":
                yield payload
            elif kind == "error":
                raise payload
            else:
                return payload
    finally:
        cancelled.set()
        worker.join()


__all__ = ["LOSSES", "BundleResult", "bundle_adjust", "bundle_adjust_progress", "bundle_sparsity",
           "project_with_jacobians", "robust_loss"]
