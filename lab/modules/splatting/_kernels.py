"""The compiled loops of the fast rasterizer: front-to-back compositing per tile and its backward pass.

Both follow the paper's code (Kerbl et al. 2023, ``renderCUDA`` in ``forward.cu`` and ``backward.cu``), one
tile after another instead of one CUDA block per tile, in the dtype of their inputs (float32 to train,
float64 in the tests). Within a tile they go Gaussian by Gaussian through its depth-sorted list, each pixel
keeping its own running state, and each Gaussian visits only the pixels of its rows' chords of the ellipse
where its alpha can reach 1/255 (:func:`_row_span`; the exact-footprint culling of "StopThePop",
Radl et al. 2024, and gsplat's tile intersection, done per row instead of per tile): the square 3-sigma
rectangle lists a Gaussian in tiles its ellipse may miss, and most pixels of the tiles it does touch lie
outside it. The per-pixel arithmetic and its order are the paper's per-pixel loop's, so the image does not
depend on the walk. The backward pass walks each pixel's list back to front from its last contributor,
recovering ``T_i`` by dividing by ``1 - alpha_i`` and the colour behind each Gaussian as a running sum, as
the paper's code does; unlike that code, it takes the clamp ``alpha <= 0.99`` into account (no gradient
through a clamped alpha: gsplat does the same), so it is the derivative autograd gives the reference.
Gradients are summed per Gaussian over a tile, then into one buffer per band of tiles (bands run on
different threads). Each tile's list comes packed in list order (:func:`pack_pairs`: reads one after the
other instead of gathers), with an exponent below which a Gaussian's alpha is surely under 1/255, which
bounds the chords and spares the ``exp`` of the pixels outside them.
"""

from __future__ import annotations

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
    """``(pairs, 7)`` in the dtype of ``means2d``: per listed Gaussian ``ids[k]`` its mean (2), conic (3),
    opacity and :func:`alpha_floor_exponents` (an exponent below which its alpha is surely under 1/255), laid
    out in list order so the kernels read them one after the other."""
    skip = alpha_floor_exponents(opacities)
    table = np.concatenate([means2d, conics, opacities[:, None], skip[:, None].astype(means2d.dtype)], axis=1)
    return np.ascontiguousarray(table[ids])


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


@kernel
def _rasterize_forward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                              packed: np.ndarray, colors: np.ndarray, background: np.ndarray, tile_size: int,
                              tiles_x: int, image: np.ndarray, final_t: np.ndarray,
                              n_contrib: np.ndarray) -> None:
    """Composite tiles ``tile_start .. tile_stop`` (row-major) into ``image`` (H, W, 3); ``final_t`` (H, W)
    the transmittance left, ``n_contrib`` (H, W) how far into its tile's list each pixel read (1 past its
    last contributor). ``packed`` (pairs, 7) holds each listed Gaussian's mean, conic, opacity and the
    exponent below which its alpha is surely under 1/255 (:func:`pack_pairs`), in list order.

    Gaussian by Gaussian through the tile's list, each visiting only the pixels of its rows' chords of the
    ellipse where its alpha can reach 1/255 (:func:`_row_span`), each pixel keeping its own transmittance
    and colour; the per-pixel arithmetic and its order are those of the paper's per-pixel loop, so the
    image is the same to the bit. A pixel is done at the Gaussian that would take its transmittance below
    1e-4, the tile when all its pixels are."""
    height, width = final_t.shape
    size = tile_size * tile_size
    trans, red, green, blue = np.empty(size), np.empty(size), np.empty(size), np.empty(size)
    last, done = np.empty(size, np.int64), np.empty(size, np.bool_)
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        x0, y0 = tx * tile_size, ty * tile_size
        x1, y1 = min(width, x0 + tile_size), min(height, y0 + tile_size)
        tw = x1 - x0
        alive = tw * (y1 - y0)
        for j in range(alive):
            trans[j], red[j], green[j], blue[j], last[j], done[j] = 1.0, 0.0, 0.0, 0.0, 0, False
        start, stop = ranges[tile, 0], ranges[tile, 1]
        for k in range(start, stop):
            if alive == 0:
                break
            mx, my, ca, cb, cc, opacity, skip = (packed[k, 0], packed[k, 1], packed[k, 2], packed[k, 3],
                                                 packed[k, 4], packed[k, 5], packed[k, 6])
            if skip > 0.0:                      # alpha under 1/255 everywhere
                continue
            i = ids[k]
            red_i, green_i, blue_i = colors[i, 0], colors[i, 1], colors[i, 2]
            row_first, row_stop = _row_range(my, ca, cb, cc, -2.0 * skip, y0, y1)
            for py in range(row_first, row_stop):
                first, after = _row_span(mx, my, ca, cb, cc, -2.0 * skip, py, x0, x1)
                dy = my - py
                for px in range(first, after):
                    j = (py - y0) * tw + px - x0
                    if done[j]:
                        continue
                    dx = mx - px
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power > 0.0 or power < skip:
                        continue
                    alpha = min(ALPHA_MAX, opacity * np.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    T = trans[j]
                    next_t = T * (1.0 - alpha)
                    if next_t < T_MIN:
                        done[j] = True
                        alive -= 1
                        continue
                    weight = alpha * T
                    red[j] += red_i * weight
                    green[j] += green_i * weight
                    blue[j] += blue_i * weight
                    trans[j] = next_t
                    last[j] = k - start + 1
        for py in range(y0, y1):
            for px in range(x0, x1):
                j = (py - y0) * tw + px - x0
                T = trans[j]
                image[py, px, 0] = red[j] + T * background[0]
                image[py, px, 1] = green[j] + T * background[1]
                image[py, px, 2] = blue[j] + T * background[2]
                final_t[py, px] = T
                n_contrib[py, px] = last[j]


@kernel
def _rasterize_backward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                               packed: np.ndarray, colors: np.ndarray, background: np.ndarray, tile_size: int,
                               tiles_x: int, final_t: np.ndarray, n_contrib: np.ndarray,
                               grad_image: np.ndarray, grads: np.ndarray) -> None:
    """Add to ``grads`` (N, 9) the gradients of the loss (whose gradient in the image is ``grad_image``)
    with respect to each Gaussian's mean (2), conic (3), colour (3) and opacity (1), over tiles
    ``tile_start .. tile_stop``.

    Gaussian by Gaussian back to front from the tile's last contributor, over its rows' chords as in the
    forward pass; each pixel keeps its transmittance and the colour behind; each Gaussian's gradient is
    summed over the tile before it is added to ``grads``."""
    height, width = final_t.shape
    size = tile_size * tile_size
    state = np.empty((size, 11))         # T, colour behind (3), last alpha, last colour (3), dL/dC (3)
    behind_bg, reach = np.empty(size), np.empty(size, np.int64)
    g = np.empty(9)
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        x0, y0 = tx * tile_size, ty * tile_size
        x1, y1 = min(width, x0 + tile_size), min(height, y0 + tile_size)
        tw = x1 - x0
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
            if skip > 0.0:
                continue
            i = ids[k]
            red, green, blue = colors[i, 0], colors[i, 1], colors[i, 2]
            g[:] = 0.0
            row_first, row_stop = _row_range(my, ca, cb, cc, -2.0 * skip, y0, y1)
            for py in range(row_first, row_stop):
                first, after = _row_span(mx, my, ca, cb, cc, -2.0 * skip, py, x0, x1)
                dy = my - py
                for px in range(first, after):
                    j = (py - y0) * tw + px - x0
                    if k - start >= reach[j]:
                        continue
                    dx = mx - px
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power > 0.0 or power < skip:
                        continue
                    G = np.exp(power)
                    raw = opacity * G
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
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
                    if raw > ALPHA_MAX:        # clamped: alpha does not depend on the parameters here
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


def _warm_up() -> None:
    """Compile the kernels for float32 (training's dtype) on a one-tile image with one Gaussian."""
    f4 = np.float32
    ranges, ids = np.array([[0, 1]], np.int64), np.zeros(1, np.int64)
    packed = pack_pairs(ids, np.array([[4.0, 4.0]], f4), np.array([[0.2, 0.0, 0.2]], f4), np.array([0.5], f4))
    colors, background = np.full((1, 3), 0.5, f4), np.ones(3, f4)
    image, final_t, n_contrib = np.zeros((8, 8, 3), f4), np.ones((8, 8), f4), np.zeros((8, 8), np.int64)
    _rasterize_forward_kernel(0, 1, ranges, ids, packed, colors, background, 16, 1, image, final_t, n_contrib)
    _rasterize_backward_kernel(0, 1, ranges, ids, packed, colors, background, 16, 1, final_t, n_contrib,
                               np.ones((8, 8, 3), f4), np.zeros((1, 9), f4))
    _bin_kernel(ids, np.array([[0, 0, 1, 1]], np.int64), np.full((1, 2), 4.0), np.array([[0.2, 0.0, 0.2]]),
                np.ones(1), True, 16, 8, 8, 1, np.zeros((1, 2), np.int64), np.zeros(1, np.int64),
                np.zeros(1, np.bool_))


register_warm_up("splatting", ["train_splats", "render_held_out", "render_view"],
                 [_rasterize_forward_kernel, _rasterize_backward_kernel, _bin_kernel], _warm_up)
