"""Training a radiance field on a bundle of rays (Mildenhall et al. 2020, section 5.3).

Each iteration draws a random batch of training rays, renders them through the network
(:func:`~lab.modules.nerf.model.render_rays`, jittered stratified samples, plus fine samples when the
configuration has them), and takes an Adam step on the mean squared colour error of every pass. The
learning rate decays exponentially, ``lr(f) = lr_0 decay^f`` with ``f`` the fraction of the budget
spent (the paper: 5e-4 decaying to 5e-5, i.e. ``decay`` = 0.1, over its run). The budget is a number
of iterations and, optionally, seconds of training (previews are not counted); whichever ends first.
A :class:`~lab.core.Cancelled` thrown in where the loop yields (the runner's Cancel) ends it too, with
the network trained so far as the result.
Randomness (initial weights, batches, jitter) comes from the step's ``rng``; torch's global state is
left untouched.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
import torch

from lab.core import Cancelled, Curve, Image, Progress
from lab.modules.nerf.evaluate import psnr_from_mse
from lab.modules.nerf.model import NerfMLP, render_image, render_rays
from lab.modules.nerf.values import FieldConfig, RayBundle

#: Iterations between two progress reports (loss and PSNR of the batch).
REPORT_EVERY = 10


@dataclass(frozen=True)
class TrainingOptions:
    """How long and how fast to train: see :func:`train_field`."""

    batch_rays: int
    learning_rate: float
    lr_decay: float
    iterations: int
    budget_seconds: float
    preview_every: int


@dataclass(frozen=True, eq=False)
class PreviewRays:
    """The rays ``(H * W, 3)`` of the low-resolution view rendered as a preview while training."""

    origins: torch.Tensor
    directions: torch.Tensor
    shape: tuple[int, int]


@dataclass(frozen=True, eq=False)
class TrainingRun:
    """A finished run: the field (a :class:`~lab.modules.nerf.model.NerfMLP` or a grid), every iteration's
    loss and PSNR (of the batch's final pass), the training seconds (previews excluded) and the samples per
    ray evaluated with gradient over the last tenth of the run."""

    net: torch.nn.Module
    losses: np.ndarray
    psnrs: np.ndarray
    seconds: float
    samples_per_ray: float

    @property
    def iterations(self) -> int:
        return len(self.losses)


def torch_generator(rng: np.random.Generator) -> torch.Generator:
    """A CPU torch generator seeded from ``rng`` (draws move to the device: the same run everywhere)."""
    return torch.Generator().manual_seed(int(rng.integers(0, 2**62)))


def train_field(rays: RayBundle, config: FieldConfig, options: TrainingOptions, *, background: torch.Tensor,
                preview: PreviewRays | None, rng: np.random.Generator,
                device: str) -> Generator[Progress, None, TrainingRun]:
    """Adam on the photometric loss (the module docstring); yields :class:`Progress` every
    :data:`REPORT_EVERY` iterations (loss, PSNR) and, every ``preview_every``, a rendering of
    ``preview`` as ``values["preview"]``."""
    generator = torch_generator(rng)
    with torch.random.fork_rng(devices=[]):  # the initial weights, from rng
        torch.manual_seed(int(rng.integers(0, 2**62)))
        net = NerfMLP(config).to(device)
    origins = torch.as_tensor(rays.origins, device=device)
    directions = torch.as_tensor(rays.directions, device=device)
    colors = torch.as_tensor(rays.colors, device=device)
    optimizer = torch.optim.Adam(net.parameters(), lr=options.learning_rate)
    losses: list[float] = []
    psnrs: list[float] = []
    elapsed = 0.0
    budget = options.budget_seconds
    while len(losses) < options.iterations and (budget <= 0 or elapsed < budget):
        tick = time.perf_counter()
        spent = len(losses) / options.iterations
        if options.budget_seconds > 0:
            spent = max(spent, elapsed / options.budget_seconds)
        for group in optimizer.param_groups:
            group["lr"] = options.learning_rate * options.lr_decay ** min(spent, 1.0)
        batch = torch.randint(len(origins), (options.batch_rays,), generator=generator).to(device)
        out = render_rays(net, origins[batch], directions[batch], rays.bounds, background=background,
                          jitter=True, generator=generator)
        final_mse = torch.mean((out.final.color - colors[batch]) ** 2)
        loss = final_mse
        if out.fine is not None:  # the coarse pass is trained too (section 5.3)
            loss = loss + torch.mean((out.coarse.color - colors[batch]) ** 2)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
        psnrs.append(psnr_from_mse(float(final_mse.detach())))
        elapsed += time.perf_counter() - tick
        done = len(losses)
        last = done == options.iterations or 0 < options.budget_seconds <= elapsed
        if done % REPORT_EVERY == 0 or last:
            values = {}
            if preview is not None and (done % options.preview_every == 0 or last):
                values["preview"] = preview_image(net, preview, rays, background)
            recent = float(np.mean(losses[-REPORT_EVERY:]))
            try:
                yield Progress(iteration=done, total=options.iterations, loss=recent,
                               message=f"PSNR {np.mean(psnrs[-REPORT_EVERY:]):.2f} dB, {elapsed:.1f} s",
                               values=values)
            except Cancelled:  # the runner's Cancel: the network trained so far is the result
                break
    return TrainingRun(net, np.asarray(losses), np.asarray(psnrs), elapsed,
                       float(config.samples + config.fine_samples))


def preview_image(net: NerfMLP, preview: PreviewRays, rays: RayBundle, background: torch.Tensor) -> Image:
    """The network's current rendering of the preview view (no jitter, no gradient)."""
    was_training = net.training
    net.eval()
    image = render_image(net, preview.origins, preview.directions, rays.bounds, preview.shape,
                         background=background)
    net.train(was_training)
    return Image(image.color, name="training preview")


def training_curves(run: TrainingRun) -> tuple[Curve, Curve]:
    """The loss and the batch PSNR over iterations, as running means over a twentieth of the run."""
    window = max(1, run.iterations // 20)
    kernel = np.ones(window) / window
    loss = np.convolve(run.losses, kernel, mode="valid")
    psnr = np.convolve(np.minimum(run.psnrs, 99.0), kernel, mode="valid")
    x = np.arange(len(loss), dtype=np.float64) + window
    return (Curve(x, loss, title="training loss", xlabel="iteration", ylabel="MSE",
                  labels=(f"photometric loss (mean of {window})",)),
            Curve(x, psnr, title="training PSNR", xlabel="iteration", ylabel="dB",
                  labels=(f"batch PSNR (mean of {window})",)))


__all__ = ["REPORT_EVERY", "PreviewRays", "TrainingOptions", "TrainingRun", "torch_generator",
           "train_field", "training_curves"]
