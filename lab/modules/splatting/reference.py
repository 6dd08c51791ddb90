"""The readable rasterizer of 3D Gaussian splatting: the tests' oracle for the image and every gradient.

Plain PyTorch autograd, one Gaussian and one pixel at a time, written as Kerbl et al. 2023 (section 4,
eqs. 2, 5, 6; section 6 and the code's ``preprocessCUDA`` / ``renderCUDA``) state it, sharing nothing with
the fast path (:mod:`.gaussians`, :mod:`.rasterize`, :mod:`._kernels`) but the spherical-harmonic basis
(checked on its own):

- per Gaussian: ``Sigma = R S S^T R^T``, the camera-frame mean, the Jacobian ``J`` of the perspective map
  there (``x/z``, ``y/z`` clamped to 1.3 times the half field of view), ``Sigma' = J W Sigma W^T J^T`` plus
  0.3 px^2, its inverse (the conic), the radius ``ceil(3 sqrt(lambda_max))`` and the tile rectangle;
- per pixel: every Gaussian whose tile rectangle holds the pixel's tile, nearest first (stable in index
  on ties), composited front to back: ``alpha = min(0.99, o exp(-d^T Sigma'^-1 d / 2))``, skipped where
  below 1/255 (or where the exponent is positive), and the pixel done before the Gaussian that would take
  the transmittance below 1e-4; ``C = sum_i c_i alpha_i T_i + T background`` (eq. 3).

Slow: for scenes of tens of Gaussians and images of tens of pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lab.modules.splatting.gaussians import DILATION, NEAR_PLANE, TILE_SIZE, View
from lab.modules.splatting.sh import sh_colors

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


@dataclass(frozen=True, eq=False)
class GaussianInImage:
    """One Gaussian as the reference rasterizer sees it (``drawn`` False: culled)."""

    mean2d: torch.Tensor
    conic: torch.Tensor
    depth: float
    radius: int
    rect: tuple[int, int, int, int]
    drawn: bool


def rotation_reference(q: torch.Tensor) -> torch.Tensor:
    """The rotation of quaternion ``q = (w, v)`` (normalized first):
    ``(w^2 - v.v) I + 2 v v^T + 2 w [v]_x``."""
    q = q / torch.sqrt(torch.sum(q * q))
    w, v = q[0], q[1:]
    cross = torch.stack([torch.stack([0 * w, -v[2], v[1]]), torch.stack([v[2], 0 * w, -v[0]]),
                         torch.stack([-v[1], v[0], 0 * w])])
    return (w * w - v @ v) * torch.eye(3, dtype=q.dtype) + 2 * torch.outer(v, v) + 2 * w * cross


def project_one_reference(mean: torch.Tensor, log_scale: torch.Tensor, quat: torch.Tensor, view: View, *,
                          tile_size: int = TILE_SIZE, near: float = NEAR_PLANE) -> GaussianInImage:
    """One Gaussian in the image (the module docstring)."""
    R = rotation_reference(quat)
    S = torch.diag(torch.exp(log_scale))
    sigma = R @ S @ S.T @ R.T                                            # eq. 6
    p = view.R @ mean + view.t
    x, y, z = p[0], p[1], p[2]
    depth = float(z.detach())
    if depth <= near:
        zero = torch.zeros(2, dtype=mean.dtype)
        return GaussianInImage(zero, torch.zeros(3, dtype=mean.dtype), depth, 0, (0, 0, 0, 0), False)
    half_x, half_y = 0.5 * view.width / view.fx, 0.5 * view.height / view.fy
    x_seen = torch.clamp(x / z, -view.cx / view.fx - 0.3 * half_x,
                         (view.width - view.cx) / view.fx + 0.3 * half_x) * z
    y_seen = torch.clamp(y / z, -view.cy / view.fy - 0.3 * half_y,
                         (view.height - view.cy) / view.fy + 0.3 * half_y) * z
    zero = 0 * z
    J = torch.stack([torch.stack([view.fx / z, zero, -view.fx * x_seen / z**2]),
                     torch.stack([zero, view.fy / z, -view.fy * y_seen / z**2])])
    W = view.R
    sigma2d = J @ W @ sigma @ W.T @ J.T + DILATION * torch.eye(2, dtype=mean.dtype)   # eq. 5
    det = sigma2d[0, 0] * sigma2d[1, 1] - sigma2d[0, 1] * sigma2d[1, 0]
    mean2d = torch.stack([view.fx * x / z + view.cx, view.fy * y / z + view.cy])
    if float(det.detach()) <= 0:
        return GaussianInImage(mean2d, torch.zeros(3, dtype=mean.dtype), depth, 0, (0, 0, 0, 0), False)
    inverse = torch.linalg.inv(sigma2d)
    conic = torch.stack([inverse[0, 0], inverse[0, 1], inverse[1, 1]])
    m = 0.5 * float((sigma2d[0, 0] + sigma2d[1, 1]).detach())
    lambda_max = m + math.sqrt(max(0.1, m * m - float(det.detach())))
    radius = math.ceil(3.0 * math.sqrt(max(lambda_max, 0.0)))
    tiles_x, tiles_y = math.ceil(view.width / tile_size), math.ceil(view.height / tile_size)
    u, v = float(mean2d[0].detach()), float(mean2d[1].detach())
    rect = (min(tiles_x, max(0, math.floor((u - radius) / tile_size))),
            min(tiles_y, max(0, math.floor((v - radius) / tile_size))),
            min(tiles_x, max(0, math.floor((u + radius + tile_size - 1) / tile_size))),
            min(tiles_y, max(0, math.floor((v + radius + tile_size - 1) / tile_size))))
    drawn = radius > 0 and rect[2] > rect[0] and rect[3] > rect[1]
    return GaussianInImage(mean2d, conic, depth, radius if drawn else 0, rect, drawn)


def composite_pixel_reference(px: int, py: int, gaussians: list[GaussianInImage], colors: torch.Tensor,
                              opacities: torch.Tensor, background: torch.Tensor,
                              tile_size: int = TILE_SIZE) -> torch.Tensor:
    """The colour (3,) of pixel ``(px, py)``: front-to-back alpha compositing (eq. 3) of the Gaussians whose
    tile rectangles hold its tile, nearest first."""
    tx, ty = px // tile_size, py // tile_size
    here = [i for i, g in enumerate(gaussians)
            if g.drawn and g.rect[0] <= tx < g.rect[2] and g.rect[1] <= ty < g.rect[3]]
    here.sort(key=lambda i: (gaussians[i].depth, i))
    color = torch.zeros(3, dtype=colors.dtype)
    T = torch.ones((), dtype=colors.dtype)
    for i in here:
        g = gaussians[i]
        dx, dy = g.mean2d[0] - px, g.mean2d[1] - py
        power = -0.5 * (g.conic[0] * dx * dx + g.conic[2] * dy * dy) - g.conic[1] * dx * dy
        if float(power.detach()) > 0:
            continue
        alpha = torch.clamp(opacities[i] * torch.exp(power), max=ALPHA_MAX)
        if float(alpha.detach()) < ALPHA_MIN:
            continue
        if float((T * (1 - alpha)).detach()) < T_MIN:
            break
        color = color + colors[i] * alpha * T
        T = T * (1 - alpha)
    return color + T * background


def render_reference(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                     opacity_logits: torch.Tensor, sh: torch.Tensor, view: View, *, sh_degree: int,
                     background: torch.Tensor, tile_size: int = TILE_SIZE) -> torch.Tensor:
    """The image ``(H, W, 3)`` of Gaussians (parameters as in :func:`~.rasterize.render`) seen by ``view``,
    differentiable in every parameter by autograd."""
    gaussians = [project_one_reference(means[i], log_scales[i], quats[i], view, tile_size=tile_size)
                 for i in range(len(means))]
    centre = -view.R.T @ view.t
    directions = torch.stack([(means[i] - centre) / torch.linalg.vector_norm(means[i] - centre)
                              for i in range(len(means))]) if len(means) else means
    colors = sh_colors(sh, directions, sh_degree)
    opacities = 1.0 / (1.0 + torch.exp(-opacity_logits))
    rows = [torch.stack([composite_pixel_reference(px, py, gaussians, colors, opacities, background,
                                                   tile_size) for px in range(view.width)])
            for py in range(view.height)]
    return torch.stack(rows)


__all__ = ["ALPHA_MAX", "ALPHA_MIN", "T_MIN", "GaussianInImage", "composite_pixel_reference",
           "project_one_reference", "render_reference", "rotation_reference"]
