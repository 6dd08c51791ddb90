"""Lesson 06, Gaussian splatting: fill in the three functions, then run

    vision-lab grade 06-splatting starter.py

You may import numpy and scipy (not the lab's own implementation). Keep the signatures.
"""

import numpy as np


def sh_dc_colors(sh_dc):
    """The RGB colour of each Gaussian from its degree-0 spherical-harmonic coefficients.

    Args:
        sh_dc: (N, 3) float64, the coefficient f_dc of each colour channel.

    Returns:
        (N, 3) float64: C0 f_dc + 0.5 with C0 = 1 / (2 sqrt(pi)) (the degree-0 basis function), clamped
        at 0 from below only (a colour may exceed 1, as in the paper's code).
    """
    raise NotImplementedError


def project_covariances(means, log_scales, quats, R, t, K):
    """The 2D covariance in pixels^2 of each Gaussian in the image (Kerbl et al. 2023, eqs. 5 and 6).

    Args:
        means: (N, 3) float64 world positions mu.
        log_scales: (N, 3) float64, S = diag(exp(log_scales)).
        quats: (N, 4) float64 quaternions (w, x, y, z), NOT normalized: normalize them first.
        R: (3, 3), t: (3,) the camera, X_cam = R X + t.  K: (3, 3) its intrinsics (fx, fy on the diagonal).

    Returns:
        (N, 2, 2) float64: Sigma' = J W Sigma W^T J^T + 0.3 I, with Sigma = R_q S S^T R_q^T (R_q the rotation
        of the normalized quaternion), W = R and J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] the
        Jacobian of the perspective map at the camera-frame mean (x, y, z) = R mu + t.
    """
    raise NotImplementedError


def composite_front_to_back(alphas, pixel_colors, background):
    """Each pixel's colour by front-to-back alpha compositing (Kerbl et al. 2023, eq. 3 and section 6).

    Args:
        alphas: (P, N) float64, pixel p's Gaussians nearest first, their alpha in [0, 0.99].
        pixel_colors: (P, N, 3) float64, their colours.
        background: (3,) float64, the colour behind them.

    Returns:
        (P, 3) float64: C = sum_i c_i alpha_i T_i + T background, T_i = prod_{j<i} (1 - alpha_j) the
        transmittance Gaussian i meets and T what is left after the last one used. An alpha under 1/255
        is skipped; the pixel is done BEFORE the Gaussian that would take T below 1e-4 (that one and all
        behind it add nothing, T stays where it was).
    """
    raise NotImplementedError
