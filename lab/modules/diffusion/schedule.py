"""The forward process: noise schedules (betas, ``abar_t``), the signal-to-noise ratio, ``q(x_t | x_0)``.

References: J. Ho, A. Jain, P. Abbeel, "Denoising diffusion probabilistic models", NeurIPS 2020
(eq. 4; the linear schedule of section 4); A. Nichol, P. Dhariwal, "Improved denoising diffusion
probabilistic models", ICML 2021 (the cosine schedule, eq. 17); D. Kingma et al., "Variational
diffusion models", NeurIPS 2021 (the SNR).
"""

from __future__ import annotations

import math

import numpy as np

from lab.core import InvalidControl
from lab.modules.diffusion.values import NoiseSchedule


def linear_betas(timesteps: int, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """``(T,)`` betas evenly spaced from ``beta_start`` to ``beta_end`` (Ho et al. 2020, section 4), given for
    T = 1000 and scaled by ``1000 / T`` for other T (Nichol & Dhariwal 2021's ``get_named_beta_schedule``),
    so that ``abar_T`` stays near 0; at most 0.999. For T = 1000 this is diffusers' "linear" schedule."""
    scale = 1000.0 / int(timesteps)
    betas = np.linspace(beta_start * scale, beta_end * scale, int(timesteps), dtype=np.float64)
    return np.minimum(betas, 0.999)


def cosine_betas(timesteps: int, *, offset: float = 0.008, max_beta: float = 0.999) -> np.ndarray:
    """``(T,)`` betas of the cosine schedule (Nichol & Dhariwal 2021, eq. 17; diffusers' "squaredcos_cap_v2").

    ``beta_t = min(1 - abar(t + 1) / abar(t), max_beta)`` with ``abar(t) = cos^2((t/T + s)/(1 + s) pi/2)``.
    """
    steps = np.arange(int(timesteps) + 1, dtype=np.float64) / int(timesteps)
    abar = np.cos((steps + offset) / (1 + offset) * math.pi / 2) ** 2
    return np.minimum(1.0 - abar[1:] / abar[:-1], max_beta)


def make_schedule(kind: str = "linear", timesteps: int = 1000, beta_start: float = 1e-4,
                  beta_end: float = 0.02) -> NoiseSchedule:
    """A :class:`NoiseSchedule` of ``kind`` "linear" or "cosine": ``abar_t = cumprod(1 - beta)``."""
    if int(timesteps) < 2:
        raise InvalidControl("timesteps", f"a schedule needs at least 2 timesteps, got {timesteps}")
    if kind == "linear":
        if not 0 < beta_start < beta_end < 1:
            raise InvalidControl("beta_end", "need 0 < beta_start < beta_end < 1, "
                                             f"got {beta_start}, {beta_end}")
        betas = linear_betas(timesteps, beta_start, beta_end)
    elif kind == "cosine":
        betas = cosine_betas(timesteps)
    else:
        raise InvalidControl("schedule", f"must be linear or cosine, got {kind!r}")
    return NoiseSchedule(betas, np.cumprod(1.0 - betas), kind)


def signal_to_noise(alphas_cumprod: np.ndarray) -> np.ndarray:
    """``SNR(t) = abar_t / (1 - abar_t)``: the signal over the noise power of ``q(x_t | x_0)``
    (Kingma et al. 2021)."""
    abar = np.asarray(alphas_cumprod, dtype=np.float64)
    return abar / (1.0 - abar)


def q_sample(x0: np.ndarray, alpha_bar: float, noise: np.ndarray) -> np.ndarray:
    """A draw of ``q(x_t | x_0)``: ``sqrt(abar) x_0 + sqrt(1 - abar) eps``.

    Ho et al. 2020, eq. 4; diffusers' ``add_noise``.
    """
    return alpha_bar ** 0.5 * x0 + (1.0 - alpha_bar) ** 0.5 * noise


__all__ = ["cosine_betas", "linear_betas", "make_schedule", "q_sample", "signal_to_noise"]
