"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the hint of
tasks.toml when the student's result is what the mistake computes. Each is built from the lab's own
functions where it can be (lab.modules.splatting.basics, the module's covariances and its reference
rasterizer's constants), so it is exact by construction.
"""

import numpy as np
import torch

from lab.modules.splatting import covariances
from lab.modules.splatting.basics import composite_front_to_back, project_covariances
from lab.modules.splatting.reference import ALPHA_MIN, T_MIN
from lab.modules.splatting.sh import C0


# --- the colour of degree 0 ----------------------------------------------------------------------------
def sh_clamped_at_one(sh_dc):
    """``C0 f_dc + 0.5`` clamped to [0, 1]: the paper's code clamps at 0 only."""
    return np.clip(C0 * np.asarray(sh_dc, dtype=np.float64) + 0.5, 0.0, 1.0)


def sh_without_offset(sh_dc):
    """``max(C0 f_dc, 0)``: the 0.5 the code adds to every colour (its coefficients are stored centred on
    grey) left out."""
    return np.maximum(C0 * np.asarray(sh_dc, dtype=np.float64), 0.0)


def sh_without_basis_constant(sh_dc):
    """``max(f_dc + 0.5, 0)``: the coefficient taken as the colour, the basis function ``Y_0 = C0`` left
    out."""
    return np.maximum(np.asarray(sh_dc, dtype=np.float64) + 0.5, 0.0)


# --- the covariance in the image -----------------------------------------------------------------------
def _world_covariances(log_scales, quats):
    """``Sigma = R_q S S^T R_q^T`` (N, 3, 3) by the module's :func:`covariances` (eq. 6)."""
    return covariances(torch.as_tensor(np.asarray(log_scales, dtype=np.float64)),
                       torch.as_tensor(np.asarray(quats, dtype=np.float64))).numpy()


def _jacobian_times_w(means, R, t, K, *, depth_column=True):
    """``T = J W`` (N, 2, 3): the perspective map's Jacobian at the camera-frame means times ``W = R``
    (``depth_column`` False: ``J`` without its third column)."""
    W = np.asarray(R, dtype=np.float64)
    p = np.asarray(means, dtype=np.float64) @ W.T + np.asarray(t, dtype=np.float64)
    fx, fy = float(K[0][0]), float(K[1][1])
    J = np.zeros((len(p), 2, 3))
    J[:, 0, 0], J[:, 1, 1] = fx / p[:, 2], fy / p[:, 2]
    if depth_column:
        J[:, 0, 2], J[:, 1, 2] = -fx * p[:, 0] / p[:, 2] ** 2, -fy * p[:, 1] / p[:, 2] ** 2
    return J @ W


def _through(T, sigma):
    """``T Sigma T^T + 0.3 I`` (N, 2, 2)."""
    return T @ sigma @ np.swapaxes(T, 1, 2) + 0.3 * np.eye(2)


def cov_without_jacobian(means, log_scales, quats, R, t, K):
    """``Sigma' = (W Sigma W^T)_(2x2) + 0.3 I``: the camera-frame covariance's x-y block, never carried
    through the perspective map's Jacobian (so in world units, not pixels)."""
    W = np.broadcast_to(np.asarray(R, dtype=np.float64)[:2], (len(np.asarray(means)), 2, 3))
    return _through(W, _world_covariances(log_scales, quats))


def cov_jacobian_without_depth_column(means, log_scales, quats, R, t, K):
    """``J = diag(fx/z, fy/z)``: the Jacobian without its third column ``-fx x/z^2``, ``-fy y/z^2`` (a
    scaled orthographic projection: how the footprint changes with depth across the Gaussian is lost)."""
    T = _jacobian_times_w(means, R, t, K, depth_column=False)
    return _through(T, _world_covariances(log_scales, quats))


def cov_rotation_transposed(means, log_scales, quats, R, t, K):
    """``Sigma = R_q^T S S^T R_q``: the quaternion's rotation transposed (its conjugate's rotation), the
    ellipsoid turned the other way."""
    conjugate = np.asarray(quats, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])
    return project_covariances(means, log_scales, conjugate, R, t, K)


def cov_quaternion_not_normalized(means, log_scales, quats, R, t, K):
    """The rotation formula ``1 - 2 (y^2 + z^2), 2 (x y - w z), ...`` applied to the quaternion as it is:
    it holds for a unit quaternion only, so without dividing by its length first the matrix is no
    rotation."""
    w, x, y, z = np.asarray(quats, dtype=np.float64).T
    Rq = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                   2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                   2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1)
    M = Rq.reshape(-1, 3, 3) * np.exp(np.asarray(log_scales, dtype=np.float64))[:, None, :]
    return _through(_jacobian_times_w(means, R, t, K), M @ np.swapaxes(M, 1, 2))


def cov_without_dilation(means, log_scales, quats, R, t, K):
    """``Sigma' = J W Sigma W^T J^T`` without the ``+ 0.3 I`` low-pass dilation."""
    return project_covariances(means, log_scales, quats, R, t, K) - 0.3 * np.eye(2)


# --- front-to-back compositing -------------------------------------------------------------------------
def _float64(*arrays):
    """The arrays as float64 (a helper: its parameters are no step's, so it is no mistake)."""
    return tuple(np.asarray(a, dtype=np.float64) for a in arrays)


def composite_back_to_front_weights(alphas, pixel_colors, background):
    """The back-to-front "over" operator, ``C = alpha_i c_i + (1 - alpha_i) C`` from the background, applied
    to the Gaussians in the front-to-back order they are given: the farthest one ends up on top."""
    a, c, bg = _float64(alphas, pixel_colors, background)
    color = np.broadcast_to(bg, (len(a), 3)).copy()
    for k in range(a.shape[1]):
        use = (a[:, k] >= ALPHA_MIN)[:, None]
        color = np.where(use, a[:, k, None] * c[:, k] + (1.0 - a[:, k, None]) * color, color)
    return color


def composite_transmittance_updated_first(alphas, pixel_colors, background):
    """``T`` multiplied by ``1 - alpha_i`` before Gaussian i adds ``c_i alpha_i T``: every Gaussian is dimmed
    by its own alpha (``T_(i+1)`` used where ``T_i`` belongs), the first one too."""
    a, c, bg = _float64(alphas, pixel_colors, background)
    T, color = np.ones(len(a)), np.zeros((len(a), 3))
    alive = np.ones(len(a), dtype=bool)
    for k in range(a.shape[1]):
        counts = a[:, k] >= ALPHA_MIN
        after = T * (1.0 - a[:, k])
        alive &= ~(counts & (after < T_MIN))
        use = alive & counts
        T = np.where(use, after, T)
        color[use] += (a[:, k] * T)[use, None] * c[use, k]
    return color + T[:, None] * bg


def composite_without_early_termination(alphas, pixel_colors, background):
    """Every Gaussian composited, however small T has become: the pixel never stops at ``T < 1e-4``."""
    a, c, bg = _float64(alphas, pixel_colors, background)
    T, color = np.ones(len(a)), np.zeros((len(a), 3))
    for k in range(a.shape[1]):
        use = a[:, k] >= ALPHA_MIN
        color[use] += (a[:, k] * T)[use, None] * c[use, k]
        T = np.where(use, T * (1.0 - a[:, k]), T)
    return color + T[:, None] * bg


def composite_stops_after_crossing(alphas, pixel_colors, background):
    """The Gaussian that takes T under 1e-4 composited, then the pixel stopped: the code stops *before* it
    (it tests ``T (1 - alpha) < 1e-4`` first and adds nothing)."""
    a, c, bg = _float64(alphas, pixel_colors, background)
    T, color = np.ones(len(a)), np.zeros((len(a), 3))
    alive = np.ones(len(a), dtype=bool)
    for k in range(a.shape[1]):
        use = alive & (a[:, k] >= ALPHA_MIN)
        color[use] += (a[:, k] * T)[use, None] * c[use, k]
        T = np.where(use, T * (1.0 - a[:, k]), T)
        alive &= T >= T_MIN
    return color + T[:, None] * bg


def composite_without_background(alphas, pixel_colors, background):
    """``sum_i c_i alpha_i T_i`` alone: the background's share ``T`` (what the Gaussians leave) never
    added."""
    a, c, _ = _float64(alphas, pixel_colors, background)
    return composite_front_to_back(a, c, np.zeros(3))
