"""The denoiser: a small MLP conditioned on time (and a label), and a checkpoint made callable for sampling.

:class:`DenoiserMLP` is the network; a :class:`~lab.modules.diffusion.values.DenoiserCheckpoint`
holds its weights as numpy arrays (a state value); :class:`Denoiser` loads one and turns the
network's output, whatever its objective, into a predicted clean sample ``x0_hat`` and noise
``eps_hat`` with ``x_t = a x0_hat + b eps_hat``, with classifier-free guidance. Randomness comes
from the step's ``rng`` through :func:`torch_generator`, drawn on the CPU (:func:`randn`) so that a
run is the same on every device.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from lab.core import InvalidControl, InvalidValue
from lab.modules.diffusion.updates import guided_noise
from lab.modules.diffusion.values import TIME_SCALE, DenoiserCheckpoint, NoiseSchedule


def timestep_embedding(t: torch.Tensor, dim: int, *, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding ``(B, dim)`` of (fractional) timesteps ``(B,)``: ``[cos(t f_i), sin(t f_i)]``,
    ``f_i = max_period^(-i / (dim/2))`` (Vaswani et al. 2017, as in Ho et al. 2020's U-Net)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=1)


class DenoiserMLP(torch.nn.Module):
    """An MLP ``f(x_t, t, c) -> (B, D)``: ``layers`` hidden layers of width ``hidden`` with SiLU, the
    time embedding (and the label's, for ``classes`` > 0; label ``classes`` is "no label") added to every
    layer."""

    def __init__(self, dim: int, hidden: int = 128, layers: int = 3, classes: int = 0,
                 embed: int = 64) -> None:
        super().__init__()
        self.embed = embed
        self.time = torch.nn.Sequential(torch.nn.Linear(embed, hidden), torch.nn.SiLU(),
                                        torch.nn.Linear(hidden, hidden))
        self.label = torch.nn.Embedding(classes + 1, hidden) if classes > 0 else None
        self.inp = torch.nn.Linear(dim, hidden)
        self.hidden = torch.nn.ModuleList([torch.nn.Linear(hidden, hidden) for _ in range(layers)])
        self.out = torch.nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor, t: torch.Tensor, labels: torch.Tensor | None = None) -> torch.Tensor:
        c = self.time(timestep_embedding(t, self.embed))
        if self.label is not None:
            c = c + self.label(labels)
        h = torch.nn.functional.silu(self.inp(x) + c)
        for layer in self.hidden:
            h = torch.nn.functional.silu(layer(h) + c)
        return self.out(h)


def network_from(checkpoint: DenoiserCheckpoint, device: str = "cpu") -> DenoiserMLP:
    """The :class:`DenoiserMLP` of a checkpoint, weights loaded, in eval mode on ``device``."""
    net = DenoiserMLP(checkpoint.dim, checkpoint.hidden, checkpoint.layers, checkpoint.classes)
    try:
        net.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in checkpoint.weights.items()})
    except RuntimeError as exc:
        raise InvalidValue("model.weights", f"do not fit the network of this configuration: {exc}") from None
    return net.to(device).eval()


def torch_generator(rng: np.random.Generator) -> torch.Generator:
    """A torch generator seeded from the step's ``rng``."""
    return torch.Generator().manual_seed(int(rng.integers(0, 2**62)))


def randn(shape: tuple[int, ...], generator: torch.Generator, device: str) -> torch.Tensor:
    """Standard normal noise drawn on the CPU (reproducible across devices) and moved to ``device``."""
    return torch.randn(shape, generator=generator, dtype=torch.float32).to(device)


def to_data(x: torch.Tensor, checkpoint: DenoiserCheckpoint) -> np.ndarray:
    """Normalized samples ``(N, D)`` back in data units, float64: ``x scale + mean``."""
    return x.detach().cpu().numpy().astype(np.float64) * checkpoint.scale + checkpoint.mean


class Denoiser:
    """A checkpoint made callable: ``predict(x, time) -> (x0_hat, eps_hat)``, normalized units, with guidance.

    ``time`` is the discrete timestep of a diffusion model or the flow time t in [0, 1].
    ``labels`` ``(N,)`` are the classes asked for (conditional models); ``guidance_scale`` w
    combines conditional and unconditional outputs by classifier-free guidance (output-space
    guidance: every objective's target is affine in the output, so guiding the output guides eps).
    """

    def __init__(self, checkpoint: DenoiserCheckpoint, schedule: NoiseSchedule | None, *, device: str = "cpu",
                 labels: torch.Tensor | None = None, guidance_scale: float = 0.0) -> None:
        self.checkpoint = checkpoint
        self.schedule = schedule
        self.device = device
        self.net = network_from(checkpoint, device)
        self.labels = labels
        self.guidance_scale = float(guidance_scale)
        self.evaluations = 0
        if guidance_scale != 0 and not checkpoint.conditional:
            raise InvalidControl("guidance_scale", "this model was trained without labels (conditional = "
                                                   "false): classifier-free guidance needs a conditional "
                                                   "model; use 0")
        if checkpoint.conditional and labels is None:
            raise InvalidValue("labels", "a conditional model needs the class of every sample")

    @property
    def diffusion_schedule(self) -> NoiseSchedule:
        """The schedule of a diffusion model (a flow-matching model has none)."""
        if self.schedule is None:
            raise InvalidValue("schedule", "a diffusion model samples on its noise schedule; none was given")
        return self.schedule

    @torch.no_grad()
    def output(self, x: torch.Tensor, time_value: float) -> torch.Tensor:
        """The network's (guided) output at ``x`` ``(N, D)`` and one time."""
        tau = torch.full((len(x),), float(time_value) * (TIME_SCALE if self.checkpoint.is_flow else 1.0),
                         device=x.device)
        self.evaluations += 1
        if not self.checkpoint.conditional or self.labels is None:  # (a conditional model has labels)
            return self.net(x, tau)
        if self.guidance_scale == 0:
            return self.net(x, tau, self.labels)
        null = torch.full_like(self.labels, self.checkpoint.classes)
        both = self.net(torch.cat([x, x]), torch.cat([tau, tau]), torch.cat([self.labels, null]))
        guided: torch.Tensor = guided_noise(both[:len(x)], both[len(x):], self.guidance_scale)
        return guided

    def coefficients(self, time_value: float) -> tuple[float, float]:
        """``(a, b)`` of the path at a time: ``x_t = a x0 + b eps``."""
        if self.checkpoint.is_flow:
            return float(time_value), 1.0 - float(time_value)
        abar = self.diffusion_schedule.abar(int(time_value))
        return abar ** 0.5, (1.0 - abar) ** 0.5

    def predict(self, x: torch.Tensor, time_value: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(x0_hat, eps_hat, output)``; x0_hat clamped to ``[-clip, clip]`` when the checkpoint says so, and
        then eps_hat recomputed from it (``x_t = a x0_hat + b eps_hat`` holds; unclipped eps with a clipped
        x0 drives deterministic DDIM off the data)."""
        out = self.output(x, time_value)
        a, b = self.coefficients(time_value)
        objective = self.checkpoint.objective
        if objective == "flow":  # x_t = (1 - t) eps + t x1, v = x1 - eps
            x0, eps = x + b * out, x - a * out
        elif objective == "epsilon":
            x0, eps = (x - b * out) / a, out
        elif objective == "x0":
            x0, eps = out, (x - a * out) / max(b, 1e-12)
        else:  # v
            x0, eps = a * x - b * out, a * out + b * x
        if self.checkpoint.clip > 0 and b > 0:  # eps from the clamped x0 (use_clipped_model_output)
            x0 = x0.clamp(-self.checkpoint.clip, self.checkpoint.clip)
            eps = (x - a * x0) / b
        return x0, eps, out


__all__ = ["Denoiser", "DenoiserMLP", "network_from", "randn", "timestep_embedding", "to_data",
           "torch_generator"]
