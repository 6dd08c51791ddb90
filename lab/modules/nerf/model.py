"""The NeRF network and rendering rays through it (Mildenhall et al. 2020, section 3 and appendix A).

:class:`NerfMLP` is the paper's architecture made small: ``layers`` ReLU layers of width ``hidden`` on
``gamma(x)`` (with ``gamma(x)`` fed again half way, the paper's skip connection at its fifth of eight
layers), a density head on position alone, then a feature vector joined with ``gamma(d)`` through one
layer of ``hidden / 2`` to the colour (sigmoid). The density is a shifted softplus,
``sigma = softplus(raw - 1)`` (mip-NeRF, Barron et al. 2021, appendix): the paper's ReLU density dies
to an empty, all-white scene at the learning rates a small CPU run needs.

:func:`render_rays` samples, queries and composites: stratified coarse samples, then (``fine_samples``
> 0) hierarchical ones drawn from the coarse weights. The paper trains a second, "fine" network for
the union of samples; here one network answers both passes (as mip-NeRF does), which halves the
parameters a CPU must train; the loss is taken on both renderings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lab.core import InvalidValue
from lab.modules.nerf.encoding import encoding_size, positional_encoding
from lab.modules.nerf.rays import stratified_samples
from lab.modules.nerf.rendering import VolumeRendering, hierarchical_samples, volume_render
from lab.modules.nerf.values import FieldConfig, NerfCheckpoint, SceneBounds

#: The shift of the softplus density: ``sigma = softplus(raw - DENSITY_SHIFT)``.
DENSITY_SHIFT = 1.0


class NerfMLP(torch.nn.Module):
    """``(gamma(x), gamma(d)) -> (sigma (N,), rgb (N, 3))``: see the module docstring."""

    def __init__(self, config: FieldConfig) -> None:
        super().__init__()
        enc = config.encoding
        self.config = config
        position = encoding_size(enc.frequencies, include_input=enc.include_input)
        direction = encoding_size(enc.direction_frequencies, include_input=enc.include_input)
        hidden, layers = config.hidden, config.layers
        self.skip = layers // 2 if layers >= 4 else -1          # the layer that sees gamma(x) again
        self.trunk = torch.nn.ModuleList(
            [torch.nn.Linear(position if i == 0 else hidden + (position if i == self.skip else 0), hidden)
             for i in range(layers)])
        self.density = torch.nn.Linear(hidden, 1)
        self.feature = torch.nn.Linear(hidden, hidden)
        self.color = torch.nn.Sequential(torch.nn.Linear(hidden + direction, hidden // 2), torch.nn.ReLU(),
                                         torch.nn.Linear(hidden // 2, 3))

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density ``(N,)`` and colour ``(N, 3)`` at normalized points ``x`` ``(N, 3)`` seen along unit
        directions ``d`` ``(N, 3)``."""
        enc = self.config.encoding
        gx = positional_encoding(x, enc.frequencies, include_input=enc.include_input)
        gd = positional_encoding(d, enc.direction_frequencies, include_input=enc.include_input)
        h = gx
        for i, layer in enumerate(self.trunk):
            if i == self.skip:
                h = torch.cat([h, gx], dim=-1)
            h = torch.relu(layer(h))
        sigma = torch.nn.functional.softplus(self.density(h)[..., 0] - DENSITY_SHIFT)
        rgb = torch.sigmoid(self.color(torch.cat([self.feature(h), gd], dim=-1)))
        return sigma, rgb


@dataclass(frozen=True, eq=False)
class RayRendering:
    """:func:`render_rays`'s result: the ``coarse`` pass with its depths ``t_coarse`` ``(R, S)``, and the
    ``fine`` one with ``t_fine`` ``(R, S + F)`` (None without fine samples). ``final`` is the last pass."""

    coarse: VolumeRendering
    t_coarse: torch.Tensor
    fine: VolumeRendering | None = None
    t_fine: torch.Tensor | None = None

    @property
    def final(self) -> VolumeRendering:
        return self.coarse if self.fine is None else self.fine


def _query(net: NerfMLP, origins: torch.Tensor, directions: torch.Tensor, t: torch.Tensor,
           bounds: SceneBounds) -> tuple[torch.Tensor, torch.Tensor]:
    """Density ``(R, S)`` and colour ``(R, S, 3)`` at ``o + t d`` (normalized by the bounds)."""
    centre = torch.as_tensor(bounds.center, dtype=origins.dtype, device=origins.device)
    points = origins[:, None, :] + t[..., None] * directions[:, None, :]
    unit = directions / directions.norm(dim=-1, keepdim=True)
    x = ((points - centre) / bounds.radius).reshape(-1, 3)
    d = unit[:, None, :].expand_as(points).reshape(-1, 3)
    sigma, rgb = net(x, d)
    return sigma.reshape(t.shape), rgb.reshape(*t.shape, 3)


def render_rays(net: NerfMLP, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds, *,
                background: torch.Tensor, jitter: bool,
                generator: torch.Generator | None = None) -> RayRendering:
    """Render rays ``origins``, ``directions`` ``(R, 3)`` (camera z = 1: ``t`` is depth) through ``net``.

    ``net.config.samples`` stratified depths in ``[near, far]`` (jittered when ``jitter``; bin
    centres otherwise) are rendered by :func:`volume_render`; with ``fine_samples`` > 0 that many more
    are drawn from the coarse weights (:func:`hierarchical_samples`, deterministic without jitter) and
    the union is rendered again.
    """
    config = net.config
    norm = directions.norm(dim=-1)
    t = stratified_samples(bounds.near, bounds.far, len(origins), config.samples, jitter=jitter,
                           generator=generator, device=origins.device)
    sigma, rgb = _query(net, origins, directions, t, bounds)
    coarse = volume_render(sigma, rgb, t, far=bounds.far, direction_norm=norm, background=background)
    if config.fine_samples <= 0:
        return RayRendering(coarse, t)
    t_all = hierarchical_samples(t, coarse.weights, bounds.far, config.fine_samples, deterministic=not jitter,
                                 generator=generator).clamp(max=bounds.far)
    sigma, rgb = _query(net, origins, directions, t_all, bounds)
    fine = volume_render(sigma, rgb, t_all, far=bounds.far, direction_norm=norm, background=background)
    return RayRendering(coarse, t, fine, t_all)


def network_from(checkpoint: NerfCheckpoint, device: str = "cpu") -> NerfMLP:
    """The :class:`NerfMLP` of a checkpoint, weights loaded, in eval mode on ``device``."""
    net = NerfMLP(checkpoint.config)
    net.load_state_dict({k: torch.as_tensor(v) for k, v in checkpoint.weights.items()})
    return net.to(device).eval()


def checkpoint_from(net: NerfMLP, bounds: SceneBounds, background: np.ndarray) -> NerfCheckpoint:
    """A :class:`NerfCheckpoint` of ``net``'s current weights (copied to the CPU)."""
    weights = {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}
    return NerfCheckpoint(weights, net.config, bounds, background)


@dataclass(frozen=True, eq=False)
class ImageRendering:
    """A whole view rendered by :func:`render_image`: ``color`` ``(H, W, 3)``, ``depth`` and ``opacity``
    ``(H, W)`` float32 numpy arrays."""

    color: np.ndarray
    depth: np.ndarray
    opacity: np.ndarray

    def box_filtered(self, factor: int) -> ImageRendering:
        """This view, rendered at ``factor`` times a resolution, at that resolution: each pixel the mean of
        its ``factor x factor`` rendered pixels (colour, depth and opacity), i.e. of rays through a regular
        grid of points inside it -- the estimate of the pixel's area integral that the shared renderer's
        supersampling makes (brute-force supersampling against aliasing: Barron et al., "Mip-NeRF",
        ICCV 2021, section 1). The view's size must divide by ``factor``."""
        height, width = self.depth.shape
        if factor < 1 or height % factor or width % factor:
            raise InvalidValue("factor", f"a {width}x{height} view does not divide into {factor}x{factor} "
                                         "blocks")

        def mean(a: np.ndarray) -> np.ndarray:
            blocks = a.reshape(height // factor, factor, width // factor, factor, *a.shape[2:])
            return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        return ImageRendering(mean(self.color), mean(self.depth), mean(self.opacity))


def render_image(net: NerfMLP, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds,
                 shape: tuple[int, int], *, background: torch.Tensor, chunk: int = 8192) -> ImageRendering:
    """Render one view's rays ``(H * W, 3)`` (row-major) without jitter, ``chunk`` rays at a time, with no
    gradient; returns :class:`ImageRendering` of ``shape = (H, W)``."""
    colors, depths, opacities = [], [], []
    with torch.no_grad():
        for start in range(0, len(origins), chunk):
            out = render_rays(net, origins[start:start + chunk], directions[start:start + chunk], bounds,
                              background=background, jitter=False).final
            colors.append(out.color)
            depths.append(out.depth)
            opacities.append(out.opacity)
    height, width = shape
    return ImageRendering(torch.cat(colors).clamp(0, 1).reshape(height, width, 3).cpu().numpy(),
                          torch.cat(depths).reshape(height, width).cpu().numpy(),
                          torch.cat(opacities).reshape(height, width).cpu().numpy())


__all__ = ["DENSITY_SHIFT", "ImageRendering", "NerfMLP", "RayRendering", "checkpoint_from", "network_from",
           "render_image", "render_rays"]
