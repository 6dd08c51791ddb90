"""The 2D warm-up: one image fitted by a coordinate MLP, with and without the positional encoding
(Tancik et al., "Fourier features let networks learn high frequency functions in low dimensional
domains", NeurIPS 2020, section 6 and their Figure 1; Mildenhall et al. 2020, section 5.1 and Figure 4).

A network ``(x, y) -> RGB`` trained on every pixel at once is the smallest case of what NeRF does: without
the encoding a ReLU MLP is biased towards low frequencies ("spectral bias") and its image stays a blur
however long it trains; fed ``gamma(x, y)`` with L frequencies it picks up detail down to about
``2^(L-1)`` periods across the image. Same network, same optimizer, same initial seed for every L, so the
PSNR curves differ only by the encoding.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from lab.core import Progress
from lab.modules.nerf.encoding import encoding_size, positional_encoding
from lab.modules.nerf.evaluate import psnr_from_mse

#: Iterations between two progress reports of a fit.
FIT_REPORT_EVERY = 50


def pixel_coordinates(height: int, width: int) -> torch.Tensor:
    """Every pixel centre ``(H * W, 2)`` float32 as ``(x, y)`` in ``[-1, 1]`` (row-major; the outermost
    centres at -1 and 1)."""
    ys, xs = torch.meshgrid(torch.linspace(-1.0, 1.0, height), torch.linspace(-1.0, 1.0, width),
                            indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)


class CoordinateMLP(torch.nn.Module):
    """``(x, y) -> RGB``: ``gamma`` with ``frequencies`` L (0: the coordinates themselves, no encoding), then
    ``layers`` ReLU layers of width ``hidden`` and a sigmoid output."""

    def __init__(self, frequencies: int, hidden: int, layers: int) -> None:
        super().__init__()
        self.frequencies = frequencies
        width = encoding_size(frequencies, include_input=True, dim=2)
        blocks: list[torch.nn.Module] = []
        for _ in range(layers):
            blocks += [torch.nn.Linear(width, hidden), torch.nn.ReLU()]
            width = hidden
        self.body = torch.nn.Sequential(*blocks, torch.nn.Linear(width, 3), torch.nn.Sigmoid())

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return self.body(positional_encoding(xy, self.frequencies, include_input=True))


def fitting_target(pixels: np.ndarray, side: int) -> np.ndarray:
    """An RGB ``(H, W, 3)`` float32 image shrunk (area averaging) so its longer side is at most ``side``."""
    image = np.asarray(pixels, dtype=np.float32)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    height, width = image.shape[:2]
    factor = min(1.0, side / max(height, width))
    if factor < 1.0:
        size = (max(1, round(width * factor)), max(1, round(height * factor)))
        image = np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.float32)
    return np.ascontiguousarray(image[:, :, :3])


@dataclass(frozen=True, eq=False)
class ImageFit:
    """One fit: its ``frequencies`` (0: none), the PSNR ``(iterations,)`` after each step and the final image
    ``(H, W, 3)``."""

    frequencies: int
    psnrs: np.ndarray
    image: np.ndarray


def fit_image(target: np.ndarray, frequencies: int, *, hidden: int, layers: int, iterations: int,
              learning_rate: float, seed: int, device: str = "cpu", before: int = 0,
              total: int | None = None) -> Generator[Progress, None, ImageFit]:
    """Fit ``target`` ``(H, W, 3)`` with a :class:`CoordinateMLP` by Adam on the mean squared error over all
    pixels (one full batch per step); initial weights from ``seed``. Yields progress every
    :data:`FIT_REPORT_EVERY` steps, counted from ``before`` steps of ``total`` (several fits in a row)."""
    height, width = target.shape[:2]
    xy = pixel_coordinates(height, width).to(device)
    colours = torch.as_tensor(target.reshape(-1, 3), device=device)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        net = CoordinateMLP(frequencies, hidden, layers).to(device)
    optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
    psnrs = np.zeros(iterations)
    name = "no encoding" if frequencies == 0 else f"L = {frequencies}"
    for i in range(iterations):
        mse = torch.mean((net(xy) - colours) ** 2)
        optimizer.zero_grad(set_to_none=True)
        mse.backward()
        optimizer.step()
        psnrs[i] = psnr_from_mse(float(mse.detach()))
        if (i + 1) % FIT_REPORT_EVERY == 0 or i + 1 == iterations:
            yield Progress(iteration=before + i + 1, total=total or iterations, loss=float(mse.detach()),
                           message=f"{name}: PSNR {psnrs[i]:.2f} dB")
    with torch.no_grad():
        image = net(xy).reshape(height, width, 3).cpu().numpy()
    return ImageFit(frequencies, psnrs, image)


__all__ = ["FIT_REPORT_EVERY", "CoordinateMLP", "ImageFit", "fit_image", "fitting_target",
           "pixel_coordinates"]
