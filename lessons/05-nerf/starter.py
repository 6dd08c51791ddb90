"""Lesson 05, neural radiance fields: fill in the four functions, then run

    vision-lab grade 05-nerf starter.py

You may import numpy and scipy (not the lab's own implementation, not torch). Keep the signatures.
Every array is float64; compute in float64 (the checks allow about 1e-9, far below float32's rounding).
"""

import numpy as np


def positional_encoding(points, *, frequencies=6):
    """The positional encoding gamma(p) (Mildenhall et al. 2020, section 5.1).

    Args:
        points: (N, D) positions, each coordinate in [-1, 1].
        frequencies: L, the number of octaves.

    Returns:
        (N, 2 L D): for k = 0 .. L-1 the block sin(2^k pi p) (D columns), then the block cos(2^k pi p),
        so [sin(pi p), cos(pi p), sin(2 pi p), cos(2 pi p), ...]; p itself is not included.
    """
    raise NotImplementedError


def ray_directions(K, R, t, image_size):
    """The world direction of the ray through every pixel centre (Mildenhall et al. 2020, section 4).

    Args:
        K: (3, 3) intrinsics. R: (3, 3), t: (3,) the pose, X_cam = R X_world + t (OpenCV's frame: x right,
            y down, z forward).
        image_size: (2,) int, (width W, height H).

    Returns:
        (H W, 3): row by row (pixel (u, v) = (column, row) at index v W + u), d = R^T K^-1 (u, v, 1)^T,
        not normalized (its camera-frame z is 1). Pixel (0, 0) is the centre of the top-left pixel.
    """
    raise NotImplementedError


def volume_weights(sigmas, depths, far):
    """The volume-rendering weights of samples along rays (Mildenhall et al. 2020, eq. 3).

    Args:
        sigmas: (R, S) densities >= 0. depths: (R, S) sorted sample depths t_1 < ... < t_S < far.
        far: float, where the last sample's interval ends.

    Returns:
        (R, S): w_i = T_i alpha_i with delta_i = t_(i+1) - t_i (t_(S+1) = far), alpha_i = 1 - exp(-sigma_i
        delta_i) and T_i = prod_(j < i) (1 - alpha_j), so T_1 = 1.
    """
    raise NotImplementedError


def sample_pdf(bins, bin_weights, uniforms):
    """Inverse-transform sampling of the weights' piecewise-constant PDF (Mildenhall et al. 2020, 5.2).

    Args:
        bins: (R, M + 1) increasing bin edges per ray. bin_weights: (R, M) weights >= 0.
        uniforms: (R, K) draws u in [0, 1).

    Returns:
        (R, K): with pdf_j = (w_j + 1e-5) / sum_j (w_j + 1e-5) and cdf = (0, pdf_1, pdf_1 + pdf_2, ..., 1),
        each u falls in the bin j with cdf_j <= u < cdf_(j+1) and is placed linearly in it:
        bins_j + (u - cdf_j) / pdf_j (bins_(j+1) - bins_j).
    """
    raise NotImplementedError
