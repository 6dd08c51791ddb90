"""Training the denoiser by regression: a diffusion objective (epsilon, x0, v) or flow matching.

Diffusion (Ho et al. 2020, Algorithm 1; eq. 14 "L_simple"): draw ``x_0``, ``t ~ U{0..T-1}``,
``eps ~ N(0, I)``, ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps`` and regress the network's
output at ``(x_t, t)`` on eps, x0 or ``v = sqrt(abar) eps - sqrt(1 - abar) x0`` (Salimans & Ho
2022). Flow matching (Lipman et al. 2023, eqs. 20-23, sigma_min = 0): ``t ~ U[0, 1]``,
``x_t = (1 - t) eps + t x_0``, target ``x_0 - eps``. Class-conditional training drops the label
with probability ``label_dropout`` (Ho & Salimans 2022, Algorithm 1).
"""

from __future__ import annotations

import math
import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
import torch

from lab.core import Curve, Progress
from lab.core.threads import single_threaded
from lab.modules.diffusion.model import DenoiserMLP, randn, torch_generator
from lab.modules.diffusion.values import TIME_SCALE


def training_target(objective: str, x0: torch.Tensor, noise: torch.Tensor,
                    alpha_bar: torch.Tensor) -> torch.Tensor:
    """What the network learns to predict from ``x_t = sqrt(abar) x0 + sqrt(1 - abar) eps``:
    eps (Ho et al. eq. 14), x0, or ``v = sqrt(abar) eps - sqrt(1 - abar) x0`` (Salimans & Ho 2022)."""
    if objective == "epsilon":
        return noise
    if objective == "x0":
        return x0
    return alpha_bar.sqrt() * noise - (1 - alpha_bar).sqrt() * x0


def flow_matching_pair(x_data: torch.Tensor, noise: torch.Tensor,
                       t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lipman et al. 2023's linear path with sigma_min = 0: ``x_t = (1 - t) x_noise + t x_data``
    (eq. 22) and its velocity target ``u_t = x_data - x_noise`` (eq. 23). ``t`` ``(B, 1)``."""
    return (1 - t) * noise + t * x_data, x_data - noise


@dataclass(frozen=True)
class TrainingSetup:
    """What a training run regresses on: normalized samples ``x`` ``(N, D)`` and their ``labels`` on
    ``device``, the schedule's ``abar`` (diffusion), the ``objective``, and ``classes`` > 0 for a conditional
    model."""

    x: torch.Tensor
    labels: torch.Tensor
    abar: torch.Tensor
    objective: str
    classes: int
    label_dropout: float
    device: str


@dataclass(frozen=True)
class TrainingRun:
    """A finished run: the network with the averaged weights, every iteration's loss, the seconds it took."""

    net: DenoiserMLP
    losses: np.ndarray
    seconds: float


Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]


def _batch(setup: TrainingSetup, batch_size: int, generator: torch.Generator) -> Batch:
    """One random batch: the noised input ``x_t``, the network's time ``tau``, the target and the labels."""
    device, timesteps = setup.device, len(setup.abar)
    idx = torch.randint(len(setup.x), (batch_size,), generator=generator).to(device)
    x0 = setup.x[idx]
    noise = randn(tuple(x0.shape), generator, device)
    if setup.objective == "flow":
        t = torch.rand((batch_size, 1), generator=generator).to(device)
        xt, target = flow_matching_pair(x0, noise, t)
        tau = t[:, 0] * TIME_SCALE
    else:
        steps = torch.randint(timesteps, (batch_size,), generator=generator).to(device)
        a = setup.abar[steps][:, None]
        xt = a.sqrt() * x0 + (1 - a).sqrt() * noise
        target = training_target(setup.objective, x0, noise, a)
        tau = steps.float()
    labels = None
    if setup.classes:
        drop = torch.rand(batch_size, generator=generator).to(device) < setup.label_dropout
        labels = torch.where(drop, torch.full_like(setup.labels[idx], setup.classes), setup.labels[idx])
    return xt, tau, target, labels


#: Multiply-adds of one layer's batch (batch size x width^2) below which torch's CPU threads only contend:
#: such a network trains on one thread (on a busy 2-core machine 10 to 30 times faster than on two).
SMALL_WORK = 1 << 20

def train_mlp(setup: TrainingSetup, *, iterations: int, batch_size: int, hidden: int, layers: int,
              learning_rate: float, rng: np.random.Generator) -> Generator[Progress, None, TrainingRun]:
    """Adam on the mean squared error with a cosine-decayed learning rate; the returned weights are an
    exponential moving average of the iterates (window about a tenth of the run). Yields the mean loss
    every 50 iterations. The initial weights and every batch come from ``rng``; torch's global random
    state is left untouched. A small network on the CPU (below :data:`SMALL_WORK`) trains on one
    thread (:func:`single_threaded`)."""
    small = setup.device == "cpu" and batch_size * hidden * hidden < SMALL_WORK
    with single_threaded(small):
        run = yield from _train(setup, iterations=iterations, batch_size=batch_size, hidden=hidden,
                                layers=layers, learning_rate=learning_rate, rng=rng)
    return run


def _train(setup: TrainingSetup, *, iterations: int, batch_size: int, hidden: int, layers: int,
           learning_rate: float, rng: np.random.Generator) -> Generator[Progress, None, TrainingRun]:
    """The loop of :func:`train_mlp`."""
    generator = torch_generator(rng)
    with torch.random.fork_rng(devices=[]):  # the network's initial weights, from rng
        torch.manual_seed(int(rng.integers(0, 2**62)))
        net = DenoiserMLP(setup.x.shape[1], hidden, layers, setup.classes).to(setup.device)
    ema = [p.detach().clone() for p in net.parameters()]
    ema_decay = 1.0 - 1.0 / max(10.0, iterations / 10.0)
    optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda i: 0.5 * (1 + math.cos(math.pi * min(i, iterations) / iterations)) * 0.98 + 0.02)
    losses = np.zeros(iterations)
    started = time.perf_counter()
    for it in range(iterations):
        xt, tau, target, labels = _batch(setup, batch_size, generator)
        loss = torch.nn.functional.mse_loss(net(xt, tau, labels), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        with torch.no_grad():
            torch._foreach_lerp_(ema, [p.detach() for p in net.parameters()], 1.0 - ema_decay)
        losses[it] = float(loss.detach())
        if (it + 1) % 50 == 0 or it + 1 == iterations:
            recent = float(losses[max(0, it - 49):it + 1].mean())
            yield Progress(iteration=it + 1, total=iterations, loss=recent, message=f"{setup.objective} loss")
    seconds = time.perf_counter() - started
    with torch.no_grad():
        for p, e in zip(net.parameters(), ema, strict=True):
            p.copy_(e)
    return TrainingRun(net, losses, seconds)


def loss_curve(losses: np.ndarray, objective: str) -> Curve:
    """The training loss as a running mean over a twentieth of the run."""
    window = max(1, len(losses) // 20)
    smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
    return Curve(np.arange(len(smooth), dtype=np.float64) + window, smooth, title="training loss",
                 xlabel="iteration", ylabel="MSE", labels=(f"{objective} loss (mean of {window})",))


__all__ = ["SMALL_WORK", "TrainingRun", "TrainingSetup", "flow_matching_pair", "loss_curve",
           "train_mlp", "training_target"]
