"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the hint of
tasks.toml when the student's result is what the mistake computes. Each is built from the lab's own
functions where it can be (lab.modules.nerf.basics and the NeRF module's volume_render), so it is exact by
construction.
"""

import numpy as np
import torch

from lab.modules.nerf import volume_render
from lab.modules.nerf.basics import positional_encoding, ray_directions, sample_pdf


# --- positional encoding -------------------------------------------------------------------------------
def encoding_without_pi(points, *, frequencies=6):
    """``sin(2^k p)``, ``cos(2^k p)``: the frequencies without the factor pi (the NeRF code's embedder)."""
    return positional_encoding(np.asarray(points, dtype=np.float64) / np.pi, frequencies=frequencies)


def encoding_octaves_from_one(points, *, frequencies=6):
    """``sin(2^(k+1) pi p)``: the octaves start at 2 pi, the lowest frequency (pi) left out."""
    return positional_encoding(2.0 * np.asarray(points, dtype=np.float64), frequencies=frequencies)


def encoding_sines_then_cosines(points, *, frequencies=6):
    """Every sine block first, then every cosine block (the right values in another layout)."""
    gamma = positional_encoding(points, frequencies=frequencies)
    n, d = np.shape(points)
    blocks = gamma.reshape(n, frequencies, 2, d)
    return np.concatenate([blocks[:, :, 0].reshape(n, -1), blocks[:, :, 1].reshape(n, -1)], axis=1)


# --- ray directions ------------------------------------------------------------------------------------
def directions_in_camera_frame(K, R, t, image_size):
    """``K^-1 (u, v, 1)``: the directions in the camera's frame, never rotated into the world."""
    return ray_directions(K, np.eye(3), np.zeros(3), image_size)


def directions_rotated_by_R(K, R, t, image_size):
    """``R K^-1 (u, v, 1)``: rotated by R (world to camera) instead of R^T (camera to world)."""
    return ray_directions(K, np.asarray(R).T, t, image_size)


def directions_half_pixel(K, R, t, image_size):
    """Through ``(u + 0.5, v + 0.5)``: pixel centres of a corner-origin convention (the lab's are integers)."""
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    return ray_directions(np.linalg.inv(shift) @ np.asarray(K), R, t, image_size)


def directions_column_major(K, R, t, image_size):
    """The right rays, column by column (x outer, y inner) instead of row by row."""
    width, height = (int(v) for v in np.asarray(image_size).reshape(2))
    d = ray_directions(K, R, t, image_size)
    return d.reshape(height, width, 3).transpose(1, 0, 2).reshape(-1, 3)


# --- volume-rendering weights --------------------------------------------------------------------------
def _weights(sigma, t, far):
    sigma, t = torch.as_tensor(np.asarray(sigma, dtype=np.float64)), torch.as_tensor(np.asarray(t, np.float64))
    return volume_render(sigma, torch.zeros((*sigma.shape, 3), dtype=sigma.dtype), t, far=float(far))


def weights_inclusive_transmittance(sigmas, depths, far):
    """``T_i`` with the product up to and including sample i (an inclusive cumprod): ``w_i = T_(i+1) alpha_i``."""
    out = _weights(sigmas, depths, far)
    return (out.transmittance * (1.0 - out.alpha) * out.alpha).numpy()


def _product_weights(alpha):
    """``T_i alpha_i`` with ``T_i = prod_(j < i) (1 - alpha_j)`` (the product form: exact for any delta)."""
    ones = np.ones((len(alpha), 1))
    return np.cumprod(np.concatenate([ones, 1.0 - alpha[:, :-1]], axis=1), axis=1) * alpha


def weights_alpha_without_delta(sigmas, depths, far):
    """``alpha_i = 1 - exp(-sigma_i)``: the density taken as an opacity per sample, the interval ignored."""
    return _product_weights(1.0 - np.exp(-np.asarray(sigmas, dtype=np.float64)))


def weights_last_interval_infinite(sigmas, depths, far):
    """The last interval 1e10 long (the NeRF code's), not ``far - t_S``: every ray with density at its last
    sample is opaque."""
    depths = np.asarray(depths, dtype=np.float64)
    delta = np.diff(depths, axis=1, append=np.full((len(depths), 1), 1e10))
    return _product_weights(1.0 - np.exp(-np.asarray(sigmas, dtype=np.float64) * delta))


# --- inverse-CDF sampling ------------------------------------------------------------------------------
def pdf_unnormalized(bins, bin_weights, uniforms):
    """The CDF of the weights (plus 1e-5) not divided by their sum: the uniforms all fall in the first bins."""
    w = np.asarray(bin_weights, dtype=np.float64) + 1e-5
    edges = np.asarray(bins, dtype=np.float64)
    cdf = np.concatenate([np.zeros((len(w), 1)), np.cumsum(w, axis=1)], axis=1)
    out = np.zeros(np.shape(uniforms))
    for r, row in enumerate(np.asarray(uniforms, dtype=np.float64)):
        j = np.clip(np.searchsorted(cdf[r], row, side="right") - 1, 0, w.shape[1] - 1)
        out[r] = edges[r, j] + (row - cdf[r, j]) / w[r, j] * (edges[r, j + 1] - edges[r, j])
    return out


def pdf_left_edges(bins, bin_weights, uniforms):
    """Each sample at the left edge of the bin its uniform falls in: the bin is right, the place in it is not."""
    samples = sample_pdf(bins, bin_weights, uniforms)
    edges = np.asarray(bins, dtype=np.float64)
    j = np.stack([np.clip(np.searchsorted(edges[r], samples[r], side="right") - 1, 0, edges.shape[1] - 2)
                  for r in range(len(edges))])
    return np.take_along_axis(edges, j, axis=1)
