"""Texture transfer: redraw a target picture with blocks of a sample (Efros & Freeman 2001, section 4).

Each block is chosen by ``alpha * overlap error + (1 - alpha) * correspondence error``, over several
passes with smaller blocks; the quilting itself is :func:`lab.modules.texture.quilting.quilt_blocks`.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from lab.modules.texture._common import as_hwc, luminance
from lab.modules.texture.quilting import block_origins, quilt_blocks, ssd_map


def correspondence_map(pixels: np.ndarray, *, sigma: float = 1.5) -> np.ndarray:
    """The correspondence quantity of texture transfer: blurred luminance ``(H, W)`` (Efros & Freeman 2001,
    section 4)."""
    import cv2

    return cv2.GaussianBlur(luminance(pixels).astype(np.float32), (0, 0), sigma).astype(np.float64)


def pass_blocks(block: int, iterations: int) -> list[int]:
    """The block side of every pass: a third smaller each time, at least 3."""
    return [max(3, round(block * (2.0 / 3.0) ** i)) for i in range(iterations)]


def _block_count(height: int, width: int, block: int) -> int:
    """Blocks of a pass with blocks of side ``block`` (overlap a sixth of it) over ``height`` x ``width``."""
    step = block - max(1, block // 6)
    return len(block_origins(height, block, step)) * len(block_origins(width, block, step))


def transfer_passes(sample: np.ndarray, target: np.ndarray, *, block: int, iterations: int, epsilon: float,
                    rng: np.random.Generator,
                    ) -> Generator[tuple[int, int, str, np.ndarray], None, np.ndarray]:
    """Texture transfer of ``sample`` onto ``target`` (``(h, w[, C])`` images of one kind).

    ``iterations`` passes over the image, the block a third smaller each time (:func:`pass_blocks`)
    and ``alpha = 0.8 (i - 1) / (N - 1) + 0.1``; from the second pass on, the overlap error also
    compares the block with the previous pass's output at its place. Overlaps are a sixth of the
    block, joined by minimum-error cuts. Yields (blocks done, blocks in all passes, message, canvas
    ``(H, W, C)`` so far) every eighth block and at the end of a pass; returns the last pass's output
    ``(H, W, C)`` float64.
    """
    height, width = target.shape[:2]
    sample_hwc = as_hwc(sample)
    sample_map = correspondence_map(sample)[:, :, None]
    target_map = correspondence_map(target)
    previous = None
    sizes = pass_blocks(block, iterations)
    total = sum(_block_count(height, width, b) for b in sizes)
    done = 0
    for i, b in enumerate(sizes):
        o = max(1, b // 6)
        alpha = 0.8 * i / (iterations - 1) + 0.1 if iterations > 1 else 0.1
        canvas_h = block_origins(height, b, b - o)[-1] + b
        canvas_w = block_origins(width, b, b - o)[-1] + b
        padded = np.pad(target_map, ((0, canvas_h - height), (0, canvas_w - width)), mode="edge")

        def correspondence(y: int, x: int, size_b: int, padded: np.ndarray = padded) -> np.ndarray:
            return ssd_map(sample_map, padded[y:y + size_b, x:x + size_b, None]) / size_b ** 2

        quilter = quilt_blocks(sample_hwc, (height, width), b, o, float(epsilon), "min_cut", rng,
                               extra_cost=correspondence, alpha=alpha, previous=previous)
        while True:
            try:
                k, count, canvas = next(quilter)
            except StopIteration as stop:
                previous, _, _ = stop.value
                done += count
                break
            if k % 8 == 0 or k == count:
                yield done + k, total, f"pass {i + 1}/{iterations}, block {k}/{count}", canvas
    assert previous is not None  # iterations >= 1
    return previous
