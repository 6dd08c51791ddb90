"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions where it can be, so it is exact by construction.
"""

import numpy as np

from lab.modules.diffusion import combine_guidance, ddim_step


def guidance_in_diffusers_convention(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``eps_u + w (eps_c - eps_u)``: diffusers' scale s = 1 + w read as the lab's w, one unit of guidance short."""
    return combine_guidance(eps_conditional, eps_unconditional, guidance_scale=guidance_scale - 1.0)


def guidance_without_unconditional(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``(1 + w) eps_c``: the conditional prediction scaled, the unconditional one never subtracted."""
    return combine_guidance(eps_conditional, np.zeros_like(eps_conditional), guidance_scale=guidance_scale)


def _sigma(abar_t, abar_prev, eta):
    """DDIM's sigma_t (Song et al. 2021, eq. 16)."""
    return eta * np.sqrt((1.0 - abar_prev) / (1.0 - abar_t) * (1.0 - abar_t / abar_prev))


def ddim_without_square_roots(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """abar where sqrt(abar) belongs, in x0_hat and in re-noising it: ``x0 = (x_t - (1 - abar_t) eps) / abar_t``."""
    abar_t, abar_prev = (float(a) for a in np.asarray(step_alphas, dtype=np.float64).reshape(2))
    x0 = (x_t - (1.0 - abar_t) * eps_guided) / abar_t
    sigma = _sigma(abar_t, abar_prev, eta)
    return abar_prev * x0 + np.sqrt(max(1.0 - abar_prev - sigma ** 2, 0.0)) * eps_guided + sigma * update_noise


def ddim_direction_keeps_sigma(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """The direction term ``sqrt(1 - abar_prev) eps`` of eta = 0 kept while ``sigma z`` is added: too much variance."""
    abar_t, abar_prev = (float(a) for a in np.asarray(step_alphas, dtype=np.float64).reshape(2))
    deterministic = ddim_step(np.asarray(x_t, np.float64), np.asarray(eps_guided, np.float64), abar_t, abar_prev)
    return deterministic + _sigma(abar_t, abar_prev, eta) * np.asarray(update_noise, np.float64)
