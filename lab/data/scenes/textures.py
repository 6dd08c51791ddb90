"""Textures for the synthetic scenes: images with a mip-map pyramid, photos and procedural patterns.

A :class:`Texture` is an ``(h, w, 3)`` float32 RGB image in [0, 1] that tiles the plane of texture
coordinates ``(u, v)``: ``u = 1`` is one texture width to the right, ``v = 1`` one height down, and
texel ``(i, j)`` (row, column) is centred at ``((j + 0.5) / w, (i + 0.5) / h)``. It is sampled
with bilinear filtering (``cv2.remap``, ``INTER_LINEAR``, wrapping at the border) on a mip-map
pyramid (``cv2.pyrDown``), blending the two levels nearest the sample's footprint (trilinear
filtering), so that a distant, minified surface is averaged instead of aliased.

Reference: L. Williams, "Pyramidal parametrics", SIGGRAPH 1983 (mip-mapping); K. Perlin, "An
image synthesizer", SIGGRAPH 1985 (multi-scale noise, here value noise: random lattices resized
with bicubic interpolation and summed over octaves).

Photos come from scikit-image's sample data shipped inside the wheel (``skimage.data``: brick,
grass, gravel, astronaut, coffee, chelsea, rocket, ... -- :data:`PHOTO_NAMES`); nothing is
downloaded. Procedural textures (:func:`noise_texture`, :func:`shapes_texture`,
:func:`wood_texture`) are deterministic per seed and are made to carry structure at every scale,
so that SIFT finds thousands of distinctive features on a view.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import cv2
import numpy as np

from lab.core.errors import InvalidValue, UnknownName

#: scikit-image sample images that load without network access (they ship in the wheel).
PHOTO_NAMES: tuple[str, ...] = ("astronaut", "brick", "camera", "cat", "chelsea", "coffee", "coins", "grass",
                                "gravel", "hubble_deep_field", "immunohistochemistry", "moon", "rocket")

#: cv2.remap refuses maps with a side of 32767 or more; samples are laid out in rows of this width.
_REMAP_ROW = 4096


@dataclass(frozen=True, eq=False)
class Texture:
    """An RGB image that tiles texture space, with its mip-map pyramid (see the module docstring).

    ``image`` is ``(h, w, 3)`` float32 in [0, 1] (uint8, ``(h, w)`` grey or ``(h, w, 4)`` RGBA are
    converted); ``name`` says where it comes from.
    """

    image: np.ndarray
    name: str = ""
    levels: tuple[np.ndarray, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        image = as_rgb(self.image, "texture")
        if min(image.shape[:2]) < 2:
            raise InvalidValue("texture", f"a texture needs at least 2 x 2 texels, got {image.shape[:2]}")
        levels = [image]
        while min(levels[-1].shape[:2]) >= 8:
            levels.append(cv2.pyrDown(levels[-1], borderType=cv2.BORDER_WRAP))
        for level in levels:
            level.setflags(write=False)
        object.__setattr__(self, "image", image)
        object.__setattr__(self, "levels", tuple(levels))

    def sample(self, uv: np.ndarray, footprint: np.ndarray | None = None) -> np.ndarray:
        """Colours ``(N, 3)`` float32 at texture coordinates ``uv`` ``(N, 2)`` (wrapping).

        ``footprint`` ``(N,)`` is the size of each sample in texture units (the distance between
        neighbouring samples on the surface, times texture tiles per metre); it selects the mip
        level ``log2(footprint * max(w, h))`` and the two nearest levels are blended linearly.
        None samples the full-resolution image (plain bilinear filtering).
        """
        uv = np.mod(np.asarray(uv, dtype=np.float64).reshape(-1, 2), 1.0).astype(np.float32)  # one tile
        out = np.zeros((len(uv), 3), dtype=np.float32)
        if len(uv) == 0:
            return out
        if footprint is None:
            return self._bilinear(0, uv)
        texels = np.asarray(footprint, dtype=np.float64).reshape(-1) * max(self.image.shape[:2])
        level = np.clip(np.log2(np.maximum(texels, 1e-12)), 0.0, len(self.levels) - 1.0).astype(np.float32)
        for index in range(int(level.min()), min(int(np.ceil(level.max())), len(self.levels) - 1) + 1):
            weight = np.maximum(1.0 - np.abs(level - index), 0.0)  # the linear "hat" around each level
            if weight.max() > 1e-3:
                out += weight[:, None] * self._bilinear(index, uv)
        return out

    def _bilinear(self, index: int, uv: np.ndarray) -> np.ndarray:
        """Bilinear lookup in mip level ``index`` at ``uv`` ``(N, 2)`` in [0, 1): ``cv2.remap`` with
        wrap-around."""
        level = self.levels[index]
        h, w = level.shape[:2]
        n = len(uv)
        rows = -(-n // _REMAP_ROW)
        map_x = np.zeros(rows * _REMAP_ROW, dtype=np.float32)
        map_y = np.zeros(rows * _REMAP_ROW, dtype=np.float32)
        np.multiply(uv[:, 0], np.float32(w), out=map_x[:n])
        np.multiply(uv[:, 1], np.float32(h), out=map_y[:n])
        map_x[:n] -= 0.5  # texel centres at half-integers; -0.5 wraps to the last column
        map_y[:n] -= 0.5
        sampled = cv2.remap(level, map_x.reshape(rows, _REMAP_ROW), map_y.reshape(rows, _REMAP_ROW),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return sampled.reshape(-1, 3)[:n]


def as_rgb(image: object, name: str) -> np.ndarray:
    """An image as contiguous ``(h, w, 3)`` float32 in [0, 1]: uint8 is scaled, grey replicated, alpha
    dropped."""
    array = np.asarray(image)
    if array.dtype == np.bool_:
        array = array.astype(np.float32)
    elif array.dtype == np.uint8:
        array = array.astype(np.float32) / 255.0
    elif array.dtype.kind in "iu":
        raise InvalidValue(name, f"integer images must be uint8, got {array.dtype}")
    array = np.asarray(array, dtype=np.float32)
    if array.ndim == 2:
        array = np.repeat(array[:, :, None], 3, axis=2)
    if array.ndim != 3 or array.shape[2] not in (3, 4):
        raise InvalidValue(name, f"expected an (h, w, 3) RGB image, got shape {array.shape}")
    array = array[:, :, :3]
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite values")
    return np.ascontiguousarray(np.clip(array, 0.0, 1.0))


def as_texture(value: object, name: str = "texture") -> Texture | None:
    """None, a :class:`Texture`, or an image array (made into a Texture)."""
    if value is None or isinstance(value, Texture):
        return value
    return Texture(as_rgb(value, name))


# --- photos ---------------------------------------------------------------------------------------------
def photo(name: str) -> np.ndarray:
    """A scikit-image sample photo as ``(h, w, 3)`` float32 in [0, 1] (grey ones replicated), read-only.

    Only :data:`PHOTO_NAMES` are offered: they ship inside the scikit-image wheel, so nothing is
    downloaded. Raises :class:`UnknownName` for any other name. Decoded once per process.
    """
    if name not in PHOTO_NAMES:
        raise UnknownName("photo", f"unknown photo {name!r}; photos are {list(PHOTO_NAMES)}")
    return _decoded_photo(name)


@cache
def _decoded_photo(name: str) -> np.ndarray:
    import skimage.data

    image = as_rgb(getattr(skimage.data, name)(), "photo")
    image.setflags(write=False)
    return image


def fit(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Crop ``image`` to the aspect ratio ``width : height`` (centred), then resize it to that size
    (``INTER_AREA``)."""
    h, w = image.shape[:2]
    scale = min(w / width, h / height)
    cw, ch = max(1, round(width * scale)), max(1, round(height * scale))
    x0, y0 = (w - cw) // 2, (h - ch) // 2
    return cv2.resize(np.ascontiguousarray(image[y0:y0 + ch, x0:x0 + cw]), (width, height),
                      interpolation=cv2.INTER_AREA)


def tinted(grey: np.ndarray, color: tuple[float, float, float], *, contrast: float = 1.0) -> np.ndarray:
    """A grey image ``(h, w)`` (or the grey of an RGB one) coloured:
    ``color * (1 + 2 contrast (g - mean(g)))``."""
    g = np.asarray(grey, dtype=np.float32)
    if g.ndim == 3:
        g = g.mean(axis=2)
    g = 1.0 + contrast * (g - g.mean()) * 2.0
    return np.clip(g[:, :, None] * np.asarray(color, dtype=np.float32), 0.0, 1.0).astype(np.float32)


def atlas(images: list[np.ndarray], *, cell: int = 256, columns: int = 3) -> np.ndarray:
    """Images laid out in a grid of ``columns`` cells of ``cell x cell`` texels (each fitted, row by row)."""
    rows = -(-len(images) // columns)
    out = np.zeros((rows * cell, columns * cell, 3), dtype=np.float32)
    for k, image in enumerate(images):
        r, c = divmod(k, columns)
        out[r * cell:(r + 1) * cell, c * cell:(c + 1) * cell] = fit(as_rgb(image, "image"), cell, cell)
    return out


# --- procedural textures --------------------------------------------------------------------------------
def noise_texture(width: int, height: int, *, seed: int, octaves: int = 7, coarsest: int = 4,
                  persistence: float = 0.7, colors: np.ndarray | None = None,
                  saturation: float = 0.6) -> np.ndarray:
    """Multi-scale value noise, ``(height, width, 3)`` float32 in [0, 1] (Perlin 1985, value-noise variant).

    Octave ``o`` is a random RGB lattice of ``coarsest * 2^o`` cells along the longer side,
    weighted by ``persistence^o``; octaves are summed coarse to fine, the running sum upsampled
    by bicubic interpolation to each finer lattice (and finally to the texture size); the sum
    is normalized to mean 0.5 and unit contrast. ``colors`` ``(2, 3)`` maps dark and bright, and
    ``saturation`` mixes per-channel noise with its grey level. Tiles seamlessly only by chance:
    textures are meant to be used once, unrepeated.
    """
    _check_size(width, height)
    rng = np.random.default_rng(seed)
    longest = max(width, height)
    total: np.ndarray | None = None
    for octave in range(octaves):
        cells = coarsest * 2 ** octave
        if cells > longest:
            break
        size = (max(2, round(cells * width / longest)), max(2, round(cells * height / longest)))
        lattice = persistence ** octave * rng.standard_normal((size[1], size[0], 3)).astype(np.float32)
        # pyramid accumulation: the coarser octaves, already summed, are upsampled once per octave
        total = lattice if total is None else cv2.resize(total, size, interpolation=cv2.INTER_CUBIC) + lattice
    if total is None:
        raise InvalidValue("octaves", f"no octave fits: {octaves} octaves from {coarsest} cells along the "
                                      f"longer side of a {width} x {height} texture")
    total = cv2.resize(total, (width, height), interpolation=cv2.INTER_CUBIC)
    grey = total.mean(axis=2, keepdims=True)
    total = grey + saturation * (total - grey)
    total = (total - total.mean()) / (4.0 * total.std() + 1e-12)
    if colors is None:
        return np.clip(0.5 + total, 0.0, 1.0).astype(np.float32)
    colors = np.asarray(colors, dtype=np.float32).reshape(2, 3)
    level = np.clip(0.5 + total.mean(axis=2, keepdims=True), 0.0, 1.0)
    detail = total - total.mean(axis=2, keepdims=True)
    return np.clip(colors[0] + level * (colors[1] - colors[0]) + 0.5 * detail, 0.0, 1.0).astype(np.float32)


def shapes_texture(width: int, height: int, *, seed: int, count: int = 400, base: np.ndarray | None = None,
                   min_size: float = 0.004, max_size: float = 0.08, opacity: float = 0.85) -> np.ndarray:
    """Random discs, rectangles and triangles of random colours over ``base`` (default: noise).

    ``count`` shapes with sizes log-uniform between ``min_size`` and ``max_size`` of the longer
    side (discs as 48-gons), drawn anti-aliased with ``cv2.fillConvexPoly`` and blended with
    ``opacity``; their corners and blobs are what SIFT and corner detectors find. Drawn in 8 bits
    (``cv2`` anti-aliases only those). Deterministic per seed. Returns ``(height, width, 3)``
    float32 in [0, 1].
    """
    _check_size(width, height)
    rng = np.random.default_rng(seed)
    base = noise_texture(width, height, seed=seed + 1) if base is None else as_rgb(base, "base")
    canvas = np.round(base * 255.0).astype(np.uint8)  # cv2 anti-aliases only 8-bit drawings
    longest = max(width, height)
    shift = 4  # sub-pixel precision bits of the cv2 drawing functions
    scale = float(1 << shift)
    for _ in range(count):
        size = longest * np.exp(rng.uniform(np.log(min_size), np.log(max_size)))
        centre = rng.uniform([0, 0], [width, height])
        colour = tuple(float(c) for c in rng.uniform(0.0, 255.0, 3))
        kind = rng.integers(3)
        if kind == 0:
            angles = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
            radii = np.full(48, size / 2)
        else:
            corners = 3 if kind == 2 else 4
            angles = rng.uniform(0, 2 * np.pi) + np.arange(corners) * 2 * np.pi / corners \
                + rng.uniform(-0.3, 0.3, corners)
            radii = size / 2 * rng.uniform(0.6, 1.0, corners)
        points = centre + np.stack([np.cos(angles), np.sin(angles)], axis=1) * radii[:, None]
        x0, y0 = np.maximum(np.floor(points.min(axis=0)).astype(int) - 2, 0)
        x1, y1 = np.minimum(np.ceil(points.max(axis=0)).astype(int) + 2, (width, height))
        if x1 <= x0 or y1 <= y0:
            continue
        region = canvas[y0:y1, x0:x1]
        layer = region.copy()
        cv2.fillConvexPoly(layer, np.round((points - (x0, y0)) * scale).astype(np.int32), colour, cv2.LINE_AA,
                           shift)
        canvas[y0:y1, x0:x1] = cv2.addWeighted(layer, opacity, region, 1.0 - opacity, 0.0)
    return canvas.astype(np.float32) / 255.0


def wood_texture(width: int, height: int, *, seed: int, rings: float = 14.0,
                 light: tuple[float, float, float] = (0.78, 0.58, 0.36),
                 dark: tuple[float, float, float] = (0.45, 0.28, 0.14)) -> np.ndarray:
    """Wood grain: rings around a far-away axis, warped by multi-scale noise, with fine noise on top.

    ``rings`` is the number of growth rings across the height. Returns ``(height, width, 3)``
    float32 in [0, 1], deterministic per seed.
    """
    _check_size(width, height)
    stretched = noise_texture(max(2, width // 6), height, seed=seed, octaves=5, saturation=0.0)[:, :, 0] - 0.5
    warp = cv2.resize(stretched, (width, height), interpolation=cv2.INTER_CUBIC)  # grain runs along x
    fine = noise_texture(width, height, seed=seed + 7, coarsest=32, octaves=5, saturation=0.3) - 0.5
    y = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    x = np.linspace(0.0, 1.0, width, dtype=np.float32)[None, :]
    phase = rings * (y + 0.05 * np.sin(2.0 * np.pi * x * 1.3) + 0.15 * warp)
    grain = (0.5 + 0.5 * np.cos(2.0 * np.pi * phase)) ** 2
    colour = np.asarray(dark, np.float32) + grain[:, :, None] * (np.asarray(light, np.float32)
                                                                 - np.asarray(dark, np.float32))
    return np.clip(colour + 0.3 * fine, 0.0, 1.0).astype(np.float32)


def _check_size(width: int, height: int) -> None:
    if int(width) < 2 or int(height) < 2:
        raise InvalidValue("size", f"a texture needs at least 2 x 2 texels, got {width} x {height}")


__all__ = ["PHOTO_NAMES", "Texture", "as_rgb", "as_texture", "atlas", "fit", "noise_texture", "photo",
           "shapes_texture", "tinted", "wood_texture"]
