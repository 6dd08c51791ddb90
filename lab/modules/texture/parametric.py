"""Heeger–Bergen's parametric synthesis: an oriented pyramid, histogram matching, the synthesis loop.

D. J. Heeger and J. R. Bergen, "Pyramid-based texture analysis/synthesis", SIGGRAPH 1995: section 3
(histogram matching), section 4 (the pyramid), section 5 (the loop), section 6 (colour through a
principal-components colour space).
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from lab.modules.texture._common import as_hwc, channel_count, from_hwc


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


def _orientation_masks(shape: tuple[int, ...], orientations: int) -> list[np.ndarray]:
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
    """An oriented Laplacian pyramid of a 2D image: ``levels * orientations`` bands, then the low-pass
    residual.

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
        gaussian = np.asarray(smaller, dtype=np.float64)
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


def colour_basis(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(C,)`` and orthonormal principal axes ``(C, C)`` of the pixel colours (Heeger & Bergen
    section 6)."""
    flat = as_hwc(pixels).reshape(-1, channel_count(pixels))
    mean = flat.mean(axis=0)
    _, _, vt = np.linalg.svd(flat - mean, full_matrices=False)
    return mean, vt.T


def heeger_bergen(sample: np.ndarray, size: tuple[int, int], *, levels: int, orientations: int,
                  iterations: int, rng: np.random.Generator,
                  ) -> Generator[tuple[int, np.ndarray], None, np.ndarray]:
    """Heeger–Bergen's loop on ``sample`` ``(h, w[, 3])``: yields (iteration, image so far), returns the
    image.

    Noise with the sample's histogram, then per iteration and per decorrelated colour channel:
    build the pyramid, match every band's histogram to the sample's band, collapse, match the pixel
    histogram (section 5). Images are ``(height, width[, 3])`` float32 in [0, 1].
    """
    height, width = size
    channels = channel_count(sample)
    mean, axes = colour_basis(sample)
    decorrelated = (as_hwc(sample).reshape(-1, channels) - mean) @ axes
    sample_channels = [decorrelated[:, c].reshape(sample.shape[0], sample.shape[1]) for c in range(channels)]
    sample_bands = [build_pyramid(s, levels=levels, orientations=orientations) for s in sample_channels]
    current = [match_histogram(rng.standard_normal((height, width)), s) for s in sample_channels]

    def image_of(channels_now: list[np.ndarray]) -> np.ndarray:
        stacked = np.stack(channels_now, axis=2).reshape(-1, channels) @ axes.T + mean
        return np.clip(from_hwc(stacked.reshape(height, width, channels), channels), 0, 1).astype(np.float32)

    for iteration in range(int(iterations)):
        for c in range(channels):
            bands = build_pyramid(current[c], levels=levels, orientations=orientations)
            matched = [match_histogram(band, ref) for band, ref in zip(bands, sample_bands[c], strict=True)]
            collapsed = collapse_pyramid(matched, orientations=orientations)
            current[c] = match_histogram(collapsed, sample_channels[c])
        yield iteration + 1, image_of(current)
    return image_of(current)
