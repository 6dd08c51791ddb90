"""Texture samples: scikit-image's brick, grass and gravel, a user's image file, and procedural textures.

Every loader returns ``Loaded(state={"sample": Image, "transfer_target": Image}, truth=...)``:
``sample`` is the texture to make more of, ``transfer_target`` the picture that texture transfer
(Efros & Freeman 2001, section 4) redraws with it, of the same kind as the sample (grayscale with
a grayscale sample, colour with a colour one). The procedural textures are drawn from processes with
known statistics, given as truth: ``mean`` and ``std`` of the pixel values (and ``period_px`` /
``orientation_deg`` of the stripes), so an evaluation can say how far a synthesized texture is
from the process it should imitate.
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

import numpy as np

from lab.core import Image, InvalidValue, Loaded, Range

#: The scikit-image textures (``skimage.data``, 512 x 512 grayscale, offline in the wheel).
SKIMAGE_TEXTURES = ("brick", "grass", "gravel")

Target = Literal["camera", "gradient", "rings"]


def _resize(pixels: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize with ``cv2.resize`` (area averaging when shrinking, linear when growing), float32."""
    import cv2

    shrinking = height <= pixels.shape[0] and width <= pixels.shape[1]
    out = cv2.resize(pixels.astype(np.float32), (width, height),
                     interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _centre_crop(pixels: np.ndarray, size: int) -> np.ndarray:
    height, width = pixels.shape[:2]
    size = min(size, height, width)
    top, left = (height - size) // 2, (width - size) // 2
    return pixels[top:top + size, left:left + size]


def transfer_target(kind: Target, size: int, *, colour: bool) -> Image:
    """A picture for texture transfer, ``size`` x ``size``: scikit-image's camera man, a gradient or rings.

    Grayscale ``(size, size)`` unless ``colour`` (then the gray picture in three equal channels, so
    that sample and target are of one kind).
    """
    from skimage import data

    ramp = np.linspace(0.0, 1.0, size, dtype=np.float32)
    if kind == "camera":
        gray = _resize(data.camera().astype(np.float32) / 255.0, size, size)
    elif kind == "gradient":
        gray = 0.5 * (ramp[None, :] + ramp[:, None])
    elif kind == "rings":
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        radius = np.hypot(yy - (size - 1) / 2, xx - (size - 1) / 2)
        gray = 0.5 + 0.5 * np.cos(2 * np.pi * radius / max(size / 4.0, 2.0))
    else:
        raise InvalidValue("target", f"unknown transfer target {kind!r}; targets are camera, gradient, rings")
    gray = np.clip(gray, 0.0, 1.0).astype(np.float32)
    pixels = np.repeat(gray[:, :, None], 3, axis=2) if colour else gray
    return Image(pixels, name=f"{kind} (transfer target)")


def _skimage_texture(name: str, size: int, downsample: int, target: Target, target_size: int) -> Loaded:
    from skimage import data

    full = getattr(data, name)().astype(np.float32) / 255.0
    factor = int(downsample)
    if factor > 1:
        full = _resize(full, full.shape[0] // factor, full.shape[1] // factor)
    sample = _centre_crop(full, int(size))
    return Loaded(state={"sample": Image(sample, name=name),
                         "transfer_target": transfer_target(target, int(target_size), colour=False)},
                  description=f"scikit-image's {name} texture, {sample.shape[1]} x {sample.shape[0]} "
                              f"(downsampled {factor}x, centre crop), grayscale")


def brick(*, size: Annotated[int, Range(8, 512)] = 64, downsample: Annotated[int, Range(1, 8)] = 2,
          target: Target = "camera", target_size: Annotated[int, Range(16, 512)] = 96) -> Loaded:
    """A brick wall (``skimage.data.brick()``, 512 x 512 gray): a near-regular texture.

    Args:
        size: side of the square sample, cut from the centre, in pixels.
        downsample: integer factor the photo is shrunk by (area averaging) before cropping.
        target: the picture texture transfer redraws with the sample.
        target_size: side of the transfer target in pixels.
    """
    return _skimage_texture("brick", size, downsample, target, target_size)


def grass(*, size: Annotated[int, Range(8, 512)] = 64, downsample: Annotated[int, Range(1, 8)] = 2,
          target: Target = "camera", target_size: Annotated[int, Range(16, 512)] = 96) -> Loaded:
    """Grass (``skimage.data.grass()``, 512 x 512 gray): a stochastic texture of oriented blades.

    Args:
        size: side of the square sample, cut from the centre, in pixels.
        downsample: integer factor the photo is shrunk by (area averaging) before cropping.
        target: the picture texture transfer redraws with the sample.
        target_size: side of the transfer target in pixels.
    """
    return _skimage_texture("grass", size, downsample, target, target_size)


def gravel(*, size: Annotated[int, Range(8, 512)] = 64, downsample: Annotated[int, Range(1, 8)] = 2,
           target: Target = "camera", target_size: Annotated[int, Range(16, 512)] = 96) -> Loaded:
    """Gravel (``skimage.data.gravel()``, 512 x 512 gray): a stochastic texture of stones.

    Args:
        size: side of the square sample, cut from the centre, in pixels.
        downsample: integer factor the photo is shrunk by (area averaging) before cropping.
        target: the picture texture transfer redraws with the sample.
        target_size: side of the transfer target in pixels.
    """
    return _skimage_texture("gravel", size, downsample, target, target_size)


def image_file(*, path: str, max_size: Annotated[int, Range(8, 1024)] = 128, target: Target = "camera",
               target_size: Annotated[int, Range(16, 512)] = 96) -> Loaded:
    """A user's image file as the sample (any format ``cv2.imread`` reads), shrunk to at most ``max_size``.

    A browser or a script can also upload an image as the state value ``sample`` of any session.

    Args:
        path: the image file.
        max_size: the longer side is shrunk (area averaging) to at most this many pixels.
        target: the picture texture transfer redraws with the sample (made colour for a colour sample).
        target_size: side of the transfer target in pixels.
    """
    from lab.data.files import read_working_images

    path = os.path.expanduser(str(path))
    if not path or not os.path.isfile(path):
        raise InvalidValue("path", f"no image file {path!r}")
    (image,) = read_working_images([path], max_side=int(max_size)).images
    pixels = image.pixels
    colour = pixels.ndim == 3
    return Loaded(state={"sample": Image(pixels, name=os.path.basename(path)),
                         "transfer_target": transfer_target(target, int(target_size), colour=colour)},
                  description=f"{os.path.basename(path)}, {pixels.shape[1]} x {pixels.shape[0]}, "
                              f"{'colour' if colour else 'grayscale'}")


Pattern = Literal["noise", "blobs", "stripes", "dots"]


def procedural_pixels(pattern: str, size: int, rng: np.random.Generator, *, period_px: float = 8.0,
                      orientation_deg: float = 30.0) -> tuple[np.ndarray, dict[str, float]]:
    """One realisation ``(size, size)`` of a texture process in [0, 1], and the process's true statistics.

    - ``noise``: i.i.d. Gaussian, mean 0.5, std 0.15 (flat spectrum: nothing to copy but the histogram).
    - ``blobs``: white noise low-passed by a Gaussian of sigma 2 px, rescaled to mean 0.5, std 0.15.
    - ``stripes``: ``0.5 + 0.35 sin(2 pi (x cos t + y sin t) / period + phase)``, std 0.35 / sqrt 2.
    - ``dots``: disks of radius 2 px at Poisson-distributed centres (density 1 per 64 px^2), value
      0.85 on 0.15.
    """
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    truth: dict[str, float]
    if pattern == "noise":
        pixels = 0.5 + 0.15 * rng.standard_normal((size, size))
        truth = {"mean": 0.5, "std": 0.15}
    elif pattern == "blobs":
        from scipy.ndimage import gaussian_filter

        field = gaussian_filter(rng.standard_normal((size, size)), 2.0, mode="wrap")
        # the std of unit white noise blurred by sigma 2: 1 / sqrt(4 pi sigma^2)
        field /= np.sqrt(1.0 / (16.0 * np.pi))
        pixels = 0.5 + 0.15 * field
        truth = {"mean": 0.5, "std": 0.15}
    elif pattern == "stripes":
        angle = np.deg2rad(orientation_deg)
        phase = rng.uniform(0.0, 2 * np.pi)
        along = xx * np.cos(angle) + yy * np.sin(angle)
        pixels = 0.5 + 0.35 * np.sin(2 * np.pi * along / period_px + phase)
        truth = {"mean": 0.5, "std": 0.35 / np.sqrt(2.0), "period_px": float(period_px),
                 "orientation_deg": float(orientation_deg)}
    elif pattern == "dots":
        count = rng.poisson(size * size / 64.0)
        centres = rng.uniform(0, size, (count, 2))
        pixels = np.full((size, size), 0.15)
        for cy, cx in centres:
            pixels[(yy - cy) ** 2 + (xx - cx) ** 2 <= 4.0] = 0.85
        coverage = 1.0 - np.exp(-np.pi * 4.0 / 64.0)  # Boolean model: share of the plane under some disk
        mean = 0.15 + 0.7 * coverage
        truth = {"mean": float(mean), "std": float(0.7 * np.sqrt(coverage * (1 - coverage)))}
    else:
        raise InvalidValue("pattern", f"unknown pattern {pattern!r}; "
                                      "patterns are noise, blobs, stripes, dots")
    return np.clip(pixels, 0.0, 1.0).astype(np.float32), truth


def procedural(*, pattern: Pattern = "blobs", size: Annotated[int, Range(8, 512)] = 48, colour: bool = False,
               period_px: Annotated[float, Range(2.0, 128.0)] = 8.0,
               orientation_deg: Annotated[float, Range(-180.0, 180.0)] = 30.0,
               target: Target = "gradient", target_size: Annotated[int, Range(16, 512)] = 64,
               quantize: Annotated[int, Range(0, 256)] = 0,
               seed: Annotated[int, Range(0, 2**31 - 1)] = 0) -> Loaded:
    """A procedural texture with known statistics (truth: ``mean``, ``std``; stripes also ``period_px`` and
    ``orientation_deg``).

    Patterns: Gaussian ``noise``, low-passed ``blobs``, sinusoidal ``stripes``, Poisson ``dots``
    (see :func:`procedural_pixels`). With ``colour`` the three channels are independent draws of
    the same process (for noise, blobs and dots) or the stripes tinted.

    Args:
        pattern: the texture process.
        size: side of the square sample in pixels.
        colour: make a colour sample (three channels).
        period_px: period of the stripes in pixels.
        orientation_deg: direction of the stripes' wave vector, degrees from the x axis.
        target: the picture texture transfer redraws with the sample.
        target_size: side of the transfer target in pixels.
        quantize: round every pixel value to a multiple of ``1 / quantize`` (0: keep them continuous).
            With a power of two every squared difference of two pixels, and every sum of them, is
            exact in floating point, so paths of equal error tie exactly, as they do often in 8-bit
            photographs (the brick texture's overlaps): data that exercises a tie rule. The truth
            stays the continuous process's statistics.
        seed: seed of the random draw.
    """
    rng = np.random.default_rng(int(seed))
    size = int(size)
    gray, truth = procedural_pixels(pattern, size, rng, period_px=float(period_px),
                                    orientation_deg=float(orientation_deg))
    if colour:
        if pattern == "stripes":
            tint = np.array([1.0, 0.8, 0.6], dtype=np.float32)
            pixels = np.clip(0.5 + (gray[:, :, None] - 0.5) * tint, 0, 1)
            truth = {**truth, "std": float(truth["std"] * np.sqrt(np.mean(tint ** 2)))}
        else:
            channels = [gray] + [procedural_pixels(pattern, size, rng)[0] for _ in range(2)]
            pixels = np.stack(channels, axis=2)
    else:
        pixels = gray
    rounded = ""
    if int(quantize):
        pixels = np.clip(np.rint(pixels * int(quantize)) / int(quantize), 0.0, 1.0)
        rounded = f", values rounded to multiples of 1/{int(quantize)}"
    return Loaded(state={"sample": Image(pixels.astype(np.float32), name=f"{pattern}"),
                         "transfer_target": transfer_target(target, int(target_size), colour=bool(colour))},
                  truth=truth,
                  description=f"procedural {pattern}, {size} x {size}, "
                              f"{'colour' if colour else 'grayscale'}{rounded}, seed {seed}")


__all__ = ["SKIMAGE_TEXTURES", "brick", "grass", "gravel", "image_file", "procedural", "procedural_pixels",
           "transfer_target"]
