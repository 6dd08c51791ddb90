"""The compiled loops of the fast rasterizer: front-to-back compositing per tile, its backward pass, tile
binning, and the projection and colours for rendering without gradients.

They follow the paper's code (Kerbl et al. 2023, ``renderCUDA`` in ``forward.cu`` and ``backward.cu``), one
tile after another instead of one CUDA block per tile. The forward pass computes in the dtype of its inputs
(float32 to train and render, float64 in the tests; its constants come as an array of that dtype,
:func:`kernel_constants`, since a Python float literal would make the arithmetic float64). Within a tile it
goes Gaussian by Gaussian through its depth-sorted list, each pixel keeping its own transmittance, colour,
last contributor and whether it is done, stored in blocks of 8 columns; each Gaussian updates, in the blocks
its ellipse where alpha can reach 1/255 reaches, the rows that ellipse spans
(:func:`footprint_half_extents`), all their pixels in one loop without branches: the per-pixel decisions
(inside the footprint, alpha >= 1/255, T would fall below 1e-4, done) are selects, and the exponential is
written out (:func:`_exp_nonpositive`, a C ``exp`` call would not vectorize), so the compiler runs the loop
on vector lanes, 8 float32 pixels at a time. The per-pixel arithmetic and its order are the paper's
per-pixel loop's. Measured on a trained model (8k Gaussians, 200 x 200, one core): 7.3 ms for the earlier
scalar walk over each row's chord of the ellipse (about 13 ns a visited pixel, mostly mispredicted branches
at the chords' ends and the C ``exp``), 4.2 ms for vectorized whole tile rows although they visit 3.6x as
many pixels, about 13 % less again with the 8-column blocks (28 % fewer lanes). The backward pass walks each
pixel's list back to front from its last contributor over the rows' chords (:func:`_row_span`, the
exact-footprint culling of "StopThePop", Radl et al. 2024, and gsplat's tile intersection, done per row),
recovering ``T_i`` by dividing by ``1 - alpha_i`` and the colour behind each Gaussian as a running sum, as
the paper's code does, with the forward pass's arithmetic for every decision so the two agree on each pixel;
unlike that code, it takes the clamp ``alpha <= 0.99`` into account (no gradient through a clamped alpha:
gsplat does the same), so it is the derivative autograd gives the reference. Gradients are summed per
Gaussian over a tile, then into one buffer per band of tiles (bands run on different threads). Each tile's
list comes packed in list order (:func:`pack_pairs`: reads one after the other instead of gathers), with an
exponent below which a Gaussian's alpha is surely under 1/255.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from lab.core.kernels import kernel, register_warm_up

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
#: Slack on the exponent below which alpha is surely under 1/255: ``o exp(p) < exp(-SLACK) / 255``, far
#: beyond rounding, so the pre-check (which spares most ``exp`` calls) never changes a decision.
SLACK = 1e-3


def alpha_floor_exponents(opacities: np.ndarray) -> np.ndarray:
    """``log(1 / (255 o)) - SLACK`` (N,) float64: an exponent below which a Gaussian of opacity ``o`` has
    alpha surely under 1/255 (positive: everywhere); the ellipse of its footprint is ``d^T conic d <= -2``
    times it."""
    with np.errstate(divide="ignore"):
        return np.log(1.0 / 255.0) - np.log(np.maximum(opacities.astype(np.float64), 1e-300)) - SLACK


def pack_pairs(ids: np.ndarray, means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """``(pairs, 9)`` in the dtype of ``means2d``: per listed Gaussian ``ids[k]`` its mean (2), conic (3),
    opacity, :func:`alpha_floor_exponents` (an exponent below which its alpha is surely under 1/255) and
    :func:`footprint_half_extents` (how far that ellipse reaches from its mean: above and below, left and
    right), laid out in list order so the kernels read them one after the other."""
    skip = alpha_floor_exponents(opacities)
    reach = footprint_half_extents(conics, -2.0 * skip)
    dtype = means2d.dtype
    table = np.concatenate([means2d, conics, opacities[:, None], skip[:, None].astype(dtype),
                            reach.astype(dtype)], axis=1)
    return np.ascontiguousarray(table[ids])


def footprint_half_extents(conics: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """(N, 2) float64: the half-height ``sqrt(limit Sigma_yy)`` and half-width ``sqrt(limit Sigma_xx)`` of
    each ellipse ``d^T conic d <= limit`` (``Sigma = [[c, -b], [-b, a]] / (a c - b^2)``, the conic's
    inverse), widened by a millionth and 1e-3 px so that rounding (float32 included) never leaves a row or
    a column of it out; ``inf`` (everywhere) where the conic is not positive definite in float64 or not
    finite, ``-inf`` (nowhere) for a negative limit."""
    a, b, c = (conics[:, k].astype(np.float64) for k in range(3))
    det = a * c - b * b
    limits = np.asarray(limits, np.float64)
    with np.errstate(all="ignore"):
        reach = np.sqrt(limits[:, None] * np.stack([a, c], axis=1) / det[:, None]) * (1.0 + 1e-6) + 1e-3
        definite = (a > 0.0) & (det > 0.0) & np.isfinite(reach).all(axis=1)
    return np.where((limits < 0.0)[:, None], -np.inf, np.where(definite[:, None], reach, np.inf))


@kernel
def _touches_box(mx: float, my: float, ca: float, cb: float, cc: float, limit: float, x0: float, x1: float,
                 y0: float, y1: float) -> bool:
    """Whether the ellipse ``d^T [[ca, cb], [cb, cc]] d <= limit`` about ``(mx, my)`` (``d = (mx - px,
    my - py)``) reaches the box ``x0 <= px <= x1``, ``y0 <= py <= y1``: the centre is in it, or the convex
    quadratic's least value on one of its four sides (the side's minimizer, clamped to it) is within
    ``limit``. Not positive definite, or not finite: True (the kernels' per-pixel test decides)."""
    if limit < 0.0:
        return False
    if not (ca > 0.0 and cc > 0.0 and ca * cc - cb * cb > 0.0):
        return True
    if x0 <= mx <= x1 and y0 <= my <= y1:
        return True
    best = np.inf
    for edge in (y0, y1):
        dy = my - edge
        dx = min(max(-cb * dy / ca, mx - x1), mx - x0)
        best = min(best, ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy)
    for edge in (x0, x1):
        dx = mx - edge
        dy = min(max(-cb * dx / cc, my - y1), my - y0)
        best = min(best, ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy)
    return not best > limit * (1.0 + 1e-9) + 1e-9       # NaN: True


@kernel
def _bin_kernel(order: np.ndarray, rects: np.ndarray, means2d: np.ndarray, conics: np.ndarray,
                limits: np.ndarray, cull: bool, tile_size: int, width: int, height: int, tiles_x: int,
                ranges: np.ndarray, ids: np.ndarray, keep: np.ndarray) -> int:
    """List the Gaussians ``order`` (nearest first) in each tile of their rectangles ``rects`` (N, 4)
    (with ``cull``, only the tiles whose pixel centres their ellipse ``d^T conic d <= limit`` reaches,
    :func:`_touches_box`): a counting sort by tile, so each tile's list keeps the depth order. Fills
    ``ranges`` (tiles, 2) and ``ids[:pairs]`` (``keep``: scratch of the rectangles' total area); returns
    the pairs listed."""
    counts = np.zeros(len(ranges), np.int64)
    n = 0
    for g in order:
        for ty in range(rects[g, 1], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 2]):
                keep[n] = not cull or _touches_box(
                    means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], limits[g],
                    tx * tile_size, min(width, (tx + 1) * tile_size) - 1,
                    ty * tile_size, min(height, (ty + 1) * tile_size) - 1)
                counts[ty * tiles_x + tx] += keep[n]
                n += 1
    total = 0
    for tile in range(len(ranges)):
        ranges[tile, 0] = total
        total += counts[tile]
        ranges[tile, 1] = ranges[tile, 0]
    n = 0
    for g in order:
        for ty in range(rects[g, 1], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 2]):
                if keep[n]:
                    tile = ty * tiles_x + tx
                    ids[ranges[tile, 1]] = g
                    ranges[tile, 1] += 1
                n += 1
    return total


@kernel
def _row_span(mx: float, my: float, ca: float, cb: float, cc: float, limit: float, py: int, x0: int,
              x1: int) -> tuple[int, int]:
    """The pixels ``x0 <= px < x1`` of row ``py`` that may lie in the ellipse ``d^T [[ca, cb], [cb, cc]] d
    <= limit`` about ``(mx, my)``, ``d = (mx - px, my - py)``, as ``(first, stop)`` (first >= stop: none).

    The row's chord solves ``ca dx^2 + 2 cb dy dx + cc dy^2 - limit = 0`` for ``dx``; the span is widened
    to whole pixels (floor and ceil), so it holds every pixel of the ellipse: the per-pixel test decides.
    A conic that is not positive definite in float64 (or not finite) keeps the whole row."""
    if not (ca > 0.0 and ca * cc - cb * cb > 0.0):
        return x0, x1
    dy = my - py
    half_b = cb * dy
    disc = half_b * half_b - ca * (cc * dy * dy - limit)
    if disc < 0.0:
        return x0, x0
    root = np.sqrt(disc)
    low = np.floor(mx - (-half_b + root) / ca)
    high = np.ceil(mx - (-half_b - root) / ca)
    if not (low <= high):               # NaN: keep the row
        return x0, x1
    first = x0 if low < x0 else (x1 if low > x1 else int(low))
    stop = x0 if high + 1.0 < x0 else (x1 if high + 1.0 > x1 else int(high) + 1)
    return first, stop


@kernel
def _row_range(my: float, ca: float, cb: float, cc: float, limit: float, y0: int, y1: int) -> tuple[int, int]:
    """The rows ``y0 <= py < y1`` that the ellipse of :func:`_row_span` may reach, ``(first, stop)``: its
    half-height is ``sqrt(limit Sigma_yy)``, ``Sigma_yy = ca / (ca cc - cb^2)`` (the conic's inverse),
    widened to whole rows. Not positive definite (or not finite): every row."""
    det = ca * cc - cb * cb
    if not (ca > 0.0 and det > 0.0 and limit >= 0.0):
        return y0, y1
    half = np.sqrt(limit * ca / det)
    low, high = np.floor(my - half), np.ceil(my + half)
    if not (low <= high):
        return y0, y1
    first = y0 if low < y0 else (y1 if low > y1 else int(low))
    stop = y0 if high + 1.0 < y0 else (y1 if high + 1.0 > y1 else int(high) + 1)
    return first, stop


@numba.njit(inline="always", nogil=True, cache=True)  # inlined: a call would keep the loop off vector lanes
def _exp_nonpositive(x: float, sixteenth: float, c: tuple) -> float:
    """``exp(x)`` for ``-5.6 <= x <= 0`` (the exponents of a Gaussian's alpha above 1/255), in the dtype of
    ``x``, written out so that the compositing loop around it vectorizes (a call to the C library's
    ``exp`` does not): ``e^y``, ``y = x / 16``, by its Taylor series to degree 13 (Estrin's scheme, the
    coefficients ``c = (1/0!, ..., 1/13!)``), raised to the 16th power by four squarings. Within a few
    1e-15 relative of ``exp`` in float64 (the truncation ``0.35^14 / 14!`` is 5e-18; the squarings
    multiply the rounding by 16), about 1e-6 in float32."""
    y = x * sixteenth
    y2 = y * y
    y4 = y2 * y2
    y8 = y4 * y4
    low = ((c[0] + y * c[1]) + y2 * (c[2] + y * c[3])) + y4 * ((c[4] + y * c[5]) + y2 * (c[6] + y * c[7]))
    high = ((c[8] + y * c[9]) + y2 * (c[10] + y * c[11])) + y4 * (c[12] + y * c[13])
    e = low + y8 * high
    e = e * e
    e = e * e
    e = e * e
    return e * e


def kernel_constants(dtype: type | np.dtype) -> np.ndarray:
    """The compositing's constants (21,) in ``dtype``, so that its arithmetic stays in the dtype of its
    inputs (a Python float literal would make it float64): 0, 1/2, 1, :data:`ALPHA_MAX`, :data:`ALPHA_MIN`,
    :data:`T_MIN`, 1/16, then :func:`_exp_nonpositive`'s fourteen coefficients ``1/k!``."""
    values = [0.0, 0.5, 1.0, ALPHA_MAX, ALPHA_MIN, T_MIN, 1.0 / 16.0]
    return np.array(values + [1.0 / math.factorial(k) for k in range(14)], dtype)


#: Columns of a tile's block (the forward kernel's state is stored block by block, so that a Gaussian updates
#: only the blocks its footprint reaches: 8 float32 lanes of a 256-bit vector).
BLOCK = 8


@kernel
def _rasterize_forward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                              packed: np.ndarray, colors: np.ndarray, background: np.ndarray,
                              constants: np.ndarray, tile_size: int, tiles_x: int, image: np.ndarray,
                              final_t: np.ndarray, n_contrib: np.ndarray) -> None:
    """Composite tiles ``tile_start .. tile_stop`` (row-major) into ``image`` (H, W, 3); ``final_t`` (H, W)
    the transmittance left, ``n_contrib`` (H, W) how far into its tile's list each pixel read (1 past its
    last contributor). ``packed`` (pairs, 9) holds each listed Gaussian's mean, conic, opacity, the
    exponent below which its alpha is surely under 1/255 and the half-height and half-width of that
    ellipse (:func:`pack_pairs`), in list order; ``constants`` is :func:`kernel_constants` of the dtype the
    arithmetic runs in (the inputs').

    Gaussian by Gaussian through the tile's list, each pixel keeping its own transmittance, colour, last
    contributor and whether it is done. The tile's state is stored in blocks of :data:`BLOCK` columns, row
    after row within a block; each Gaussian updates, in each block its ellipse's columns reach, the rows
    its ellipse spans, all their pixels in one branch-free loop (the decisions as selects, so it runs on
    vector lanes), the per-pixel arithmetic and its order the paper's per-pixel loop's. A pixel is done at
    the Gaussian that would take its transmittance below 1e-4, the tile when all its pixels are (the
    padding of a block past the image's edge starts done)."""
    height, width = final_t.shape
    zero, half, one = constants[0], constants[1], constants[2]
    alpha_max, alpha_min, t_min, sixteenth = constants[3], constants[4], constants[5], constants[6]
    c = (constants[7], constants[8], constants[9], constants[10], constants[11], constants[12],
         constants[13], constants[14], constants[15], constants[16], constants[17], constants[18],
         constants[19], constants[20])
    blocks = (tile_size + BLOCK - 1) // BLOCK
    size, dtype = blocks * BLOCK * tile_size, constants.dtype
    # the tile's state, one array each (allocated here: the compiler then knows they do not overlap)
    trans, red, green = np.empty(size, dtype), np.empty(size, dtype), np.empty(size, dtype)
    blue, done = np.empty(size, dtype), np.empty(size, dtype)        # done: 1 once T would fall below 1e-4
    xs, ys, last = np.empty(size, dtype), np.empty(size, dtype), np.empty(size, np.int64)
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        x0, y0 = tx * tile_size, ty * tile_size
        x1, y1 = min(width, x0 + tile_size), min(height, y0 + tile_size)
        th = y1 - y0
        stride = th * BLOCK                          # one block: th rows of BLOCK columns
        alive = (x1 - x0) * th
        for j in range(blocks * stride):
            column = (j // stride) * BLOCK + j % BLOCK
            trans[j], red[j], green[j], blue[j], last[j] = one, zero, zero, zero, 0
            done[j] = zero if x0 + column < x1 else one
            xs[j] = x0 + column
            ys[j] = y0 + (j % stride) // BLOCK
        start, stop = ranges[tile, 0], ranges[tile, 1]
        for k in range(start, stop):
            if alive == 0:
                break
            skip = packed[k, 6]
            if skip > zero:                     # alpha under 1/255 everywhere
                continue
            mx, my, ca, cb, cc, opacity = (packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3],
                                           packed[k, 4], packed[k, 5])
            low, high = np.floor(my - packed[k, 7]), np.ceil(my + packed[k, 7])   # NaN or inf: every row
            first = y0 if not low > y0 else (y1 if low > y1 else int(low))
            after = y1 if not high + 1 < y1 else (y0 if high + 1 < y0 else int(high) + 1)
            low, high = np.floor(mx - packed[k, 8]), np.ceil(mx + packed[k, 8])
            left = x0 if not low > x0 else (x1 if low > x1 else int(low))
            right = x1 if not high + 1 < x1 else (x0 if high + 1 < x0 else int(high) + 1)
            if first >= after or left >= right:
                continue
            i = ids[k]
            red_i, green_i, blue_i = colors[i, 0], colors[i, 1], colors[i, 2]
            order = k - start + 1
            ended = 0
            for block in range((left - x0) // BLOCK, (right - 1 - x0) // BLOCK + 1):
                lo, hi = block * stride + (first - y0) * BLOCK, block * stride + (after - y0) * BLOCK
                # the rows as views from their first pixel (indices from 0: the loop then vectorizes)
                t_, r_, g_, b_ = trans[lo:hi], red[lo:hi], green[lo:hi], blue[lo:hi]
                d_, l_, x_, y_ = done[lo:hi], last[lo:hi], xs[lo:hi], ys[lo:hi]
                for j in range(hi - lo):
                    dx = mx - x_[j]
                    dy = my - y_[j]
                    power = -half * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    inside = (skip <= power) & (power <= zero)
                    G = _exp_nonpositive(power if inside else zero, sixteenth, c)
                    alpha = min(alpha_max, opacity * G)
                    T = t_[j]
                    next_t = T * (one - alpha)
                    live = inside & (alpha >= alpha_min) & (d_[j] == zero)
                    ends = live & (next_t < t_min)
                    used = live & (next_t >= t_min)
                    weight = alpha * T if used else zero
                    r_[j] += red_i * weight
                    g_[j] += green_i * weight
                    b_[j] += blue_i * weight
                    t_[j] = next_t if used else T
                    l_[j] = order if used else l_[j]
                    d_[j] = one if ends else d_[j]
                    ended += 1 if ends else 0
            alive -= ended
        for py in range(y0, y1):
            for px in range(x0, x1):
                j = ((px - x0) // BLOCK) * stride + (py - y0) * BLOCK + (px - x0) % BLOCK
                T = trans[j]
                image[py, px, 0] = red[j] + T * background[0]
                image[py, px, 1] = green[j] + T * background[1]
                image[py, px, 2] = blue[j] + T * background[2]
                final_t[py, px] = T
                n_contrib[py, px] = last[j]


@kernel
def _rasterize_backward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                               packed: np.ndarray, colors: np.ndarray, background: np.ndarray,
                               constants: np.ndarray, tile_size: int, tiles_x: int, final_t: np.ndarray,
                               n_contrib: np.ndarray, grad_image: np.ndarray, grads: np.ndarray) -> None:
    """Add to ``grads`` (N, 9) the gradients of the loss (whose gradient in the image is ``grad_image``)
    with respect to each Gaussian's mean (2), conic (3), colour (3) and opacity (1), over tiles
    ``tile_start .. tile_stop``.

    Gaussian by Gaussian back to front from the tile's last contributor, over its rows' chords of the
    ellipse (:func:`_row_span`, widened by a hundred-thousandth); each pixel keeps its transmittance and
    the colour behind; each Gaussian's gradient is summed over the tile before it is added to ``grads``.
    Which Gaussians a pixel composites is decided by the forward pass's arithmetic (its ``constants``,
    its exponential, the inputs' dtype), so the two passes agree on every pixel; the gradients are
    summed in float64."""
    height, width = final_t.shape
    size = tile_size * tile_size
    zero, half = constants[0], constants[1]
    alpha_max, alpha_min, sixteenth = constants[3], constants[4], constants[6]
    c = (constants[7], constants[8], constants[9], constants[10], constants[11], constants[12],
         constants[13], constants[14], constants[15], constants[16], constants[17], constants[18],
         constants[19], constants[20])
    xs, ys = np.empty(tile_size, constants.dtype), np.empty(tile_size, constants.dtype)
    state = np.empty((size, 11))         # T, colour behind (3), last alpha, last colour (3), dL/dC (3)
    behind_bg, reach = np.empty(size), np.empty(size, np.int64)
    g = np.empty(9)
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        x0, y0 = tx * tile_size, ty * tile_size
        x1, y1 = min(width, x0 + tile_size), min(height, y0 + tile_size)
        tw = x1 - x0
        for m in range(tile_size):
            xs[m], ys[m] = x0 + m, y0 + m
        start = ranges[tile, 0]
        deepest = 0
        for py in range(y0, y1):
            for px in range(x0, x1):
                j = (py - y0) * tw + px - x0
                T_final = final_t[py, px]
                dr, dg, db = grad_image[py, px, 0], grad_image[py, px, 1], grad_image[py, px, 2]
                state[j, 0] = T_final
                state[j, 1:8] = 0.0
                state[j, 8], state[j, 9], state[j, 10] = dr, dg, db
                behind_bg[j] = -T_final * (background[0] * dr + background[1] * dg + background[2] * db)
                reach[j] = n_contrib[py, px]
                deepest = max(deepest, reach[j])
        for k in range(start + deepest - 1, start - 1, -1):
            mx, my, ca, cb, cc, opacity, skip = (packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3],
                                                 packed[k, 4], packed[k, 5], packed[k, 6])
            if skip > zero:
                continue
            i = ids[k]
            red, green, blue = colors[i, 0], colors[i, 1], colors[i, 2]
            g[:] = 0.0
            limit = -2.0 * skip * (1.0 + 1e-5) + 1e-5
            row_first, row_stop = _row_range(my, ca, cb, cc, limit, y0, y1)
            for py in range(row_first, row_stop):
                first, after = _row_span(mx, my, ca, cb, cc, limit, py, x0, x1)
                dy = my - ys[py - y0]
                for px in range(first, after):
                    j = (py - y0) * tw + px - x0
                    if k - start >= reach[j]:
                        continue
                    dx = mx - xs[px - x0]
                    power = -half * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if not (skip <= power <= zero):
                        continue
                    G = _exp_nonpositive(power, sixteenth, c)
                    raw = opacity * G
                    alpha = min(alpha_max, raw)
                    if alpha < alpha_min:
                        continue
                    s = state[j]
                    T = s[0] / (1.0 - alpha)
                    s[0] = T
                    weight = alpha * T
                    # the colour composited behind this Gaussian, per unit of the light reaching it
                    la = s[4]
                    acc_r = la * s[5] + (1.0 - la) * s[1]
                    acc_g = la * s[6] + (1.0 - la) * s[2]
                    acc_b = la * s[7] + (1.0 - la) * s[3]
                    s[1], s[2], s[3] = acc_r, acc_g, acc_b
                    s[4], s[5], s[6], s[7] = alpha, red, green, blue
                    dr, dg, db = s[8], s[9], s[10]
                    g[5] += weight * dr
                    g[6] += weight * dg
                    g[7] += weight * db
                    if raw > alpha_max:        # clamped: alpha does not depend on the parameters here
                        continue
                    d_alpha = T * ((red - acc_r) * dr + (green - acc_g) * dg + (blue - acc_b) * db)
                    d_alpha += behind_bg[j] / (1.0 - alpha)
                    g[8] += G * d_alpha
                    d_power = d_alpha * raw
                    g[0] += d_power * -(ca * dx + cb * dy)
                    g[1] += d_power * -(cc * dy + cb * dx)
                    g[2] += d_power * -0.5 * dx * dx
                    g[3] += d_power * -dx * dy
                    g[4] += d_power * -0.5 * dy * dy
            for m in range(9):
                grads[i, m] += g[m]


@kernel
def _preprocess_kernel(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, logits: np.ndarray,
                       sh: np.ndarray, degree: int, basis_constants: np.ndarray, view: np.ndarray,
                       width: int, height: int, tile_size: int, near: float, dilation: float,
                       means2d: np.ndarray, conics: np.ndarray, depths: np.ndarray, radii: np.ndarray,
                       rects: np.ndarray, colors: np.ndarray, opacities: np.ndarray) -> None:
    """The projection and colours of :func:`.gaussians.project`, :func:`.gaussians.view_colors` and the
    opacities' sigmoid in one compiled pass, for rendering without gradients (where torch's per-operation
    overhead on (N,) vectors is most of the time): per Gaussian, in float64, the same formulas in the same
    order (Kerbl et al. 2023 eq. 5 and 6, the code's ``computeCov2D``, ``getRect`` and
    ``computeColorFromSH``). ``view`` (16,) is ``R`` (9, row-major), ``t`` (3), ``fx, fy, cx, cy``;
    ``basis_constants`` the SH constants ``C0, C1, C2 (5), C3 (7)``. Writes every output row (N of
    each)."""
    W, t = view[0:9], view[9:12]
    fx, fy, cx, cy = view[12], view[13], view[14], view[15]
    centre_x = -(W[0] * t[0] + W[3] * t[1] + W[6] * t[2])        # -R^T t
    centre_y = -(W[1] * t[0] + W[4] * t[1] + W[7] * t[2])
    centre_z = -(W[2] * t[0] + W[5] * t[1] + W[8] * t[2])
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u_low, u_high = -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x
    v_low, v_high = -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y
    tiles_x, tiles_y = (width + tile_size - 1) // tile_size, (height + tile_size - 1) // tile_size
    k = basis_constants
    for n in range(len(means)):
        mx, my, mz = np.float64(means[n, 0]), np.float64(means[n, 1]), np.float64(means[n, 2])
        x = W[0] * mx + W[1] * my + W[2] * mz + t[0]
        y = W[3] * mx + W[4] * my + W[5] * mz + t[1]
        z = W[6] * mx + W[7] * my + W[8] * mz + t[2]
        u = min(max(x / z, u_low), u_high)
        v = min(max(y / z, v_low), v_high)
        fx_z, fy_z = fx / z, fy / z
        T00, T01, T02 = fx_z * (W[0] - u * W[6]), fx_z * (W[1] - u * W[7]), fx_z * (W[2] - u * W[8])
        T10, T11, T12 = fy_z * (W[3] - v * W[6]), fy_z * (W[4] - v * W[7]), fy_z * (W[5] - v * W[8])
        qw, qx, qy, qz = (np.float64(quats[n, 0]), np.float64(quats[n, 1]), np.float64(quats[n, 2]),
                          np.float64(quats[n, 3]))
        norm = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        R00, R01, R02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        R10, R11, R12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        R20, R21, R22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        s0, s1, s2 = np.exp(np.float64(log_scales[n, 0])), np.exp(np.float64(log_scales[n, 1])), \
            np.exp(np.float64(log_scales[n, 2]))
        V00, V01, V02 = ((T00 * R00 + T01 * R10 + T02 * R20) * s0, (T00 * R01 + T01 * R11 + T02 * R21) * s1,
                         (T00 * R02 + T01 * R12 + T02 * R22) * s2)
        V10, V11, V12 = ((T10 * R00 + T11 * R10 + T12 * R20) * s0, (T10 * R01 + T11 * R11 + T12 * R21) * s1,
                         (T10 * R02 + T11 * R12 + T12 * R22) * s2)
        a = V00 * V00 + V01 * V01 + V02 * V02 + dilation
        b = V00 * V10 + V01 * V11 + V02 * V12
        c = V10 * V10 + V11 * V11 + V12 * V12 + dilation
        safe_z = z if z > near else 1.0
        u2d, v2d = fx * x / safe_z + cx, fy * y / safe_z + cy
        det = a * c - b * b
        ok = z > near and det > 0.0
        safe_det = det if ok else 1.0
        means2d[n, 0], means2d[n, 1] = u2d, v2d
        conics[n, 0], conics[n, 1], conics[n, 2] = c / safe_det, -b / safe_det, a / safe_det
        depths[n] = z
        mid = 0.5 * (a + c)
        lambda_max = mid + np.sqrt(max(mid * mid - det, 0.1))
        radius = int(np.ceil(3.0 * np.sqrt(max(lambda_max, 0.0)))) if ok else 0
        # clamped as floats before the conversion (a float beyond int64 has no defined conversion)
        x0 = int(min(max(np.floor((u2d - radius) / tile_size), 0.0), tiles_x))
        y0 = int(min(max(np.floor((v2d - radius) / tile_size), 0.0), tiles_y))
        x1 = int(min(max(np.floor((u2d + radius + tile_size - 1) / tile_size), 0.0), tiles_x))
        y1 = int(min(max(np.floor((v2d + radius + tile_size - 1) / tile_size), 0.0), tiles_y))
        if (x1 - x0) * (y1 - y0) == 0:
            radius = 0
        if radius == 0:
            x0 = y0 = x1 = y1 = 0
        radii[n] = radius
        rects[n, 0], rects[n, 1], rects[n, 2], rects[n, 3] = x0, y0, x1, y1
        # the colour seen from the camera centre (unit direction, clamped norm as view_colors)
        dx, dy, dz = mx - centre_x, my - centre_y, mz - centre_z
        length = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        dx, dy, dz = dx / length, dy / length, dz / length
        for ch in range(3):
            total = k[0] * sh[n, 0, ch] + 0.5
            if degree >= 1:
                total += -k[1] * dy * sh[n, 1, ch] + k[1] * dz * sh[n, 2, ch] - k[1] * dx * sh[n, 3, ch]
            if degree >= 2:
                xx, yy, zz = dx * dx, dy * dy, dz * dz
                total += (k[2] * dx * dy * sh[n, 4, ch] + k[3] * dy * dz * sh[n, 5, ch]
                          + k[4] * (2 * zz - xx - yy) * sh[n, 6, ch] + k[5] * dx * dz * sh[n, 7, ch]
                          + k[6] * (xx - yy) * sh[n, 8, ch])
                if degree >= 3:
                    total += (k[7] * dy * (3 * xx - yy) * sh[n, 9, ch] + k[8] * dx * dy * dz * sh[n, 10, ch]
                              + k[9] * dy * (4 * zz - xx - yy) * sh[n, 11, ch]
                              + k[10] * dz * (2 * zz - 3 * xx - 3 * yy) * sh[n, 12, ch]
                              + k[11] * dx * (4 * zz - xx - yy) * sh[n, 13, ch]
                              + k[12] * dz * (xx - yy) * sh[n, 14, ch]
                              + k[13] * dx * (xx - 3 * yy) * sh[n, 15, ch])
            colors[n, ch] = max(total, 0.0)
        opacities[n] = 1.0 / (1.0 + np.exp(-np.float64(logits[n])))


def _warm_up() -> None:
    """Compile the kernels for float32 (training's dtype) on a one-tile image with one Gaussian."""
    f4 = np.float32
    ranges, ids = np.array([[0, 1]], np.int64), np.zeros(1, np.int64)
    packed = pack_pairs(ids, np.array([[4.0, 4.0]], f4), np.array([[0.2, 0.0, 0.2]], f4), np.array([0.5], f4))
    colors, background = np.full((1, 3), 0.5, f4), np.ones(3, f4)
    image, final_t, n_contrib = np.zeros((8, 8, 3), f4), np.ones((8, 8), f4), np.zeros((8, 8), np.int64)
    _rasterize_forward_kernel(0, 1, ranges, ids, packed, colors, background, kernel_constants(f4), 16, 1,
                              image, final_t, n_contrib)
    _rasterize_backward_kernel(0, 1, ranges, ids, packed, colors, background, kernel_constants(f4), 16, 1,
                               final_t, n_contrib, np.ones((8, 8, 3), f4), np.zeros((1, 9), f4))
    _bin_kernel(ids, np.array([[0, 0, 1, 1]], np.int64), np.full((1, 2), 4.0), np.array([[0.2, 0.0, 0.2]]),
                np.ones(1), True, 16, 8, 8, 1, np.zeros((1, 2), np.int64), np.zeros(1, np.int64),
                np.zeros(1, np.bool_))
    quats = np.array([[1.0, 0.0, 0.0, 0.0]], f4)
    camera = np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 8, 8, 4, 4], np.float64)
    _preprocess_kernel(np.array([[0.0, 0.0, 2.0]], f4), np.full((1, 3), -2.0, f4), quats, np.zeros(1, f4),
                       np.zeros((1, 16, 3), f4), 3, np.ones(14), camera, 8, 8, 16, 0.2, 0.3, np.empty((1, 2)),
                       np.empty((1, 3)), np.empty(1), np.empty(1, np.int64), np.empty((1, 4), np.int64),
                       np.empty((1, 3)), np.empty(1))


register_warm_up("splatting", ["train_splats", "render_held_out", "render_view", "render_path"],
                 [_rasterize_forward_kernel, _rasterize_backward_kernel, _bin_kernel, _preprocess_kernel],
                 _warm_up)
