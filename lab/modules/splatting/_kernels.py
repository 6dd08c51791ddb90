"""The compiled loops of the fast rasterizer: front-to-back compositing per tile and its backward pass.

Both follow the paper's code (Kerbl et al. 2023, ``renderCUDA`` in ``forward.cu`` and ``backward.cu``), one
tile after another instead of one CUDA block per tile, in the dtype of their inputs (float32 to train,
float64 in the tests). The backward pass walks each pixel's list back to front from its last contributor,
recovering ``T_i`` by dividing by ``1 - alpha_i`` and the colour behind each Gaussian as a running sum, as
the paper's code does; unlike that code, it takes the clamp ``alpha <= 0.99`` into account (no gradient
through a clamped alpha: gsplat does the same), so it is the derivative autograd gives the reference.
Gradients are summed into one buffer per band of tiles (bands run on different threads). Each tile's list
comes packed in list order (:func:`pack_pairs`: reads one after the other instead of gathers), with an
exponent below which a Gaussian's alpha is surely under 1/255, which spares the ``exp`` of most pairs.
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


def pack_pairs(ids: np.ndarray, means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """``(pairs, 7)`` in the dtype of ``means2d``: per listed Gaussian ``ids[k]`` its mean (2), conic (3),
    opacity and ``log(1 / (255 o)) - SLACK`` (an exponent below which its alpha is surely under 1/255), laid
    out in list order so the kernels read them one after the other."""
    with np.errstate(divide="ignore"):
        skip = np.log(1.0 / 255.0) - np.log(np.maximum(opacities.astype(np.float64), 1e-300)) - SLACK
    table = np.concatenate([means2d, conics, opacities[:, None], skip[:, None].astype(means2d.dtype)], axis=1)
    return np.ascontiguousarray(table[ids])


@kernel
def _rasterize_forward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                              packed: np.ndarray, colors: np.ndarray, background: np.ndarray, tile_size: int,
                              tiles_x: int, image: np.ndarray, final_t: np.ndarray,
                              n_contrib: np.ndarray) -> None:
    """Composite tiles ``tile_start .. tile_stop`` (row-major) into ``image`` (H, W, 3); ``final_t`` (H, W)
    the transmittance left, ``n_contrib`` (H, W) how far into its tile's list each pixel read (1 past its
    last contributor). ``packed`` (pairs, 7) holds each listed Gaussian's mean, conic, opacity and the
    exponent below which its alpha is surely under 1/255 (:func:`pack_pairs`), in list order."""
    height, width = final_t.shape
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        start, stop = ranges[tile, 0], ranges[tile, 1]
        for py in range(ty * tile_size, min(height, (ty + 1) * tile_size)):
            for px in range(tx * tile_size, min(width, (tx + 1) * tile_size)):
                T = 1.0
                r = 0.0
                g = 0.0
                b = 0.0
                last = 0
                for k in range(start, stop):
                    dx = packed[k, 0] - px
                    dy = packed[k, 1] - py
                    power = -0.5 * (packed[k, 2] * dx * dx + packed[k, 4] * dy * dy) - packed[k, 3] * dx * dy
                    if power > 0.0 or power < packed[k, 6]:
                        continue
                    i = ids[k]
                    alpha = min(ALPHA_MAX, packed[k, 5] * np.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    next_t = T * (1.0 - alpha)
                    if next_t < T_MIN:
                        break
                    weight = alpha * T
                    r += colors[i, 0] * weight
                    g += colors[i, 1] * weight
                    b += colors[i, 2] * weight
                    T = next_t
                    last = k - start + 1
                image[py, px, 0] = r + T * background[0]
                image[py, px, 1] = g + T * background[1]
                image[py, px, 2] = b + T * background[2]
                final_t[py, px] = T
                n_contrib[py, px] = last


@kernel
def _rasterize_backward_kernel(tile_start: int, tile_stop: int, ranges: np.ndarray, ids: np.ndarray,
                               packed: np.ndarray, colors: np.ndarray, background: np.ndarray, tile_size: int,
                               tiles_x: int, final_t: np.ndarray, n_contrib: np.ndarray,
                               grad_image: np.ndarray, grads: np.ndarray) -> None:
    """Add to ``grads`` (N, 9) the gradients of the loss (whose gradient in the image is ``grad_image``)
    with respect to each Gaussian's mean (2), conic (3), colour (3) and opacity (1), over tiles
    ``tile_start .. tile_stop``."""
    height, width = final_t.shape
    for tile in range(tile_start, tile_stop):
        ty, tx = tile // tiles_x, tile % tiles_x
        start = ranges[tile, 0]
        for py in range(ty * tile_size, min(height, (ty + 1) * tile_size)):
            for px in range(tx * tile_size, min(width, (tx + 1) * tile_size)):
                T_final = final_t[py, px]
                T = T_final
                dr, dg, db = grad_image[py, px, 0], grad_image[py, px, 1], grad_image[py, px, 2]
                behind_bg = -T_final * (background[0] * dr + background[1] * dg + background[2] * db)
                acc_r = 0.0
                acc_g = 0.0
                acc_b = 0.0
                last_alpha = 0.0
                last_r = 0.0
                last_g = 0.0
                last_b = 0.0
                for k in range(start + n_contrib[py, px] - 1, start - 1, -1):
                    dx = packed[k, 0] - px
                    dy = packed[k, 1] - py
                    ca, cb, cc = packed[k, 2], packed[k, 3], packed[k, 4]
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power > 0.0 or power < packed[k, 6]:
                        continue
                    i = ids[k]
                    G = np.exp(power)
                    raw = packed[k, 5] * G
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    T = T / (1.0 - alpha)
                    weight = alpha * T
                    # the colour composited behind this Gaussian, per unit of the light reaching it
                    acc_r = last_alpha * last_r + (1.0 - last_alpha) * acc_r
                    acc_g = last_alpha * last_g + (1.0 - last_alpha) * acc_g
                    acc_b = last_alpha * last_b + (1.0 - last_alpha) * acc_b
                    red, green, blue = colors[i, 0], colors[i, 1], colors[i, 2]
                    last_r, last_g, last_b = red, green, blue
                    last_alpha = alpha
                    grads[i, 5] += weight * dr
                    grads[i, 6] += weight * dg
                    grads[i, 7] += weight * db
                    if raw > ALPHA_MAX:        # clamped: alpha does not depend on the parameters here
                        continue
                    d_alpha = T * ((red - acc_r) * dr + (green - acc_g) * dg + (blue - acc_b) * db)
                    d_alpha += behind_bg / (1.0 - alpha)
                    grads[i, 8] += G * d_alpha
                    d_power = d_alpha * raw
                    grads[i, 0] += d_power * -(ca * dx + cb * dy)
                    grads[i, 1] += d_power * -(cc * dy + cb * dx)
                    grads[i, 2] += d_power * -0.5 * dx * dx
                    grads[i, 3] += d_power * -dx * dy
                    grads[i, 4] += d_power * -0.5 * dy * dy


def _warm_up() -> None:
    """Compile both kernels for float32 (training's dtype) on a one-tile image with one Gaussian."""
    f4 = np.float32
    ranges, ids = np.array([[0, 1]], np.int64), np.zeros(1, np.int64)
    packed = pack_pairs(ids, np.array([[4.0, 4.0]], f4), np.array([[0.2, 0.0, 0.2]], f4), np.array([0.5], f4))
    colors, background = np.full((1, 3), 0.5, f4), np.ones(3, f4)
    image, final_t, n_contrib = np.zeros((8, 8, 3), f4), np.ones((8, 8), f4), np.zeros((8, 8), np.int64)
    _rasterize_forward_kernel(0, 1, ranges, ids, packed, colors, background, 16, 1, image, final_t, n_contrib)
    _rasterize_backward_kernel(0, 1, ranges, ids, packed, colors, background, 16, 1, final_t, n_contrib,
                               np.ones((8, 8, 3), f4), np.zeros((1, 9), f4))


register_warm_up("splatting", ["train_splats", "render_held_out", "render_view"],
                 [_rasterize_forward_kernel, _rasterize_backward_kernel], _warm_up)
