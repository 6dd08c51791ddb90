"""The texture pipeline's steps, in order: the lesson's pieces of Efros–Leung (a query window, its
distances to the sample, the match) and of quilting (an overlap, its cut, the joined blocks), then the
three syntheses, texture transfer and the texture on a mesh.

The math lives beside: :mod:`~lab.modules.texture.efros_leung`, :mod:`~lab.modules.texture.quilting`,
:mod:`~lab.modules.texture.parametric`, :mod:`~lab.modules.texture.transfer`,
:mod:`~lab.modules.texture.mesh`; the metrics in :mod:`~lab.modules.texture.evaluate`.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Image, InvalidControl, InvalidValue, Mesh, Points2D, Progress, Range, Segments2D, metric
from lab.core.step import step_result
from lab.modules.texture._common import (Size, as_hwc, as_image, channel_count, check_block, check_size,
                                         check_window, from_hwc, relay)
from lab.modules.texture.efros_leung import (EfrosLeungTrace, candidates_within, gaussian_window,
                                             grow_efros_leung)
from lab.modules.texture.evaluate import quantiles, seam_score, texture_statistics_distance
from lab.modules.texture.mesh import parametric_surface, sample_texture
from lab.modules.texture.parametric import heeger_bergen
from lab.modules.texture.quilting import (QuiltLayout, cut_segments, min_error_boundary_cut,
                                          overlap_error_surface, path_cost, quilt_blocks)
from lab.modules.texture.reference import fill_layer_reference
from lab.modules.texture.transfer import correspondence_map, transfer_passes


# ----------------------------------------------------------------------------------------------------
# Efros–Leung, one pixel: a query window, its distance to every sample window, the match
# ----------------------------------------------------------------------------------------------------
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
    sample = as_image(sample, "sample")
    w = check_window(window, sample)
    top = int(rng.integers(0, sample.height - w + 1))
    left = int(rng.integers(0, sample.width - w + 1))
    mask = rng.random((w, w)) < known_fraction
    mask[w // 2, w // 2] = False
    if not mask.any():
        mask[w // 2, w // 2 - 1 if w > 1 else 0] = True
    query = as_hwc(sample.pixels)[top:top + w, left:left + w] * mask[:, :, None]
    return QueryWindow(from_hwc(query, channel_count(sample.pixels)).copy(), mask,
                       np.array([top, left], dtype=np.int64), int(mask.sum()))


def _check_query(sample: Image, query_window: Any, query_mask: Any) -> tuple[np.ndarray, np.ndarray]:
    query = np.asarray(query_window, dtype=np.float64)
    mask = np.asarray(query_mask)
    if query.ndim not in (2, 3) or query.shape[0] != query.shape[1]:
        raise InvalidValue("query_window", f"a window is (w, w) or (w, w, C), got shape {query.shape}")
    if channel_count(query) != channel_count(sample.pixels):
        raise InvalidValue("query_window", f"has {channel_count(query)} channel(s) but the sample "
                                           f"{channel_count(sample.pixels)}: grayscale and colour do not "
                                           "compare")
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
    sample = as_image(sample, "sample")
    query, mask = _check_query(sample, query_window, query_mask)
    w = query.shape[0]
    weights = (gaussian_window(w) if weighting == "gaussian" else np.ones((w, w))) * mask
    windows = np.lib.stride_tricks.sliding_window_view(as_hwc(sample.pixels), (w, w), axis=(0, 1))
    # windows: (h - w + 1, ws - w + 1, C, w, w); SSD expanded: sum g (q^2 - 2 q s + s^2)
    q = np.moveaxis(as_hwc(query), 2, 0)  # (C, w, w)
    constant = float((weights * (q ** 2)).sum())
    cross = np.einsum("ijcab,cab->ij", windows, weights * q, optimize=True)
    squares = np.einsum("ijcab,ab->ij", windows ** 2, weights, optimize=True)
    distances = np.maximum(constant - 2.0 * cross + squares, 0.0)
    return distances / weights.sum() if normalize else distances


@step_result
class WindowMatch:
    """Result of :func:`match_window`."""

    match_candidates: Points2D
    chosen_match: np.ndarray
    best_distance: float = metric("distance of the best window")
    candidates: int = metric("windows within (1 + epsilon) of the best")


#: Negative distances down to this share of the largest distance are rounding, not a mistake: an
#: expanded SSD (``q^2 - 2 q s + s^2``) in float64 is off by about 1e-16 of it, in float32 (e.g.
#: ``cv2.matchTemplate``) by about 2e-6.
ROUNDING_NEGATIVE = 1e-5


def checked_distances(window_distances: Any) -> np.ndarray:
    """``window_distances`` as a float64 ``(rows, cols)`` array with rounding-level negatives set to 0.

    A weighted sum of squared differences is never negative; a distance computed by expanding the
    square comes out slightly negative where two windows agree (-5.7e-17). Entries down to
    :data:`ROUNDING_NEGATIVE` times the largest ``|distance|`` (or 1e-12) are therefore read as 0;
    anything more negative, NaN or infinity is refused with an :class:`InvalidValue` naming it.
    """
    distances = np.asarray(window_distances, dtype=np.float64)
    if distances.ndim != 2 or distances.size == 0:
        raise InvalidValue("window_distances", f"must be a 2D array (one distance per sample window), got "
                                               f"shape {distances.shape}")
    bad = ~np.isfinite(distances)
    if bad.any():
        raise InvalidValue("window_distances", f"holds {int(np.isnan(distances).sum())} NaN and "
                                               f"{int(np.isinf(distances).sum())} infinite entries of "
                                               f"{distances.size}: every window needs a finite distance")
    smallest = float(distances.min())
    rounding = max(ROUNDING_NEGATIVE * float(np.abs(distances).max()), 1e-12)
    if smallest < -rounding:
        raise InvalidValue("window_distances", f"has negative entries, the smallest {smallest:.3g} (beyond "
                                               f"rounding: -{rounding:.2g}); a weighted sum of squared "
                                               "differences is never negative")
    return np.maximum(distances, 0.0)


def match_window(sample: Image, window_distances: np.ndarray, *,
                 epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1, rng: np.random.Generator) -> WindowMatch:
    """Keep the windows within ``(1 + epsilon)`` of the best and draw one (Efros & Leung 1999, section 2.1).

    Rounding-level negative distances (an expanded SSD's, where the query's own window is compared)
    count as 0; larger negatives, NaN and infinity are refused (:func:`checked_distances`).

    Args:
        epsilon: relative tolerance above the best distance.

    Returns the candidates' centres (``Points2D`` on ``sample``, x = column) and the chosen window's
    top-left ``(row, col)``.
    """
    sample = as_image(sample, "sample")
    distances = checked_distances(window_distances)
    half = (sample.height - distances.shape[0]) // 2
    chosen_flat = candidates_within(distances, epsilon)
    rows, cols = np.unravel_index(chosen_flat, distances.shape)
    pick = int(rng.integers(len(chosen_flat)))
    centres = np.column_stack([cols + half, rows + half]).astype(np.float64)
    return WindowMatch(Points2D(centres, image="sample"), np.array([rows[pick], cols[pick]], dtype=np.int64),
                       float(distances.min()), len(chosen_flat))


# ----------------------------------------------------------------------------------------------------
# Quilting, one seam: two overlapping blocks, the minimum-error cut, the blocks joined along it
# ----------------------------------------------------------------------------------------------------
@step_result
class OverlapPair:
    """Result of :func:`pick_overlap`."""

    overlap_left: Image
    overlap_right: Image
    overlap_error: np.ndarray
    overlap_mean_error: float = metric("mean squared difference in the overlap")


def pick_overlap(sample: Image, *, block: Annotated[int, Range(2, 256)] = 24,
                 overlap: Annotated[int, Range(1, 128)] = 6, rng: np.random.Generator) -> OverlapPair:
    """Two random blocks of the sample side by side, overlapping by ``overlap`` columns, and their error
    surface.

    ``overlap_error`` ``(block, overlap)``: the squared difference of the left block's last
    ``overlap`` columns and the right block's first ones, summed over colour (Efros & Freeman
    2001, section 2.1: the surface the minimum-error cut runs through).

    Args:
        block: side of the square blocks in pixels.
        overlap: width of the overlap in pixels.
    """
    sample = as_image(sample, "sample")
    block, overlap = check_block(block, overlap, sample)
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
        raise InvalidValue("cut_path", f"columns must lie in the overlap, 0 to {cols - 1}; got {path.min()} "
                                       f"to {path.max()}")
    return path


def join_blocks(overlap_left: Image, overlap_right: Image, overlap_error: np.ndarray,
                cut_path: np.ndarray) -> JoinedBlocks:
    """Join two overlapping blocks along a cut: the left block left of it, the right block from it on.

    Returns the joined image ``(block, 2 block - overlap[, 3])`` and the cut's cost, its largest step
    and the cost of the best straight (one column) cut, which the boundary cut never exceeds.
    """
    left = as_image(overlap_left, "overlap_left").pixels
    right = as_image(overlap_right, "overlap_right").pixels
    errors = np.asarray(overlap_error, dtype=np.float64)
    rows, overlap = errors.shape
    block = left.shape[1]
    path = _check_path(cut_path, rows, overlap)
    channels = channel_count(left)
    joined = np.zeros((rows, 2 * block - overlap, channels), dtype=np.float32)
    joined[:, :block] = as_hwc(left)
    take_right = np.arange(overlap)[None, :] >= path[:, None]
    region = joined[:, block - overlap:block]
    joined[:, block - overlap:block] = np.where(take_right[:, :, None], as_hwc(right)[:, :overlap], region)
    joined[:, block:] = as_hwc(right)[:, overlap:]
    return JoinedBlocks(Image(from_hwc(joined, channels), name="joined along the cut"),
                        path_cost(errors, path), int(np.abs(np.diff(path)).max()) if rows > 1 else 0,
                        float(errors.sum(axis=0).min()))


# ----------------------------------------------------------------------------------------------------
# The three syntheses
# ----------------------------------------------------------------------------------------------------
@step_result
class ParametricResult:
    """Result of :func:`synthesize_parametric`."""

    parametric: Image
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")
    histogram_error: float = metric("mean absolute difference of pixel quantiles to the sample's",
                                    unit="intensity")


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
    sample = as_image(sample, "sample")
    height, width = check_size(size, smallest=8, what="8 pixels")
    smallest = min(height, width, sample.height, sample.width)
    if 2 ** int(levels) * 2 > smallest:
        raise InvalidControl("levels", f"{levels} levels halve the image {levels} times: the smaller of "
                                       f"sample and output ({smallest} px) allows at most "
                                       f"{max(1, int(math.log2(smallest / 2)))}")
    grower = heeger_bergen(sample.pixels, (height, width), levels=levels, orientations=orientations,
                           iterations=iterations, rng=rng)
    pixels = yield from relay(grower, lambda item: Progress(
        iteration=item[0], total=int(iterations), message="histograms matched",
        values={"parametric": Image(item[1], name="parametric (iterating)")}))
    return ParametricResult(
        parametric=Image(pixels, name="Heeger-Bergen"),
        stat_distance=texture_statistics_distance(pixels, sample.pixels),
        histogram_error=float(np.abs(quantiles(pixels) - quantiles(sample.pixels)).mean()))


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
    sample = as_image(sample, "sample")
    height, width = (int(v) for v in size)
    fill = fill_layer_reference if implementation == "reference" else None  # None: the fast fill_layer
    grower = grow_efros_leung(sample, size=(height, width), window=window, epsilon=epsilon,
                              seed_size=seed_size, rng=rng, fill=fill)
    pixels, trace = yield from relay(grower, lambda item: Progress(
        iteration=item[1], total=height * width, message=f"onion layer {item[0]}",
        values={"efros_leung": Image(item[2], name="Efros-Leung (growing)")}))
    return EfrosLeungResult(Image(pixels, name="Efros-Leung"), trace,
                            stat_distance=texture_statistics_distance(pixels, sample.pixels),
                            seam_score=seam_score(pixels, trace.source, sample.pixels), layers=trace.layers)


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
    sample = as_image(sample, "sample")
    block, overlap = check_block(block, overlap, sample)
    height, width = check_size(size, smallest=block, what="a block")
    channels = channel_count(sample.pixels)
    quilter = quilt_blocks(as_hwc(sample.pixels), (height, width), block, overlap, float(epsilon), mode, rng)
    pixels, source, layout = yield from relay(quilter, lambda item: Progress(
        iteration=item[0], total=item[1], message=f"block {item[0]} of {item[1]}",
        values={"quilting": Image(from_hwc(item[2], channels).astype(np.float32),
                                  name="quilting (growing)")}))
    image = np.clip(from_hwc(pixels, channels), 0, 1).astype(np.float32)
    return QuiltResult(Image(image, name=f"quilting ({mode})"), layout, cut_segments(layout, (height, width)),
                       stat_distance=texture_statistics_distance(image, sample.pixels),
                       seam_score=seam_score(image, source, sample.pixels), blocks=len(layout.positions))


# ----------------------------------------------------------------------------------------------------
# Texture transfer and the texture on a mesh
# ----------------------------------------------------------------------------------------------------
@step_result
class TransferResult:
    """Result of :func:`transfer_texture`."""

    transferred: Image
    correspondence_error: float = metric("mean squared difference of the correspondence maps, output vs "
                                         "target")
    stat_distance: float = metric("texture statistics distance to the sample (0 = the same)")


def transfer_texture(sample: Image, transfer_target: Image, *, block: Annotated[int, Range(3, 128)] = 15,
                     iterations: Annotated[int, Range(1, 5)] = 2,
                     epsilon: Annotated[float, Range(0.0, 1.0)] = 0.1,
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
    sample = as_image(sample, "sample")
    target = as_image(transfer_target, "transfer_target")
    channels = channel_count(sample.pixels)
    if channels != channel_count(target.pixels):
        kinds = {1: "grayscale", 3: "colour"}
        raise InvalidValue("transfer_target", f"the sample is {kinds[channels]} but the target is "
                                              f"{kinds[channel_count(target.pixels)]}: convert one so both "
                                              "are of one kind")
    check_block(int(block), max(1, int(block) // 6), sample)
    check_size((target.height, target.width), smallest=int(block), what="a block")
    passes = transfer_passes(sample.pixels, target.pixels, block=int(block), iterations=int(iterations),
                             epsilon=float(epsilon), rng=rng)
    output = yield from relay(passes, lambda item: Progress(
        iteration=item[0], total=item[1], message=item[2],
        values={"transferred": Image(np.clip(from_hwc(item[3], channels), 0, 1).astype(np.float32),
                                     name="transfer (growing)")}))
    pixels = np.clip(from_hwc(output, channels), 0, 1).astype(np.float32)
    error = float(np.mean((correspondence_map(pixels) - correspondence_map(target.pixels)) ** 2))
    return TransferResult(Image(pixels, name="texture transfer"), error,
                          texture_statistics_distance(pixels, sample.pixels))


@step_result
class TexturedMesh:
    """Result of :func:`wrap_on_mesh`."""

    textured_mesh: Mesh
    mesh_uv: np.ndarray
    vertices: int = metric("vertices of the mesh")


def wrap_on_mesh(sample: Image, parametric: Image | None = None, efros_leung: Image | None = None,
                 quilting: Image | None = None, transferred: Image | None = None, *,
                 texture: Literal["quilting", "efros_leung", "parametric", "transferred",
                                  "sample"] = "quilting",
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
        step = {"parametric": "synthesize_parametric", "efros_leung": "synthesize_efros_leung",
                "quilting": "quilt", "transferred": "transfer_texture"}
        raise InvalidValue(texture, f"there is no {texture!r} texture yet: run step {step[texture]!r} first, "
                                    "or pick another texture")
    image = as_image(chosen, texture)
    vertices, faces, uv = parametric_surface(shape, int(resolution))
    colours = sample_texture(image.pixels, uv, repeats=float(repeats))
    return TexturedMesh(Mesh(vertices, faces, colours), uv, len(vertices))
