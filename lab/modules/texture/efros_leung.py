"""Efros–Leung's non-parametric sampling: the window weights, the onion order, the fast exact synthesis,
and a pixel's choice replayed for the viewer.

A. A. Efros and T. K. Leung, "Texture synthesis by non-parametric sampling", ICCV 1999 (section 2.1:
the Gaussian-weighted SSD over the known neighbours, the candidates within (1 + epsilon) of the best;
section 2.2: growing from a 3 x 3 seed, pixels with the most known neighbours first). The pseudocode
followed is Efros's "Algorithm details" page (GrowImage / FindMatches / GetUnfilledNeighbors), without
its MaxErrThreshold (every pixel is filled).

Efros–Leung runs on 8-bit levels with integer Gaussian weights, so every SSD is an exact integer in
float64: the fast version (:func:`efros_leung`, the SSD expanded into matrix products batched over the
pixels of an onion layer, the sequential rest in a Numba kernel) and the slow readable one
(:func:`lab.modules.texture.reference.efros_leung_reference`, one window at a time) compute the same
numbers, draw the same random numbers (per layer: a permutation of the frontier, then one uniform per
pixel that picks among its candidates) and return the same texture for the same seed.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from lab.core import Image, InvalidControl, InvalidValue
from lab.modules.texture._common import (as_hwc, as_image, channel_count, check_size, check_window, exhaust,
                                         from_hwc)
from lab.modules.texture._kernels import _fill_layer_kernel

#: Efros and Leung's Gaussian: sigma = window / 6.4 (section 2.1).
SIGMA_FRACTION = 1.0 / 6.4

#: Integer scale of the Gaussian weights of the exact Efros–Leung (weights 1 .. 4096).
WEIGHT_SCALE = 4096

#: Output pixels times sample windows above which Efros–Leung refuses (it would take minutes).
MAX_EL_WORK = 4e9

#: How one onion layer is filled: ``(levels, out, filled, order, source, pixels, weights, epsilon,
#: uniforms, counter) -> counter`` (:func:`fill_layer`, or the reference's ``fill_layer_reference``).
FillLayer = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                      float, np.ndarray, int], int]


def gaussian_window(window: int, *, sigma_fraction: float = SIGMA_FRACTION) -> np.ndarray:
    """``(w, w)`` weights ``exp(-(dx^2 + dy^2) / (2 sigma^2))``, ``sigma = sigma_fraction * w``, 1 at the
    centre."""
    half = window // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    sigma = sigma_fraction * window
    return np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma ** 2))


def candidates_within(distances: np.ndarray, epsilon: float) -> np.ndarray:
    """Flat indices of the entries within ``(1 + epsilon)`` of the smallest (Efros & Leung 1999,
    section 2.1): those at most ``best + epsilon |best|``.

    For a distance (never negative) that is ``best (1 + epsilon)``; written with ``|best|`` so that
    the smallest entry is always a candidate, also when it is a rounding-level negative such as an
    expanded SSD (``q^2 - 2 q s + s^2``) gives where two windows agree (``best (1 + epsilon)`` would
    then lie *below* it and keep nothing). Never empty for a non-empty, finite array.
    """
    flat = np.asarray(distances, dtype=np.float64).ravel()
    best = flat.min()
    return np.flatnonzero(flat <= best + epsilon * abs(best))


def pick_candidate(candidates: np.ndarray, uniform: float) -> int:
    """The candidate a uniform draw in [0, 1) selects: entry ``floor(u K)`` of the ``K`` candidates (each as
    likely)."""
    return int(candidates[min(int(uniform * len(candidates)), len(candidates) - 1)])


@dataclass(frozen=True)
class EfrosLeungTrace:
    """How an Efros–Leung texture grew: ``fill_order`` ``(H, W)`` int (0, 1, ... the seed first) and
    ``source`` ``(H, W, 2)`` int, the sample pixel (row, col) each output pixel copies; the controls used,
    the number of onion layers and of seed pixels (fill orders below it were copied with the seed)."""

    fill_order: np.ndarray
    source: np.ndarray
    window: int
    epsilon: float
    layers: int
    seed_pixels: int = 9


def sample_levels(pixels: np.ndarray) -> np.ndarray:
    """8-bit levels ``(H, W, C)`` int64 of an image in [0, 1] (what Efros–Leung copies and compares)."""
    return np.clip(np.rint(as_hwc(pixels) * 255.0), 0, 255).astype(np.int64)


def integer_gaussian(window: int) -> np.ndarray:
    """``(w, w)`` int64 Gaussian weights ``max(1, round(4096 g))``, sigma = w / 6.4: integers keep every SSD
    exact."""
    return np.maximum(1, np.rint(WEIGHT_SCALE * gaussian_window(window))).astype(np.int64)


def onion_layer(filled: np.ndarray, window: int, rng: np.random.Generator) -> np.ndarray:
    """The next pixels to fill, in order: unfilled pixels next to a filled one, most known neighbours first.

    The frontier is the 3 x 3 dilation of ``filled`` minus ``filled`` (Efros's GetUnfilledNeighbors),
    listed in raster order, randomly permuted (``rng.permutation``), then stably sorted by the
    number of filled pixels in their window, decreasing. Returns ``(K, 2)`` (row, col).
    """
    from scipy.ndimage import binary_dilation, uniform_filter

    frontier = binary_dilation(filled, structure=np.ones((3, 3), bool)) & ~filled
    pixels = np.argwhere(frontier)
    known_share = uniform_filter(filled.astype(np.float64), size=window, mode="constant")
    counts = np.rint(known_share * window * window)
    counts = counts[pixels[:, 0], pixels[:, 1]].astype(np.int64)
    permutation = rng.permutation(len(pixels))
    pixels, counts = pixels[permutation], counts[permutation]
    return pixels[np.argsort(-counts, kind="stable")]


def _plant_seed(levels: np.ndarray, size: tuple[int, int], seed_size: int,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Output levels, filled mask, fill order and source, with a random ``seed_size``^2 patch of the sample in
    the middle (Efros & Leung 1999, section 2.2: a 3 x 3 seed)."""
    height, width = size
    h, w, channels = levels.shape
    out = np.zeros((height, width, channels), dtype=np.int64)
    filled = np.zeros((height, width), dtype=bool)
    order = np.full((height, width), -1, dtype=np.int64)
    source = np.full((height, width, 2), -1, dtype=np.int64)
    top, left = int(rng.integers(0, h - seed_size + 1)), int(rng.integers(0, w - seed_size + 1))
    oy, ox = (height - seed_size) // 2, (width - seed_size) // 2
    out[oy:oy + seed_size, ox:ox + seed_size] = levels[top:top + seed_size, left:left + seed_size]
    filled[oy:oy + seed_size, ox:ox + seed_size] = True
    order[oy:oy + seed_size, ox:ox + seed_size] = np.arange(seed_size ** 2).reshape(seed_size, seed_size)
    rows, cols = np.mgrid[top:top + seed_size, left:left + seed_size]
    source[oy:oy + seed_size, ox:ox + seed_size] = np.stack([rows, cols], axis=2)
    return out, filled, order, source


class _SampleWindows:
    """Every window of the sample, unrolled once: ``values`` ``(N, w*w, C)`` and ``squares`` ``(N, w*w)``."""

    def __init__(self, levels: np.ndarray, window: int) -> None:
        _, w_s, channels = levels.shape
        view = np.lib.stride_tricks.sliding_window_view(levels.astype(np.float64), (window, window),
                                                        axis=(0, 1))
        # view: (h-w+1, ws-w+1, C, w, w) -> (N, w*w, C)
        self.values = np.ascontiguousarray(np.moveaxis(view, 2, -1).reshape(-1, window * window, channels))
        self.squares = (self.values ** 2).sum(axis=2)
        # [values, squares] side by side: one matrix product gives both sums of the expanded SSD
        flat = self.values.reshape(len(self.values), -1)
        self.stacked = np.concatenate([flat, self.squares], axis=1).T.copy()
        self.columns = w_s - window + 1


def fill_layer(levels: np.ndarray, out: np.ndarray, filled: np.ndarray, order: np.ndarray, source: np.ndarray,
               pixels: np.ndarray, weights: np.ndarray, epsilon: float, uniforms: np.ndarray, counter: int, *,
               windows: _SampleWindows | None = None, chunk: int = 256) -> int:
    """Fill one onion layer; the same numbers and draws as ``fill_layer_reference``, computed fast.

    ``levels`` ``(h, ws, C)`` the sample's 8-bit levels; ``out``, ``filled``, ``order``, ``source``
    the synthesis so far (updated in place); ``pixels`` ``(K, 2)`` the layer in order, ``uniforms``
    ``(K,)`` one draw each; ``weights`` ``(w, w)`` the integer Gaussian. Returns the fill counter.

    The masked SSD expands into ``sum a q^2 - 2 sum a q s + sum a s^2`` (``a = g m``): the last two
    are one matrix product of the layer's weighted templates (``(B, w^2 (C + 1))``) with all
    sample windows, for all pixels of a chunk at once, with the pixels known at the start of the
    layer. Pixels of the same layer filled before a pixel are then added one by one, in a compiled
    loop (``_fill_layer_kernel``). Everything is an integer below 2^53 in float64, so the sums are
    exact in any order. ``windows``: the sample's windows unrolled once per synthesis.
    """
    w = len(weights)
    if windows is None:
        windows = _SampleWindows(levels, w)
    half = w // 2
    height, width = filled.shape
    channels = out.shape[2]
    g = weights.astype(np.float64).ravel()
    padded_out = np.zeros((height + 2 * half, width + 2 * half, channels), dtype=np.float64)
    padded_out[half:half + height, half:half + width] = out
    padded_known = np.zeros((height + 2 * half, width + 2 * half), dtype=bool)
    padded_known[half:half + height, half:half + width] = filled
    in_layer = np.zeros_like(padded_known)  # pixels of this layer filled so far
    out_view = np.lib.stride_tricks.sliding_window_view(padded_out, (w, w), axis=(0, 1))  # (H, W, C, w, w)
    known_view = np.lib.stride_tricks.sliding_window_view(padded_known, (w, w))
    for start in range(0, len(pixels), chunk):
        batch = pixels[start:start + chunk]
        rows, cols = np.ascontiguousarray(batch[:, 0]), np.ascontiguousarray(batch[:, 1])
        templates = np.moveaxis(out_view[rows, cols], 1, -1).reshape(len(batch), w * w, channels)
        a = known_view[rows, cols].reshape(len(batch), w * w) * g  # (B, w*w), known at the layer's start
        weighted = a[:, :, None] * templates
        constant = (weighted * templates).sum(axis=(1, 2))
        left = np.concatenate([-2.0 * weighted.reshape(len(batch), -1), a], axis=1)
        sums = constant[:, None] + left @ windows.stacked  # (B, N)
        counter = _fill_layer_kernel(sums, a.sum(axis=1), rows, cols, uniforms[start:start + chunk],
                                     windows.values, g, levels, padded_out, in_layer, out, source, filled,
                                     order, counter, float(epsilon), w, windows.columns)
    return counter


def _check_efros_leung(sample: Image, size: tuple[int, int], window: int,
                       seed_size: int) -> tuple[tuple[int, int], int]:
    window = check_window(window, sample)
    height, width = check_size(size, smallest=int(seed_size), what="the seed")
    if seed_size > min(sample.height, sample.width):
        raise InvalidControl("seed_size", f"the seed ({seed_size} px) is larger than the sample")
    windows = (sample.height - window + 1) * (sample.width - window + 1)
    work = height * width * windows
    if work > MAX_EL_WORK:
        raise InvalidControl("size", f"{height} x {width} pixels each compared with {windows} sample "
                                     f"windows is too much work ({work:.1e} > {MAX_EL_WORK:.0e}); use a "
                                     "smaller output or sample, or image quilting")
    return (height, width), window


def grow_efros_leung(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1,
                     seed_size: int = 3, rng: np.random.Generator, fill: FillLayer | None = None,
                     ) -> Generator[tuple[int, int, np.ndarray], None, tuple[np.ndarray, EfrosLeungTrace]]:
    """Grow an Efros–Leung texture layer by layer: yields (layer, pixels filled, image so far).

    Per layer: :func:`onion_layer` orders the frontier (one ``rng.permutation``), then
    ``rng.random(len(layer))`` draws one uniform per pixel, which :func:`pick_candidate` turns into
    a choice among the pixel's candidates. Returns the texture ``(H, W[, C])`` float32 (8-bit
    levels / 255) and its :class:`EfrosLeungTrace`. ``fill`` fills a layer: None for the fast
    :func:`fill_layer`, or the slow per-window ``fill_layer_reference``; both give the same result
    for the same ``rng`` state.
    """
    sample = as_image(sample, "sample")
    (height, width), window = _check_efros_leung(sample, size, window, int(seed_size))
    channels = channel_count(sample.pixels)
    levels = sample_levels(sample.pixels)
    weights = integer_gaussian(window)
    out, filled, order, source = _plant_seed(levels, (height, width), int(seed_size), rng)
    counter = int(filled.sum())
    fill_one: FillLayer = fill or functools.partial(fill_layer, windows=_SampleWindows(levels, window))
    layer = 0
    while not filled.all():
        pixels = onion_layer(filled, window, rng)
        uniforms = rng.random(len(pixels))  # one draw per pixel picks among its candidates
        counter = fill_one(levels, out, filled, order, source, pixels, weights, epsilon, uniforms, counter)
        layer += 1
        yield layer, counter, from_hwc(out / 255.0, channels).astype(np.float32)
    image = from_hwc(out / 255.0, channels).astype(np.float32)
    return image, EfrosLeungTrace(order, source, window, float(epsilon), layer, int(seed_size) ** 2)


def efros_leung(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1,
                seed_size: int = 3, rng: np.random.Generator) -> tuple[np.ndarray, EfrosLeungTrace]:
    """Efros–Leung, fast and exact (:func:`grow_efros_leung` with the batched SSD): ``(texture, trace)``."""
    return exhaust(grow_efros_leung(sample, size=size, window=window, epsilon=epsilon, seed_size=seed_size,
                                    rng=rng))


@dataclass(frozen=True)
class PixelMatches:
    """Why an Efros–Leung pixel got its value (for the viewer): its window when it was filled, the
    distances to every sample window, the candidates and the window actually copied."""

    window: np.ndarray          # (w, w[, C]) float, unknown pixels 0
    known: np.ndarray           # (w, w) bool
    distances: np.ndarray       # (h - w + 1, ws - w + 1)
    candidates: np.ndarray      # (K, 2) int top-left (row, col) of the candidate windows
    chosen: np.ndarray          # (2,) int top-left (row, col) of the window copied
    order: int                  # when the pixel was filled


def efros_leung_pixel_matches(sample: Image, texture: Image, trace: EfrosLeungTrace, row: int,
                              col: int) -> PixelMatches:
    """Replay the choice of output pixel ``(row, col)``: its window as it was, its distances and candidates.

    The window holds the pixels filled before it (``trace.fill_order``); the distances are those the
    synthesis computed (the texture module's ``window_distances`` with the integer weights the
    synthesis used, on 8-bit levels); the chosen window is the one whose centre is
    ``trace.source[row, col]``.
    """
    height, width = trace.fill_order.shape
    if not (0 <= row < height and 0 <= col < width):
        raise InvalidValue("pixel", f"({row}, {col}) is outside the {width} x {height} texture")
    w, half = trace.window, trace.window // 2
    order = int(trace.fill_order[row, col])
    levels = sample_levels(texture.pixels)
    channels = levels.shape[2]
    window = np.zeros((w, w, channels))
    known = np.zeros((w, w), dtype=bool)
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            y, x = row + dy, col + dx
            if 0 <= y < height and 0 <= x < width and 0 <= trace.fill_order[y, x] < order:
                window[dy + half, dx + half] = levels[y, x]
                known[dy + half, dx + half] = True
    chosen = trace.source[row, col] - half
    if order < trace.seed_pixels:  # a seed pixel: copied with the seed patch, not matched
        known[:] = False
        distances = np.zeros((sample.height - w + 1, sample.width - w + 1))
        return PixelMatches(from_hwc(window / 255.0, channels), known, distances, chosen[None], chosen, order)
    levels_sample = sample_levels(sample.pixels).astype(np.float64)
    weights = integer_gaussian(w) * known
    view = np.lib.stride_tricks.sliding_window_view(levels_sample, (w, w), axis=(0, 1))
    difference = view - np.moveaxis(window, 2, 0)[None, None]
    distances = np.einsum("ijcab,ab->ij", difference ** 2, weights) / weights.sum()
    flat = candidates_within(distances, trace.epsilon)
    candidates = np.column_stack(np.unravel_index(flat, distances.shape)).astype(np.int64)
    return PixelMatches(from_hwc(window / 255.0, channels), known, distances, candidates, chosen, order)
