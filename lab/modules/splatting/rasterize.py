"""The fast rasterizer of 3D Gaussian splatting on the CPU: tile binning, per-tile depth sort, compiled
front-to-back compositing and its hand-written backward pass, wrapped in a ``torch.autograd.Function``.

Kerbl et al. 2023, section 6 ("Fast differentiable rasterizer for Gaussians"): the image is cut into
16 x 16 px tiles; each Gaussian is listed once in every tile its 3-sigma rectangle touches and its
ellipse (where alpha can reach 1/255) reaches (:func:`bin_gaussians`); each tile's list is sorted by
depth (the paper's radix sort of (tile, depth) keys done as one depth sort and a compiled counting sort
by tile); each pixel composites its tile's list front to back and stops
when the transmittance would fall below 1e-4 (:mod:`._kernels`). The backward pass re-walks each pixel's
list back to front. The projection before it (:func:`.gaussians.project`) and the spherical harmonics stay
in torch autograd, so :func:`render` is differentiable in every parameter. :mod:`.reference` is the slow
per-pixel oracle of the whole.

Tensors on a CUDA device are rasterized on the CPU and the image moved back (the same results; gsplat is
the tool for speed there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from lab.core import CapacityExceeded
from lab.core.kernels import bands, in_parallel, workers
from lab.modules.splatting._kernels import (_bin_kernel, _preprocess_kernel, _rasterize_backward_kernel,
                                            _rasterize_forward_kernel, alpha_floor_exponents,
                                            kernel_constants, pack_pairs)
from lab.modules.splatting.gaussians import (DILATION, NEAR_PLANE, TILE_SIZE, View, activated_opacities,
                                             project, view_colors)
from lab.modules.splatting.sh import C0, C1, C2, C3, check_sh
from lab.modules.splatting.values import check_count

#: Most (Gaussian, tile) pairs one image may list (about 0.5 GB of sort keys and indices).
MAX_TILE_PAIRS = 2**25


@dataclass(frozen=True, eq=False)
class Binning:
    """Every tile's depth-sorted list of Gaussians: tile ``k`` (row-major) holds ``ids[ranges[k, 0]:
    ranges[k, 1]]``, nearest first (ties in index order)."""

    ranges: np.ndarray
    ids: np.ndarray
    tiles_x: int
    tiles_y: int

    @property
    def pairs(self) -> int:
        """(Gaussian, tile) pairs listed."""
        return len(self.ids)


def bin_gaussians(rects: np.ndarray, depths: np.ndarray, *, width: int, height: int,
                  tile_size: int = TILE_SIZE,
                  footprints: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Binning:
    """List each Gaussian in every tile of its rectangle ``rects`` (N, 4) ``(x0, y0, x1, y1)`` (an empty
    rectangle: not drawn) and sort each tile's list by ``depths`` (N,) (ties in index order: a stable
    counting sort by tile of the Gaussians in depth order). With ``footprints``, the Gaussians' ``(means2d
    (N, 2), conics (N, 3), opacities (N,))``, a tile that the ellipse where the Gaussian's alpha can reach
    1/255 misses is left out (the 3-sigma square lists the corners of a thin diagonal one, and a faint one
    reaches less far): it would add nothing there. :class:`CapacityExceeded` past :data:`MAX_TILE_PAIRS`
    pairs (of the rectangles, before that culling)."""
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    rects = np.ascontiguousarray(np.asarray(rects, dtype=np.int64).reshape(-1, 4))
    counts = np.maximum(rects[:, 2] - rects[:, 0], 0) * np.maximum(rects[:, 3] - rects[:, 1], 0)
    total = int(counts.sum())
    if total > MAX_TILE_PAIRS:
        raise CapacityExceeded("gaussians", f"the Gaussians cover {total} (Gaussian, tile) pairs in one "
                                            f"{width}x{height} image, more than {MAX_TILE_PAIRS}: use fewer "
                                            "or smaller Gaussians")
    drawn = np.flatnonzero(counts > 0)
    order = drawn[np.argsort(np.asarray(depths)[drawn], kind="stable")]
    if footprints is None:
        means2d, conics, limits = np.zeros((len(rects), 2)), np.zeros((len(rects), 3)), np.zeros(len(rects))
    else:
        means2d, conics = (np.ascontiguousarray(a, dtype=np.float64) for a in footprints[:2])
        limits = -2.0 * alpha_floor_exponents(np.asarray(footprints[2]))
    ranges = np.zeros((tiles_x * tiles_y, 2), np.int64)
    ids = np.empty(total, np.int64)
    pairs = _bin_kernel(order, rects, means2d, conics, limits, footprints is not None, tile_size, width,
                        height, tiles_x, ranges, ids, np.empty(total, np.bool_))
    return Binning(ranges, ids[:pairs], tiles_x, tiles_y)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy())


def _tile_bands(binning: Binning) -> list[tuple[int, int]]:
    """Bands of tiles for the threads: four per worker, so that the busy tiles spread over them; one band
    (run in the calling thread, no pool) where the process has one CPU."""
    threads = workers()
    return bands(binning.tiles_x * binning.tiles_y, parts=1 if threads == 1 else 4 * threads)


def _composite(means2d: np.ndarray, conics: np.ndarray, colors: np.ndarray, opacities: np.ndarray,
               background: np.ndarray, binning: Binning, *, width: int, height: int,
               tile_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled front-to-back compositing of ``binning``'s lists, in the dtype of ``means2d`` (the
    others in it too): the image (H, W, 3), the transmittance left (H, W), how far into its tile's list
    each pixel read (H, W) and the packed lists (:func:`._kernels.pack_pairs`)."""
    packed = pack_pairs(binning.ids, means2d, conics, opacities)
    image = np.zeros((height, width, 3), means2d.dtype)
    final_t = np.ones((height, width), means2d.dtype)
    n_contrib = np.zeros((height, width), np.int64)
    constants = kernel_constants(means2d.dtype)
    in_parallel(_rasterize_forward_kernel,
                [(a, b, binning.ranges, binning.ids, packed, colors, background, constants, tile_size,
                  binning.tiles_x, image, final_t, n_contrib) for a, b in _tile_bands(binning)])
    return image, final_t, n_contrib, packed


class _Rasterize(torch.autograd.Function):
    """The compiled compositing with its hand-written backward (gradients for means2d, conics, colours and
    opacities; none for the background)."""

    @staticmethod
    def forward(ctx: Any, means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                opacities: torch.Tensor, background: torch.Tensor, binning: Binning, width: int, height: int,
                tile_size: int) -> torch.Tensor:
        mean, conic, color, opacity, bg = (_numpy(t)
                                           for t in (means2d, conics, colors, opacities, background))
        image, final_t, n_contrib, packed = _composite(mean, conic, color, opacity, bg, binning,
                                                       width=width, height=height, tile_size=tile_size)
        ctx.arrays, ctx.binning, ctx.tile_size, ctx.count = (packed, color, bg), binning, tile_size, len(mean)
        ctx.final_t, ctx.n_contrib = final_t, n_contrib
        return torch.from_numpy(image).to(means2d.device)

    @staticmethod
    def backward(ctx: Any, grad_image: torch.Tensor) -> tuple[Any, ...]:
        arrays, binning = ctx.arrays, ctx.binning
        dtype = arrays[0].dtype
        jobs = _tile_bands(binning)
        grads = np.zeros((len(jobs), ctx.count, 9), dtype)
        grad = _numpy(grad_image).astype(dtype, copy=False)
        constants = kernel_constants(dtype)
        in_parallel(_rasterize_backward_kernel,
                    [(a, b, binning.ranges, binning.ids, *arrays, constants, ctx.tile_size, binning.tiles_x,
                      ctx.final_t, ctx.n_contrib, grad, grads[j]) for j, (a, b) in enumerate(jobs)])
        total = torch.from_numpy(grads.sum(axis=0)).to(grad_image.device)
        return (total[:, 0:2], total[:, 2:5], total[:, 5:8], total[:, 8], None, None, None, None, None)


def rasterize_image(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                    opacities: torch.Tensor, depths: torch.Tensor, rects: torch.Tensor,
                    background: torch.Tensor, *, width: int, height: int,
                    tile_size: int = TILE_SIZE) -> torch.Tensor:
    """Composite projected Gaussians into an image ``(H, W, 3)``: ``means2d`` (N, 2) px, ``conics`` (N, 3),
    ``colors`` (N, 3), ``opacities`` (N,) in [0, 1], ``depths`` (N,) and tile ``rects`` (N, 4) (empty: not
    drawn) as :func:`.gaussians.project` gives them, over ``background`` (3,). Differentiable in the first
    four."""
    footprints = (_numpy(means2d), _numpy(conics), _numpy(opacities))
    binning = bin_gaussians(_numpy(rects), _numpy(depths), width=width, height=height, tile_size=tile_size,
                            footprints=footprints)
    dtype = means2d.dtype
    return _Rasterize.apply(means2d, conics.to(dtype), colors.to(dtype), opacities.to(dtype),
                            background.to(dtype), binning, width, height, tile_size)


@dataclass(frozen=True, eq=False)
class Rendering:
    """One rendered view: the ``image`` (H, W, 3) and what the density control reads: the projected
    ``means2d`` (N, 2) (their gradient, once the loss is backpropagated, is the view-space positional
    gradient) and the screen ``radii`` (N,) (0: not drawn)."""

    image: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor


def render(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity_logits: torch.Tensor,
           sh: torch.Tensor, view: View, *, sh_degree: int, background: torch.Tensor,
           tile_size: int = TILE_SIZE) -> Rendering:
    """Render Gaussians ``means`` (N, 3), ``log_scales`` (N, 3), ``quats`` (N, 4) ``(w, x, y, z)``,
    ``opacity_logits`` (N,) and spherical harmonics ``sh`` (N, K, 3) (degrees up to ``sh_degree`` used)
    seen by ``view``, over ``background`` (3,) (Kerbl et al. 2023, sections 4 and 6): projection and colours
    in torch, compositing by the compiled tile rasterizer; differentiable in every parameter.
    :class:`CapacityExceeded` (``gaussians``) past :data:`.values.MAX_GAUSSIANS`, before anything is
    allocated."""
    check_count(len(means))
    projected = project(means, log_scales, quats, view, tile_size=tile_size)
    means2d = projected.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    colors = view_colors(means, sh, sh_degree, view)
    image = rasterize_image(means2d, projected.conics, colors, activated_opacities(opacity_logits),
                            projected.depths, projected.rects, background, width=view.width,
                            height=view.height, tile_size=tile_size)
    return Rendering(image, means2d, projected.radii)


def render_image(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, opacity_logits: np.ndarray,
                 sh: np.ndarray, view: View, *, sh_degree: int, background: np.ndarray,
                 tile_size: int = TILE_SIZE) -> np.ndarray:
    """:func:`render`'s image ``(H, W, 3)`` float32 without gradients, all compiled (NumPy arrays in, as
    :class:`.values.SplatModel` holds them): the projection, colours and opacities in one pass
    (:func:`._kernels._preprocess_kernel`, the formulas of :func:`.gaussians.project` and
    :func:`.gaussians.view_colors` per Gaussian in float64), then the same binning and float32
    compositing. torch's overhead per operation on (N,) vectors was a third of a 200 x 200 render of 8k
    Gaussians. :class:`CapacityExceeded` past :data:`.values.MAX_GAUSSIANS`."""
    check_count(len(means))
    check_sh(sh_degree, sh.shape[1])
    n = len(means)
    means2d, conics, depths = np.empty((n, 2)), np.empty((n, 3)), np.empty(n)
    radii, rects = np.empty(n, np.int64), np.empty((n, 4), np.int64)
    colors, opacities = np.empty((n, 3)), np.empty(n)
    camera = np.concatenate([_numpy(view.R).reshape(9), _numpy(view.t).reshape(3),
                             [view.fx, view.fy, view.cx, view.cy]]).astype(np.float64)
    _preprocess_kernel(means, log_scales, quats, opacity_logits, sh, sh_degree, SH_CONSTANTS, camera,
                       view.width, view.height, tile_size, NEAR_PLANE, DILATION, means2d, conics, depths,
                       radii, rects, colors, opacities)
    f4 = np.float32
    means32, conics32, colors32, opacities32 = (a.astype(f4) for a in (means2d, conics, colors, opacities))
    binning = bin_gaussians(rects, depths, width=view.width, height=view.height, tile_size=tile_size,
                            footprints=(means32, conics32, opacities32))
    image, _, _, _ = _composite(means32, conics32, colors32, opacities32, np.asarray(background, f4),
                                binning, width=view.width, height=view.height, tile_size=tile_size)
    return image


#: The SH basis constants :func:`._kernels._preprocess_kernel` takes: C0, C1, C2 (5), C3 (7).
SH_CONSTANTS = np.array([C0, C1, *C2, *C3], np.float64)

__all__ = ["MAX_TILE_PAIRS", "Binning", "Rendering", "bin_gaussians", "rasterize_image", "render",
           "render_image"]
