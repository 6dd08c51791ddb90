"""Texture synthesis three classic ways: parametric (Heeger–Bergen), pixel by pixel (Efros–Leung), by blocks (quilting).

References:
- D. J. Heeger and J. R. Bergen, "Pyramid-based texture analysis/synthesis", SIGGRAPH 1995
  (section 3: histogram matching; section 4: the pyramid; section 5: the synthesis loop; colour
  through a principal-components colour space, section 6).
- A. A. Efros and T. K. Leung, "Texture synthesis by non-parametric sampling", ICCV 1999
  (section 2.1: the Gaussian-weighted SSD over the known neighbours, the candidates within
  (1 + epsilon) of the best; section 2.2: growing from a 3 x 3 seed, pixels with the most known
  neighbours first). The pseudocode followed is Efros's "Algorithm details" page (GrowImage /
  FindMatches / GetUnfilledNeighbors), without its MaxErrThreshold (every pixel is filled).
- A. A. Efros and W. T. Freeman, "Image quilting for texture synthesis and transfer", SIGGRAPH 2001
  (section 2.1: random blocks, blocks that agree in the overlap, the minimum error boundary cut
  by dynamic programming; section 4: texture transfer with a correspondence map and iterations).

Conventions. Images are float32 ``(H, W)`` or ``(H, W, 3)`` in [0, 1]; pixel ``(row, col)``. A
window of odd side ``w`` around pixel ``(r, c)`` covers rows ``r - w//2 .. r + w//2``. Sample
windows lie wholly inside the sample: there are ``(h - w + 1) x (w_s - w + 1)`` of them, indexed
by their top-left corner (their centre is ``w//2`` further). Output sizes are ``(height, width)``.

State names:
    sample              Image               the texture to imitate (dataset or upload)
    transfer_target     Image               the picture texture transfer redraws (dataset)
    query_window        (w, w[, 3])         a partly known window (unknown pixels 0)  [lesson helper]
    query_mask          (w, w) bool         which pixels of the query are known
    query_origin        (2,) int64          top-left (row, col) of the sample window the query was cut from
    window_distances    (h-w+1, ws-w+1)     Gaussian-weighted masked SSD of the query to every sample window
    match_candidates    Points2D on sample  centres of the windows within (1 + epsilon) of the best
    chosen_match        (2,) int64          top-left (row, col) of the window drawn among the candidates
    overlap_left/right  Image               two blocks that overlap by a band of columns  [lesson helper]
    overlap_error       (B, O)              squared difference of the blocks in the overlap (summed over colour)
    cut_path            (B,) int64          the minimum-error cut: its column in every row of the overlap
    joined              Image               the two blocks joined along the cut
    parametric          Image               Heeger–Bergen's texture
    efros_leung         Image               Efros–Leung's texture
    efros_leung_trace   EfrosLeungTrace     fill order and source pixel of every output pixel
    quilting            Image               the quilted texture
    quilting_layout     QuiltLayout         every block: place, source, overlap error surface, cut
    quilting_seams      Segments2D          the cuts, drawn on ``quilting``
    transferred         Image               the target redrawn with the sample (texture transfer)
    textured_mesh       Mesh                a plane, cylinder or torus coloured by a texture through its UVs
    mesh_uv             (V, 2)              the UV coordinates of the mesh's vertices

Efros–Leung runs on 8-bit levels with integer Gaussian weights, so every SSD is an exact integer
in float64: the fast version (:func:`efros_leung`, the SSD expanded into matrix products batched
over the pixels of an onion layer, the sequential rest in a Numba kernel) and the slow readable one
(:func:`efros_leung_reference`, one window at a time) compute the same numbers, draw the same
random numbers (per layer: a permutation of the frontier, then one uniform per pixel that picks
among its candidates) and return the same texture for the same seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, Generator, Literal

import numpy as np

from lab.core.step import step_result
from lab.core import (Image, InvalidControl, InvalidValue, Mesh, Pipeline, Points2D, Progress, Range, Segments2D,
                      metric)
from lab.data.textures import brick, grass, gravel, image_file, procedural

Size = Annotated[tuple[int, int], Range(1, 1024)]

#: Efros and Leung's Gaussian: sigma = window / 6.4 (section 2.1).
SIGMA_FRACTION = 1.0 / 6.4

#: Integer scale of the Gaussian weights of the exact Efros–Leung (weights 1 .. 4096).
WEIGHT_SCALE = 4096

#: Output pixels times sample windows above which Efros–Leung refuses (it would take minutes).
MAX_EL_WORK = 4e9


# ----------------------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------------------
def _image(value: Any, name: str) -> Image:
    if not isinstance(value, Image):
        raise InvalidValue(name, f"expected an Image, got {type(value).__name__}")
    return value


def _channels(pixels: np.ndarray) -> int:
    return 1 if pixels.ndim == 2 else pixels.shape[2]


def _as_hwc(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` -> ``(H, W, C)`` float64."""
    array = np.asarray(pixels, dtype=np.float64)
    return array[:, :, None] if array.ndim == 2 else array


def _from_hwc(array: np.ndarray, like_channels: int) -> np.ndarray:
    return array[:, :, 0] if like_channels == 1 else array


def _check_window(window: int, sample: Image, *, name: str = "window") -> int:
    window = int(window)
    if window < 1 or window % 2 == 0:
        raise InvalidControl(name, f"must be odd so that the window has a centre pixel (3, 5, 7 ...), got {window}")
    if window > min(sample.height, sample.width):
        raise InvalidControl(name, f"the window ({window} x {window}) is larger than the sample "
                                   f"({sample.width} x {sample.height}); use at most "
                                   f"{_largest_odd(min(sample.height, sample.width))}")
    return window


def _largest_odd(value: int) -> int:
    return value if value % 2 else value - 1


def _check_size(size: tuple[int, int], *, smallest: int = 1, what: str = "") -> tuple[int, int]:
    height, width = (int(v) for v in size)
    if height < smallest or width < smallest:
        raise InvalidControl("size", f"the output ({height} x {width}) is smaller than {what or smallest} "
                                     f"({smallest} px); make it at least {smallest} x {smallest}")
    return height, width


def _check_block(block: int, overlap: int, sample: Image) -> tuple[int, int]:
    block, overlap = int(block), int(overlap)
    if block > min(sample.height, sample.width):
        raise InvalidControl("block", f"the block ({block} x {block}) is larger than the sample "
                                      f"({sample.width} x {sample.height}); use at most "
                                      f"{min(sample.height, sample.width)}")
    if block < 2:
        raise InvalidControl("block", f"must be at least 2 pixels, got {block}")
    if not 0 < overlap < block:
        raise InvalidControl("overlap", f"must be at least 1 and smaller than the block ({block}), got {overlap}")
    return block, overlap


# ----------------------------------------------------------------------------------------------------
# Metrics: texture statistics and visible seams
# ----------------------------------------------------------------------------------------------------
def luminance(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64 luminance (BT.601 weights, as ``cv2.cvtColor`` RGB2GRAY)."""
    array = np.asarray(pixels, dtype=np.float64)
    if array.ndim == 2:
        return array
    return array @ np.array([0.299, 0.587, 0.114])


def _quantiles(values: np.ndarray, count: int = 64) -> np.ndarray:
    return np.quantile(values.ravel(), (np.arange(count) + 0.5) / count)


def _pyramid_levels_for(shape: tuple[int, ...], wanted: int = 3) -> int:
    side = min(shape[:2])
    return int(max(1, min(wanted, math.floor(math.log2(max(side, 2) / 8.0)) + 1)))


def texture_statistics_distance(output: np.ndarray, sample: np.ndarray, *, levels: int = 3,
                                orientations: int = 4) -> float:
    """How far the texture statistics of ``output`` are from those of ``sample`` (0 = the same), any sizes.

    Two terms, averaged: (1) subband histograms: the 1D Wasserstein distance between the value
    distributions of every band of an oriented pyramid (:func:`build_pyramid`) of the luminance, and
    of every colour channel's pixels, each divided by the sample band's standard deviation (the mean
    absolute difference of 64 quantiles); (2) Gram matrices of filter responses: per pyramid level,
    ``G = F^T F / n`` of the oriented bands and their magnitudes, relative Frobenius difference
    (Gatys et al. 2015 with a fixed filter bank in place of a CNN's). Heeger–Bergen matches the
    histograms of its own pyramid exactly, so it is favoured by term (1); term (2) sees the
    joint statistics that it does not copy.

    ``output``, ``sample``: ``(H, W)`` or ``(H, W, 3)`` images in [0, 1]. ``levels`` shrinks for small images.
    """
    out, ref = np.asarray(output, dtype=np.float64), np.asarray(sample, dtype=np.float64)
    if _channels(out) != _channels(ref):
        raise InvalidValue("output", f"has {_channels(out)} channel(s) but the sample {_channels(ref)}")
    levels = min(levels, _pyramid_levels_for(out.shape), _pyramid_levels_for(ref.shape))
    hist_terms = []
    for c in range(_channels(ref)):
        a, b = _as_hwc(out)[:, :, c], _as_hwc(ref)[:, :, c]
        hist_terms.append(np.abs(_quantiles(a) - _quantiles(b)).mean() / (b.std() + 1e-3))
    bands_out = build_pyramid(luminance(out), levels=levels, orientations=orientations)
    bands_ref = build_pyramid(luminance(ref), levels=levels, orientations=orientations)
    for a, b in zip(bands_out, bands_ref):
        hist_terms.append(np.abs(_quantiles(a) - _quantiles(b)).mean() / (b.std() + 1e-3))
    gram_terms = []
    for level in range(levels):
        chunk = slice(level * orientations, (level + 1) * orientations)
        grams = []
        for bands in (bands_out[chunk], bands_ref[chunk]):
            features = np.stack([b.ravel() for b in bands] + [np.abs(b).ravel() for b in bands], axis=1)
            grams.append(features.T @ features / len(features))
        gram_terms.append(np.linalg.norm(grams[0] - grams[1]) / (np.linalg.norm(grams[1]) + 1e-12))
    return float(0.5 * np.mean(hist_terms) + 0.5 * np.mean(gram_terms))


def seam_score(output: np.ndarray, source: np.ndarray, sample: np.ndarray) -> float:
    """Visible seams: contrast across seams relative to the texture's own contrast (about 1: invisible).

    ``source`` ``(H, W, 2)`` int: the sample pixel each output pixel was copied from. A pair of
    4-neighbours is *across a seam* when their sources are not neighbours in the same way (the
    copy jumps). The score is the mean squared difference of the pairs across seams divided by the
    mean squared difference of all neighbour pairs of the sample; 1.0 when there is no seam.
    Seams a viewer sees are differences larger than the texture's usual ones (Efros & Freeman 2001,
    figure 2's visible block edges).
    """
    out = _as_hwc(output)
    ref = _as_hwc(sample)
    source = np.asarray(source)
    jumps, base = [], []
    for axis, step in ((0, (1, 0)), (1, (0, 1))):
        a = np.take(out, range(out.shape[axis] - 1), axis=axis)
        b = np.take(out, range(1, out.shape[axis]), axis=axis)
        sa = np.take(source, range(source.shape[axis] - 1), axis=axis)
        sb = np.take(source, range(1, source.shape[axis]), axis=axis)
        seam = np.any(sb - sa != np.array(step), axis=2)
        jumps.append(((a - b) ** 2).sum(axis=2)[seam])
        ra = np.take(ref, range(ref.shape[axis] - 1), axis=axis)
        rb = np.take(ref, range(1, ref.shape[axis]), axis=axis)
        base.append(((ra - rb) ** 2).sum(axis=2).ravel())
    across = np.concatenate(jumps)
    typical = np.concatenate(base).mean()
    if len(across) == 0:
        return 1.0
    return float(across.mean() / max(typical, 1e-12))


# ----------------------------------------------------------------------------------------------------
# Heeger–Bergen: pyramid, histogram matching, synthesis
# ----------------------------------------------------------------------------------------------------
def match_histogram(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``values`` remapped so that their histogram is ``reference``'s (any sizes), by ranks.

    The k-th smallest of ``n`` values becomes the reference's quantile ``(k + 0.5) / n`` (linear
    interpolation between its sorted values): Heeger & Bergen section 3's match-histogram, exact
    up to ties. ``skimage.exposure.match_histograms`` does the same per channel through unique values.
    """
    flat = np.asarray(values, dtype=np.float64).ravel()
    ref = np.sort(np.asarray(reference, dtype=np.float64).ravel())
    order = np.argsort(flat, kind="stable")
    positions = (np.arange(len(flat)) + 0.5) / len(flat) * len(ref) - 0.5
    matched = np.empty_like(flat)
    matched[order] = np.interp(positions, np.arange(len(ref)), ref)
    return matched.reshape(np.shape(values))


def _orientation_masks(shape: tuple[int, int], orientations: int) -> list[np.ndarray]:
    """Angular raised-cosine masks in the Fourier plane that add up to one (a steerable split).

    Band ``k`` keeps orientations near ``k pi / K``: ``cos^2(K d / 2)`` for ``|d| < pi / K``, with
    ``d`` the angle to ``k pi / K`` modulo pi. Adjacent masks are cos^2 and sin^2 of one angle, so
    the bands add up to the image exactly (and each band is real: the masks are even).
    """
    if orientations == 1:
        return [np.ones(shape)]
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.fftfreq(shape[1])[None, :]
    theta = np.arctan2(fy, fx) % np.pi
    masks = []
    for k in range(orientations):
        d = (theta - k * np.pi / orientations + np.pi / 2) % np.pi - np.pi / 2
        masks.append(np.where(np.abs(d) < np.pi / orientations, np.cos(orientations * d / 2) ** 2, 0.0))
    return masks


def build_pyramid(image: np.ndarray, *, levels: int, orientations: int = 4) -> list[np.ndarray]:
    """An oriented Laplacian pyramid of a 2D image: ``levels * orientations`` bands, then the low-pass residual.

    Level ``i`` is the Laplacian band ``G_i - up(G_{i+1})`` (``cv2.pyrDown`` / ``cv2.pyrUp``, Burt &
    Adelson 1983), split into ``orientations`` bands by Fourier masks that add up to one
    (:func:`_orientation_masks`); the last entry is ``G_levels``. ``collapse_pyramid`` inverts it
    exactly (to rounding). Heeger & Bergen section 4 use the steerable pyramid; with
    ``orientations = 1`` this is their Laplacian-pyramid variant.
    """
    import cv2

    gaussian = np.asarray(image, dtype=np.float64)
    bands: list[np.ndarray] = []
    for _ in range(levels):
        smaller = cv2.pyrDown(gaussian, dstsize=((gaussian.shape[1] + 1) // 2, (gaussian.shape[0] + 1) // 2))
        up = cv2.pyrUp(smaller, dstsize=(gaussian.shape[1], gaussian.shape[0]))
        laplacian = gaussian - up
        spectrum = np.fft.fft2(laplacian)
        for mask in _orientation_masks(laplacian.shape, orientations):
            bands.append(np.real(np.fft.ifft2(spectrum * mask)))
        gaussian = smaller
    bands.append(gaussian)
    return bands


def collapse_pyramid(bands: list[np.ndarray], *, orientations: int = 4) -> np.ndarray:
    """The image whose :func:`build_pyramid` is ``bands`` (sum the orientations, then up-sample and add)."""
    import cv2

    levels = (len(bands) - 1) // orientations
    image = bands[-1]
    for level in reversed(range(levels)):
        laplacian = np.sum(bands[level * orientations:(level + 1) * orientations], axis=0)
        image = cv2.pyrUp(image, dstsize=(laplacian.shape[1], laplacian.shape[0])) + laplacian
    return image


def _colour_basis(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(C,)`` and orthonormal principal axes ``(C, C)`` of the pixel colours (Heeger & Bergen section 6)."""
    flat = _as_hwc(pixels).reshape(-1, _channels(pixels))
    mean = flat.mean(axis=0)
    _, _, vt = np.linalg.svd(flat - mean, full_matrices=False)
    return mean, vt.T


@step_result
class ParametricResult:
    """Result of :func:`synthesize_parametric`."""

    parametric: Image
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")
    histogram_error: float = metric("mean absolute difference of pixel quantiles to the sample's", unit="intensity")


def synthesize_parametric(sample: Image, *, size: Size = (96, 96), levels: Annotated[int, Range(1, 8)] = 4,
                          orientations: Annotated[int, Range(1, 8)] = 4,
                          iterations: Annotated[int, Range(1, 50)] = 5,
                          rng: np.random.Generator) -> Generator[Progress, None, ParametricResult]:
    """Heeger–Bergen synthesis: match the histogram of every pyramid band and of the pixels, iterate.

    Start from white noise with the sample's histogram; each iteration builds the oriented pyramid
    of the current image (:func:`build_pyramid`), matches each band's histogram to the same band of
    the sample's pyramid (:func:`match_histogram`), collapses it and matches the pixel histogram
    (Heeger & Bergen 1995, section 5). A colour sample is synthesized channel by channel in its
    principal-components colour space (section 6). Yields the image after every iteration.

    Args:
        size: (height, width) of the output in pixels.
        levels: pyramid levels (each halves the size; limited by the smaller of sample and output).
        orientations: oriented bands per level (1: a plain Laplacian pyramid).
        iterations: rounds of histogram matching.

    Returns the texture ``(height, width[, 3])``; metrics: the statistics distance to the sample.
    """
    sample = _image(sample, "sample")
    height, width = _check_size(size, smallest=8, what="8 pixels")
    smallest = min(height, width, sample.height, sample.width)
    if 2 ** int(levels) * 2 > smallest:
        raise InvalidControl("levels", f"{levels} levels halve the image {levels} times: the smaller of sample and "
                                       f"output ({smallest} px) allows at most "
                                       f"{max(1, int(math.log2(smallest / 2)))}")
    channels = _channels(sample.pixels)
    mean, axes = _colour_basis(sample.pixels)
    decorrelated = (_as_hwc(sample.pixels).reshape(-1, channels) - mean) @ axes
    sample_channels = [decorrelated[:, c].reshape(sample.height, sample.width) for c in range(channels)]
    sample_bands = [build_pyramid(s, levels=levels, orientations=orientations) for s in sample_channels]
    current = [match_histogram(rng.standard_normal((height, width)), s) for s in sample_channels]

    def image_of(channels_now: list[np.ndarray]) -> np.ndarray:
        stacked = np.stack(channels_now, axis=2).reshape(-1, channels) @ axes.T + mean
        return np.clip(_from_hwc(stacked.reshape(height, width, channels), channels), 0, 1).astype(np.float32)

    for iteration in range(int(iterations)):
        for c in range(channels):
            bands = build_pyramid(current[c], levels=levels, orientations=orientations)
            matched = [match_histogram(band, ref) for band, ref in zip(bands, sample_bands[c])]
            current[c] = match_histogram(collapse_pyramid(matched, orientations=orientations), sample_channels[c])
        preview = image_of(current)
        yield Progress(iteration=iteration + 1, total=int(iterations), message="histograms matched",
                       values={"parametric": Image(preview, name="parametric (iterating)")})
    pixels = image_of(current)
    return ParametricResult(
        parametric=Image(pixels, name="Heeger-Bergen"),
        stat_distance=texture_statistics_distance(pixels, sample.pixels),
        histogram_error=float(np.abs(_quantiles(pixels) - _quantiles(sample.pixels)).mean()))


# ----------------------------------------------------------------------------------------------------
# Efros–Leung: the lesson's window distance, the exact fast and the slow reference synthesis
# ----------------------------------------------------------------------------------------------------
def gaussian_window(window: int, *, sigma_fraction: float = SIGMA_FRACTION) -> np.ndarray:
    """``(w, w)`` weights ``exp(-(dx^2 + dy^2) / (2 sigma^2))``, ``sigma = sigma_fraction * w``, 1 at the centre."""
    half = window // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    sigma = sigma_fraction * window
    return np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma ** 2))


def _check_query(sample: Image, query_window: Any, query_mask: Any) -> tuple[np.ndarray, np.ndarray]:
    query = np.asarray(query_window, dtype=np.float64)
    mask = np.asarray(query_mask)
    if query.ndim not in (2, 3) or query.shape[0] != query.shape[1]:
        raise InvalidValue("query_window", f"a window is (w, w) or (w, w, C), got shape {query.shape}")
    if _channels(query) != _channels(sample.pixels):
        raise InvalidValue("query_window", f"has {_channels(query)} channel(s) but the sample "
                                           f"{_channels(sample.pixels)}: grayscale and colour do not compare")
    if mask.shape != query.shape[:2] or mask.dtype != bool:
        raise InvalidValue("query_mask", f"must be a boolean (w, w) = {query.shape[:2]} array, got "
                                         f"{mask.dtype} {mask.shape}")
    if query.shape[0] % 2 == 0:
        raise InvalidValue("query_window", f"must have an odd side (a centre pixel), got {query.shape[0]}")
    if query.shape[0] > min(sample.height, sample.width):
        raise InvalidValue("query_window", f"the window ({query.shape[0]} px) is larger than the sample "
                                           f"({sample.width} x {sample.height})")
    if not mask.any():
        raise InvalidValue("query_mask", "no pixel of the window is known: there is nothing to compare")
    return query, mask


def window_distances(sample: Image, query_window: np.ndarray, query_mask: np.ndarray, *,
                     weighting: Literal["gaussian", "uniform"] = "gaussian",
                     normalize: bool = True) -> Annotated[np.ndarray, "window_distances"]:
    """Efros–Leung's distance of a partly known window to every window of the sample.

    ``d(i, j) = sum_k g_k m_k |q_k - s_{(i, j) + k}|^2 / sum_k g_k m_k`` over the window offsets
    ``k``, with ``m`` the known pixels (``query_mask``), ``g`` the Gaussian of sigma ``w / 6.4``
    (``weighting = "gaussian"``) or 1 (``"uniform"``), and ``|.|^2`` summed over colour channels
    (Efros & Leung 1999, section 2.1). Without ``normalize`` the sum is not divided by the known
    weight. The same as ``cv2.matchTemplate(sample, query, cv2.TM_SQDIFF, mask=sqrt(g m))`` divided by
    ``sum g m``.

    Args:
        weighting: Gaussian weights (nearer pixels count more) or none.
        normalize: divide by the total weight of the known pixels.

    Inputs: ``sample`` ``(h, ws[, C])``; ``query_window`` ``(w, w[, C])`` float (unknown pixels any
    value), ``w`` odd and at most the sample's side; ``query_mask`` ``(w, w)`` bool.
    Returns ``(h - w + 1, ws - w + 1)`` float64; entry ``(i, j)`` for the window with top-left ``(i, j)``.
    """
    sample = _image(sample, "sample")
    query, mask = _check_query(sample, query_window, query_mask)
    w = query.shape[0]
    weights = (gaussian_window(w) if weighting == "gaussian" else np.ones((w, w))) * mask
    windows = np.lib.stride_tricks.sliding_window_view(_as_hwc(sample.pixels), (w, w), axis=(0, 1))
    # windows: (h - w + 1, ws - w + 1, C, w, w); SSD expanded: sum g (q^2 - 2 q s + s^2)
    q = np.moveaxis(_as_hwc(query), 2, 0)  # (C, w, w)
    constant = float((weights * (q ** 2)).sum())
    cross = np.einsum("ijcab,cab->ij", windows, weights * q, optimize=True)
    squares = np.einsum("ijcab,ab->ij", windows ** 2, weights, optimize=True)
    distances = np.maximum(constant - 2.0 * cross + squares, 0.0)
    return distances / weights.sum() if normalize else distances


@step_result
class QueryWindow:
    """Result of :func:`pick_query_window`."""

    query_window: np.ndarray
    query_mask: np.ndarray
    query_origin: np.ndarray
    known_pixels: int = metric("known pixels of the query window")


def pick_query_window(sample: Image, *, window: Annotated[int, Range(3, 31)] = 9,
                      known_fraction: Annotated[float, Range(0.05, 1.0)] = 0.5,
                      rng: np.random.Generator) -> QueryWindow:
    """A partly known window cut from the sample: what Efros–Leung sees around a pixel it is about to fill.

    A random window of the sample; each pixel is known with probability ``known_fraction``, the
    centre never (it is the pixel to fill), at least one always. Unknown pixels are set to 0.
    ``query_origin`` is where it was cut from, so the best match is known.

    Args:
        window: side of the window (odd).
        known_fraction: share of the window's pixels that are known.
    """
    sample = _image(sample, "sample")
    w = _check_window(window, sample)
    top = int(rng.integers(0, sample.height - w + 1))
    left = int(rng.integers(0, sample.width - w + 1))
    mask = rng.random((w, w)) < known_fraction
    mask[w // 2, w // 2] = False
    if not mask.any():
        mask[w // 2, w // 2 - 1 if w > 1 else 0] = True
    query = _as_hwc(sample.pixels)[top:top + w, left:left + w] * mask[:, :, None]
    return QueryWindow(_from_hwc(query, _channels(sample.pixels)).copy(), mask,
                       np.array([top, left], dtype=np.int64), int(mask.sum()))


def candidates_within(distances: np.ndarray, epsilon: float) -> np.ndarray:
    """Flat indices of the entries within ``(1 + epsilon)`` of the smallest (Efros & Leung 1999, section 2.1)."""
    flat = np.asarray(distances, dtype=np.float64).ravel()
    return np.flatnonzero(flat <= flat.min() * (1.0 + epsilon))


@step_result
class WindowMatch:
    """Result of :func:`match_window`."""

    match_candidates: Points2D
    chosen_match: np.ndarray
    best_distance: float = metric("distance of the best window")
    candidates: int = metric("windows within (1 + epsilon) of the best")


def match_window(sample: Image, window_distances: np.ndarray, *, epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1,
                 rng: np.random.Generator) -> WindowMatch:
    """Keep the windows within ``(1 + epsilon)`` of the best and draw one (Efros & Leung 1999, section 2.1).

    Args:
        epsilon: relative tolerance above the best distance.

    Returns the candidates' centres (``Points2D`` on ``sample``, x = column) and the chosen window's
    top-left ``(row, col)``.
    """
    sample = _image(sample, "sample")
    distances = np.asarray(window_distances, dtype=np.float64)
    if distances.ndim != 2 or distances.size == 0 or not np.all(np.isfinite(distances)):
        raise InvalidValue("window_distances", f"must be a finite 2D array, got shape {distances.shape}")
    half = (sample.height - distances.shape[0]) // 2
    chosen_flat = candidates_within(distances, epsilon)
    rows, cols = np.unravel_index(chosen_flat, distances.shape)
    pick = int(rng.integers(len(chosen_flat)))
    centres = np.column_stack([cols + half, rows + half]).astype(np.float64)
    return WindowMatch(Points2D(centres, image="sample"), np.array([rows[pick], cols[pick]], dtype=np.int64),
                       float(distances.min()), int(len(chosen_flat)))


def evaluate_match(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``match_error_px``: how far the chosen window is from where the query was cut."""
    if "chosen_match" not in state or "query_origin" not in state:
        return {}
    return {"match_error_px": float(np.hypot(*(state["chosen_match"] - state["query_origin"])))}


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
    return np.clip(np.rint(_as_hwc(pixels) * 255.0), 0, 255).astype(np.int64)


def integer_gaussian(window: int) -> np.ndarray:
    """``(w, w)`` int64 Gaussian weights ``max(1, round(4096 g))``, sigma = w / 6.4: integers keep every SSD exact."""
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
    counts = np.rint(uniform_filter(filled.astype(np.float64), size=window, mode="constant") * window * window)
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
    order[oy:oy + seed_size, ox:ox + seed_size] = np.arange(seed_size * seed_size).reshape(seed_size, seed_size)
    rows, cols = np.mgrid[top:top + seed_size, left:left + seed_size]
    source[oy:oy + seed_size, ox:ox + seed_size] = np.stack([rows, cols], axis=2)
    return out, filled, order, source


def pick_candidate(candidates: np.ndarray, uniform: float) -> int:
    """The candidate a uniform draw in [0, 1) selects: entry ``floor(u K)`` of the ``K`` candidates (each as likely)."""
    return int(candidates[min(int(uniform * len(candidates)), len(candidates) - 1)])


def _fill_layer_reference(levels: np.ndarray, out: np.ndarray, filled: np.ndarray, order: np.ndarray,
                          source: np.ndarray, pixels: np.ndarray, weights: np.ndarray, epsilon: float,
                          uniforms: np.ndarray, counter: int) -> int:
    """Fill ``pixels`` one after the other, comparing each window with every sample window in a loop.

    ``uniforms`` holds one draw in [0, 1) per pixel, which picks among its candidates."""
    h, w_s, _ = levels.shape
    w = len(weights)
    half = w // 2
    height, width = filled.shape
    for (row, col), uniform in zip(pixels, uniforms):
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


class _SampleWindows:
    """Every window of the sample, unrolled once: ``values`` ``(N, w*w, C)`` and ``squares`` ``(N, w*w)``."""

    def __init__(self, levels: np.ndarray, window: int) -> None:
        h, w_s, channels = levels.shape
        view = np.lib.stride_tricks.sliding_window_view(levels.astype(np.float64), (window, window), axis=(0, 1))
        # view: (h-w+1, ws-w+1, C, w, w) -> (N, w*w, C)
        self.values = np.ascontiguousarray(np.moveaxis(view, 2, -1).reshape(-1, window * window, channels))
        self.squares = (self.values ** 2).sum(axis=2)
        # [values, squares] side by side: one matrix product gives both sums of the expanded SSD
        self.stacked = np.concatenate([self.values.reshape(len(self.values), -1), self.squares], axis=1).T.copy()
        self.columns = w_s - window + 1


def _kernel(func: Any) -> Any:
    """``numba.njit`` without the GIL, cached on disk where possible (as the stereo module's kernels)."""
    import numba

    try:
        return numba.njit(cache=True, nogil=True)(func)
    except RuntimeError:  # no writable cache location
        return numba.njit(nogil=True)(func)


def _fill_chunk(sums, totals, rows, cols, uniforms, values, g, levels, padded_out, in_layer, out, source, filled,
                order, counter, epsilon, w, columns):
    """The sequential part of a chunk of an onion layer (compiled by Numba): for each pixel in turn add
    the terms of the pixels filled earlier in this layer, divide, keep the candidates, pick, copy.

    Every sum is of integers below 2^53 (exact in float64), so the order of the additions does not
    change the result: the distances equal the reference's bit for bit.
    """
    half = w // 2
    n_windows = sums.shape[1]
    channels = values.shape[2]
    distances = np.empty(n_windows)
    for b in range(len(rows)):
        row, col = rows[b], cols[b]
        total = totals[b]
        for n in range(n_windows):
            distances[n] = sums[b, n]
        for dy in range(w):
            for dx in range(w):
                if in_layer[row + dy, col + dx]:
                    k = dy * w + dx
                    gk = g[k]
                    total += gk
                    for n in range(n_windows):
                        acc = 0.0
                        for c in range(channels):
                            diff = values[n, k, c] - padded_out[row + dy, col + dx, c]
                            acc += diff * diff
                        distances[n] += gk * acc
        best = np.inf
        for n in range(n_windows):
            distances[n] = distances[n] / total
            if distances[n] < best:
                best = distances[n]
        threshold = best * (1.0 + epsilon)
        count = 0
        for n in range(n_windows):
            if distances[n] <= threshold:
                count += 1
        wanted = min(int(uniforms[b] * count), count - 1)
        chosen = -1
        for n in range(n_windows):
            if distances[n] <= threshold:
                if wanted == 0:
                    chosen = n
                    break
                wanted -= 1
        i = chosen // columns
        j = chosen % columns
        for c in range(channels):
            out[row, col, c] = levels[i + half, j + half, c]
            padded_out[row + half, col + half, c] = levels[i + half, j + half, c]
        in_layer[row + half, col + half] = True
        source[row, col, 0] = i + half
        source[row, col, 1] = j + half
        filled[row, col] = True
        order[row, col] = counter
        counter += 1
    return counter


_fill_chunk_compiled: Any = None


def _fill_layer_fast(levels: np.ndarray, windows: _SampleWindows, out: np.ndarray, filled: np.ndarray,
                     order: np.ndarray, source: np.ndarray, pixels: np.ndarray, weights: np.ndarray,
                     epsilon: float, uniforms: np.ndarray, counter: int, *, chunk: int = 256) -> int:
    """Fill one onion layer; the same numbers and draws as :func:`_fill_layer_reference`, computed fast.

    The masked SSD expands into ``sum a q^2 - 2 sum a q s + sum a s^2`` (``a = g m``): the last two
    are one matrix product of the layer's weighted templates (``(B, w^2 (C + 1))``) with all
    sample windows, for all pixels of a chunk at once, with the pixels known at the start of the
    layer. Pixels of the same layer filled before a pixel are then added one by one, in a compiled
    loop (:func:`_fill_chunk`). Everything is an integer below 2^53 in float64, so the sums are
    exact in any order.
    """
    global _fill_chunk_compiled
    if _fill_chunk_compiled is None:
        _fill_chunk_compiled = _kernel(_fill_chunk)
    w = len(weights)
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
        counter = _fill_chunk_compiled(sums, a.sum(axis=1), rows, cols, uniforms[start:start + chunk], windows.values,
                                       g, levels, padded_out, in_layer, out, source, filled, order, counter,
                                       float(epsilon), w, windows.columns)
    return counter


def _check_efros_leung(sample: Image, size: tuple[int, int], window: int,
                       seed_size: int) -> tuple[tuple[int, int], int]:
    window = _check_window(window, sample)
    height, width = _check_size(size, smallest=int(seed_size), what="the seed")
    if seed_size > min(sample.height, sample.width):
        raise InvalidControl("seed_size", f"the seed ({seed_size} px) is larger than the sample")
    work = height * width * (sample.height - window + 1) * (sample.width - window + 1)
    if work > MAX_EL_WORK:
        raise InvalidControl("size", f"{height} x {width} pixels each compared with "
                                     f"{(sample.height - window + 1) * (sample.width - window + 1)} sample windows "
                                     f"is too much work ({work:.1e} > {MAX_EL_WORK:.0e}); use a smaller output or "
                                     "sample, or image quilting")
    return (height, width), window


def grow_efros_leung(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1,
                     seed_size: int = 3, rng: np.random.Generator, reference: bool = False,
                     ) -> Generator[tuple[int, int, np.ndarray], None, tuple[np.ndarray, EfrosLeungTrace]]:
    """Grow an Efros–Leung texture layer by layer: yields (layer, pixels filled, image so far).

    Per layer: :func:`onion_layer` orders the frontier (one ``rng.permutation``), then
    ``rng.random(len(layer))`` draws one uniform per pixel, which :func:`pick_candidate` turns into
    a choice among the pixel's candidates. Returns the texture ``(H, W[, C])`` float32 (8-bit
    levels / 255) and its :class:`EfrosLeungTrace`. ``reference`` picks the slow per-window loop;
    both give the same result for the same ``rng`` state.
    """
    sample = _image(sample, "sample")
    (height, width), window = _check_efros_leung(sample, size, window, int(seed_size))
    channels = _channels(sample.pixels)
    levels = sample_levels(sample.pixels)
    weights = integer_gaussian(window)
    out, filled, order, source = _plant_seed(levels, (height, width), int(seed_size), rng)
    counter = int(filled.sum())
    windows = None if reference else _SampleWindows(levels, window)
    layer = 0
    while not filled.all():
        pixels = onion_layer(filled, window, rng)
        uniforms = rng.random(len(pixels))  # one draw per pixel picks among its candidates
        if reference:
            counter = _fill_layer_reference(levels, out, filled, order, source, pixels, weights, epsilon, uniforms,
                                            counter)
        else:
            counter = _fill_layer_fast(levels, windows, out, filled, order, source, pixels, weights, epsilon,
                                       uniforms, counter)
        layer += 1
        yield layer, counter, _from_hwc(out / 255.0, channels).astype(np.float32)
    image = _from_hwc(out / 255.0, channels).astype(np.float32)
    return image, EfrosLeungTrace(order, source, window, float(epsilon), layer, int(seed_size) ** 2)


def _exhaust(generator: Generator[Any, None, Any]) -> Any:
    while True:
        try:
            next(generator)
        except StopIteration as stop:
            return stop.value


def efros_leung(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1, seed_size: int = 3,
                rng: np.random.Generator) -> tuple[np.ndarray, EfrosLeungTrace]:
    """Efros–Leung, fast and exact (:func:`grow_efros_leung` with the batched SSD): ``(texture, trace)``."""
    return _exhaust(grow_efros_leung(sample, size=size, window=window, epsilon=epsilon, seed_size=seed_size, rng=rng))


def efros_leung_reference(sample: Image, *, size: tuple[int, int], window: int = 11, epsilon: float = 0.1,
                          seed_size: int = 3, rng: np.random.Generator) -> tuple[np.ndarray, EfrosLeungTrace]:
    """Efros–Leung, slow and readable: every pixel's window compared with every sample window in a loop.

    The oracle of :func:`efros_leung`: same onion order, same integer SSD, same random draws.
    """
    return _exhaust(grow_efros_leung(sample, size=size, window=window, epsilon=epsilon, seed_size=seed_size, rng=rng,
                                     reference=True))


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
    synthesis computed (:func:`window_distances` with the integer weights the synthesis used, on
    8-bit levels); the chosen window is the one whose centre is ``trace.source[row, col]``.
    """
    height, width = trace.fill_order.shape
    if not (0 <= row < height and 0 <= col < width):
        raise InvalidValue("pixel", f"({row}, {col}) is outside the {width} x {height} texture")
    w, half = trace.window, trace.window // 2
    order = int(trace.fill_order[row, col])
    levels = sample_levels(texture.pixels)
    window = np.zeros((w, w, levels.shape[2]))
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
        return PixelMatches(_from_hwc(window / 255.0, levels.shape[2]), known, distances, chosen[None], chosen, order)
    levels_sample = sample_levels(sample.pixels).astype(np.float64)
    weights = integer_gaussian(w) * known
    view = np.lib.stride_tricks.sliding_window_view(levels_sample, (w, w), axis=(0, 1))
    difference = view - np.moveaxis(window, 2, 0)[None, None]
    distances = np.einsum("ijcab,ab->ij", difference ** 2, weights) / weights.sum()
    flat = candidates_within(distances, trace.epsilon)
    candidates = np.column_stack(np.unravel_index(flat, distances.shape)).astype(np.int64)
    return PixelMatches(_from_hwc(window / 255.0, levels.shape[2]), known, distances, candidates, chosen, order)


@step_result
class EfrosLeungResult:
    """Result of :func:`synthesize_efros_leung`."""

    efros_leung: Image
    efros_leung_trace: EfrosLeungTrace
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")
    seam_score: float = metric("contrast across copy seams / the sample's contrast (1 = invisible)")
    layers: int = metric("onion layers grown")


def synthesize_efros_leung(sample: Image, *, size: Size = (48, 48), window: Annotated[int, Range(3, 31)] = 11,
                           epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1,
                           seed_size: Annotated[int, Range(1, 15)] = 3,
                           implementation: Literal["fast", "reference"] = "fast",
                           rng: np.random.Generator) -> Generator[Progress, None, EfrosLeungResult]:
    """Efros–Leung non-parametric sampling: grow the texture pixel by pixel from a seed, in onion order.

    A random ``seed_size`` x ``seed_size`` patch of the sample seeds the middle of the output. Then,
    layer after layer, every unfilled pixel next to the filled region (those with the most known
    neighbours first, :func:`onion_layer`) compares its window with every window of the sample by
    the Gaussian-weighted SSD over its known pixels (:func:`window_distances`), keeps the windows
    within ``(1 + epsilon)`` of the best and copies the centre of one drawn at random (Efros &
    Leung 1999, sections 2.1 and 2.2). ``implementation`` "fast" (batched matrix products) and
    "reference" (a loop over windows) give the same texture. Yields the texture after every layer.

    Args:
        size: (height, width) of the output in pixels.
        window: side of the neighbourhood window (odd; Efros & Leung's w).
        epsilon: relative tolerance above the best match (0.1 in the paper).
        seed_size: side of the seed patch.
        implementation: the fast exact version or the slow readable reference (the same texture; the
            reference takes about a minute at the default sizes).
    """
    sample = _image(sample, "sample")
    height, width = (int(v) for v in size)
    grower = grow_efros_leung(sample, size=(height, width), window=window, epsilon=epsilon, seed_size=seed_size,
                              rng=rng, reference=implementation == "reference")
    total = height * width
    while True:
        try:
            layer, done, preview = next(grower)
        except StopIteration as stop:
            pixels, trace = stop.value
            break
        yield Progress(iteration=done, total=total, message=f"onion layer {layer}",
                       values={"efros_leung": Image(preview, name="Efros-Leung (growing)")})
    return EfrosLeungResult(Image(pixels, name="Efros-Leung"), trace,
                            stat_distance=texture_statistics_distance(pixels, sample.pixels),
                            seam_score=seam_score(pixels, trace.source, sample.pixels), layers=trace.layers)


# ----------------------------------------------------------------------------------------------------
# Image quilting: overlap error, minimum-error boundary cut, quilting, transfer
# ----------------------------------------------------------------------------------------------------
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


@step_result
class OverlapPair:
    """Result of :func:`pick_overlap`."""

    overlap_left: Image
    overlap_right: Image
    overlap_error: np.ndarray
    overlap_mean_error: float = metric("mean squared difference in the overlap")


def overlap_error_surface(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``(rows, cols)`` squared difference of two overlapping regions, summed over colour channels."""
    return ((_as_hwc(old) - _as_hwc(new)) ** 2).sum(axis=2)


def pick_overlap(sample: Image, *, block: Annotated[int, Range(2, 256)] = 24,
                 overlap: Annotated[int, Range(1, 128)] = 6, rng: np.random.Generator) -> OverlapPair:
    """Two random blocks of the sample side by side, overlapping by ``overlap`` columns, and their error surface.

    ``overlap_error`` ``(block, overlap)``: the squared difference of the left block's last
    ``overlap`` columns and the right block's first ones, summed over colour (Efros & Freeman
    2001, section 2.1: the surface the minimum-error cut runs through).

    Args:
        block: side of the square blocks in pixels.
        overlap: width of the overlap in pixels.
    """
    sample = _image(sample, "sample")
    block, overlap = _check_block(block, overlap, sample)
    corners = rng.integers(0, [sample.height - block + 1, sample.width - block + 1], size=(2, 2))
    left, right = (sample.pixels[y:y + block, x:x + block] for y, x in corners)
    errors = overlap_error_surface(left[:, block - overlap:], right[:, :overlap])
    return OverlapPair(Image(left.copy(), name="left block"), Image(right.copy(), name="right block"), errors,
                       float(errors.mean()))


def min_error_cut(overlap_error: np.ndarray) -> Annotated[np.ndarray, "cut_path"]:
    """The minimum-error boundary cut through a vertical overlap (Efros & Freeman 2001, section 2.1).

    Input ``overlap_error`` ``(rows, cols)``: the squared difference of the two blocks in their
    overlap. Returns ``(rows,)`` int64: the column of the cut in every row, a path from the top to
    the bottom that moves at most one column between rows and whose summed error is the smallest
    (dynamic programming, :func:`min_error_boundary_cut`). Left of the cut the old block is kept,
    from the cut on the new one.
    """
    return min_error_boundary_cut(overlap_error)


@step_result
class JoinedBlocks:
    """Result of :func:`join_blocks`."""

    joined: Image
    cut_cost: float = metric("summed overlap error along the cut")
    cut_max_step: int = metric("largest column change between neighbouring rows of the cut", unit="px")
    straight_cost: float = metric("summed error of the best straight cut, for comparison")


def _check_path(cut_path: Any, rows: int, cols: int) -> np.ndarray:
    path = np.asarray(cut_path)
    if path.shape != (rows,):
        raise InvalidValue("cut_path", f"must hold one column per row of the overlap, shape ({rows},), "
                                       f"got {path.shape}")
    if path.dtype.kind not in "iu" and not (path.dtype.kind == "f" and np.all(np.isfinite(path))
                                            and np.all(path == np.round(path))):
        raise InvalidValue("cut_path", f"must hold integer columns, got dtype {path.dtype}")
    path = path.astype(np.int64)
    if path.min() < 0 or path.max() >= cols:
        raise InvalidValue("cut_path", f"columns must lie in the overlap, 0 to {cols - 1}; got {path.min()} to "
                                       f"{path.max()}")
    return path


def join_blocks(overlap_left: Image, overlap_right: Image, overlap_error: np.ndarray,
                cut_path: np.ndarray) -> JoinedBlocks:
    """Join two overlapping blocks along a cut: the left block left of it, the right block from it on.

    Returns the joined image ``(block, 2 block - overlap[, 3])`` and the cut's cost, its largest step
    and the cost of the best straight (one column) cut, which the boundary cut never exceeds.
    """
    left, right = _image(overlap_left, "overlap_left").pixels, _image(overlap_right, "overlap_right").pixels
    errors = np.asarray(overlap_error, dtype=np.float64)
    rows, overlap = errors.shape
    block = left.shape[1]
    path = _check_path(cut_path, rows, overlap)
    channels = _channels(left)
    joined = np.zeros((rows, 2 * block - overlap, channels), dtype=np.float32)
    joined[:, :block] = _as_hwc(left)
    take_right = np.arange(overlap)[None, :] >= path[:, None]
    region = joined[:, block - overlap:block]
    joined[:, block - overlap:block] = np.where(take_right[:, :, None], _as_hwc(right)[:, :overlap], region)
    joined[:, block:] = _as_hwc(right)[:, overlap:]
    return JoinedBlocks(Image(_from_hwc(joined, channels), name="joined along the cut"), path_cost(errors, path),
                        int(np.abs(np.diff(path)).max()) if rows > 1 else 0, float(errors.sum(axis=0).min()))


@dataclass(frozen=True)
class QuiltLayout:
    """Every block of a quilt: ``positions`` ``(K, 2)`` top-left (row, col) in the output, ``sources``
    ``(K, 2)`` top-left in the sample, ``errors`` ``(K, B, B)`` the overlap error surface in the block's
    frame (0 outside the overlap), ``new_pixels`` ``(K, B, B)`` bool the pixels the block kept after its cuts."""

    positions: np.ndarray
    sources: np.ndarray
    errors: np.ndarray
    new_pixels: np.ndarray
    block: int
    overlap: int


def _masked_ssd_map(sample: np.ndarray, template: np.ndarray, mask: np.ndarray) -> np.ndarray:
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


def _ssd_map(sample: np.ndarray, template: np.ndarray) -> np.ndarray:
    import cv2

    total = np.zeros((sample.shape[0] - template.shape[0] + 1, sample.shape[1] - template.shape[1] + 1))
    for c in range(sample.shape[2]):
        total += cv2.matchTemplate(np.ascontiguousarray(sample[:, :, c], dtype=np.float32),
                                   np.ascontiguousarray(template[:, :, c], dtype=np.float32), cv2.TM_SQDIFF)
    return np.maximum(total, 0.0)


def _grid(length: int, block: int, step: int) -> list[int]:
    """Block origins along one axis so that the last block ends at or after ``length``."""
    origins = [0]
    while origins[-1] + block < length:
        origins.append(origins[-1] + step)
    return origins


def _quilt(sample: np.ndarray, size: tuple[int, int], block: int, overlap: int, epsilon: float, mode: str,
           rng: np.random.Generator, *, extra_cost: Any = None, alpha: float = 1.0,
           previous: np.ndarray | None = None) -> Generator[tuple[int, int, np.ndarray], None,
                                                           tuple[np.ndarray, np.ndarray, QuiltLayout]]:
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
    ys, xs = _grid(height, block, step), _grid(width, block, step)
    canvas_h, canvas_w = ys[-1] + block, xs[-1] + block
    canvas = np.zeros((canvas_h, canvas_w, channels))
    source = np.full((canvas_h, canvas_w, 2), -1, dtype=np.int64)
    if previous is not None:
        padded_previous = np.zeros((canvas_h, canvas_w, channels))
        padded_previous[:height, :width] = previous
        padded_previous[height:, :] = padded_previous[height - 1:height, :]
        padded_previous[:, width:] = padded_previous[:, width - 1:width]
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
                    cost += alpha * _masked_ssd_map(sample, old, mask) / mask.sum()
                if previous is not None:
                    cost += alpha * _ssd_map(sample, padded_previous[y:y + block, x:x + block]) / block ** 2
                if extra_cost is not None:
                    cost += (1.0 - alpha) * extra_cost(y, x, block)
                flat = candidates_within(cost, epsilon)
                sy, sx = np.unravel_index(int(flat[rng.integers(len(flat))]), cost.shape)
                sy, sx = int(sy), int(sx)
            new = sample[sy:sy + block, sx:sx + block]
            surface = overlap_error_surface(old, new) * mask
            take = np.ones((block, block), dtype=bool)
            if mode == "min_cut":
                if x > 0:
                    take &= grid_cols >= min_error_boundary_cut(surface[:, :overlap])[:, None]
                if y > 0:
                    take &= grid_rows >= min_error_boundary_cut(surface[:overlap, :].T)[None, :]
            else:  # straight edges: the new block is pasted over the overlap
                pass
            region_source = source[y:y + block, x:x + block]
            canvas[y:y + block, x:x + block] = np.where(take[:, :, None], new, old)
            new_source = np.stack([grid_rows + sy, grid_cols + sx], axis=2)
            source[y:y + block, x:x + block] = np.where(take[:, :, None], new_source, region_source)
            positions[k], sources[k], errors[k], kept[k] = (y, x), (sy, sx), surface, take
            k += 1
            yield k, count, canvas[:height, :width]
    layout = QuiltLayout(positions, sources, errors, kept, block, overlap)
    return canvas[:height, :width].copy(), source[:height, :width].copy(), layout


def image_quilting(sample: Image, *, size: tuple[int, int], block: int = 24, overlap: int = 5, epsilon: float = 0.1,
                   mode: str = "min_cut", rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, QuiltLayout]:
    """Image quilting as a plain function (what :func:`quilt` runs, without progress and metrics):
    ``(texture (H, W[, C]) float32, source (H, W, 2) int, layout)``."""
    sample = _image(sample, "sample")
    block, overlap = _check_block(block, overlap, sample)
    height, width = _check_size(size, smallest=block, what="a block")
    pixels, source, layout = _exhaust(_quilt(_as_hwc(sample.pixels), (height, width), block, overlap, float(epsilon),
                                             mode, rng))
    return np.clip(_from_hwc(pixels, _channels(sample.pixels)), 0, 1).astype(np.float32), source, layout


def cut_segments(layout: QuiltLayout, size: tuple[int, int], *, image: str = "quilting") -> Segments2D:
    """The boundary of each block's kept pixels inside its overlap, as short segments between pixel centres
    (drawn on the output image)."""
    starts, ends = [], []
    b, o = layout.block, layout.overlap
    height, width = size
    for (y, x), keep, errors in zip(layout.positions, layout.new_pixels, layout.errors):
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
    inside = ((starts_a[:, 0] < width) & (starts_a[:, 1] < height) & (ends_a[:, 0] < width) & (ends_a[:, 1] < height))
    colours = np.tile([[1.0, 0.2, 0.2]], (int(inside.sum()), 1))
    return Segments2D(starts_a[inside], ends_a[inside], colors=colours, image=image)


@step_result
class QuiltResult:
    """Result of :func:`quilt`."""

    quilting: Image
    quilting_layout: QuiltLayout
    quilting_seams: Segments2D
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")
    seam_score: float = metric("contrast across copy seams / the sample's contrast (1 = invisible)")
    blocks: int = metric("blocks placed")


def quilt(sample: Image, *, size: Size = (128, 128), block: Annotated[int, Range(2, 256)] = 24,
          overlap: Annotated[int, Range(1, 128)] = 5, epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1,
          mode: Literal["random", "best_overlap", "min_cut"] = "min_cut",
          rng: np.random.Generator) -> Generator[Progress, None, QuiltResult]:
    """Image quilting: tile the output with sample blocks that agree in their overlaps, joined along cuts.

    Blocks are placed in raster order, ``block - overlap`` apart. ``mode`` follows Efros & Freeman
    2001, figure 2: (a) "random" blocks; (b) "best_overlap": each block drawn among those whose
    SSD with what is already there in the overlap (left, top or both) is within ``(1 + epsilon)``
    of the best (``cv2.matchTemplate`` with a mask); (c) "min_cut": the same, each overlap then
    split along the minimum-error boundary cut (:func:`min_error_boundary_cut`; section 2.1).
    Yields the quilt after every block.

    Args:
        size: (height, width) of the output in pixels, at least one block.
        block: side of the square blocks (at most the sample's side).
        overlap: width of the overlap between neighbouring blocks (Efros & Freeman use block / 6).
        epsilon: relative tolerance above the best overlap error.
        mode: random blocks, best-overlap blocks, or best-overlap blocks with minimum-error cuts.
    """
    sample = _image(sample, "sample")
    block, overlap = _check_block(block, overlap, sample)
    height, width = _check_size(size, smallest=block, what="a block")
    channels = _channels(sample.pixels)
    quilter = _quilt(_as_hwc(sample.pixels), (height, width), block, overlap, float(epsilon), mode, rng)
    while True:
        try:
            k, count, canvas = next(quilter)
        except StopIteration as stop:
            pixels, source, layout = stop.value
            break
        yield Progress(iteration=k, total=count, message=f"block {k} of {count}",
                       values={"quilting": Image(_from_hwc(canvas, channels).astype(np.float32),
                                                 name="quilting (growing)")})
    image = np.clip(_from_hwc(pixels, channels), 0, 1).astype(np.float32)
    return QuiltResult(Image(image, name=f"quilting ({mode})"), layout, cut_segments(layout, (height, width)),
                       stat_distance=texture_statistics_distance(image, sample.pixels),
                       seam_score=seam_score(image, source, sample.pixels), blocks=len(layout.positions))


def correspondence_map(pixels: np.ndarray, *, sigma: float = 1.5) -> np.ndarray:
    """The correspondence quantity of texture transfer: blurred luminance ``(H, W)`` (Efros & Freeman 2001,
    section 4)."""
    import cv2

    return cv2.GaussianBlur(luminance(pixels).astype(np.float32), (0, 0), sigma).astype(np.float64)


@step_result
class TransferResult:
    """Result of :func:`transfer_texture`."""

    transferred: Image
    correspondence_error: float = metric("mean squared difference of the correspondence maps, output vs target")
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")


def transfer_texture(sample: Image, transfer_target: Image, *, block: Annotated[int, Range(3, 128)] = 15,
                     iterations: Annotated[int, Range(1, 5)] = 2, epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1,
                     rng: np.random.Generator) -> Generator[Progress, None, TransferResult]:
    """Texture transfer: redraw the target with blocks of the sample (Efros & Freeman 2001, section 4).

    Each block is chosen by ``alpha * overlap error + (1 - alpha) * correspondence error``: the
    correspondence map is blurred luminance (:func:`correspondence_map`) of the target block and the
    sample block. ``iterations`` passes over the image, the block a third smaller each time and
    ``alpha = 0.8 (i - 1) / (N - 1) + 0.1``; from the second pass on, the overlap error also
    compares the block with the previous pass's output at its place. Overlaps are joined by
    minimum-error cuts; the overlap is a sixth of the block.

    Args:
        block: side of the blocks of the first pass.
        iterations: passes, each with smaller blocks (N).
        epsilon: relative tolerance above the best error.

    Sample and target must both be grayscale or both colour.
    """
    sample = _image(sample, "sample")
    target = _image(transfer_target, "transfer_target")
    if _channels(sample.pixels) != _channels(target.pixels):
        kinds = {1: "grayscale", 3: "colour"}
        raise InvalidValue("transfer_target", f"the sample is {kinds[_channels(sample.pixels)]} but the target is "
                                              f"{kinds[_channels(target.pixels)]}: convert one so both are of one kind")
    _check_block(int(block), max(1, int(block) // 6), sample)
    _check_size((target.height, target.width), smallest=int(block), what="a block")
    channels = _channels(sample.pixels)
    sample_hwc = _as_hwc(sample.pixels)
    sample_map = correspondence_map(sample.pixels)[:, :, None]
    target_map = correspondence_map(target.pixels)
    previous = None
    total = int(iterations)
    sizes = [max(3, round(int(block) * (2.0 / 3.0) ** i)) for i in range(total)]
    counts = [len(_grid(target.height, b, b - max(1, b // 6))) * len(_grid(target.width, b, b - max(1, b // 6)))
              for b in sizes]
    done = 0
    for i in range(total):
        b = sizes[i]
        o = max(1, b // 6)
        alpha = 0.8 * i / (total - 1) + 0.1 if total > 1 else 0.1
        canvas_h = _grid(target.height, b, b - o)[-1] + b
        canvas_w = _grid(target.width, b, b - o)[-1] + b
        padded = np.pad(target_map, ((0, canvas_h - target.height), (0, canvas_w - target.width)), mode="edge")

        def correspondence(y: int, x: int, size_b: int, padded: np.ndarray = padded) -> np.ndarray:
            return _ssd_map(sample_map, padded[y:y + size_b, x:x + size_b, None]) / size_b ** 2

        quilter = _quilt(sample_hwc, (target.height, target.width), b, o, float(epsilon), "min_cut", rng,
                         extra_cost=correspondence, alpha=alpha, previous=previous)
        while True:
            try:
                k, count, canvas = next(quilter)
            except StopIteration as stop:
                previous, _, _ = stop.value
                done += count
                break
            if k % 8 == 0 or k == count:
                preview = np.clip(_from_hwc(canvas, channels), 0, 1).astype(np.float32)
                yield Progress(iteration=done + k, total=sum(counts), message=f"pass {i + 1}/{total}, block {k}/{count}",
                               values={"transferred": Image(preview, name="transfer (growing)")})
    pixels = np.clip(_from_hwc(previous, channels), 0, 1).astype(np.float32)
    error = float(np.mean((correspondence_map(pixels) - target_map) ** 2))
    return TransferResult(Image(pixels, name="texture transfer"), error,
                          texture_statistics_distance(pixels, sample.pixels))


# ----------------------------------------------------------------------------------------------------
# The texture on a 3D mesh
# ----------------------------------------------------------------------------------------------------
def parametric_surface(shape: str, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A plane, cylinder or torus as a ``(resolution + 1)^2`` grid of vertices with UVs in [0, 1].

    Returns ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` (two triangles per grid cell, consistent
    winding) and ``uv`` ``(V, 2)``. The seam column (u = 0 and u = 1) is duplicated so the UVs do not
    wrap inside a triangle. Plane: 2 x 2 in z = 0; cylinder: radius 1 / pi (circumference 2),
    height 2; torus: radii 1 and 0.4.
    """
    n = int(resolution)
    u, v = np.meshgrid(np.linspace(0.0, 1.0, n + 1), np.linspace(0.0, 1.0, n + 1))
    if shape == "plane":
        xyz = np.stack([2 * u - 1, 1 - 2 * v, np.zeros_like(u)], axis=-1)
    elif shape == "cylinder":
        angle = 2 * np.pi * u
        radius = 1.0 / np.pi
        xyz = np.stack([radius * np.cos(angle), radius * np.sin(angle), 1 - 2 * v], axis=-1)
    elif shape == "torus":
        angle, tube = 2 * np.pi * u, 2 * np.pi * v
        major, minor = 1.0, 0.4
        xyz = np.stack([(major + minor * np.cos(tube)) * np.cos(angle), (major + minor * np.cos(tube)) * np.sin(angle),
                        minor * np.sin(tube)], axis=-1)
    else:
        raise InvalidControl("shape", f"must be plane, cylinder or torus, got {shape!r}")
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, d, b], axis=1), np.stack([b, d, c], axis=1)])
    return xyz.reshape(-1, 3), faces.astype(np.int64), np.stack([u.ravel(), v.ravel()], axis=1)


def sample_texture(texture: np.ndarray, uv: np.ndarray, *, repeats: float = 1.0) -> np.ndarray:
    """RGB ``(V, 3)`` of a texture at UVs (u right, v down, wrapping: the texture tiles ``repeats`` times),
    bilinear (``scipy.ndimage.map_coordinates`` with ``mode="grid-wrap"``)."""
    from scipy.ndimage import map_coordinates

    pixels = _as_hwc(texture)
    height, width = pixels.shape[:2]
    cols = (uv[:, 0] * repeats * width - 0.5)
    rows = (uv[:, 1] * repeats * height - 0.5)
    channels = [map_coordinates(pixels[:, :, c], [rows, cols], order=1, mode="grid-wrap")
                for c in range(pixels.shape[2])]
    rgb = np.stack(channels, axis=1)
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    return np.clip(rgb, 0.0, 1.0)


@step_result
class TexturedMesh:
    """Result of :func:`wrap_on_mesh`."""

    textured_mesh: Mesh
    mesh_uv: np.ndarray
    vertices: int = metric("vertices of the mesh")


def wrap_on_mesh(sample: Image, parametric: Image | None = None, efros_leung: Image | None = None,
                 quilting: Image | None = None, transferred: Image | None = None, *,
                 texture: Literal["quilting", "efros_leung", "parametric", "transferred", "sample"] = "quilting",
                 shape: Literal["plane", "cylinder", "torus"] = "torus",
                 repeats: Annotated[int, Range(1, 16)] = 2,
                 resolution: Annotated[int, Range(4, 256)] = 96) -> TexturedMesh:
    """A synthesized texture on a 3D surface: vertex colours looked up through the vertices' UVs.

    The surface is a UV-parametrized grid (:func:`parametric_surface`); each vertex takes the
    texture's colour at ``(u, v) * repeats`` (:func:`sample_texture`, the texture tiles). A
    texture that does not tile shows its edges as seams around a cylinder or a torus. The viewer
    also shows the mesh with the texture as an image map (UVs, ``trimesh.visual.TextureVisuals``).

    Args:
        texture: which texture to wrap (it must have been made).
        shape: the surface.
        repeats: how many times the texture repeats along u and v.
        resolution: grid cells along u and v.
    """
    chosen = {"sample": sample, "parametric": parametric, "efros_leung": efros_leung, "quilting": quilting,
              "transferred": transferred}[texture]
    if chosen is None:
        step = {"parametric": "synthesize_parametric", "efros_leung": "synthesize_efros_leung", "quilting": "quilt",
                "transferred": "transfer_texture"}
        raise InvalidValue(texture, f"there is no {texture!r} texture yet: run step {step[texture]!r} first, or pick "
                                    "another texture")
    image = _image(chosen, texture)
    vertices, faces, uv = parametric_surface(shape, int(resolution))
    colours = sample_texture(image.pixels, uv, repeats=float(repeats))
    return TexturedMesh(Mesh(vertices, faces, colours), uv, len(vertices))


def textured_trimesh(mesh: Mesh, uv: np.ndarray, texture: np.ndarray, *, repeats: float = 1.0):
    """A ``trimesh.Trimesh`` with the texture as an image map (``TextureVisuals``), for GLB export and the viewer.

    trimesh's UV origin is the bottom-left (OpenGL): ``v`` is flipped. The texture is tiled
    ``repeats`` times into the image instead of relying on the renderer's wrap mode.
    """
    import trimesh
    from PIL import Image as PILImage

    pixels = _as_hwc(texture)
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    reps = max(1, int(round(repeats)))
    tiled = np.tile(pixels, (reps, reps, 1))
    picture = PILImage.fromarray(np.clip(tiled * 255 + 0.5, 0, 255).astype(np.uint8))
    uv_gl = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    visual = trimesh.visual.TextureVisuals(uv=uv_gl, image=picture)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, visual=visual, process=False)


# ----------------------------------------------------------------------------------------------------
# Evaluations against the known statistics of procedural textures
# ----------------------------------------------------------------------------------------------------
def _statistics_evaluation(name: str):
    def evaluate(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
        if name not in state or "mean" not in truth:
            return {}
        pixels = state[name].pixels
        return {"mean_error": float(abs(pixels.mean() - truth["mean"])),
                "std_ratio": float(pixels.std() / truth["std"])}

    evaluate.__name__ = f"evaluate_{name}"
    evaluate.__doc__ = f"``mean_error`` and ``std_ratio`` of {name!r} against the procedural texture's true statistics."
    return evaluate


evaluate_parametric = _statistics_evaluation("parametric")
evaluate_efros_leung = _statistics_evaluation("efros_leung")
evaluate_quilting = _statistics_evaluation("quilting")


PIPELINE = Pipeline.build(
    name="texture",
    title="Texture synthesis",
    summary="Make more of a texture from a small sample three classic ways and watch each grow: Heeger-Bergen "
            "histogram matching on an oriented pyramid, Efros-Leung pixel-by-pixel sampling, and image quilting "
            "with minimum-error cuts; texture transfer; the result wrapped on a plane, cylinder or torus.",
    steps=[pick_query_window, window_distances, match_window, pick_overlap, min_error_cut, join_blocks,
           synthesize_parametric, synthesize_efros_leung, quilt, transfer_texture, wrap_on_mesh],
    datasets=[brick, grass, gravel, procedural, image_file],
    evaluations={"match_window": evaluate_match, "synthesize_parametric": evaluate_parametric,
                 "synthesize_efros_leung": evaluate_efros_leung, "quilt": evaluate_quilting},
)

__all__ = ["PIPELINE", "SIGMA_FRACTION", "WEIGHT_SCALE", "EfrosLeungTrace", "QuiltLayout", "PixelMatches",
           "ParametricResult", "EfrosLeungResult", "QuiltResult", "TransferResult", "TexturedMesh", "QueryWindow",
           "WindowMatch", "OverlapPair", "JoinedBlocks", "pick_query_window", "window_distances", "match_window",
           "pick_overlap", "min_error_cut", "join_blocks", "synthesize_parametric", "synthesize_efros_leung",
           "quilt", "transfer_texture", "wrap_on_mesh", "efros_leung", "efros_leung_reference", "grow_efros_leung",
           "efros_leung_pixel_matches", "image_quilting", "min_error_boundary_cut", "path_cost",
           "overlap_error_surface", "texture_statistics_distance", "seam_score", "match_histogram",
           "build_pyramid", "collapse_pyramid", "gaussian_window", "integer_gaussian", "sample_levels",
           "onion_layer", "candidates_within", "pick_candidate", "luminance", "parametric_surface",
           "sample_texture", "textured_trimesh", "correspondence_map", "cut_segments"]
