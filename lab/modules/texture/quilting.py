"""Image quilting: the overlap error, the minimum-error boundary cut, blocks placed in raster order.

A. A. Efros and W. T. Freeman, "Image quilting for texture synthesis and transfer", SIGGRAPH 2001
(section 2.1: random blocks, blocks that agree in the overlap, the minimum error boundary cut by
dynamic programming; section 4: texture transfer, :mod:`lab.modules.texture.transfer`, which quilts
with an extra cost).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from lab.core import Image, InvalidValue, Segments2D
from lab.modules.texture._common import (as_hwc, as_image, channel_count, check_block, check_size, exhaust,
                                         from_hwc)
from lab.modules.texture.efros_leung import candidates_within

#: For texture transfer: ``extra_cost(y, x, block)``, a cost over the sample positions of the block at (y, x).
ExtraCost = Callable[[int, int, int], np.ndarray]


def min_error_boundary_cut(errors: np.ndarray) -> np.ndarray:
    """The cheapest top-to-bottom path through an error surface, moving at most one column per row.

    Dynamic programming (Efros & Freeman 2001, section 2.1): ``E[0] = e[0]``,
    ``E[i, j] = e[i, j] + min(E[i-1, j-1], E[i-1, j], E[i-1, j+1])``; the path ends at the
    smallest ``E`` of the last row (the leftmost on ties) and is traced back choosing, among the
    columns allowed, the one with the smallest ``E`` (the leftmost on ties).

    ``errors`` ``(rows, cols)`` float, finite. Returns ``(rows,)`` int64 columns.
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 2 or e.shape[0] < 1 or e.shape[1] < 1:
        raise InvalidValue("overlap_error", f"an error surface is a (rows, cols) array, got shape {e.shape}")
    if not np.all(np.isfinite(e)):
        raise InvalidValue("overlap_error", "contains NaN or infinite errors")
    rows, cols = e.shape
    cumulative = np.full((rows, cols + 2), np.inf)  # a column of infinity on each side: no step outside
    cumulative[:, 1:-1] = e
    for i in range(1, rows):
        previous = cumulative[i - 1]
        cumulative[i, 1:-1] += np.minimum(np.minimum(previous[:-2], previous[1:-1]), previous[2:])
    table = cumulative[:, 1:-1].tolist()
    path = [0] * rows
    path[-1] = min(range(cols), key=table[-1].__getitem__)  # min() keeps the first (leftmost) of equal values
    for i in range(rows - 2, -1, -1):
        j = path[i + 1]
        path[i] = min(range(max(j - 1, 0), min(j + 2, cols)), key=table[i].__getitem__)
    return np.array(path, dtype=np.int64)


def path_cost(errors: np.ndarray, path: np.ndarray) -> float:
    """Sum of ``errors[i, path[i]]``."""
    e = np.asarray(errors, dtype=np.float64)
    return float(e[np.arange(len(path)), np.asarray(path)].sum())


def overlap_error_surface(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``(rows, cols)`` squared difference of two overlapping regions, summed over colour channels."""
    return ((as_hwc(old) - as_hwc(new)) ** 2).sum(axis=2)


@dataclass(frozen=True)
class QuiltLayout:
    """Every block of a quilt: ``positions`` ``(K, 2)`` top-left (row, col) in the output, ``sources``
    ``(K, 2)`` top-left in the sample, ``errors`` ``(K, B, B)`` the overlap error surface in the block's
    frame (0 outside the overlap), ``new_pixels`` ``(K, B, B)`` bool the pixels the block kept after its
    cuts."""

    positions: np.ndarray
    sources: np.ndarray
    errors: np.ndarray
    new_pixels: np.ndarray
    block: int
    overlap: int


def masked_ssd_map(sample: np.ndarray, template: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """SSD of ``template`` over ``mask`` against every same-size window of ``sample``: ``cv2.matchTemplate``
    ``TM_SQDIFF`` with a mask (float32), ``(h - b + 1, w - b + 1)``; clipped at 0 (rounding)."""
    import cv2

    sample32 = np.ascontiguousarray(sample, dtype=np.float32)
    template32 = np.ascontiguousarray(template * mask[:, :, None], dtype=np.float32)
    total = np.zeros((sample.shape[0] - template.shape[0] + 1, sample.shape[1] - template.shape[1] + 1))
    mask32 = np.ascontiguousarray(mask, dtype=np.float32)
    for c in range(sample.shape[2]):
        total += cv2.matchTemplate(sample32[:, :, c], template32[:, :, c], cv2.TM_SQDIFF, mask=mask32)
    return np.maximum(total, 0.0)


def ssd_map(sample: np.ndarray, template: np.ndarray) -> np.ndarray:
    """SSD of ``template`` ``(b, b, C)`` against every same-size window of ``sample`` ``(h, w, C)``
    (``cv2.matchTemplate`` ``TM_SQDIFF``, float32), ``(h - b + 1, w - b + 1)``; clipped at 0."""
    import cv2

    total = np.zeros((sample.shape[0] - template.shape[0] + 1, sample.shape[1] - template.shape[1] + 1))
    for c in range(sample.shape[2]):
        total += cv2.matchTemplate(np.ascontiguousarray(sample[:, :, c], dtype=np.float32),
                                   np.ascontiguousarray(template[:, :, c], dtype=np.float32), cv2.TM_SQDIFF)
    return np.maximum(total, 0.0)


def block_origins(length: int, block: int, step: int) -> list[int]:
    """Block origins along one axis so that the last block ends at or after ``length``."""
    origins = [0]
    while origins[-1] + block < length:
        origins.append(origins[-1] + step)
    return origins


def _padded(previous: np.ndarray, canvas_shape: tuple[int, int]) -> np.ndarray:
    """``previous`` ``(H, W, C)`` on a canvas of ``canvas_shape``, its last row and column repeated."""
    height, width, channels = previous.shape
    padded = np.zeros((*canvas_shape, channels))
    padded[:height, :width] = previous
    padded[height:, :] = padded[height - 1:height, :]
    padded[:, width:] = padded[:, width - 1:width]
    return padded


def _draw_source(cost: np.ndarray, epsilon: float, rng: np.random.Generator) -> tuple[int, int]:
    """Top-left of a sample block drawn among those within ``(1 + epsilon)`` of the cheapest."""
    flat = candidates_within(cost, epsilon)
    row, col = np.unravel_index(int(flat[rng.integers(len(flat))]), cost.shape)
    return int(row), int(col)


def _kept_pixels(surface: np.ndarray, overlap: int, *, left: bool, top: bool) -> np.ndarray:
    """``(B, B)`` bool: the new block's pixels right of the cut through its left overlap and below the cut
    through its top overlap (minimum-error boundary cuts of ``surface``)."""
    block = surface.shape[0]
    grid_rows, grid_cols = np.mgrid[0:block, 0:block]
    take = np.ones((block, block), dtype=bool)
    if left:
        take &= grid_cols >= min_error_boundary_cut(surface[:, :overlap])[:, None]
    if top:
        take &= grid_rows >= min_error_boundary_cut(surface[:overlap, :].T)[None, :]
    return take


def quilt_blocks(sample: np.ndarray, size: tuple[int, int], block: int, overlap: int, epsilon: float,
                 mode: str, rng: np.random.Generator, *, extra_cost: ExtraCost | None = None,
                 alpha: float = 1.0, previous: np.ndarray | None = None) -> Generator[
                     tuple[int, int, np.ndarray], None, tuple[np.ndarray, np.ndarray, QuiltLayout]]:
    """Quilt ``sample`` ``(h, w, C)`` float into ``size``; yields (block, blocks, canvas so far).

    ``mode``: "random" blocks, "best_overlap" (blocks within (1 + epsilon) of the best overlap SSD,
    straight edges) or "min_cut" (the same, joined along minimum-error boundary cuts). For texture
    transfer, ``extra_cost(y, x, b)`` gives a correspondence cost map over the sample positions,
    weighed ``1 - alpha`` against ``alpha`` times the overlap error (plus the error against
    ``previous``, an earlier iteration's output, when given). Returns (image, source, layout).
    """
    height, width = size
    h, w, channels = sample.shape
    step = block - overlap
    ys, xs = block_origins(height, block, step), block_origins(width, block, step)
    canvas_h, canvas_w = ys[-1] + block, xs[-1] + block
    canvas = np.zeros((canvas_h, canvas_w, channels))
    source = np.full((canvas_h, canvas_w, 2), -1, dtype=np.int64)
    padded_previous = None if previous is None else _padded(previous, (canvas_h, canvas_w))
    count = len(ys) * len(xs)
    positions = np.zeros((count, 2), dtype=np.int64)
    sources = np.zeros((count, 2), dtype=np.int64)
    errors = np.zeros((count, block, block))
    kept = np.ones((count, block, block), dtype=bool)
    grid_rows, grid_cols = np.mgrid[0:block, 0:block]
    k = 0
    for y in ys:
        for x in xs:
            old = canvas[y:y + block, x:x + block]
            mask = np.zeros((block, block), dtype=bool)
            if x > 0:
                mask[:, :overlap] = True
            if y > 0:
                mask[:overlap, :] = True
            if mode == "random" or (not mask.any() and extra_cost is None):
                sy, sx = int(rng.integers(0, h - block + 1)), int(rng.integers(0, w - block + 1))
            else:
                cost = np.zeros((h - block + 1, w - block + 1))
                if mask.any():
                    cost += alpha * masked_ssd_map(sample, old, mask) / mask.sum()
                if padded_previous is not None:
                    cost += alpha * ssd_map(sample, padded_previous[y:y + block, x:x + block]) / block ** 2
                if extra_cost is not None:
                    cost += (1.0 - alpha) * extra_cost(y, x, block)
                sy, sx = _draw_source(cost, epsilon, rng)
            new = sample[sy:sy + block, sx:sx + block]
            surface = overlap_error_surface(old, new) * mask
            if mode == "min_cut":
                take = _kept_pixels(surface, overlap, left=x > 0, top=y > 0)
            else:  # straight edges: the new block is pasted over the overlap
                take = np.ones((block, block), dtype=bool)
            region_source = source[y:y + block, x:x + block]
            canvas[y:y + block, x:x + block] = np.where(take[:, :, None], new, old)
            new_source = np.stack([grid_rows + sy, grid_cols + sx], axis=2)
            source[y:y + block, x:x + block] = np.where(take[:, :, None], new_source, region_source)
            positions[k], sources[k], errors[k], kept[k] = (y, x), (sy, sx), surface, take
            k += 1
            yield k, count, canvas[:height, :width]
    layout = QuiltLayout(positions, sources, errors, kept, block, overlap)
    return canvas[:height, :width].copy(), source[:height, :width].copy(), layout


def image_quilting(sample: Image, *, size: tuple[int, int], block: int = 24, overlap: int = 5,
                   epsilon: float = 0.1, mode: str = "min_cut",
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, QuiltLayout]:
    """Image quilting as a plain function (what the ``quilt`` step runs, without progress and metrics):
    ``(texture (H, W[, C]) float32, source (H, W, 2) int, layout)``."""
    sample = as_image(sample, "sample")
    block, overlap = check_block(block, overlap, sample)
    height, width = check_size(size, smallest=block, what="a block")
    pixels, source, layout = exhaust(quilt_blocks(as_hwc(sample.pixels), (height, width), block, overlap,
                                                  float(epsilon), mode, rng))
    return np.clip(from_hwc(pixels, channel_count(sample.pixels)), 0, 1).astype(np.float32), source, layout


def cut_segments(layout: QuiltLayout, size: tuple[int, int], *, image: str = "quilting") -> Segments2D:
    """The boundary of each block's kept pixels inside its overlap, as short segments between pixel centres
    (drawn on the output image)."""
    starts, ends = [], []
    b, o = layout.block, layout.overlap
    height, width = size
    for (y, x), keep, errors in zip(layout.positions, layout.new_pixels, layout.errors, strict=True):
        if not errors.any() and keep.all():
            continue
        # the first kept pixel in each row of a left overlap, in each column of a top overlap
        if x > 0:
            cols = np.argmax(keep[:, :o], axis=1)
            for r in range(b - 1):
                starts.append((x + cols[r], y + r))
                ends.append((x + cols[r + 1], y + r + 1))
        if y > 0:
            rows = np.argmax(keep[:o, :], axis=0)
            for c in range(b - 1):
                starts.append((x + c, y + rows[c]))
                ends.append((x + c + 1, y + rows[c + 1]))
    starts_a = np.array(starts, dtype=np.float64).reshape(-1, 2)
    ends_a = np.array(ends, dtype=np.float64).reshape(-1, 2)
    inside = ((starts_a[:, 0] < width) & (starts_a[:, 1] < height)
              & (ends_a[:, 0] < width) & (ends_a[:, 1] < height))
    colours = np.tile([[1.0, 0.2, 0.2]], (int(inside.sum()), 1))
    return Segments2D(starts_a[inside], ends_a[inside], colors=colours, image=image)
