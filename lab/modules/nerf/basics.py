"""The arithmetic of NeRF, one small step each on exact float64 arrays: the teaching pipeline of lesson 05.

The NeRF module (:mod:`lab.modules.nerf`) does these inside its training step, on tensors. Here each is a
step a student replaces with their own function, checked against the module's implementation and against
closed forms (it is not a registered module: the lesson names it ``lab.modules.nerf.basics:PIPELINE``):

1. :func:`positional_encoding`  gamma(p) = (sin(2^k pi p), cos(2^k pi p)), k < L (lesson task 1)
2. :func:`ray_directions`       one ray direction per pixel, R^T K^-1 (u, v, 1) (lesson task 2)
3. :func:`points_along_rays`    the points at depth :data:`RAY_DEPTH` on those rays (they must project back
                                onto their pixels: evaluated)
4. :func:`volume_weights`       w_i = T_i alpha_i of samples along rays (lesson task 3)
5. :func:`composite`            colour, depth and opacity from the weights (evaluated against a homogeneous
                                slab's 1 - exp(-sigma d) and an opaque step's depth)
6. :func:`sample_pdf`           inverse-CDF samples of the weights' piecewise-constant PDF (lesson task 4)
7. :func:`bin_shares`           the share of those samples in each bin (evaluated against the PDF)

State names (float64): ``points`` (N, 3) in [-1, 1]; the camera ``K`` (3, 3), ``R`` (3, 3), ``t`` (3,),
``image_size`` (2,) int (W, H); along ``R`` rays: ``sigmas`` (R, S) >= 0, sorted ``depths`` (R, S) and
``far`` (the last interval ends there), ``colors`` (R, S, 3); for sampling ``bins`` (R, M + 1) increasing
edges, ``bin_weights`` (R, M) >= 0, ``uniforms`` (R, K) in [0, 1).

Reference: B. Mildenhall et al., "NeRF: Representing scenes as neural radiance fields for view synthesis",
ECCV 2020 (section 4 eq. 3, section 5.1, section 5.2); the module's functions are the reference
implementations (:func:`lab.modules.nerf.positional_encoding`, :func:`lab.modules.nerf.volume_render`,
:func:`lab.modules.nerf.sample_pdf` with its readable
:func:`~lab.modules.nerf.reference.sample_pdf_reference`).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
import torch

from lab.core import InvalidValue, Loaded, Pipeline, Range, step_result
from lab.geometry.camera_views import camera_centre, lift_pixels
from lab.modules.nerf.encoding import positional_encoding as encode
from lab.modules.nerf.rays import pixel_centres
from lab.modules.nerf.reference import sample_pdf_reference
from lab.modules.nerf.rendering import volume_render

#: Depth (camera z) of the points :func:`points_along_rays` places on each ray.
RAY_DEPTH = 2.5


def _array(value: Any, name: str, ndim: int) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim or not np.all(np.isfinite(array)):
        raise InvalidValue(name, f"expected a finite {ndim}-D array, got shape {array.shape}")
    return array


def positional_encoding(points: np.ndarray, *,
                        frequencies: Annotated[int, Range(0, 16)] = 6) -> Annotated[np.ndarray, "encoded"]:
    """``gamma(p)`` ``(N, 2 L D)`` of points ``(N, D)``, ``L = frequencies`` (Mildenhall et al. section 5.1):
    for ``k = 0 .. L-1`` the block ``sin(2^k pi p)`` then the block ``cos(2^k pi p)``, each ``D`` wide
    (``[sin(pi p), cos(pi p), sin(2 pi p), cos(2 pi p), ...]``); the formula alone, without ``p`` itself.

    Args:
        frequencies: L, the number of octaves.
    """
    p = _array(points, "points", 2)
    return encode(torch.as_tensor(p), frequencies, include_input=False).numpy()


def ray_directions(K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   image_size: np.ndarray) -> Annotated[np.ndarray, "directions"]:
    """The world direction ``R^T K^-1 (u, v, 1)^T`` ``(H W, 3)`` of the ray through every pixel centre, row
    by row (pixel ``(u, v) = (column, row)``, ``(0, 0)`` the centre of the top-left pixel); its camera-frame
    z is 1, so the ray ``C + s d`` (``C = -R^T t``) is at camera depth ``s``. Mildenhall et al. section 4
    (their code's ``get_rays``, in OpenCV's camera frame: x right, y down, z forward)."""
    width, height = (int(v) for v in np.asarray(image_size).reshape(2))
    pixels = pixel_centres(width, height).numpy()
    return lift_pixels(_array(K, "K", 2), _array(R, "R", 2), t, pixels, 1.0) - camera_centre(R, t)


def points_along_rays(directions: np.ndarray, R: np.ndarray,
                      t: np.ndarray) -> Annotated[np.ndarray, "ray_points"]:
    """The points ``C + RAY_DEPTH d`` ``(H W, 3)`` on each ray (:data:`RAY_DEPTH` = 2.5)."""
    return camera_centre(R, t) + RAY_DEPTH * _array(directions, "directions", 2)


def volume_weights(sigmas: np.ndarray, depths: np.ndarray, far: float) -> Annotated[np.ndarray, "weights"]:
    """The weights ``w_i = T_i alpha_i`` ``(R, S)`` of samples at sorted ``depths`` with densities ``sigmas``
    (Mildenhall et al. eq. 3): ``delta_i = t_(i+1) - t_i`` with ``t_(S+1) = far``, ``alpha_i = 1 -
    exp(-sigma_i delta_i)``, ``T_i = prod_(j < i) (1 - alpha_j)`` (``T_1 = 1``)."""
    sigma = torch.as_tensor(_array(sigmas, "sigmas", 2))
    depth = torch.as_tensor(_array(depths, "depths", 2))
    rendering = volume_render(sigma, torch.zeros((*sigma.shape, 3), dtype=sigma.dtype), depth, far=float(far))
    return rendering.weights.numpy()


@step_result
class Composite:
    """Result of :func:`composite`."""

    rendered_color: np.ndarray
    rendered_depth: np.ndarray
    rendered_opacity: np.ndarray


def composite(weights: np.ndarray, colors: np.ndarray, depths: np.ndarray, far: float) -> Composite:
    """Colour ``sum w_i c_i + (1 - sum w_i)`` (a white background) ``(R, 3)``, expected depth ``sum w_i t_i +
    (1 - sum w_i) far`` and opacity ``sum w_i`` ``(R,)`` from the weights (Mildenhall et al. eq. 3)."""
    w = _array(weights, "weights", 2)
    opacity = w.sum(axis=1)
    color = np.einsum("rs,rsc->rc", w, _array(colors, "colors", 3)) + (1.0 - opacity)[:, None]
    depth = np.sum(w * _array(depths, "depths", 2), axis=1) + (1.0 - opacity) * float(far)
    return Composite(color, depth, opacity)


def sample_pdf(bins: np.ndarray, bin_weights: np.ndarray,
               uniforms: np.ndarray) -> Annotated[np.ndarray, "fine_samples"]:
    """Inverse-CDF samples ``(R, K)``, one per uniform ``u`` (Mildenhall et al. section 5.2): ``pdf_j = (w_j +
    1e-5) / sum (w + 1e-5)`` over the bins ``[bins_j, bins_(j+1)]``, ``cdf = (0, pdf_1, pdf_1 + pdf_2, ...,
    1)``; ``u`` falls in the bin ``j`` with ``cdf_j <= u < cdf_(j+1)`` and is placed linearly inside it,
    ``bins_j + (u - cdf_j) / pdf_j (bins_(j+1) - bins_j)``."""
    return sample_pdf_reference(_array(bins, "bins", 2), _array(bin_weights, "bin_weights", 2),
                                _array(uniforms, "uniforms", 2))


def bin_shares(fine_samples: np.ndarray, bins: np.ndarray) -> Annotated[np.ndarray, "shares"]:
    """The share of each ray's samples that falls in each bin ``(R, M)``."""
    samples, edges = _array(fine_samples, "fine_samples", 2), _array(bins, "bins", 2)
    inside = (samples[:, :, None] >= edges[:, None, :-1]) & (samples[:, :, None] < edges[:, None, 1:])
    return inside.mean(axis=1)


def synthetic(*, profile: Literal["random", "slab", "step"] = "random",
              rays: Annotated[int, Range(1, 4096)] = 48, samples: Annotated[int, Range(2, 256)] = 24,
              bins: Annotated[int, Range(2, 256)] = 16, fine: Annotated[int, Range(1, 1024)] = 64,
              evenly: bool = False, width: Annotated[int, Range(2, 256)] = 16,
              height: Annotated[int, Range(2, 256)] = 12, seed: int = 0) -> Loaded:
    """Random points, a random camera and random samples along rays, drawn from ``seed``.

    ``profile`` shapes the densities: ``random`` (exponential, a third of them 0), ``slab`` (one density per
    ray, every sample: the opacity is ``1 - exp(-sigma (far - t_1))``) or ``step`` (0 but for one sample per
    ray, opaque: the ray ends at its depth). The camera looks from about 4 units away, ``width x height``
    pixels, the principal point off centre. Depths are jittered strata of ``[2, 6)``, ``far = 6``. The
    sampling bins are jittered strata of ``[2, 6]`` with weights of which a quarter are 0; ``evenly``:
    uniforms ``(k + 0.5) / fine`` instead of random ones.

    Truth: ``pixels`` (H W, 2) the pixel centres; ``opacity`` and ``depth`` (R,) for ``slab`` / ``step``;
    ``pdf`` (R, M) the normalized weights.
    """
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.0, 1.0, size=(97, 3))
    axis = rng.normal(size=3)
    angle = rng.uniform(0.3, 2.5)
    R = _rotation(axis / np.linalg.norm(axis), angle)
    centre = rng.normal(size=3)
    centre = 4.0 * centre / np.linalg.norm(centre)
    t = -R @ centre
    focal = rng.uniform(0.9, 1.4) * width
    K = np.array([[focal, 0.0, width / 2.0 - 0.7], [0.0, focal * rng.uniform(0.95, 1.05), height / 2.0 + 0.4],
                  [0.0, 0.0, 1.0]])
    near, far = 2.0, 6.0
    depths = near + (far - near) * (np.arange(samples) + rng.uniform(0.0, 1.0, (rays, samples))) / samples
    truth: dict[str, Any] = {}
    if profile == "random":
        sigmas = rng.exponential(1.0, (rays, samples)) * (rng.uniform(size=(rays, samples)) > 1.0 / 3.0)
    elif profile == "slab":
        density = rng.uniform(0.05, 1.5, rays)
        sigmas = np.repeat(density[:, None], samples, axis=1)
        truth["opacity"] = 1.0 - np.exp(-density * (far - depths[:, 0]))
    else:
        sigmas = np.zeros((rays, samples))
        hit = rng.integers(0, samples, rays)
        sigmas[np.arange(rays), hit] = 1e4
        truth["depth"] = depths[np.arange(rays), hit]
        truth["opacity"] = np.ones(rays)
    edges = near + (far - near) * np.concatenate(
        [np.zeros((rays, 1)), (np.arange(1, bins) + rng.uniform(-0.4, 0.4, (rays, bins - 1))) / bins,
         np.ones((rays, 1))], axis=1)
    weights = rng.uniform(0.0, 1.0, (rays, bins)) * (rng.uniform(size=(rays, bins)) > 0.25)
    uniforms = (np.broadcast_to((np.arange(fine) + 0.5) / fine, (rays, fine)).copy() if evenly
                else rng.uniform(0.0, 1.0, (rays, fine)))
    truth["pixels"] = pixel_centres(width, height).numpy()
    truth["pdf"] = (weights + 1e-5) / np.sum(weights + 1e-5, axis=1, keepdims=True)
    state = {"points": points, "K": K, "R": R, "t": t, "image_size": np.array([width, height]),
             "sigmas": sigmas, "depths": depths, "far": far,
             "colors": rng.uniform(0.0, 1.0, (rays, samples, 3)),
             "bins": edges, "bin_weights": weights, "uniforms": uniforms}
    return Loaded(state, truth, description=f"{rays} rays of {samples} samples ({profile} densities), a "
                                            f"{width} x {height} camera, {bins} bins, {fine} uniforms")


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation about a unit ``axis``."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def evaluate_ray_points(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest distance (px) of the points on the rays projected from their pixel centres, and largest
    difference of their camera depth from :data:`RAY_DEPTH`."""
    points, K, R, t = state["ray_points"], state["K"], state["R"], state["t"]
    if "pixels" not in truth or np.shape(points) != (len(truth["pixels"]), 3):
        return {}
    camera = points @ np.asarray(R).T + np.asarray(t)
    pixels = camera[:, :2] / camera[:, 2:] @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
    return {"reprojection_error_px": float(np.max(np.linalg.norm(pixels - truth["pixels"], axis=1))),
            "ray_depth_error": float(np.max(np.abs(camera[:, 2] - RAY_DEPTH)))}


def evaluate_composite(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest error of the opacity (and, for the opaque step, the depth) from the closed forms."""
    out = {}
    if "opacity" in truth and np.shape(state["rendered_opacity"]) == np.shape(truth["opacity"]):
        out["opacity_error"] = float(np.max(np.abs(state["rendered_opacity"] - truth["opacity"])))
    if "depth" in truth and np.shape(state["rendered_depth"]) == np.shape(truth["depth"]):
        out["depth_error"] = float(np.max(np.abs(state["rendered_depth"] - truth["depth"])))
    return out


def evaluate_shares(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Largest difference between the share of samples in a bin and the bin's probability."""
    if "pdf" not in truth or np.shape(state["shares"]) != np.shape(truth["pdf"]):
        return {}
    return {"share_error": float(np.max(np.abs(state["shares"] - truth["pdf"])))}


PIPELINE = Pipeline.build(
    name="nerf_basics",
    title="Neural radiance fields: the arithmetic",
    summary="The positional encoding, ray directions from a camera, the volume-rendering weights and "
            "inverse-CDF sampling, each a step on exact arrays, checked against closed forms.",
    steps=[positional_encoding, ray_directions, points_along_rays, volume_weights, composite, sample_pdf,
           bin_shares],
    datasets=[synthetic],
    evaluations={"points_along_rays": evaluate_ray_points, "composite": evaluate_composite,
                 "bin_shares": evaluate_shares},
)

__all__ = ["PIPELINE", "RAY_DEPTH", "Composite", "bin_shares", "composite", "points_along_rays",
           "positional_encoding", "ray_directions", "sample_pdf", "synthetic", "volume_weights"]
