"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions where it can be, so it is exact by construction. A mistake that cannot be told
apart from another one at a check's controls raises instead of answering (the grader then names
neither), so its hint never names the wrong cause.
"""

import numpy as np

from lab.modules.diffusion import combine_guidance, ddim_step


def guidance_in_diffusers_convention(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``eps_u + w (eps_c - eps_u)``: diffusers' scale s = 1 + w read as the lab's w, one unit of guidance short.

    At w = 0 that is eps_u, which is also what the two arguments swapped give: it names nothing there.
    """
    if guidance_scale == 0.0:
        raise ValueError("at w = 0 diffusers' convention and swapped arguments both give eps_u")
    return combine_guidance(eps_conditional, eps_unconditional, guidance_scale=guidance_scale - 1.0)


def unconditional_prediction(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``eps_u`` itself: at w = 0 both diffusers' convention and the two arguments swapped give it."""
    return np.array(eps_unconditional, dtype=np.float64, copy=True)


def guidance_without_unconditional(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``(1 + w) eps_c``: the conditional prediction scaled, the unconditional one never subtracted."""
    return combine_guidance(eps_conditional, np.zeros_like(eps_conditional), guidance_scale=guidance_scale)


def guidance_reversed(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """``eps_c + w (eps_u - eps_c)``: the guidance direction reversed, towards the unconditional prediction."""
    return combine_guidance(eps_conditional, eps_unconditional, guidance_scale=-guidance_scale)


#: Lin et al. (2024)'s recommended guidance rescale, phi = 0.7 (diffusers' ``guidance_rescale``).
RESCALE_PHI = 0.7


def guidance_rescaled(eps_conditional, eps_unconditional, *, guidance_scale=2.0):
    """The guided prediction rescaled to the standard deviation of eps_c per sample and mixed back with
    phi = 0.7 (Lin et al. 2024, diffusers' ``rescale_noise_cfg``): a sampler option, not eq. 6."""
    guided = combine_guidance(eps_conditional, eps_unconditional, guidance_scale=guidance_scale)
    ratio = np.std(eps_conditional, axis=-1, keepdims=True) / np.std(guided, axis=-1, keepdims=True)
    return RESCALE_PHI * guided * ratio + (1.0 - RESCALE_PHI) * guided


def _alphas(step_alphas):
    abar_t, abar_prev = (float(a) for a in np.asarray(step_alphas, dtype=np.float64).reshape(2))
    return abar_t, abar_prev


def _sigma(abar_t, abar_prev, eta):
    """DDIM's sigma_t (Song et al. 2021, eq. 16)."""
    return eta * np.sqrt((1.0 - abar_prev) / (1.0 - abar_t) * (1.0 - abar_t / abar_prev))


def _x0(x_t, eps, abar_t):
    return (np.asarray(x_t, np.float64) - np.sqrt(1.0 - abar_t) * np.asarray(eps, np.float64)) / np.sqrt(abar_t)


def _renoised(x0, eps, noise, abar_prev, sigma):
    """``sqrt(abar_prev) x0 + sqrt(1 - abar_prev - sigma^2) eps + sigma z`` (eq. 12) for any sigma."""
    direction = np.sqrt(max(1.0 - abar_prev - sigma ** 2, 0.0)) * np.asarray(eps, np.float64)
    return np.sqrt(abar_prev) * x0 + direction + sigma * np.asarray(noise, np.float64)


def ddim_without_square_roots(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """abar where sqrt(abar) belongs, in x0_hat and in re-noising it: ``x0 = (x_t - (1 - abar_t) eps) / abar_t``."""
    abar_t, abar_prev = _alphas(step_alphas)
    x0 = (x_t - (1.0 - abar_t) * eps_guided) / abar_t
    sigma = _sigma(abar_t, abar_prev, eta)
    return abar_prev * x0 + np.sqrt(max(1.0 - abar_prev - sigma ** 2, 0.0)) * eps_guided + sigma * update_noise


def ddim_direction_keeps_sigma(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """The direction term ``sqrt(1 - abar_prev) eps`` of eta = 0 kept while ``sigma z`` is added: too much variance."""
    abar_t, abar_prev = _alphas(step_alphas)
    deterministic = ddim_step(np.asarray(x_t, np.float64), np.asarray(eps_guided, np.float64), abar_t, abar_prev)
    return deterministic + _sigma(abar_t, abar_prev, eta) * np.asarray(update_noise, np.float64)


def ddim_eta_under_square_root(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """sigma_t = sqrt(eta (1 - abar_prev) / (1 - abar_t) (1 - abar_t / abar_prev)): eta scaling the variance,
    not the standard deviation (right at eta = 0 and 1 only)."""
    abar_t, abar_prev = _alphas(step_alphas)
    sigma = np.sqrt(eta) * _sigma(abar_t, abar_prev, 1.0)
    return _renoised(_x0(x_t, eps_guided, abar_t), eps_guided, update_noise, abar_prev, sigma)


def ddim_sigma_ratio_inverted(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """sigma_t with its first ratio upside down: ``eta sqrt((1 - abar_t) / (1 - abar_prev)) sqrt(1 - abar_t /
    abar_prev)``."""
    abar_t, abar_prev = _alphas(step_alphas)
    if abar_prev >= 1.0:
        raise ValueError("the inverted ratio divides by 1 - abar_prev = 0")
    sigma = eta * np.sqrt((1.0 - abar_t) / (1.0 - abar_prev) * (1.0 - abar_t / abar_prev))
    return _renoised(_x0(x_t, eps_guided, abar_t), eps_guided, update_noise, abar_prev, sigma)


def ddim_renoises_with_fresh_noise(x_t, eps_guided, step_alphas, update_noise, *, eta=0.0):
    """x0_hat noised to t_prev by the forward process with the fresh noise, ``sqrt(abar_prev) x0_hat +
    sqrt(1 - abar_prev) z``: eps_hat is not reused as the direction and eta is ignored."""
    abar_t, abar_prev = _alphas(step_alphas)
    return _renoised(_x0(x_t, eps_guided, abar_t), update_noise, update_noise, abar_prev, 0.0)
