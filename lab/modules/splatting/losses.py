"""The photometric loss of 3D Gaussian splatting: ``L = (1 - lambda) L1 + lambda D-SSIM``, lambda = 0.2
(Kerbl et al. 2023, section 7.1, eq. 7; the code's ``l1_loss`` and ``ssim``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: The weight of D-SSIM in the loss (the paper's lambda).
SSIM_WEIGHT = 0.2
_C1 = 0.01**2
_C2 = 0.03**2


def gaussian_window(size: int = 11, sigma: float = 1.5, *, dtype: torch.dtype = torch.float32,
                    device: str | torch.device = "cpu") -> torch.Tensor:
    """The normalized 1D Gaussian ``(size,)`` (sigma 1.5 px) whose outer product is SSIM's window."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).to(dtype=dtype, device=device)


def ssim(image: torch.Tensor, target: torch.Tensor, *, window: int = 11) -> torch.Tensor:
    """Mean structural similarity (Wang et al. 2004, eq. 13) of two ``(H, W, C)`` images, with local
    statistics under an 11 x 11 Gaussian window (sigma 1.5), zero-padded as the paper's code does; the
    window is separable, so each blur is a column pass then a row pass (the same sums, 5x fewer products)."""
    channels = image.shape[-1]
    g = gaussian_window(window, dtype=image.dtype, device=image.device)
    rows = g.reshape(1, 1, window, 1).expand(channels, 1, window, 1)
    cols = g.reshape(1, 1, 1, window).expand(channels, 1, 1, window)
    x, y = image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    pad = window // 2

    def blur(z: torch.Tensor) -> torch.Tensor:
        z = F.conv2d(z, rows, padding=(pad, 0), groups=channels)
        return F.conv2d(z, cols, padding=(0, pad), groups=channels)

    stacked = blur(torch.cat([x, y, x * x, y * y, x * y], dim=0))          # one batch of 5 maps
    mu_x, mu_y, xx, yy, xy = stacked.unbind(0)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    value = ((2 * mu_x * mu_y + _C1) * (2 * cov + _C2)) / ((mu_x**2 + mu_y**2 + _C1) * (var_x + var_y + _C2))
    return value.mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, *,
                     ssim_weight: float = SSIM_WEIGHT) -> tuple[torch.Tensor, torch.Tensor]:
    """``(1 - lambda) |I - I_gt|_1 + lambda (1 - SSIM(I, I_gt))`` (eq. 7) and the L1 term alone."""
    l1 = torch.mean(torch.abs(image - target))
    if ssim_weight == 0:
        return l1, l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(image, target)), l1


__all__ = ["SSIM_WEIGHT", "gaussian_window", "photometric_loss", "ssim"]
