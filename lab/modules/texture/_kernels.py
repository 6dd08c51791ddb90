"""The texture module's compiled loop (Numba, :func:`lab.core.kernels.kernel`): the sequential part of
an Efros–Leung onion layer. :func:`lab.modules.texture.efros_leung.fill_layer` calls it;
:func:`lab.modules.texture.reference.fill_layer_reference` is the readable version.
"""

from __future__ import annotations

import numpy as np

from lab.core.kernels import dispatchers_in, kernel, register_warm_up, warm_up_steps


@kernel
def _fill_layer_kernel(sums: np.ndarray, totals: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                       uniforms: np.ndarray, values: np.ndarray, g: np.ndarray, levels: np.ndarray,
                       padded_out: np.ndarray, in_layer: np.ndarray, out: np.ndarray, source: np.ndarray,
                       filled: np.ndarray, order: np.ndarray, counter: int, epsilon: float, w: int,
                       columns: int) -> int:
    """Fill a chunk of an onion layer in turn: for each pixel add the terms of the pixels filled earlier
    in this layer to its precomputed sums, divide, keep the candidates, pick, copy.

    ``sums`` ``(B, N)``: each pixel's weighted SSD to the ``N`` sample windows over the pixels known
    at the start of the layer; ``totals`` ``(B,)`` their weight. Every sum is of integers below 2^53
    (exact in float64), so the order of the additions does not change the result: the distances
    equal the reference's bit for bit. Returns the fill counter after the chunk.
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


# ----------------------------------------------------------------------------------------------------
# Warm-up (lab.core.kernels): Efros-Leung on a tiny gray and a tiny colour sample
# ----------------------------------------------------------------------------------------------------
def _warm_up() -> None:
    """Efros-Leung's fast fill on 16 x 16 outputs of a gray and a colour procedural sample."""
    from lab.modules.texture import PIPELINE

    for colour in (False, True):
        warm_up_steps(PIPELINE, "procedural", {"size": 24, "colour": colour}, "synthesize_efros_leung",
                      {"synthesize_efros_leung": {"size": (16, 16), "window": 5}})


register_warm_up("texture", ("synthesize_efros_leung",), dispatchers_in(globals()), _warm_up)
