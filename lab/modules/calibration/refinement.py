"""Levenberg-Marquardt on the reprojection error of every corner, over all parameters at once.

Parameters: ``theta`` = (fx, fy, cx, cy, skew, k1, k2, p1, p2, k3) shared by all views (``free``
marks those optimized), and per view ``w`` (axis-angle, 3) and ``t`` (3). The residual of corner
``j`` in view ``v`` is ``project(K, dist, R(w_v) X_j + t_v) - x_j`` (:class:`ReprojectionProblem`,
with its analytic Jacobian). Each pose touches only its own view's corners, so ``J^T J`` is an
arrow matrix and every damped step is solved by the Schur complement on the 6x6 pose blocks
(:func:`solve_damped`), as in bundle adjustment. :func:`standard_deviations` gives the parameters'
uncertainties from the Jacobian at the solution.

Reference: Z. Zhang (2000), sections 3.2 and 3.3; K. Levenberg (1944), D. Marquardt (1963);
Triggs et al., "Bundle adjustment - a modern synthesis" (2000), section 6.1 (the Schur complement);
J.-Y. Bouguet, Camera Calibration Toolbox for Matlab (uncertainties).
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from lab.core import InvalidValue, Points2D, Progress, StepFailed
from lab.geometry.camera import distort_components
from lab.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix, so3_left_jacobian
from lab.modules.calibration.observations import Observations

#: Names of the intrinsic parameters, in the order of ``theta`` and of ``std_intrinsics``.
INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")


def free_parameters(*, estimate_skew: bool, fix_k3: bool, fix_tangential: bool) -> np.ndarray:
    """``(10,)`` booleans: which of :data:`INTRINSIC_NAMES` are optimized (the others are held at 0)."""
    tangential = not fix_tangential
    return np.array([True, True, True, True, estimate_skew, True, True, tangential, tangential, not fix_k3])


class ReprojectionProblem:
    """The reprojection residuals of all corners and their Jacobian, blocked by view.

    The corners are laid out as ``(M views, S slots)`` (views with fewer corners padded with
    rows whose residual and Jacobian are zero), so that every block of ``J^T J`` is one batched
    matrix product. ``index`` maps the observations (sorted by view) to their slots.
    """

    def __init__(self, seen: Observations, free: np.ndarray) -> None:
        num_views = len(seen.views)
        self.num_free = int(free.sum()) + 6 * num_views
        if 2 * len(seen) <= self.num_free:
            raise InvalidValue("corners", f"{len(seen)} corners give {2 * len(seen)} equations, not enough "
                                          f"for {self.num_free} parameters; use more views or more corners")
        self.seen = seen
        self.free = free
        counts = np.bincount(seen.position, minlength=num_views)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(len(seen.position)) - starts[seen.position]  # observations are sorted by view
        size = int(counts.max())
        self.index = (seen.position, slot)
        self.counts = counts
        weight = np.zeros((num_views, size))
        weight[self.index] = 1.0
        self.weight = weight
        self.observed = np.zeros((num_views, size, 2))
        self.observed[self.index] = seen.pixels
        # the padding repeats a real corner (with weight 0)
        self.points = np.repeat(seen.points[starts][:, None, :], size, axis=1)
        self.points[self.index] = seen.points

    def residuals(self, theta: np.ndarray, w: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Residuals ``(M, S, 2)`` (zero in the padding)."""
        return self.linearize(theta, w, t, jacobian=False)[0]

    def linearize(self, theta: np.ndarray, w: np.ndarray, t: np.ndarray, *,
                  jacobian: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals ``(M, S, 2)``, ``d r / d theta[free]`` ``(M, S, 2, p)`` and ``d r / d (w_v, t_v)``
        ``(M, S, 2, 6)`` (empty Jacobians without ``jacobian``)."""
        fx, fy, cx, cy, s = theta[:5]
        R = rotvec_to_matrix(w)
        Y = self.points @ np.swapaxes(R, 1, 2)  # R X, (M, S, 3)
        Xc = Y + t[:, None, :]
        inv_z = 1.0 / Xc[..., 2]
        x = Xc[..., 0] * inv_z
        y = Xc[..., 1] * inv_z
        xd, yd, dxx, dxy, dyy = distort_components(x, y, theta[5:])
        weight = self.weight
        r = np.stack([(fx * xd + s * yd + cx - self.observed[..., 0]) * weight,
                      (fy * yd + cy - self.observed[..., 1]) * weight], axis=-1)
        if not jacobian:
            return r, np.empty(0), np.empty(0)
        M, S = x.shape
        J_in = np.zeros((M, S, 2, 10))
        J_in[..., 0, 0] = xd * weight
        J_in[..., 1, 1] = yd * weight
        J_in[..., 0, 2] = weight
        J_in[..., 1, 3] = weight
        J_in[..., 0, 4] = yd * weight
        # d(x_d, y_d)/d(k1, k2, p1, p2, k3), then through A = [[fx, s], [0, fy]]
        r2 = x * x + y * y
        r4 = r2 * r2
        xy2 = 2.0 * x * y
        dx = np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x, x * r4 * r2], axis=-1)
        dy = np.stack([y * r2, y * r4, r2 + 2.0 * y * y, xy2, y * r4 * r2], axis=-1)
        J_in[..., 0, 5:] = (fx * dx + s * dy) * weight[..., None]
        J_in[..., 1, 5:] = fy * dy * weight[..., None]
        # d(u, v)/d(Xc) = A Jd Dproj with Jd = d(x_d, y_d)/d(x, y), Dproj = d(x, y)/d(Xc)
        scale = inv_z * weight
        a00 = (fx * dxx + s * dxy) * scale
        a01 = (fx * dxy + s * dyy) * scale
        a10 = fy * dxy * scale
        a11 = fy * dyy * scale
        P = np.empty((M, S, 2, 3))
        P[..., 0, 0], P[..., 0, 1], P[..., 0, 2] = a00, a01, -(a00 * x + a01 * y)
        P[..., 1, 0], P[..., 1, 1], P[..., 1, 2] = a10, a11, -(a10 * x + a11 * y)
        # dXc/dw = -[Y]x J_left(w); a row p of P gives p (-[Y]x) = Y x p, then times J_left per view
        Yb = Y[:, :, None, :]
        cross = np.stack([Yb[..., 1] * P[..., 2] - Yb[..., 2] * P[..., 1],
                          Yb[..., 2] * P[..., 0] - Yb[..., 0] * P[..., 2],
                          Yb[..., 0] * P[..., 1] - Yb[..., 1] * P[..., 0]], axis=-1)  # (M, S, 2, 3)
        J_pose = np.empty((M, S, 2, 6))
        J_pose[..., :3] = (cross.reshape(M, 2 * S, 3) @ so3_left_jacobian(w)).reshape(M, S, 2, 3)
        J_pose[..., 3:] = P
        return r, J_in[..., self.free], J_pose

    @staticmethod
    def normal_equations(r: np.ndarray, J_in: np.ndarray, J_pose: np.ndarray) -> tuple[np.ndarray, ...]:
        """Blocks of ``J^T J`` and ``J^T r``: ``U`` (p, p), ``W`` (M, p, 6), ``V`` (M, 6, 6), ``g_in``,
        ``g_pose``."""
        M, p = J_in.shape[0], J_in.shape[-1]
        A = J_in.reshape(M, -1, p)
        B = J_pose.reshape(M, -1, 6)
        e = r.reshape(M, -1, 1)
        flat = A.reshape(-1, p)
        At, Bt = np.swapaxes(A, 1, 2), np.swapaxes(B, 1, 2)
        return flat.T @ flat, At @ B, Bt @ B, flat.T @ e.reshape(-1), (Bt @ e)[..., 0]

    def per_view_rms(self, r: np.ndarray) -> np.ndarray:
        """RMS reprojection error ``(M,)`` of each view."""
        return np.sqrt(np.sum(r * r, axis=(1, 2)) / self.counts)

    def by_observation(self, r: np.ndarray) -> np.ndarray:
        """Residuals ``(n, 2)`` in the order of the observations (reprojected minus detected)."""
        return r[self.index]


def solve_damped(U: np.ndarray, W: np.ndarray, V: np.ndarray, g_in: np.ndarray, g_pose: np.ndarray,
                 damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``(J^T J + damping diag(J^T J)) delta = -J^T r`` by the Schur complement on the pose blocks.

    ``S = U* - sum_v W_v V*_v^-1 W_v^T`` is the small system in the intrinsics; each view's pose
    update follows from it: ``delta_v = V*_v^-1 (-g_v - W_v^T delta_in)``.
    """
    Ud = U + damping * np.diag(np.diag(U))
    idx = np.arange(6)
    Vd = V.copy()
    Vd[:, idx, idx] *= 1.0 + damping
    V_inv = np.linalg.inv(Vd)
    WVinv = W @ V_inv  # (M, p, 6)
    S = Ud - np.einsum("mij,mkj->ik", WVinv, W)
    rhs = -g_in + np.einsum("mij,mj->i", WVinv, g_pose)
    delta_in = np.linalg.solve(S, rhs)
    delta_pose = np.einsum("mij,mj->mi", V_inv, -g_pose - np.einsum("mji,j->mi", W, delta_in))
    return delta_in, delta_pose


@dataclass(frozen=True)
class Fit:
    """Where Levenberg-Marquardt stopped: the parameters, residuals and Jacobians there, the cost
    (sum of squared residuals), the RMS error after every iteration and the iterations run."""

    theta: np.ndarray
    w: np.ndarray
    t: np.ndarray
    r: np.ndarray
    J_in: np.ndarray
    J_pose: np.ndarray
    cost: float
    history: list[float]
    iterations: int

    @property
    def K(self) -> np.ndarray:
        theta = self.theta
        return np.array([[theta[0], theta[4], theta[2]], [0.0, theta[1], theta[3]], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return self.theta[5:].copy()

    @property
    def rotations(self) -> np.ndarray:
        return rotvec_to_matrix(self.w)


def levenberg_marquardt(problem: ReprojectionProblem, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                        t: np.ndarray, *, max_iterations: int) -> Generator[Progress, None, Fit]:
    """Minimize the problem's cost from ``K``, ``dist``, poses ``R``, ``t``; yields the RMS every iteration.

    ``lambda`` shrinks 10x after a step that lowers the cost and grows 10x after one that does not;
    stops when the relative decrease of the cost or the step falls below 1e-10. The progress
    carries the reprojected corners as a preview (``reprojected``).
    """
    free, seen = problem.free, problem.seen
    theta = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1], *dist])
    theta[~free] = 0.0
    w = matrix_to_rotvec(R)
    t = t.copy()
    r, J_in, J_pose = problem.linearize(theta, w, t)
    cost = float(np.sum(r * r))
    if not np.isfinite(cost):
        raise InvalidValue("K_init", "the initial parameters put board corners behind the camera")
    n_points = len(seen)
    history = [np.sqrt(cost / n_points)]
    damping = 1e-3
    iterations = 0
    for iterations in range(1, int(max_iterations) + 1):
        U, W, V, g_in, g_pose = problem.normal_equations(r, J_in, J_pose)
        try:
            delta_in, delta_pose = solve_damped(U, W, V, g_in, g_pose, damping)
        except np.linalg.LinAlgError:
            raise StepFailed("refine_calibration", "the normal equations are singular: the views do not "
                                                   "constrain the parameters (too few or parallel "
                                                   "views?)") from None
        theta_new = theta.copy()
        theta_new[free] += delta_in
        w_new = w + delta_pose[:, :3]
        t_new = t + delta_pose[:, 3:]
        r_new = problem.residuals(theta_new, w_new, t_new)
        cost_new = float(np.sum(r_new * r_new))
        step = np.sqrt(np.sum(delta_in**2) + np.sum(delta_pose**2))
        size = np.sqrt(np.sum(theta[free] ** 2) + np.sum(w**2) + np.sum(t**2))
        converged = False
        if np.isfinite(cost_new) and cost_new < cost:
            converged = (cost - cost_new) <= 1e-10 * cost or step <= 1e-10 * size
            theta, w, t, cost = theta_new, w_new, t_new, cost_new
            r, J_in, J_pose = problem.linearize(theta, w, t)
            damping = max(damping / 10.0, 1e-12)
        else:
            damping *= 10.0
            converged = damping > 1e12 or step <= 1e-12 * size
        history.append(np.sqrt(cost / n_points))
        preview = Points2D(seen.pixels + problem.by_observation(r), view=seen.image, ids=seen.ids,
                           image="images")
        yield Progress(iteration=iterations, total=int(max_iterations), loss=history[-1],
                       message=f"RMS {history[-1]:.5f} px, lambda {damping:.1e}",
                       values={"reprojected": preview})
        if converged:
            break
    return Fit(theta, w, t, r, J_in, J_pose, cost, history, iterations)


def standard_deviations(problem: ReprojectionProblem, fit: Fit) -> np.ndarray:
    """``(10,)`` standard deviations of :data:`INTRINSIC_NAMES` at the solution (0: fixed; NaN: singular).

    ``sigma^2 = RSS / (m - n)`` (m residuals, n free parameters) times the diagonal of
    ``(J^T J)^-1``, whose intrinsic block is the inverse of the Schur complement;
    ``cv2.calibrateCameraExtended`` reports the same ``stdDeviationsIntrinsics`` and Bouguet's
    toolbox prints three times them as the error bars.
    """
    U, W, V, _, _ = problem.normal_equations(fit.r, fit.J_in, fit.J_pose)
    std = np.zeros(10)
    try:
        S = U - np.einsum("mij,mkj->ik", W @ np.linalg.inv(V), W)
        sigma2 = fit.cost / (2 * len(problem.seen) - problem.num_free)
        std[problem.free] = np.sqrt(np.maximum(np.diag(np.linalg.pinv(S)), 0.0) * sigma2)
    except np.linalg.LinAlgError:
        std[:] = np.nan
    return std


__all__ = ["INTRINSIC_NAMES", "Fit", "ReprojectionProblem", "free_parameters", "levenberg_marquardt",
           "solve_damped", "standard_deviations"]
