"""The readable versions of the texture module's fast code: slow, one window at a time, and the oracles
the tests compare the fast versions with (they give the same numbers and the same texture).

    ``fill_layer_reference``   :func:`lab.modules.texture.efros_leung.fill_layer` (one onion layer)
    ``efros_leung_reference``  :func:`lab.modules.texture.efros_leung.efros_leung` (the whole synthesis)
"""

from __future__ import annotations

import numpy as np

from lab.core import Image
from lab.modules.texture._common import exhaust
from lab.modules.texture.efros_leung import (EfrosLeungTrace, candidates_within, grow_efros_leung,
                                             pick_candidate)


def fill_layer_reference(levels: np.ndarray, out: np.ndarray, filled: np.ndarray, order: np.ndarray,
                         source: np.ndarray, pixels: np.ndarray, weights: np.ndarray, epsilon: float,
                         uniforms: np.ndarray, counter: int) -> int:
    """Fill ``pixels`` one after the other, comparing each window with every sample window in a loop.

    ``uniforms`` holds one draw in [0, 1) per pixel, which picks among its candidates. The arguments
    are those of :func:`lab.modules.texture.efros_leung.fill_layer`; returns the fill counter."""
    h, w_s, _ = levels.shape
    w = len(weights)
    half = w // 2
    height, width = filled.shape
    for (row, col), uniform in zip(pixels, uniforms, strict=True):
        # the output window around (row, col): offsets outside the output are unknown
        template = np.zeros((w, w, out.shape[2]), dtype=np.int64)
        known = np.zeros((w, w), dtype=bool)
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                y, x = row + dy, col + dx
                if 0 <= y < height and 0 <= x < width and filled[y, x]:
                    template[dy + half, dx + half] = out[y, x]
                    known[dy + half, dx + half] = True
        weight = weights * known
        total_weight = weight.sum()
        distances = np.empty((h - w + 1, w_s - w + 1), dtype=np.float64)
        for i in range(h - w + 1):
            for j in range(w_s - w + 1):
                difference = template - levels[i:i + w, j:j + w]
                distances[i, j] = (weight * (difference ** 2).sum(axis=2)).sum() / total_weight
        candidates = candidates_within(distances, epsilon)
        i, j = divmod(pick_candidate(candidates, uniform), w_s - w + 1)
        out[row, col] = levels[i + half, j + half]
        source[row, col] = (i + half, j + half)
        filled[row, col] = True
        order[row, col] = counter
        counter += 1
    return counter


def efros_leung_reference(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1,
                          seed_size: int = 3, rng: np.random.Generator) -> tuple[np.ndarray, EfrosLeungTrace]:
    """Efros–Leung, slow and readable: every pixel's window compared with every sample window in a loop.

    The oracle of :func:`lab.modules.texture.efros_leung.efros_leung`: same onion order, same integer
    SSD, same random draws.
    """
    return exhaust(grow_efros_leung(sample, size=size, window=window, epsilon=epsilon, seed_size=seed_size,
                                    rng=rng, fill=fill_layer_reference))
