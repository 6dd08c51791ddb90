"""Samplers: generators that turn noise into samples, yielding ``(x_t, x0_hat)`` after every step.

DDPM ancestral sampling (Ho et al. 2020, Algorithm 2) and DDIM (Song et al. 2021) run on diffusion
models; Euler and Heun on the sampling ODE (Karras et al. 2022, Algorithm 1) and the ancestral SDE
sampler (Song et al. 2021, k-diffusion's ``euler_ancestral``) run on diffusion and flow-matching
models alike. :class:`TraceRecorder` keeps evenly spaced frames of a run for scrubbing.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from lab.core import Image, InvalidControl, PointCloud
from lab.modules.diffusion.display import display
from lab.modules.diffusion.model import Denoiser, randn, to_data
from lab.modules.diffusion.updates import (ancestral_step, check_eta, check_steps, ddim_step, ddpm_step,
                                           leading_timesteps)
from lab.modules.diffusion.values import MAX_TRACE_FRAMES, DenoiserCheckpoint, SamplingTrace


@dataclass(frozen=True)
class SamplerState:
    """One snapshot of a sampler: after ``step`` of ``steps`` (0: the initial noise), ``x_t`` and ``x0``
    ``(N, D)`` float32 tensors in the normalized space, and the noise level ``sigma = b/a`` reached."""

    step: int
    steps: int
    x_t: torch.Tensor
    x0: torch.Tensor
    noise_level: float
    evaluations: int


def require_diffusion(checkpoint: DenoiserCheckpoint, sampler: str) -> None:
    """Refuse a flow-matching model where ``sampler`` needs a diffusion model (:class:`InvalidControl`)."""
    if checkpoint.is_flow:
        raise InvalidControl("sampler", f"{sampler} needs a diffusion model (objective epsilon, x0 or v); "
                                        "this model was trained by flow matching: use euler, heun or sde")


def _noise_level(a: float, b: float) -> float:
    return math.inf if a <= 0 else b / a


def _sigma_of(abar: float) -> float:
    return ((1.0 - abar) / abar) ** 0.5


def _ode_grid(denoiser: Denoiser, steps: int) -> list[tuple[float, float]]:
    """``(time, time_next)`` pairs from noise to data: flow t = i/n; diffusion the leading timesteps."""
    if denoiser.checkpoint.is_flow:
        check_steps(steps)
        return [(i / steps, (i + 1) / steps) for i in range(steps)]
    return [(float(t), float(p)) for t, p in leading_timesteps(denoiser.diffusion_schedule.timesteps, steps)]


def _abar_at(denoiser: Denoiser, time_value: float) -> float:
    return denoiser.diffusion_schedule.abar(int(time_value))


def sample_ddpm(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int,
                generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """Ancestral sampling (Ho et al. 2020, Algorithm 2) over ``steps`` strided timesteps (``ddpm_step``)."""
    require_diffusion(denoiser.checkpoint, "ddpm")
    schedule = denoiser.diffusion_schedule
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (t, t_prev) in enumerate(leading_timesteps(schedule.timesteps, steps)):
        x0, _, _ = denoiser.predict(x, t)
        noise = randn(tuple(x.shape), generator, str(x.device)) if t > 0 else None
        x = ddpm_step(x, x0, schedule.abar(t), schedule.abar(t_prev), noise=noise)
        yield SamplerState(i + 1, steps, x, x0, _sigma_of(schedule.abar(t_prev)), denoiser.evaluations)
    return x


def sample_ddim(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float = 0.0,
                generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """DDIM (Song et al. 2021, eq. 12) over ``steps`` strided timesteps (:func:`ddim_step`); eta in [0, 1]."""
    require_diffusion(denoiser.checkpoint, "ddim")
    check_eta(eta)
    schedule = denoiser.diffusion_schedule
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (t, t_prev) in enumerate(leading_timesteps(schedule.timesteps, steps)):
        x0, eps, _ = denoiser.predict(x, t)
        noise = randn(tuple(x.shape), generator, str(x.device)) if eta > 0 else None
        x = ddim_step(x, eps, schedule.abar(t), schedule.abar(t_prev), eta=eta, noise=noise,
                      x0=x0 if denoiser.checkpoint.clip > 0 else None)
        yield SamplerState(i + 1, steps, x, x0, _sigma_of(schedule.abar(t_prev)), denoiser.evaluations)
    return x


def sample_ode(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int,
               method: Literal["euler", "heun"] = "euler") -> Generator[SamplerState, None, torch.Tensor]:
    """Euler or Heun (Karras et al. 2022, Algorithm 1) on the sampling ODE.

    Flow matching: ``dx/dt = v(x, t)`` from t = 0 (noise) to 1 (data) with ``h = 1 / steps``;
    Heun averages the slopes at both ends (``x' = x + h (v(x, t) + v(x_e, t + h)) / 2``, ``x_e``
    the Euler guess). Diffusion: the probability-flow ODE in ``x~ = x / sqrt(abar)``,
    ``sigma = sqrt((1 - abar) / abar)``: ``dx~/dsigma = eps_hat`` over the leading timesteps; its
    Euler step is exactly DDIM with eta = 0, and Heun's correction is skipped at sigma = 0 (Karras).
    """
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    flow = denoiser.checkpoint.is_flow
    for i, (tc, tn) in enumerate(_ode_grid(denoiser, steps)):
        if flow:
            h = tn - tc
            x0, _, v = denoiser.predict(x, tc)
            x_next = x + h * v
            if method == "heun":
                _, _, v2 = denoiser.predict(x_next, tn)
                x_next = x + h * 0.5 * (v + v2)
            x = x_next
            level = _noise_level(tn, 1 - tn)
        else:
            a_c, a_n = _abar_at(denoiser, tc), (1.0 if tn < 0 else _abar_at(denoiser, tn))
            s_c, s_n = _sigma_of(a_c), _sigma_of(a_n)
            x0, eps, _ = denoiser.predict(x, tc)
            xt = x / a_c ** 0.5 + (s_n - s_c) * eps  # Euler in x~
            if method == "heun" and s_n > 0:
                _, eps2, _ = denoiser.predict(xt * a_n ** 0.5, tn)
                xt = x / a_c ** 0.5 + (s_n - s_c) * 0.5 * (eps + eps2)
            x = xt * a_n ** 0.5
            level = s_n
        yield SamplerState(i + 1, steps, x, x0, level, denoiser.evaluations)
    return x


def sample_sde(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float = 1.0,
               generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """A stochastic sampler of the reverse SDE (Song et al. 2021) by ancestral steps (:func:`ancestral_step`).

    Runs on diffusion and flow-matching models alike; ``eta`` scales the fresh noise (0: the
    deterministic DDIM / Euler path, 1: the full reverse-SDE noise, the sample step's choice). On
    a diffusion model with eta = 1 each step draws DDPM's posterior over the stride.
    """
    check_eta(eta)
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (tc, tn) in enumerate(_ode_grid(denoiser, steps)):
        a_c, b_c = denoiser.coefficients(tc)
        if denoiser.checkpoint.is_flow:
            a_n, b_n = tn, 1.0 - tn
        else:
            abar_n = 1.0 if tn < 0 else _abar_at(denoiser, tn)
            a_n, b_n = abar_n ** 0.5, (1.0 - abar_n) ** 0.5
        x0, eps, _ = denoiser.predict(x, tc)
        noise = randn(tuple(x.shape), generator, str(x.device))
        x = ancestral_step(x0, eps, a_n, b_n, _noise_level(a_c, b_c), eta=eta, noise=noise)
        yield SamplerState(i + 1, steps, x, x0, _noise_level(a_n, b_n), denoiser.evaluations)
    return x


def run_sampler(sampler: str, denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float,
                generator: torch.Generator) -> Iterator[SamplerState]:
    """The generator of sampler ``sampler`` ("ddpm", "ddim", "euler", "heun", "sde"); ``eta`` is DDIM's (the
    SDE sampler always adds the full reverse-SDE noise: call :func:`sample_sde` for another eta)."""
    check_steps(steps, None if denoiser.checkpoint.is_flow else denoiser.diffusion_schedule.timesteps)
    if sampler == "ddpm":
        return sample_ddpm(denoiser, x_T, steps=steps, generator=generator)
    if sampler == "ddim":
        return sample_ddim(denoiser, x_T, steps=steps, eta=eta, generator=generator)
    if sampler == "euler":
        return sample_ode(denoiser, x_T, steps=steps, method="euler")
    if sampler == "heun":
        return sample_ode(denoiser, x_T, steps=steps, method="heun")
    if sampler == "sde":
        return sample_sde(denoiser, x_T, steps=steps, eta=1.0, generator=generator)
    raise InvalidControl("sampler", f"must be one of ddpm, ddim, euler, heun, sde; got {sampler!r}")


@dataclass
class TraceRecorder:
    """Collects a sampling run for scrubbing: the first ``traced`` samples at up to :data:`MAX_TRACE_FRAMES`
    evenly spaced steps (first and last included), in data units, and previews to draw."""

    checkpoint: DenoiserCheckpoint
    kind: str
    steps: int
    traced: int
    frames: list[tuple[int, float, np.ndarray, np.ndarray]] = field(default_factory=list)

    def __post_init__(self) -> None:
        frames = min(MAX_TRACE_FRAMES, self.steps + 1)
        self.keep = set(np.unique(np.round(np.linspace(0, self.steps, frames)).astype(int)).tolist())
        self.preview_every = max(1, self.steps // 100)

    def add(self, state: SamplerState) -> None:
        """Keep ``state`` as a frame if its step is one of the kept ones."""
        if state.step in self.keep:
            self.frames.append((state.step, state.noise_level,
                                to_data(state.x_t[:self.traced], self.checkpoint),
                                to_data(state.x0[:self.traced], self.checkpoint)))

    def preview(self, state: SamplerState) -> dict[str, PointCloud | Image]:
        """``samples`` and ``predicted_x0`` to draw at this step (about 100 previews a run; {} in between)."""
        if state.step % self.preview_every != 0 and state.step != self.steps:
            return {}
        return {"samples": display(to_data(state.x_t[:self.traced], self.checkpoint), self.kind),
                "predicted_x0": display(to_data(state.x0[:self.traced], self.checkpoint), self.kind)}

    def trace(self, requested: np.ndarray, sampler: str) -> SamplingTrace:
        """The kept frames as a :class:`SamplingTrace` (``requested``: each sample's class, -1 for none)."""
        frames = self.frames
        return SamplingTrace(np.stack([f[2] for f in frames]), np.stack([f[3] for f in frames]),
                             np.array([f[0] for f in frames]), np.array([f[1] for f in frames]),
                             requested[:self.traced], self.kind, sampler, self.steps)


__all__ = ["SamplerState", "TraceRecorder", "require_diffusion", "run_sampler", "sample_ddim", "sample_ddpm",
           "sample_ode", "sample_sde"]
