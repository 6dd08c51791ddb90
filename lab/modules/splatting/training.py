"""The training loop of 3D Gaussian splatting (Kerbl et al. 2023, sections 5 and 7.1; the code's
``train.py``), as a generator yielding progress and previews.

Each iteration renders one training view (a random order of the views, drawn again when used up) with
the fast rasterizer, takes the loss ``0.8 L1 + 0.2 D-SSIM`` against its image, backpropagates to every
parameter and takes an Adam step (:class:`~.density.TrainedGaussians`). The spherical-harmonic degree
starts at 0 and rises by one every ``sh_every`` iterations up to ``sh_degree``; the density control runs
every ``densify_every`` iterations from ``densify_from`` on until ``densify_until`` of the run, and the
opacities are reset every ``opacity_reset_every``. The budget is a number of iterations and, optionally,
seconds of training (previews excluded); whichever ends first. A :class:`~lab.core.Cancelled` thrown in
where the loop yields (the runner's Cancel) ends it too, with the Gaussians trained so far as the result.
Randomness comes from the step's ``rng``.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
import torch

from lab.core import Cameras, Cancelled, Image, Progress
from lab.modules.nerf import image_psnr
from lab.modules.splatting.density import DensityEvent, TrainedGaussians, position_lr
from lab.modules.splatting.gaussians import View, view_of
from lab.modules.splatting.losses import photometric_loss
from lab.modules.splatting.rasterize import render
from lab.modules.splatting.values import SplatModel, model_from_tensors

#: Iterations between two progress reports.
REPORT_EVERY = 10


@dataclass(frozen=True)
class SplatTrainingOptions:
    """How long and how to train: see the module docstring and :func:`train_gaussians`."""

    iterations: int
    budget_seconds: float
    sh_degree: int
    sh_every: int
    densify_from: int
    densify_every: int
    densify_until: float
    grad_threshold: float
    percent_dense: float
    min_opacity: float
    opacity_reset_every: int
    ssim_weight: float
    preview_every: int


@dataclass(frozen=True, eq=False)
class SplatTrainingRun:
    """A finished run: the trained ``model``, every iteration's loss and PSNR (of its view), the training
    seconds (previews excluded) and the density control's events."""

    model: SplatModel
    losses: np.ndarray
    psnrs: np.ndarray
    seconds: float
    events: tuple[DensityEvent, ...]

    @property
    def iterations(self) -> int:
        return len(self.losses)


def scene_extent(cameras: Cameras) -> float:
    """1.1 times the largest distance of a camera centre from their mean (the code's ``getNerfppNorm``):
    the scale of the means' learning rate and of the density control's size tests."""
    centres = cameras.centers
    return 1.1 * float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)) or 1.0)


def train_gaussians(initial: SplatModel, images: np.ndarray, cameras: Cameras,
                    options: SplatTrainingOptions, *, preview_view: int, rng: np.random.Generator,
                    device: str) -> Generator[Progress, None, SplatTrainingRun]:
    """Train ``initial`` on ``images`` (V, H, W, 3) seen by ``cameras`` (the module docstring); yields
    :class:`Progress` every :data:`REPORT_EVERY` iterations and, every ``preview_every``, training view
    ``preview_view`` rendered as ``values["preview"]``."""
    generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    extent = scene_extent(cameras)
    gaussians = TrainedGaussians(_training_tensors(initial, device), extent=extent)
    background = torch.as_tensor(initial.background, device=device)
    targets = torch.as_tensor(images, dtype=torch.float32, device=device)
    views = [view_of(cameras, v, device=device) for v in range(len(cameras))]
    order: list[int] = []
    losses: list[float] = []
    psnrs: list[float] = []
    events: list[DensityEvent] = []
    elapsed = 0.0
    degree = 0
    budget = options.budget_seconds
    while len(losses) < options.iterations and (budget <= 0 or elapsed < budget):
        tick = time.perf_counter()
        done = len(losses)
        spent = done / options.iterations
        if options.budget_seconds > 0:
            spent = max(spent, elapsed / options.budget_seconds)
        gaussians.set_position_lr(position_lr(0.00016 * extent, spent))
        if options.sh_every > 0 and done > 0 and done % options.sh_every == 0:
            degree = min(options.sh_degree, degree + 1)
        if not order:
            order = [int(v) for v in rng.permutation(len(views))]
        v = order.pop()
        p = gaussians.params
        rendering = render(p["means"], p["log_scales"], p["quats"], p["opacity_logits"], gaussians.sh(),
                           views[v], sh_degree=degree, background=background)
        loss, _ = photometric_loss(rendering.image, targets[v], ssim_weight=options.ssim_weight)
        gaussians.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        gaussians.record(rendering, views[v].width, views[v].height)
        gaussians.optimizer.step()
        losses.append(float(loss.detach()))
        psnrs.append(image_psnr(rendering.image.detach().cpu().numpy(), images[v]))
        done += 1
        event = _control_density(gaussians, options, done, spent, generator)
        if event is not None:
            events.append(event)
        elapsed += time.perf_counter() - tick
        last = done == options.iterations or 0 < options.budget_seconds <= elapsed
        if done % REPORT_EVERY == 0 or last:
            values = {}
            if done % options.preview_every == 0 or last:
                values["preview"] = _preview(gaussians, views[preview_view], degree, background)
            recent = float(np.mean(losses[-REPORT_EVERY:]))
            try:
                yield Progress(iteration=done, total=options.iterations, loss=recent,
                               message=f"PSNR {np.mean(psnrs[-REPORT_EVERY:]):.2f} dB, {len(gaussians)} "
                                       f"Gaussians, {elapsed:.1f} s", values=values)
            except Cancelled:  # the runner's Cancel: the Gaussians trained so far are the result
                break
    model = model_from_tensors({**gaussians.params, "sh": gaussians.sh()}, sh_degree=degree,
                               background=initial.background)
    return SplatTrainingRun(model, np.asarray(losses), np.asarray(psnrs), elapsed, tuple(events))


def _training_tensors(model: SplatModel, device: str) -> dict[str, torch.Tensor]:
    t = model.tensors(device=device)
    return {**t, "sh_dc": t["sh"][:, :1].contiguous(), "sh_rest": t["sh"][:, 1:].contiguous()}


def _control_density(gaussians: TrainedGaussians, options: SplatTrainingOptions, done: int, spent: float,
                     generator: torch.Generator) -> DensityEvent | None:
    """The density control and opacity reset due after iteration ``done`` (1-based), if any."""
    event = None
    if spent < options.densify_until and done >= options.densify_from and options.densify_every > 0 \
            and done % options.densify_every == 0:
        after_reset = options.opacity_reset_every > 0 and done > options.opacity_reset_every
        event = gaussians.densify_and_prune(iteration=done, grad_threshold=options.grad_threshold,
                                            percent_dense=options.percent_dense,
                                            min_opacity=options.min_opacity,
                                            max_screen_size=20.0 if after_reset else 0.0, generator=generator)
    reset = options.opacity_reset_every
    if spent < options.densify_until and reset > 0 and done % reset == 0:
        gaussians.reset_opacity()
    return event


def _preview(gaussians: TrainedGaussians, view: View, degree: int, background: torch.Tensor) -> Image:
    with torch.no_grad():
        p = gaussians.params
        image = render(p["means"], p["log_scales"], p["quats"], p["opacity_logits"], gaussians.sh(), view,
                       sh_degree=degree, background=background).image
    return Image(np.clip(image.cpu().numpy(), 0.0, 1.0), name="training preview")


__all__ = ["REPORT_EVERY", "SplatTrainingOptions", "SplatTrainingRun", "scene_extent", "train_gaussians"]
