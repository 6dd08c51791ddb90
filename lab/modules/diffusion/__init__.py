"""Diffusion sampling made watchable: forward noising, DDPM, DDIM, flow matching, ODE and SDE samplers,
guidance.

References (equation numbers as in the papers):
- J. Ho, A. Jain, P. Abbeel, "Denoising diffusion probabilistic models", NeurIPS 2020 (DDPM):
  the forward process ``q(x_t | x_0) = N(sqrt(abar_t) x_0, (1 - abar_t) I)`` (eq. 4), the
  epsilon objective (eq. 14, "L_simple"), the posterior mean ``mu~_t(x_t, x_0)`` and variance
  ``beta~_t`` (eqs. 6-7) used by the ancestral sampler (Algorithm 2); the linear beta schedule
  (section 4: 1e-4 .. 0.02 over T = 1000).
- A. Nichol, P. Dhariwal, "Improved denoising diffusion probabilistic models", ICML 2021: the
  cosine schedule ``abar(t) = cos^2(((t/T + s) / (1 + s)) pi/2)``, betas clipped at 0.999 (eq. 17).
- J. Song, C. Meng, S. Ermon, "Denoising diffusion implicit models", ICLR 2021 (DDIM): the update
  of eq. 12 with ``sigma_t(eta)`` of eq. 16; eta = 0 is deterministic, eta = 1 is DDPM's variance.
- T. Salimans, J. Ho, "Progressive distillation", ICLR 2022: the v objective
  ``v = sqrt(abar) eps - sqrt(1 - abar) x_0`` (section 4).
- Y. Lipman, R. T. Q. Chen, H. Ben-Hamu, M. Nickel, M. Le, "Flow matching for generative
  modeling", ICLR 2023: conditional flow matching with the linear (optimal-transport) path
  ``x_t = (1 - (1 - sigma_min) t) x_noise + t x_data`` and its velocity
  ``u_t = x_data - (1 - sigma_min) x_noise`` (eqs. 20-23; here sigma_min = 0); t = 0 is noise,
  t = 1 is data; samples solve ``dx/dt = v(x, t)`` from 0 to 1.
- T. Karras, M. Aittala, T. Aila, S. Laine, "Elucidating the design space of diffusion-based
  generative models", NeurIPS 2022 (EDM): the probability-flow ODE in ``sigma`` with
  ``x~ = x / sqrt(abar)``, ``sigma = sqrt((1 - abar) / abar)``, ``dx~/dsigma = eps_hat`` (eq. 4
  with s = 1), Euler and Heun's second-order method (Algorithm 1); Euler on it is DDIM with eta = 0.
- Y. Song et al., "Score-based generative modeling through SDEs", ICLR 2021: the reverse SDE;
  the stochastic sampler here is its ancestral discretization (k-diffusion's ``euler_ancestral``).
- J. Ho, T. Salimans, "Classifier-free diffusion guidance", 2022: one model trained with labels
  dropped with probability ``p_uncond`` (Algorithm 1) and sampled with
  ``eps~ = (1 + w) eps(x, c) - w eps(x, null)`` (eq. 6; w = 0 is the plain conditional model).

Every noise path here is ``x_t = a_t x_0 + b_t eps``: diffusion ``a = sqrt(abar_t)``,
``b = sqrt(1 - abar_t)``; flow matching ``a = t``, ``b = 1 - t``. Samplers turn the model's output
into a predicted clean sample ``x0_hat`` and noise ``eps_hat`` with ``x_t = a x0_hat + b eps_hat``
and step from one noise level to the next.

Conventions: points are float64 ``(N, 2)`` / ``(N, 3)`` (2D points are drawn at z = 0); digits
are 8 x 8 images with values in [0, 1] flattened to 64 values. Networks run in float32 on
``device``; data are normalized (mean 0, about unit spread; digits to [-1, 1]) and samples mapped
back. The DDPM and DDIM updates follow diffusers' ``DDPMScheduler`` / ``DDIMScheduler`` (leading
timestep spacing, ``set_alpha_to_one``) and match their ``step`` to float32 rounding.

The package (this file is its only import surface):

    steps.py      the steps in pipeline order, each with its result class
    values.py     the typed values: TrainingData, NoiseSchedule, DenoiserCheckpoint, SamplingTrace
    schedule.py   noise schedules and the forward process
    model.py      the MLP denoiser and the checkpoint made callable (Denoiser), with guidance
    training.py   the regression targets and the training loop
    updates.py    the lesson's math: DDPM, DDIM, ancestral updates, guidance, timestep spacing
    samplers.py   the samplers as generators, and the trace a run leaves for scrubbing
    display.py    samples as point clouds or digit grids
    evaluate.py   Chamfer, MMD, digit accuracy and diversity of the samples
    datasets.py   3D shapes, 2D curves and the 8 x 8 digits

State names:
    training_data       TrainingData        the samples a model learns (points or digits, labels)
    points              PointCloud          the training points (digits: absent)
    digits              Image               a grid of training digits (points: absent)
    schedule            NoiseSchedule       betas and abar_t of the forward process
    schedule_plot       Curve               beta_t, abar_t, sqrt(abar_t), sqrt(1 - abar_t) over t
    snr_plot            Curve               log10 SNR(t) = log10(abar_t / (1 - abar_t))
    noised              PointCloud | Image  a draw of q(x_t | x_0) at the chosen t
    model               DenoiserCheckpoint  the trained network's weights and configuration
    loss_curve          Curve               training loss over iterations
    samples             PointCloud | Image  the sampler's output (digits: a grid)
    predicted_x0        PointCloud | Image  the model's x0 prediction at the last step
    generated           (N, D)              the samples in data units (points, or flattened digits)
    generated_labels    (N,) int            the class each sample was asked for (-1: none)
    trace               SamplingTrace       x_t and x0_hat at every step (at most 101 frames)
    x_t, eps_conditional, eps_unconditional, step_alphas, update_noise   [lesson helpers]
    eps_guided          (N, D)              the classifier-free-guidance combination  [lesson]
    x_prev              (N, D)              one DDIM update  [lesson]
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.diffusion.datasets import digits, shape_3d, swiss_roll, two_moons
from lab.modules.diffusion.display import digit_grid
from lab.modules.diffusion.evaluate import (chamfer_distance, digit_metrics, diversity_score, evaluate_sample,
                                            mmd_rbf, train_digit_classifier)
from lab.modules.diffusion.model import Denoiser, DenoiserMLP, network_from, timestep_embedding
from lab.modules.diffusion.samplers import (SamplerState, run_sampler, sample_ddim, sample_ddpm, sample_ode,
                                            sample_sde)
from lab.modules.diffusion.schedule import (cosine_betas, linear_betas, make_schedule, q_sample,
                                            signal_to_noise)
from lab.modules.diffusion.steps import (combine_guidance, ddim_update, forward_noising, noise_schedule,
                                         prepare_update, sample, train_denoiser)
from lab.modules.diffusion.training import flow_matching_pair, training_target
from lab.modules.diffusion.updates import (ancestral_step, ddim_step, ddpm_step, leading_timesteps,
                                           predicted_x0_from_eps)
from lab.modules.diffusion.values import (DIFFUSION_OBJECTIVES, DIGIT_SHAPE, MAX_TRACE_FRAMES, TIME_SCALE,
                                          TRACE_DIGITS, TRACE_POINTS, DenoiserCheckpoint, NoiseSchedule,
                                          Objective, SamplerName, SamplingTrace, TrainingData,
                                          check_checkpoint, normalization)

PIPELINE = Pipeline.build(
    name="diffusion",
    title="Diffusion sampling",
    summary="Generative models made watchable: noise data with the forward process (linear or cosine "
            "schedule), train a small denoiser (epsilon, x0, v or flow matching, optionally "
            "class-conditional), then watch DDPM, DDIM, Euler/Heun ODE and SDE samplers turn noise into "
            "a 3D shape or into digits, with classifier-free guidance.",
    steps=[noise_schedule, forward_noising, train_denoiser, sample, prepare_update, combine_guidance,
           ddim_update],
    datasets=[shape_3d, two_moons, swiss_roll, digits],
    evaluations={"sample": evaluate_sample},
    # lab/viewer/interactions/diffusion.py scrubs the ``trace`` and re-samples once there is a ``model``.
    views=["trace", "model"],
)

__all__ = [
    "DIFFUSION_OBJECTIVES", "DIGIT_SHAPE", "MAX_TRACE_FRAMES", "PIPELINE", "TIME_SCALE", "TRACE_DIGITS",
    "TRACE_POINTS", "Denoiser", "DenoiserCheckpoint", "DenoiserMLP", "NoiseSchedule", "Objective",
    "SamplerName", "SamplerState", "SamplingTrace", "TrainingData", "ancestral_step", "chamfer_distance",
    "check_checkpoint", "combine_guidance", "cosine_betas", "ddim_step", "ddim_update", "ddpm_step",
    "digit_grid", "digit_metrics", "digits", "diversity_score", "evaluate_sample", "flow_matching_pair",
    "forward_noising", "leading_timesteps", "linear_betas", "make_schedule", "mmd_rbf", "network_from",
    "noise_schedule", "normalization", "predicted_x0_from_eps", "prepare_update", "q_sample", "run_sampler",
    "sample", "sample_ddim", "sample_ddpm", "sample_ode", "sample_sde", "shape_3d", "signal_to_noise",
    "swiss_roll", "timestep_embedding", "train_denoiser", "train_digit_classifier", "training_target",
    "two_moons",
]
