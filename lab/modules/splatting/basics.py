"""The three formulas at the heart of Gaussian splatting, one small step each: the teaching pipeline of
lesson 06 (``lab.modules.splatting:BASICS``; not a registered module).

On a few Gaussians in front of one small camera (no training, no tiles), each step can be run, inspected
and replaced by a student's function:

1. :func:`sh_dc_colors` - the colour of degree-0 spherical harmonics, ``max(C0 f_dc + 0.5, 0)`` (the code's
   ``computeColorFromSH`` at degree 0; lesson task 1);
2. :func:`project_covariances` - ``Sigma = R S S^T R^T`` and the image-plane covariance
   ``Sigma' = J W Sigma W^T J^T + 0.3 I`` (Kerbl et al. 2023, eqs. 5-6, with the code's low-pass dilation;
   lesson task 2);
3. :func:`pixel_alphas` - every pixel's Gaussians nearest first, with ``alpha = min(0.99,
   o exp(-d^T Sigma'^-1 d / 2))`` (0 under 1/255), from the covariances of step 2;
4. :func:`composite_front_to_back` - each pixel's colour ``sum_i c_i alpha_i T_i + T background`` with
   ``T_i = prod_{j<i} (1 - alpha_j)``, the pixel done before the Gaussian that would take T under 1e-4
   (eq. 3 and section 6; lesson task 3).

State names (float64): ``means`` (N, 3) world, ``log_scales`` (N, 3), ``quats`` (N, 4), ``opacities`` (N,),
``sh_dc`` (N, 3), ``R`` (3, 3) and ``t`` (3,) world to camera (``X_c = R X + t``), ``K`` (3, 3), ``width``,
``height``,
``background`` (3,) (dataset); ``colors`` (N, 3); ``covariances2d`` (N, 2, 2); ``alphas`` (P, N) and
``pixel_colors`` (P, N, 3), pixel ``p = v W + u`` row-major, its Gaussians nearest first; ``image`` (P, 3).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import torch

from lab.core import InvalidValue, Loaded, Pipeline, Range, step_result
from lab.modules.splatting.gaussians import DILATION, covariances
from lab.modules.splatting.reference import ALPHA_MAX, ALPHA_MIN, T_MIN
from lab.modules.splatting.sh import sh_colors


def _array(value: object, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape`` (``None``: any length), else :class:`InvalidValue`."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != len(shape) or any(n not in (None, m) for n, m in zip(shape, array.shape, strict=True)):
        wanted = "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
        raise InvalidValue(name, f"expected an array of shape {wanted}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "has NaN or infinite entries")
    return array


def gaussians_in_view(*, count: Annotated[int, Range(8, 200)] = 12, opaque: Annotated[int, Range(0, 8)] = 6,
                      width: Annotated[int, Range(8, 200)] = 40, height: Annotated[int, Range(8, 200)] = 30,
                      seed: int = 0) -> Loaded:
    """``count`` random Gaussians 3 to 6 units in front of a ``width`` x ``height`` camera (focal length
    ``width``, turned a little from the world axes), inside its view, of random orientation and scale
    (quaternions not normalized, opacities 0.3 to 0.95); the first ``opaque`` of them large (about a unit),
    of opacity 0.99 and overlapping at the image centre, so that with 3 or more the pixels there stop early
    (two leave T just over 1e-4, the third would take it under). Degree-0 SH coefficients from -3.5 to 3.5
    (colours under 0 and over 1); white background.

    Args:
        count: Gaussians N.
        opaque: how many of them are the large opaque ones at the centre.
        width: image width in pixels.
        height: image height in pixels.
        seed: the random seed.
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    K = np.array([[float(width), 0.0, (width - 1) / 2], [0.0, float(width), (height - 1) / 2], [0, 0, 1.0]])
    R = Rotation.from_rotvec(rng.normal(0.0, 0.2, 3)).as_matrix()
    t = rng.normal(0.0, 0.5, 3)
    z = rng.uniform(3.0, 6.0, count)
    ray = np.stack([rng.uniform(-0.4, 0.4, count) * width / K[0, 0],
                    rng.uniform(-0.4, 0.4, count) * height / K[1, 1], np.ones(count)], axis=1)
    ray[:opaque, :2] = rng.normal(0.0, 0.01, (opaque, 2))
    camera = ray * z[:, None]
    means = (camera - t) @ R
    quats = rng.normal(size=(count, 4)) * rng.uniform(0.5, 2.0, (count, 1))       # not normalized
    log_scales = rng.uniform(-3.5, -1.5, (count, 3))
    log_scales[:opaque] = np.log([1.0, 0.8, 0.9])
    opacities = rng.uniform(0.3, 0.95, count)
    opacities[:opaque] = 0.99
    state = {"means": means, "log_scales": log_scales, "quats": quats, "opacities": opacities,
             "sh_dc": rng.uniform(-3.5, 3.5, (count, 3)), "R": R, "t": t, "K": K, "width": int(width),
             "height": int(height), "background": np.ones(3)}
    return Loaded(state, {}, f"{count} Gaussians in front of a {width}x{height} camera")


def sh_dc_colors(sh_dc: np.ndarray) -> Annotated[np.ndarray, "colors"]:
    """The RGB colour (N, 3) of degree-0 spherical harmonics ``sh_dc`` (N, 3): ``C0 f_dc + 0.5``, clamped
    at 0 (not at 1), ``C0 = 1 / (2 sqrt(pi))`` (the code's ``computeColorFromSH``, ``SH2RGB``)."""
    dc = torch.as_tensor(_array(sh_dc, "sh_dc", (None, 3)))[:, None, :]
    directions = torch.zeros((len(dc), 3), dtype=torch.float64)
    return sh_colors(dc, directions, 0).numpy()


def project_covariances(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, R: np.ndarray,
                        t: np.ndarray, K: np.ndarray) -> Annotated[np.ndarray, "covariances2d"]:
    """The image-plane covariances (N, 2, 2) in pixels^2 of Gaussians at ``means`` (N, 3) with log-scales
    ``log_scales`` (N, 3) and quaternions ``quats`` (N, 4) ``(w, x, y, z)`` (not normalized) seen by camera
    ``R``, ``t``, ``K``: ``Sigma = R_q S S^T R_q^T`` (eq. 6; ``S = diag(exp(log_scales))``, ``R_q`` the
    rotation of the normalized quaternion), then ``Sigma' = J W Sigma W^T J^T + 0.3 I`` with ``W = R`` and
    ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` the Jacobian of the perspective map at the
    camera-frame mean ``(x, y, z) = R mu + t`` (eq. 5 and the code's low-pass dilation; the Gaussians here
    are inside the view, where the lab's clamping of ``x/z`` and ``y/z`` changes nothing). The readable
    form of :func:`~lab.modules.splatting.project`'s covariance (its conic is this matrix's inverse)."""
    mu = _array(means, "means", (None, 3))
    q = _array(quats, "quats", (len(mu), 4))
    log_s, K = _array(log_scales, "log_scales", (len(mu), 3)), _array(K, "K", (3, 3))
    R, t = _array(R, "R", (3, 3)), _array(t, "t", (3,))
    norms = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(norms == 0):
        raise InvalidValue("quats", "a quaternion of length 0 is no rotation")
    sigma = covariances(torch.as_tensor(log_s), torch.as_tensor(q)).numpy()     # R_q S S^T R_q^T (eq. 6)
    p = mu @ R.T + t
    if np.any(p[:, 2] <= 0):
        raise InvalidValue("means", "a Gaussian is behind the camera (camera z <= 0): it has no projection")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    J = np.zeros((len(p), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = fx / p[:, 2], -fx * p[:, 0] / p[:, 2] ** 2
    J[:, 1, 1], J[:, 1, 2] = fy / p[:, 2], -fy * p[:, 1] / p[:, 2] ** 2
    T = J @ R
    return T @ sigma @ np.swapaxes(T, 1, 2) + DILATION * np.eye(2)


@step_result
class PixelAlphas:
    """Result of :func:`pixel_alphas`."""

    alphas: np.ndarray
    pixel_colors: np.ndarray


def pixel_alphas(means: np.ndarray, covariances2d: np.ndarray, opacities: np.ndarray, colors: np.ndarray,
                 R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> PixelAlphas:
    """Every pixel's Gaussians, nearest first (by camera depth; all of them, no tiles): ``alphas`` (P, N)
    ``min(0.99, o exp(-d^T Sigma'^-1 d / 2))``, ``d`` the pixel minus the projected mean, set to 0 under
    1/255 (or where ``Sigma'`` is not positive definite), and their colours ``pixel_colors`` (P, N, 3)."""
    means = _array(means, "means", (None, 3))
    cov = _array(covariances2d, "covariances2d", (len(means), 2, 2))
    opacities = _array(opacities, "opacities", (len(means),))
    colors = _array(colors, "colors", (len(means), 3))
    camera = means @ _array(R, "R", (3, 3)).T + _array(t, "t", (3,))
    order = np.argsort(camera[:, 2], kind="stable")
    mean2d = camera[:, :2] / camera[:, 2:] @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
    v, u = np.mgrid[0:height, 0:width]
    d = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :] - mean2d[None]          # (P, N, 2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    ok = (det > 0) & (cov[:, 0, 0] > 0)
    inverse = np.linalg.inv(np.where(ok[:, None, None], cov, np.eye(2)))
    power = -0.5 * np.einsum("pni,nij,pnj->pn", d, inverse, d)
    alpha = np.minimum(ALPHA_MAX, opacities[None] * np.exp(np.minimum(power, 0.0)))
    alpha = np.where(ok[None] & (alpha >= ALPHA_MIN), alpha, 0.0)
    ordered = colors[order]
    return PixelAlphas(alpha[:, order], np.broadcast_to(ordered, (len(d), *ordered.shape)).copy())


def composite_front_to_back(alphas: np.ndarray, pixel_colors: np.ndarray,
                            background: np.ndarray) -> Annotated[np.ndarray, "image"]:
    """Each pixel's colour (P, 3): its Gaussians ``alphas`` (P, N) with colours ``pixel_colors`` (P, N, 3),
    nearest first, composited front to back, ``C = sum_i c_i alpha_i T_i + T background``,
    ``T_i = prod_{j<i} (1 - alpha_j)``; an alpha under 1/255 is skipped, and the pixel is done before the
    Gaussian that would take the transmittance under 1e-4 (that one and those behind it add nothing)."""
    alphas = _array(alphas, "alphas", (None, None))
    pixel_colors = _array(pixel_colors, "pixel_colors", (*alphas.shape, 3))
    T = np.ones(len(alphas))
    color = np.zeros((len(alphas), 3))
    alive = np.ones(len(alphas), dtype=bool)
    for k in range(alphas.shape[1]):
        a = alphas[:, k]
        counts = a >= ALPHA_MIN
        alive &= ~(counts & (T * (1.0 - a) < T_MIN))
        use = alive & counts
        color[use] += (a * T)[use, None] * pixel_colors[use, k]
        T = np.where(use, T * (1.0 - a), T)
    return color + T[:, None] * _array(background, "background", (3,))


BASICS = Pipeline.build(
    name="splatting_basics",
    title="Gaussian splatting: the formulas",
    summary="The colour of degree-0 spherical harmonics, the image-plane covariance J W Sigma W^T J^T + "
            "0.3 I, each pixel's alphas, and front-to-back compositing, each a step, on a few Gaussians "
            "before one small camera.",
    steps=[sh_dc_colors, project_covariances, pixel_alphas, composite_front_to_back],
    datasets=[gaussians_in_view],
)

__all__ = ["BASICS", "PixelAlphas", "composite_front_to_back", "gaussians_in_view", "pixel_alphas",
           "project_covariances", "sh_dc_colors"]
