"""The steps of the diffusion module, in pipeline order: each reads state by name and returns what it writes.

1. :func:`noise_schedule`   the forward process's betas, ``abar_t`` and SNR
2. :func:`forward_noising`  the training data noised to step ``t``
3. :func:`train_denoiser`   the MLP denoiser (epsilon, x0, v or flow matching, optionally conditional)
4. :func:`sample`           noise to samples by DDPM, DDIM, Euler, Heun or the SDE sampler, with guidance

and the lesson's micro-steps, one guided DDIM update taken apart:

5. :func:`prepare_update`   noised samples and the model's conditional and unconditional noise predictions
6. :func:`combine_guidance` classifier-free guidance of the two predictions
7. :func:`ddim_update`      one DDIM step from ``x_t`` with the guided prediction
"""

from __future__ import annotations

import math
import time
from collections.abc import Generator
from typing import Annotated, Literal

import numpy as np
import torch

from lab.core import (Curve, Image, InvalidControl, InvalidValue, PointCloud, Progress, Range, metric,
                      step_result)
from lab.modules.diffusion.display import display
from lab.modules.diffusion.model import Denoiser, randn, to_data, torch_generator
from lab.modules.diffusion.samplers import TraceRecorder, require_diffusion, run_sampler
from lab.modules.diffusion.schedule import make_schedule, q_sample, signal_to_noise
from lab.modules.diffusion.training import TrainingSetup, loss_curve, train_mlp
from lab.modules.diffusion.updates import check_eta, ddim_step, guided_noise
from lab.modules.diffusion.values import (TRACE_DIGITS, TRACE_POINTS, DenoiserCheckpoint, NoiseSchedule,
                                          Objective, SamplerName, SamplingTrace, TrainingData, as_schedule,
                                          as_training_data, check_checkpoint, normalization)


# ----------------------------------------------------------------------------------------------------
# 1. The noise schedule
# ----------------------------------------------------------------------------------------------------
@step_result
class ScheduleResult:
    """Result of :func:`noise_schedule`."""

    schedule: NoiseSchedule
    schedule_plot: Curve
    snr_plot: Curve
    final_abar: float = metric("abar at the last timestep (signal left in x_T)")
    final_snr_db: float = metric("SNR at the last timestep", unit="dB")


def noise_schedule(*, schedule: Literal["linear", "cosine"] = "linear",
                   timesteps: Annotated[int, Range(2, 4000)] = 1000,
                   beta_start: Annotated[float, Range(1e-6, 0.1)] = 1e-4,
                   beta_end: Annotated[float, Range(1e-5, 0.5)] = 0.02) -> ScheduleResult:
    """The forward process's betas, ``abar_t`` and signal-to-noise ratio ``SNR = abar / (1 - abar)``.

    ``q(x_t | x_0) = N(sqrt(abar_t) x_0, (1 - abar_t) I)`` with ``abar_t = prod_{s <= t} (1 - beta_s)``
    (Ho et al. 2020, eq. 4). Linear: betas from ``beta_start`` to ``beta_end`` (Ho et al.; for T = 1000,
    scaled by 1000 / T otherwise); cosine:
    Nichol & Dhariwal 2021 eq. 17 (``diffusers`` "linear" / "squaredcos_cap_v2").

    Args:
        schedule: linear or cosine betas.
        timesteps: T, the number of noise levels.
        beta_start: the first beta at T = 1000 (linear only).
        beta_end: the last beta at T = 1000 (linear only).
    """
    sched = make_schedule(schedule, timesteps, beta_start, beta_end)
    t = np.arange(sched.timesteps, dtype=np.float64)
    abar = sched.alphas_cumprod
    plot = Curve(t, np.stack([sched.betas, abar, np.sqrt(abar), np.sqrt(1 - abar)]),
                 title=f"{schedule} schedule", xlabel="t", ylabel="value",
                 labels=("beta_t", "abar_t", "sqrt(abar_t)", "sqrt(1 - abar_t)"))
    snr = signal_to_noise(abar)
    snr_plot = Curve(t, np.log10(snr), title="signal-to-noise ratio", xlabel="t", ylabel="log10 SNR",
                     labels=("log10 abar/(1 - abar)",))
    return ScheduleResult(sched, plot, snr_plot, float(abar[-1]), float(10 * np.log10(snr[-1])))


# ----------------------------------------------------------------------------------------------------
# 2. The forward process
# ----------------------------------------------------------------------------------------------------
@step_result
class ForwardResult:
    """Result of :func:`forward_noising`."""

    noised: PointCloud | Image
    snr_db: float = metric("signal-to-noise ratio at t", unit="dB")
    signal_fraction: float = metric("sqrt(abar_t): how much of x_0 is left")


def forward_noising(training_data: TrainingData, schedule: NoiseSchedule, *,
                    t: Annotated[int, Range(0, 3999)] = 250, rng: np.random.Generator) -> ForwardResult:
    """The training data noised to step ``t`` by ``q(x_t | x_0)`` (Ho et al. 2020, eq. 4), normalized units.

    Data are normalized as the network sees them (:func:`normalization`), noised, and mapped back,
    so the cloud spreads out as t grows. Digits are shown as a grid of the first 100.

    Args:
        t: the timestep (0 .. T - 1).
    """
    data = as_training_data(training_data)
    sched = as_schedule(schedule)
    if not 0 <= t < sched.timesteps:
        raise InvalidControl("t", f"must be in [0, {sched.timesteps - 1}] for this schedule, got {t}")
    mean, scale = normalization(data)
    x = data.x[:TRACE_DIGITS] if data.kind == "digits" else data.x
    x0 = (x - mean) / scale
    xt = q_sample(x0, sched.abar(t), rng.standard_normal(x0.shape)) * scale + mean
    snr = signal_to_noise(sched.alphas_cumprod[t:t + 1])[0]
    return ForwardResult(display(xt, data.kind), float(10 * np.log10(snr)), float(math.sqrt(sched.abar(t))))


# ----------------------------------------------------------------------------------------------------
# 3. Training
# ----------------------------------------------------------------------------------------------------
@step_result
class TrainResult:
    """Result of :func:`train_denoiser`."""

    model: DenoiserCheckpoint
    loss_curve: Curve
    final_loss: float = metric("mean training loss over the last 10 % of iterations")
    train_seconds: float = metric("wall-clock training time", unit="s")


def train_denoiser(training_data: TrainingData, schedule: NoiseSchedule, *, objective: Objective = "epsilon",
                   conditional: bool = False, label_dropout: Annotated[float, Range(0.0, 1.0)] = 0.15,
                   iterations: Annotated[int, Range(1, 200000)] = 4000,
                   batch_size: Annotated[int, Range(1, 65536)] = 512,
                   hidden: Annotated[int, Range(4, 2048)] = 128, layers: Annotated[int, Range(1, 12)] = 3,
                   learning_rate: Annotated[float, Range(1e-6, 1.0)] = 3e-3,
                   rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, TrainResult]:
    """Train the MLP denoiser by regression: a diffusion objective or flow matching, optionally conditional.

    Diffusion (Ho et al. 2020, Algorithm 1): draw ``x_0``, ``t ~ U{0..T-1}``, ``eps ~ N(0, I)``,
    ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps`` and regress the network's output at
    ``(x_t, t)`` on eps, x0 or v (:func:`training_target`). Flow matching (Lipman et al. 2023,
    eq. 23): ``t ~ U[0, 1]``, ``x_t = (1 - t) eps + t x_0``, target ``x_0 - eps``
    (:func:`flow_matching_pair`); the network sees ``1000 t``. Conditional (Ho & Salimans 2022,
    Algorithm 1): the label joins the input and is replaced by the null label with probability
    ``label_dropout``. Adam with a cosine-decayed learning rate; the returned weights are an
    exponential moving average of the iterates (window about a tenth of the run). Yields the loss
    every 50 iterations.

    Args:
        objective: what the network predicts: epsilon, x0, v (diffusion) or flow (the velocity).
        conditional: learn p(x | label) too (needs a dataset with labels: digits).
        label_dropout: probability of dropping the label during training (classifier-free guidance).
        iterations: optimizer steps.
        batch_size: samples per step.
        hidden: width of the MLP.
        layers: hidden layers.
        learning_rate: Adam's initial learning rate.
    """
    data = as_training_data(training_data)
    sched = as_schedule(schedule)
    if conditional and (data.labels is None or data.classes < 1):
        raise InvalidControl("conditional", f"dataset {data.name!r} has no labels: train an unconditional "
                                            "model (conditional = false) or use the digits")
    classes = data.classes if conditional else 0
    mean, scale = normalization(data)
    setup = TrainingSetup(
        x=torch.as_tensor((data.x - mean) / scale, dtype=torch.float32, device=device),
        labels=torch.as_tensor(data.labels if classes else np.zeros(len(data.x), np.int64), device=device),
        abar=torch.as_tensor(sched.alphas_cumprod, dtype=torch.float32, device=device),
        objective=objective, classes=classes, label_dropout=label_dropout, device=device)
    run = yield from train_mlp(setup, iterations=iterations, batch_size=batch_size, hidden=hidden,
                               layers=layers, learning_rate=learning_rate, rng=rng)
    weights = {k: v.detach().cpu().numpy().copy() for k, v in run.net.state_dict().items()}
    checkpoint = DenoiserCheckpoint(weights, data.name, data.dim, objective, hidden, layers, classes,
                                    sched.timesteps, mean, scale, 1.0 if data.kind == "digits" else 0.0,
                                    label_dropout if classes else 0.0)
    final_loss = float(run.losses[-max(1, iterations // 10):].mean())
    return TrainResult(checkpoint, loss_curve(run.losses, objective), final_loss, run.seconds)


# ----------------------------------------------------------------------------------------------------
# 4. Sampling
# ----------------------------------------------------------------------------------------------------
@step_result
class SampleResult:
    """Result of :func:`sample`."""

    samples: PointCloud | Image
    predicted_x0: PointCloud | Image
    generated: np.ndarray
    generated_labels: np.ndarray
    trace: SamplingTrace
    sampling_seconds: float = metric("wall-clock sampling time", unit="s")
    evaluations: int = metric("network evaluations per sample")


def sample(model: DenoiserCheckpoint, schedule: NoiseSchedule, training_data: TrainingData, *,
           sampler: SamplerName = "ddim", steps: Annotated[int, Range(1, 4000)] = 50,
           eta: Annotated[float, Range(0.0, 1.0)] = 0.0,
           guidance_scale: Annotated[float, Range(0.0, 20.0)] = 0.0,
           label: Annotated[int, Range(-1, 1000)] = -1,
           count: Annotated[int, Range(1, 20000)] = 1000,
           rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, SampleResult]:
    """Draw ``count`` samples from the trained model, one sampler step at a time.

    Starts from ``x_T ~ N(0, I)`` (flow: ``x_0`` at t = 0) and runs DDPM ancestral sampling, DDIM
    with ``eta``, Euler or Heun on the ODE, or the stochastic SDE sampler (see the ``sample_*``
    generators). A conditional model samples class ``label`` (-1: classes 0, 1, 2 ... in turn)
    with classifier-free guidance of scale ``guidance_scale`` (w in ``(1 + w) eps_c - w eps_u``).
    Yields after every step; the progress carries the current ``x_t`` and the predicted ``x0`` as
    previews (``samples``, ``predicted_x0``) at every step up to 100 steps, every ``steps // 100``-th beyond.

    Args:
        sampler: ddpm, ddim, euler, heun or sde.
        steps: sampler steps (ddpm and ddim: at most T; 1000 ddpm steps is Ho et al.'s sampler).
        eta: stochasticity of ddim (0 deterministic, 1 DDPM's variance); sde always adds the full noise.
        guidance_scale: classifier-free guidance w (conditional models only).
        label: the class to draw (-1: all classes in turn; conditional models only).
        count: number of samples.
    """
    data = as_training_data(training_data)
    checkpoint = check_checkpoint(model, data)
    sched = as_schedule(schedule)
    check_eta(eta)
    _check_sampling(checkpoint, sched, label)
    requested = np.full(count, -1, dtype=np.int64)
    if checkpoint.conditional:
        requested = np.full(count, label) if label >= 0 else np.arange(count) % checkpoint.classes
    labels = torch.as_tensor(requested, device=device) if checkpoint.conditional else None
    denoiser = Denoiser(checkpoint, sched, device=device, labels=labels, guidance_scale=guidance_scale)
    generator = torch_generator(rng)
    x_T = randn((count, checkpoint.dim), generator, device)
    started = time.perf_counter()
    recorder = TraceRecorder(checkpoint, data.kind, steps,
                             min(count, TRACE_DIGITS if data.kind == "digits" else TRACE_POINTS))
    x_t, x0 = x_T, x_T
    for state in run_sampler(sampler, denoiser, x_T, steps=steps, eta=eta, generator=generator):
        recorder.add(state)
        x_t, x0 = state.x_t, state.x0
        if state.step > 0:
            yield Progress(iteration=state.step, total=steps, message=f"{sampler} step",
                           values=recorder.preview(state))
    seconds = time.perf_counter() - started
    final = to_data(x_t, checkpoint)
    if data.kind == "digits":
        final = np.clip(final, 0.0, 1.0)
    return SampleResult(display(final, data.kind), display(to_data(x0, checkpoint), data.kind), final,
                        requested, recorder.trace(requested, sampler), seconds, denoiser.evaluations)


def _check_sampling(checkpoint: DenoiserCheckpoint, schedule: NoiseSchedule, label: int) -> None:
    """The model fits the schedule, and ``label`` fits the model."""
    if not checkpoint.is_flow and checkpoint.timesteps != schedule.timesteps:
        raise InvalidValue("schedule", f"the model was trained on a schedule of {checkpoint.timesteps} "
                                       f"timesteps, this one has {schedule.timesteps}: rerun train_denoiser")
    if label >= 0 and not checkpoint.conditional:
        raise InvalidControl("label", "this model was trained without labels: use -1")
    if label >= checkpoint.classes > 0:
        raise InvalidControl("label", f"must be -1 or in [0, {checkpoint.classes - 1}], got {label}")


# ----------------------------------------------------------------------------------------------------
# 5-7. The lesson: one DDIM update on guided noise predictions
# ----------------------------------------------------------------------------------------------------
@step_result
class UpdateInputs:
    """Result of :func:`prepare_update`: what one guided DDIM step reads."""

    x_t: np.ndarray
    eps_conditional: np.ndarray
    eps_unconditional: np.ndarray
    step_alphas: np.ndarray
    update_noise: np.ndarray


def prepare_update(model: DenoiserCheckpoint, schedule: NoiseSchedule, training_data: TrainingData, *,
                   timestep: Annotated[int, Range(0, 3999)] = 600,
                   stride: Annotated[int, Range(1, 4000)] = 20,
                   label: Annotated[int, Range(0, 1000)] = 3, count: Annotated[int, Range(1, 4096)] = 64,
                   rng: np.random.Generator, device: str = "cpu") -> UpdateInputs:
    """Noised training samples at ``timestep`` and the model's noise predictions, for one guided DDIM step.

    ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` for ``count`` training samples (normalized
    units); ``eps_conditional`` is the model's eps for class ``label``, ``eps_unconditional`` for
    the null label (for an unconditional model both are its eps). ``step_alphas`` is
    ``[abar_t, abar_prev]`` with ``t_prev = timestep - stride`` (abar_prev = 1 when negative);
    ``update_noise`` the z a stochastic (eta > 0) update adds. Output arrays are float64 ``(count, D)``.

    Args:
        timestep: t of x_t.
        stride: how far the update jumps: t_prev = t - stride.
        label: the class of the conditional prediction.
        count: samples.
    """
    data = as_training_data(training_data)
    checkpoint = check_checkpoint(model, data)
    sched = as_schedule(schedule)
    require_diffusion(checkpoint, "a DDIM update")
    if not 0 <= timestep < sched.timesteps:
        raise InvalidControl("timestep", f"must be in [0, {sched.timesteps - 1}], got {timestep}")
    if checkpoint.conditional and label >= checkpoint.classes:
        raise InvalidControl("label", f"must be in [0, {checkpoint.classes - 1}], got {label}")
    pick = rng.choice(len(data.x), size=count, replace=count > len(data.x))
    x0 = (data.x[pick] - checkpoint.mean) / checkpoint.scale
    abar_t, abar_prev = sched.abar(timestep), sched.abar(timestep - stride)
    x_t = q_sample(x0, abar_t, rng.standard_normal(x0.shape))
    no_labels = torch.zeros(count, dtype=torch.long, device=device)
    denoiser = Denoiser(checkpoint, sched, device=device, labels=no_labels)
    if checkpoint.conditional:
        asked = torch.full((count,), label, device=device)
        null = torch.full((count,), checkpoint.classes, device=device)
        eps_c = _noise_prediction(denoiser, x_t, timestep, asked)
        eps_u = _noise_prediction(denoiser, x_t, timestep, null)
    else:
        eps_c = eps_u = _noise_prediction(denoiser, x_t, timestep, None)
    return UpdateInputs(x_t, eps_c, eps_u.copy(), np.array([abar_t, abar_prev]),
                        rng.standard_normal(x0.shape))


def _noise_prediction(denoiser: Denoiser, x_t: np.ndarray, timestep: int,
                      labels: torch.Tensor | None) -> np.ndarray:
    """The network's raw prediction at ``x_t`` as eps ``(N, D)`` float64 (no guidance, no clipping)."""
    xt = torch.as_tensor(x_t, dtype=torch.float32, device=denoiser.device)
    tau = torch.full((len(xt),), float(timestep), device=denoiser.device)
    with torch.no_grad():
        out = denoiser.net(xt, tau, labels)
        a, b = denoiser.coefficients(timestep)
        objective = denoiser.checkpoint.objective
        if objective == "epsilon":
            eps = out
        elif objective == "x0":
            eps = (xt - a * out) / max(b, 1e-12)
        else:  # v
            eps = a * out + b * xt
        return eps.cpu().numpy().astype(np.float64)


def combine_guidance(eps_conditional: np.ndarray, eps_unconditional: np.ndarray, *,
                     guidance_scale: Annotated[float, Range(0.0, 20.0)] = 2.0,
                     ) -> Annotated[np.ndarray, "eps_guided"]:
    """Classifier-free guidance: ``eps~ = (1 + w) eps(x, c) - w eps(x, null)`` (Ho & Salimans 2022, eq. 6).

    ``w = 0`` is the conditional model; larger ``w`` pushes samples towards what distinguishes the
    class. (diffusers writes the same with ``s = 1 + w``: ``eps_u + s (eps_c - eps_u)``.) Works on
    numpy arrays and torch tensors of any equal shapes, e.g. ``(N, D)``.

    Args:
        guidance_scale: w >= 0.
    """
    guided: np.ndarray = guided_noise(eps_conditional, eps_unconditional, guidance_scale)
    return guided


def ddim_update(x_t: np.ndarray, eps_guided: np.ndarray, step_alphas: np.ndarray, update_noise: np.ndarray, *,
                eta: Annotated[float, Range(0.0, 1.0)] = 0.0) -> Annotated[np.ndarray, "x_prev"]:
    """One DDIM step from ``x_t`` to ``x_prev`` given the noise prediction (Song et al. 2021, eqs. 12 and 16).

    ``step_alphas = [abar_t, abar_prev]``; ``x_t``, ``eps_guided``, ``update_noise`` ``(N, D)``.
    See :func:`ddim_step` for the equations; diffusers' ``DDIMScheduler.step`` computes the same.

    Args:
        eta: 0 deterministic DDIM, 1 DDPM's variance.
    """
    check_eta(eta)
    abar_t, abar_prev = (float(a) for a in np.asarray(step_alphas, dtype=np.float64).reshape(2))
    x_prev = ddim_step(np.asarray(x_t, np.float64), np.asarray(eps_guided, np.float64), abar_t, abar_prev,
                       eta=eta, noise=np.asarray(update_noise, np.float64))
    return np.asarray(x_prev, dtype=np.float64)


__all__ = ["ForwardResult", "SampleResult", "ScheduleResult", "TrainResult", "UpdateInputs",
           "combine_guidance", "ddim_update", "forward_noising", "noise_schedule", "prepare_update", "sample",
           "train_denoiser"]
