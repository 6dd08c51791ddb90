"""Optimizing Gaussians: Adam with per-parameter learning rates, and adaptive density control.

Kerbl et al. 2023, section 5 and the code's ``GaussianModel``:

- Adam (torch's, eps 1e-15) with one learning rate per parameter (:data:`LEARNING_RATES`); the means' rate
  decays exponentially from ``0.00016`` to ``0.0000016`` times the scene extent over the run
  (:func:`position_lr`, the code's ``get_expon_lr_func``).
- Adaptive density control (section 5.2): over each interval the norm of every Gaussian's view-space
  positional gradient (that of its projected mean, in the code's normalized device coordinates) is
  averaged over the views that saw it; those above the threshold are **cloned** when small (largest scale
  at most ``percent_dense`` of the scene extent: under-reconstruction) and **split** in two when large
  (over-reconstruction: two samples from the Gaussian itself, scales divided by 1.6); Gaussians nearly
  transparent (opacity below 0.005), larger than 10 % of the scene extent or, after the first opacity reset,
  bigger than 20 px on screen are **pruned**; every few thousand iterations the opacities are **reset** to
  at most 0.01.

When Gaussians are added or removed the optimizer's moments follow them (new ones start at zero), as the
code's ``cat_tensors_to_optimizer`` and ``_prune_optimizer`` do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lab.modules.splatting.gaussians import quaternion_rotations
from lab.modules.splatting.rasterize import Rendering
from lab.modules.splatting.values import MAX_GAUSSIANS

#: Adam's learning rate of each trained tensor (the code's ``OptimizationParams``; the means' is the initial
#: one, times the scene extent, and decays).
LEARNING_RATES = {"means": 0.00016, "sh_dc": 0.0025, "sh_rest": 0.0025 / 20, "opacity_logits": 0.025,
                  "log_scales": 0.005, "quats": 0.001}
TRAINED = tuple(LEARNING_RATES)
#: Where the means' learning rate ends, as a fraction of where it starts (0.0000016 / 0.00016).
POSITION_LR_FINAL = 0.01


def position_lr(initial: float, fraction: float) -> float:
    """The means' learning rate after ``fraction`` of the run: log-linear from ``initial`` to
    ``POSITION_LR_FINAL * initial`` (the code's ``get_expon_lr_func`` without its warm-up)."""
    f = min(max(fraction, 0.0), 1.0)
    return math.exp((1 - f) * math.log(initial) + f * math.log(initial * POSITION_LR_FINAL))


@dataclass(frozen=True)
class DensityEvent:
    """What one densification did: at ``iteration``, ``clones`` + ``splits`` new Gaussians (a split removes
    its original), ``prunes`` removed, ``count`` after it."""

    iteration: int
    clones: int
    splits: int
    prunes: int
    count: int


class TrainedGaussians:
    """The Gaussians being trained: their parameters (``torch.nn.Parameter`` by name, :data:`TRAINED`), the
    Adam optimizer over them, and the statistics the density control reads."""

    def __init__(self, tensors: dict[str, torch.Tensor], *, extent: float) -> None:
        self.params = {name: torch.nn.Parameter(tensors[name].detach().clone()) for name in TRAINED}
        self.extent = extent
        groups = [{"params": [self.params[name]], "name": name,
                   "lr": LEARNING_RATES[name] * (extent if name == "means" else 1.0)} for name in TRAINED]
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        self._reset_statistics()

    def __len__(self) -> int:
        return len(self.params["means"])

    def _reset_statistics(self) -> None:
        device = self.params["means"].device
        self.grad_sum = torch.zeros(len(self), device=device)
        self.seen = torch.zeros(len(self), device=device)
        self.max_radii = torch.zeros(len(self), device=device)

    def sh(self) -> torch.Tensor:
        """All spherical-harmonic coefficients ``(N, 16, 3)`` (degree 0 first)."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    def set_position_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lr

    def record(self, rendering: Rendering, width: int, height: int) -> None:
        """Add one view's view-space positional gradients (after ``backward``) and screen radii: the norm of
        ``d loss / d mean2d`` in normalized device coordinates (pixels times ``(W/2, H/2)``, the units of the
        paper's threshold 0.0002), for the Gaussians the view drew."""
        seen = rendering.radii > 0
        grad = rendering.means2d.grad
        if grad is None:
            return
        scale = torch.tensor([0.5 * width, 0.5 * height], dtype=grad.dtype, device=grad.device)
        norms = torch.linalg.vector_norm(grad.detach() * scale, dim=-1)
        self.grad_sum[seen] += norms[seen].to(self.grad_sum.dtype)
        self.seen[seen] += 1
        radii = rendering.radii[seen].to(self.max_radii.dtype)
        self.max_radii[seen] = torch.maximum(self.max_radii[seen], radii)

    # --- changing the set of Gaussians, moments and all --------------------------------------------------
    def _replace(self, build: dict[str, torch.Tensor],
                 moments: dict[str, tuple[torch.Tensor, torch.Tensor]]) -> None:
        for group in self.optimizer.param_groups:
            name = group["name"]
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            new = torch.nn.Parameter(build[name])
            group["params"][0] = new
            self.params[name] = new
            if state:
                state["exp_avg"], state["exp_avg_sq"] = moments[name]
                self.optimizer.state[new] = state

    def _moments(self, name: str) -> tuple[torch.Tensor, torch.Tensor] | None:
        state = self.optimizer.state.get(self.params[name])
        return (state["exp_avg"], state["exp_avg_sq"]) if state else None

    def append(self, new: dict[str, torch.Tensor]) -> None:
        """Add Gaussians (tensors by name); their moments start at zero, their statistics too."""
        build, moments = {}, {}
        for name in TRAINED:
            build[name] = torch.cat([self.params[name].detach(), new[name].detach()])
            old = self._moments(name)
            if old is not None:
                zeros = torch.zeros_like(new[name])
                moments[name] = (torch.cat([old[0], zeros]), torch.cat([old[1], zeros]))
        added = len(new["means"])
        self._replace(build, moments)
        pad = torch.zeros(added, device=self.grad_sum.device)
        self.grad_sum, self.seen = torch.cat([self.grad_sum, pad]), torch.cat([self.seen, pad])
        self.max_radii = torch.cat([self.max_radii, pad])

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where ``mask`` (N,) is true."""
        build = {name: self.params[name].detach()[mask] for name in TRAINED}
        moments = {}
        for name in TRAINED:
            old = self._moments(name)
            if old is not None:
                moments[name] = (old[0][mask], old[1][mask])
        self._replace(build, moments)
        self.grad_sum, self.seen, self.max_radii = self.grad_sum[mask], self.seen[mask], self.max_radii[mask]

    # --- adaptive density control ------------------------------------------------------------------------
    def densify_and_prune(self, *, iteration: int, grad_threshold: float, percent_dense: float,
                          min_opacity: float, max_screen_size: float,
                          generator: torch.Generator) -> DensityEvent:
        """Clone, split and prune (the module docstring; the code's ``densify_and_prune``), then start new
        statistics. No more Gaussians are added past :data:`MAX_GAUSSIANS`."""
        average = torch.nan_to_num(self.grad_sum / self.seen, nan=0.0)
        large = torch.exp(self.params["log_scales"].detach()).amax(dim=1) > percent_dense * self.extent
        hot = average >= grad_threshold
        room = MAX_GAUSSIANS - len(self)
        clone = hot & ~large
        split = hot & large
        if int(clone.sum()) + 2 * int(split.sum()) > room:
            clone = split = torch.zeros_like(hot)
        count_before = len(self)
        clones = {name: self.params[name].detach()[clone] for name in TRAINED}
        splits = self._split(split, generator)
        self.append(clones)
        self.append(splits)
        split_padded = torch.cat([split, torch.zeros(len(self) - count_before, dtype=torch.bool,
                                                     device=split.device)])
        opacity = torch.sigmoid(self.params["opacity_logits"].detach())
        scale = torch.exp(self.params["log_scales"].detach()).amax(dim=1)
        prune = opacity < min_opacity
        if max_screen_size > 0:
            prune |= (self.max_radii > max_screen_size) | (scale > 0.1 * self.extent)
        pruned = int((prune & ~split_padded).sum())
        self.keep(~(prune | split_padded))
        self._reset_statistics()
        return DensityEvent(iteration, int(clone.sum()), int(split.sum()), pruned, len(self))

    def _split(self, mask: torch.Tensor, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Two Gaussians for each one of ``mask``: means drawn from the Gaussian (``mu + R diag(s) z``),
        scales divided by 1.6 (0.8 times the 2 samples), other parameters copied."""
        p = {name: self.params[name].detach()[mask] for name in TRAINED}
        scales = torch.exp(p["log_scales"]).repeat(2, 1)
        z = torch.randn(scales.shape, generator=generator).to(scales)
        rotations = quaternion_rotations(p["quats"]).repeat(2, 1, 1)
        out = {name: value.repeat(2, *([1] * (value.dim() - 1))) for name, value in p.items()}
        out["means"] = (rotations @ (z * scales)[..., None])[..., 0] + p["means"].repeat(2, 1)
        out["log_scales"] = torch.log(scales / 1.6)
        return out

    def reset_opacity(self, ceiling: float = 0.01) -> None:
        """Opacities to at most ``ceiling`` (their logits, with zero moments: the code's
        ``reset_opacity``)."""
        logits = self.params["opacity_logits"].detach()
        capped = torch.minimum(logits, torch.full_like(logits, math.log(ceiling / (1 - ceiling))))
        moments = {}
        for name in TRAINED:
            old = self._moments(name)
            if old is not None:
                zeros = (torch.zeros_like(old[0]), torch.zeros_like(old[1]))
                moments[name] = zeros if name == "opacity_logits" else old
        self._replace({**{name: self.params[name].detach() for name in TRAINED}, "opacity_logits": capped},
                      moments)


__all__ = ["LEARNING_RATES", "POSITION_LR_FINAL", "TRAINED", "DensityEvent", "TrainedGaussians",
           "position_lr"]
