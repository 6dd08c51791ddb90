"""Model selection between F and a homography: the robust noise scale of residuals and Torr's GRIC.

Reference: P. Torr, "An assessment of information criteria for motion model selection", CVPR 1997;
"Geometric motion segmentation and model selection", Phil. Trans. R. Soc. A 356, 1998; P. Torr and
A. Zisserman, "MLESAC", CVIU 78(1), 2000; H&Z section 4.2.6 (the Sampson error of a homography).
"""

from __future__ import annotations

import math

import numpy as np

from lab.geometry.homogeneous import to_homogeneous
from lab.modules.epipolar._kernels import _noise_sigma_kernel

#: Torr's GRIC for two views: ``r = 4`` coordinates per correspondence (x1, y1, x2, y2), ``lambda3 = 2``
#: (the robust cap of a squared normalized residual is ``lambda3 (r - d)``). F: a 3-dimensional variety
#: (``d = 3``) with ``k = 7`` parameters; H: ``d = 2``, ``k = 8``.
GRIC_R = 4
GRIC_LAMBDA3 = 2.0
GRIC_F = (3, 7)
GRIC_H = (2, 8)

#: Noise floor (px) of the scale estimate, so that exact synthetic data (residuals ~1e-10) give finite GRIC.
SIGMA_FLOOR_PX = 0.01


def truncated_variance_factor(c: float, dof: int = 1) -> float:
    """``E[q | q <= c^2] / dof`` for ``q`` chi-square with ``dof`` (1 or 2) degrees of freedom.

    One: ``1 - 2 c phi(c) / (2 Phi(c) - 1)`` (a truncated normal); two: ``(1 - (1 + c^2/2) e^(-c^2/2)) /
    (1 - e^(-c^2/2))`` (a truncated Rayleigh). 0.973 and 0.949 at ``c = 3``.
    """
    if dof == 2:
        tail = math.exp(-0.5 * c * c)
        return (1.0 - (1.0 + 0.5 * c * c) * tail) / (1.0 - tail)
    inside = math.erf(c / math.sqrt(2.0))
    return 1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi) / inside


def noise_sigma(residuals: np.ndarray, *, start_px: float = 1.0, cut: float = 3.0,
                iterations: int = 30) -> float:
    """Robust noise scale (px) of residuals ``(N,)``: ``sigma |N(0, 1)|`` for inliers, anything for outliers.

    The iteration is compiled; ``noise_sigma_reference`` is its readable form.

    Start from ``max(1.4826 median, start_px)`` (at or above sigma with up to ~50 % outliers), then
    iterate the truncated estimate: keep ``|d| <= cut sigma`` and set ``sigma^2 = mean(d^2) / E[z^2 | |z|
    <= cut]`` (the correction for the truncation, 0.973 at 3 sigma) until it settles; it descends to the
    inliers' scale whatever the RANSAC threshold was (a 1 px threshold on 2 px noise keeps only a
    truncated core, whose spread alone would say ~0.5 px). Floored at ``SIGMA_FLOOR_PX``. Reference:
    Huber, Robust Statistics (1981), the MAD; P. Torr and A. Zisserman, "MLESAC", CVIU 78(1), 2000.
    """
    d = np.abs(residuals[np.isfinite(residuals)])
    if len(d) == 0:
        return SIGMA_FLOOR_PX
    start = max(1.4826 * float(np.median(d)), float(start_px), SIGMA_FLOOR_PX)
    factor = truncated_variance_factor(cut)
    return float(_noise_sigma_kernel(d, start, cut, factor, iterations, SIGMA_FLOOR_PX))


def gric(residuals: np.ndarray, sigma: float, d: int, k: int, r: int = GRIC_R) -> float:
    """Torr's geometric robust information criterion of a model with residuals ``(n,)`` (px): lower is better.

    ``GRIC = sum rho(e_i^2 / sigma^2) + lambda1 d n + lambda2 k``, ``rho(x) = min(x, lambda3 (r - d))``,
    ``lambda1 = ln r``, ``lambda2 = ln(r n)``, ``lambda3 = 2``; ``d`` the dimension of the model's
    variety, ``k`` its parameters, ``r`` the dimension of the data (4 for two views). A model of lower
    dimension pays less per point (``lambda1 d``) but fits worse: a homography (d = 2) beats F (d = 3)
    when its residuals are hardly larger. Reference: P. Torr, "An assessment of information criteria
    for motion model selection", CVPR 1997; "Geometric motion segmentation and model selection",
    Phil. Trans. R. Soc. A 356, 1998.
    """
    n = len(residuals)
    capped = np.minimum(np.nan_to_num(residuals / sigma, nan=np.inf) ** 2, GRIC_LAMBDA3 * (r - d))
    return float(capped.sum() + np.log(r) * d * n + np.log(r * n) * k)


def homography_sampson_distance(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error (px) of each pair ``(N, 2)`` under a homography ``H`` ``(3, 3)``: ``(N,)``.

    The two equations ``e = (a - u c, b - v c)`` with ``(a, b, c) = H x1`` and ``x2 = (u, v)`` (the
    rows of H&Z's ``A_i h``) vanish on the variety ``x2 ~ H x1``; linearized, the smallest move of the
    pair ``(x1, y1, x2, y2)`` onto it has squared length ``e^T (J J^T)^-1 e``, ``J`` the 2 x 4
    Jacobian of ``e``. It is the Sampson error of H (H&Z section 4.2.6, eq. 4.12), the same kind of
    distance as :func:`sampson_distance` for F: both measure the move in the joint image space, with
    the noise of both images, which is what GRIC compares (the transfer error ``|x2 - H x1|`` counts
    only image 2 and doubles the variance; the symmetric transfer error counts the noise twice).
    Identity H and ``x2 = x1 + d``: ``|d| / sqrt(2)`` (half the move in each image).
    """
    u, v = x2[:, 0], x2[:, 1]
    a, b, c = (H @ to_homogeneous(x1).T)
    e1, e2 = a - u * c, b - v * c
    p1, q1 = H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]  # J row 1: (p1, q1, -c, 0)
    p2, q2 = H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]  # J row 2: (p2, q2, 0, -c)
    m11, m22, m12 = p1 * p1 + q1 * q1 + c * c, p2 * p2 + q2 * q2 + c * c, p1 * p2 + q1 * q2
    with np.errstate(divide="ignore", invalid="ignore"):
        squared = (m22 * e1 * e1 - 2.0 * m12 * e1 * e2 + m11 * e2 * e2) / (m11 * m22 - m12 * m12)
    return np.sqrt(np.maximum(squared, 0.0))


__all__ = ["GRIC_F", "GRIC_H", "GRIC_LAMBDA3", "GRIC_R", "SIGMA_FLOOR_PX", "gric",
           "homography_sampson_distance", "noise_sigma", "truncated_variance_factor"]
