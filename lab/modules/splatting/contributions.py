"""Which Gaussians make one pixel: the depth-sorted list a pixel composites, with each Gaussian's alpha, the
transmittance it meets and its weight ``w_i = alpha_i T_i`` (Kerbl et al. 2023, eq. 3 and section 6).

The list is the fast rasterizer's: the Gaussians whose tile rectangle holds the pixel's tile
(:func:`.gaussians.project`), nearest first (ties in index order, as :func:`.rasterize.bin_gaussians`
sorts), each skipped where its alpha ``min(0.99, o exp(-d^T Sigma'^-1 d / 2))`` is under 1/255 or its
exponent is positive, the walk ending before the Gaussian that would take the transmittance under 1e-4
(the constants of :mod:`.reference`). So ``sum_i w_i c_i + T_end background`` is the rendered pixel, which
the tests check against :func:`.rasterize.render`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lab.core import Cameras, InvalidControl
from lab.modules.splatting.gaussians import TILE_SIZE, activated_opacities, project, view_colors, view_of
from lab.modules.splatting.reference import ALPHA_MAX, ALPHA_MIN, T_MIN
from lab.modules.splatting.values import SplatModel, as_model


@dataclass(frozen=True, eq=False)
class PixelContributions:
    """The Gaussians composited into pixel ``(u, v)``, front to back: their indices ``ids`` (K,) into the
    model, camera ``depths`` (K,), ``alphas`` (K,), the transmittance ``before`` (K,) each one meets, their
    ``weights`` (K,) ``alpha T``, view-dependent ``colors`` (K, 3); ``remaining`` is the transmittance
    left for the background and ``color`` (3,) the pixel's colour."""

    u: int
    v: int
    ids: np.ndarray
    depths: np.ndarray
    alphas: np.ndarray
    before: np.ndarray
    weights: np.ndarray
    colors: np.ndarray
    remaining: float
    color: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def pixel_contributions(model: SplatModel, cameras: Cameras, index: int, u: int, v: int, *,
                        tile_size: int = TILE_SIZE) -> PixelContributions:
    """The Gaussians of ``model`` that camera ``index`` of ``cameras`` composites into pixel ``(u, v)``
    (column, row; pixel (0, 0) is the centre of the top-left pixel), as the module docstring says.
    :class:`InvalidControl` for a pixel outside the image."""
    model = as_model(model, "model")
    if not (0 <= u < cameras.width and 0 <= v < cameras.height):
        raise InvalidControl("pixel_u" if not 0 <= u < cameras.width else "pixel_v",
                             f"pixel ({u}, {v}) is outside the {cameras.width}x{cameras.height} image")
    t = model.tensors()
    view = view_of(cameras, index)
    with torch.no_grad():
        projected = project(t["means"], t["log_scales"], t["quats"], view, tile_size=tile_size)
        rgb = view_colors(t["means"], t["sh"], model.sh_degree, view).numpy()
        opacity = activated_opacities(t["opacity_logits"]).numpy()
    rects, depths = projected.rects.numpy(), projected.depths.numpy()
    tx, ty = u // tile_size, v // tile_size
    here = np.flatnonzero((projected.radii.numpy() > 0) & (rects[:, 0] <= tx) & (tx < rects[:, 2])
                          & (rects[:, 1] <= ty) & (ty < rects[:, 3]))
    here = here[np.lexsort((here, depths[here]))]
    d = projected.means2d.numpy()[here] - np.array([u, v], np.float32)
    a, b, c = projected.conics.numpy()[here].T
    power = -0.5 * (a * d[:, 0] ** 2 + c * d[:, 1] ** 2) - b * d[:, 0] * d[:, 1]
    alpha = np.minimum(ALPHA_MAX, opacity[here] * np.exp(np.minimum(power, 0.0)))
    kept: list[int] = []
    before: list[float] = []
    T = 1.0
    for k in np.flatnonzero((power <= 0) & (alpha >= ALPHA_MIN)):
        if T * (1.0 - alpha[k]) < T_MIN:
            break
        kept.append(int(k))
        before.append(T)
        T *= 1.0 - float(alpha[k])
    ids = here[kept]
    weights = alpha[kept] * np.asarray(before, np.float64)
    color = (weights[:, None] * rgb[ids]).sum(axis=0) + T * model.background
    return PixelContributions(u, v, ids, depths[ids].astype(np.float64), alpha[kept].astype(np.float64),
                              np.asarray(before, np.float64), weights.astype(np.float64),
                              rgb[ids].astype(np.float64), T, color.astype(np.float64))


__all__ = ["PixelContributions", "pixel_contributions"]
