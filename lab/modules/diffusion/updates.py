"""The updates of the samplers: the lesson's math, array-agnostic (numpy arrays or torch tensors, float abar).

Every noise path here is ``x_t = a_t x_0 + b_t eps``: diffusion ``a = sqrt(abar_t)``,
``b = sqrt(1 - abar_t)``; flow matching ``a = t``, ``b = 1 - t``. The DDPM and DDIM updates follow
diffusers' ``DDPMScheduler`` / ``DDIMScheduler`` (leading timestep spacing, ``set_alpha_to_one``)
and match their ``step`` to float32 rounding.

References: J. Ho, A. Jain, P. Abbeel (2020), eqs. 6-7 and 15 (DDPM); J. Song, C. Meng, S. Ermon
(2021), eqs. 12 and 16 (DDIM); T. Karras et al. (2022) and k-diffusion (the ancestral step);
J. Ho, T. Salimans (2022), eq. 6 (classifier-free guidance).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from lab.core import InvalidControl


def guided_noise(eps_conditional: Any, eps_unconditional: Any, guidance_scale: float) -> Any:
    """Classifier-free guidance ``(1 + w) eps(x, c) - w eps(x, null)`` (Ho & Salimans 2022, eq. 6)."""
    return (1.0 + guidance_scale) * eps_conditional - guidance_scale * eps_unconditional


def _coefficient(value: Any, like: Any) -> Any:
    """A schedule number in the arithmetic of ``like``: a 0-d tensor of its dtype (float32 samples round as
    diffusers' schedulers do) or a float64 number for numpy arrays."""
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)
    return np.float64(value)


def _at_least(value: Any, floor: float) -> Any:
    return value.clamp(min=floor) if isinstance(value, torch.Tensor) else np.maximum(value, floor)


def predicted_x0_from_eps(x_t: Any, eps: Any, alpha_bar: float) -> Any:
    """``x0_hat = (x_t - sqrt(1 - abar) eps) / sqrt(abar)`` (Ho et al. 2020, eq. 15; DDIM eq. 12's
    "predicted x0")."""
    abar = _coefficient(alpha_bar, x_t)
    return (x_t - (1 - abar) ** 0.5 * eps) / abar ** 0.5


def ddim_step(x_t: Any, eps: Any, alpha_bar: float, alpha_bar_prev: float, *, eta: float = 0.0,
              noise: Any = None, x0: Any = None) -> Any:
    """One DDIM update ``x_t -> x_{t_prev}`` (Song et al. 2021, eq. 12 with sigma of eq. 16):

        x0_hat  = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)
        sigma   = eta sqrt((1 - abar_prev) / (1 - abar_t)) sqrt(1 - abar_t / abar_prev)
        x_prev  = sqrt(abar_prev) x0_hat + sqrt(1 - abar_prev - sigma^2) eps + sigma z

    ``x0`` replaces ``x0_hat`` (e.g. clipped) while ``eps`` stays the model's, as diffusers'
    ``DDIMScheduler.step`` (``use_clipped_model_output=False``). ``noise`` z is needed when eta > 0.
    Works on numpy arrays (float64 arithmetic) and torch tensors (the coefficients in the tensor's
    dtype, so float32 samples round as diffusers does: no Python work per element either way).
    """
    if x0 is None and eta == 0 and isinstance(x_t, torch.Tensor):
        # deterministic: x_prev = c1 x_t + c2 eps with the coefficients in float64, two kernels
        a, ap = float(alpha_bar), float(alpha_bar_prev)
        c1 = math.sqrt(ap / a)
        c2 = math.sqrt(max(1.0 - ap, 0.0)) - math.sqrt(ap) * math.sqrt(1.0 - a) / math.sqrt(a)
        return torch.add(x_t * c1, eps, alpha=c2)
    abar, abar_prev = _coefficient(alpha_bar, x_t), _coefficient(alpha_bar_prev, x_t)
    if x0 is None:
        x0 = (x_t - (1 - abar) ** 0.5 * eps) / abar ** 0.5
    variance = _at_least((1 - abar_prev) / (1 - abar) * (1 - abar / abar_prev), 0.0)
    sigma = eta * variance ** 0.5
    x_prev = abar_prev ** 0.5 * x0 + _at_least(1 - abar_prev - sigma ** 2, 0.0) ** 0.5 * eps
    if eta > 0:
        x_prev = x_prev + sigma * noise
    return x_prev


def ddpm_step(x_t: Any, x0: Any, alpha_bar: float, alpha_bar_prev: float, *, noise: Any = None) -> Any:
    """One ancestral DDPM update: a draw of the posterior ``q(x_prev | x_t, x0_hat)`` (Ho et al. 2020,
    eqs. 6-7)::

        alpha   = abar_t / abar_prev,  beta = 1 - alpha
        mu      = sqrt(abar_prev) beta / (1 - abar_t) x0_hat + sqrt(alpha) (1 - abar_prev) / (1 - abar_t) x_t
        x_prev  = mu + sqrt(beta~) z,   beta~ = (1 - abar_prev) / (1 - abar_t) beta

    (no noise when ``noise`` is None).

    With strided timesteps (fewer steps than T) ``alpha`` spans the stride, as diffusers' ``DDPMScheduler``
    ("fixed_small" variance). Arithmetic as in :func:`ddim_step`.
    """
    abar, abar_prev = _coefficient(alpha_bar, x_t), _coefficient(alpha_bar_prev, x_t)
    alpha = abar / abar_prev
    beta = 1 - alpha
    mean = (abar_prev ** 0.5 * beta / (1 - abar)) * x0 + (alpha ** 0.5 * (1 - abar_prev) / (1 - abar)) * x_t
    if noise is None:
        return mean
    variance = _at_least((1 - abar_prev) / (1 - abar) * beta, 1e-20)
    return mean + variance ** 0.5 * noise


def ancestral_step(x0: Any, eps: Any, a_next: float, b_next: float, sigma: float, *, eta: float,
                   noise: Any) -> Any:
    """One step of the reverse SDE's ancestral discretization on the path ``x = a x0 + b eps`` (``b / a``:
    ``sigma``).

    In Karras et al.'s variable ``x~ = x / a`` the step from ``sigma`` to ``sigma'`` splits the
    target noise into a deterministic and a fresh part (k-diffusion's ``get_ancestral_step``):
    ``sigma_up = min(sigma', eta sigma' sqrt(1 - sigma'^2 / sigma^2))``,
    ``sigma_down^2 = sigma'^2 - sigma_up^2``, ``x~' = x0_hat + sigma_down eps_hat + sigma_up z``. In ``x``:
    ``x' = a' x0_hat + b' (r_down eps_hat + r_up z)`` with ``r = sigma_. / sigma'``. For a diffusion model
    and eta = 1 its variance is DDPM's posterior variance; it also runs on a flow-matching model
    (``a = t``, ``b = 1 - t``).
    """
    if b_next <= 0:
        return x0
    sigma_next = b_next / a_next
    ratio = 0.0 if not math.isfinite(sigma) else sigma_next / sigma
    r_up = min(1.0, eta * max(0.0, 1.0 - ratio ** 2) ** 0.5)
    r_down = (1.0 - r_up ** 2) ** 0.5
    return a_next * x0 + b_next * (r_down * eps + r_up * noise)


def leading_timesteps(timesteps: int, steps: int) -> list[tuple[int, int]]:
    """``(t, t_prev)`` pairs of a sampler with ``steps`` steps: diffusers' "leading" spacing.

    ``t = (steps - 1 - i) * (T // steps)``, ``t_prev = t - T // steps`` (negative: the clean sample,
    abar = 1).
    """
    check_steps(steps, timesteps)
    ratio = timesteps // steps
    return [((steps - 1 - i) * ratio, (steps - 2 - i) * ratio) for i in range(steps)]


def check_steps(steps: int, timesteps: int | None = None) -> None:
    """At least one sampler step, at most ``timesteps`` on a diffusion schedule (:class:`InvalidControl`)."""
    if int(steps) < 1:
        raise InvalidControl("steps", f"a sampler needs at least one step, got {steps}")
    if timesteps is not None and int(steps) > int(timesteps):
        raise InvalidControl("steps", f"at most {timesteps} steps on a schedule of {timesteps} timesteps, "
                                      f"got {steps}")


def check_eta(eta: float) -> None:
    """``eta`` in [0, 1] (:class:`InvalidControl`)."""
    if not 0.0 <= float(eta) <= 1.0:
        raise InvalidControl("eta", "must be in [0, 1] (0: deterministic DDIM, 1: DDPM's variance), "
                                    f"got {eta}")


__all__ = ["ancestral_step", "check_eta", "check_steps", "ddim_step", "ddpm_step", "guided_noise",
           "leading_timesteps", "predicted_x0_from_eps"]
