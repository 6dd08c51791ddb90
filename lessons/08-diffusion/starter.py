"""Lesson 08, diffusion sampling: fill in both functions, then run

    vision-lab grade 08-diffusion starter.py

You may import numpy (not the lab's own implementation, not torch). Keep the signatures.
Every array is float64 (N, D): N noised digits of D = 64 pixels in the network's units ([-1, 1]);
you may compute in float32 or float64 (the checks allow 1e-5).
"""

import numpy as np


def combine_guidance(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """Classifier-free guidance (Ho & Salimans 2022, eq. 6).

    Args:
        eps_conditional: (N, D) the model's noise prediction for the wanted class, eps(x_t, c).
        eps_unconditional: (N, D) its prediction with the label dropped, eps(x_t, null).
        guidance_scale: w >= 0; w = 0 is the plain conditional model.

    Returns:
        (N, D) the guided prediction (1 + w) eps(x_t, c) - w eps(x_t, null).
    """
    raise NotImplementedError


def ddim_update(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """One DDIM step from x_t to x_prev (Song et al. 2021, eq. 12, sigma of eq. 16).

    Args:
        x_t: (N, D) the noisy samples at timestep t.
        eps_guided: (N, D) the noise prediction eps_hat at (x_t, t).
        step_alphas: (2,) [abar_t, abar_prev], the cumulative alphas at t and at the step's target.
        update_noise: (N, D) standard normal z, to add when eta > 0.
        eta: in [0, 1]; 0 deterministic DDIM, 1 DDPM's variance.

    Returns:
        (N, D) x_prev = sqrt(abar_prev) x0_hat + sqrt(1 - abar_prev - sigma^2) eps_hat + sigma z, with
        x0_hat = (x_t - sqrt(1 - abar_t) eps_hat) / sqrt(abar_t) and
        sigma = eta sqrt((1 - abar_prev) / (1 - abar_t)) sqrt(1 - abar_t / abar_prev).
    """
    raise NotImplementedError
