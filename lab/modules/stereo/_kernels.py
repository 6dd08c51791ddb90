"""The stereo module's fast kernels (Numba, compiled by :func:`lab.core.kernels.kernel`): arrays in and out.

Private: the public functions that call them (checks, banding of rows on the shared thread pool of
:mod:`lab.core.kernels`) live beside the math they speed up (:mod:`.costs`, :mod:`.sgm`,
:mod:`.winners`), and the readable version of each is in :mod:`.reference`, the tests' oracle.
Names pair up as :mod:`lab.core.kernels` says: ``_box_rows_kernel`` here, ``box_mean`` the fast
function, ``box_mean_reference`` the oracle.

A kernel that takes ``y0, y1`` (or ``x0, x1``) works on that band of rows (columns) only, so the
bands of one call run at once on the pool; every kernel releases the GIL.
"""

from __future__ import annotations

import numpy as np

from lab.core.kernels import dispatchers_in, kernel, register_warm_up, warm_up_steps

#: Path costs of the SGM kernel are int16: every ``L <= C + P2`` must stay below this (and the padding).
SGM_LARGEST = 16383


# ----------------------------------------------------------------------------------------------------
# Box filtering: the O(1)-per-window sum (box_mean, in .costs)
# ----------------------------------------------------------------------------------------------------
@kernel
def _box_rows_kernel(volume, radius, y0, y1):
    """In place, rows ``y0:y1``: each ``volume[y, :, d]`` becomes its running sums over ``2 radius + 1``
    columns (borders replicated), read from a copy of the row."""
    _H, W, D = volume.shape
    line = np.empty((W, D), volume.dtype)
    sums = np.zeros(D, np.float64)
    for y in range(y0, y1):
        row = volume[y]
        for x in range(W):
            for d in range(D):
                line[x, d] = row[x, d]
        for d in range(D):
            sums[d] = 0.0
        for k in range(-radius, radius + 1):
            column = min(max(k, 0), W - 1)
            for d in range(D):
                sums[d] += line[column, d]
        for x in range(W):
            enter = min(x + radius + 1, W - 1)
            leave = max(x - radius, 0)
            for d in range(D):
                row[x, d] = sums[d]
                sums[d] += line[enter, d] - line[leave, d]


@kernel
def _box_columns_kernel(volume, radius, factor, x0, x1):
    """In place, columns ``x0:x1``: ``factor`` times the running sums over ``2 radius + 1`` rows (borders
    replicated), the rows that leave the window kept in a ring of the last ``2 radius + 2``."""
    H, _W, D = volume.shape
    size = 2 * radius + 2
    ring = np.empty((size, x1 - x0, D), volume.dtype)
    acc = np.zeros((x1 - x0, D), np.float64)
    for k in range(-radius, radius + 1):
        source = volume[min(max(k, 0), H - 1)]
        for x in range(x0, x1):
            for d in range(D):
                acc[x - x0, d] += source[x, d]
    for y in range(H):
        row = volume[y]
        saved = ring[y % size]
        for x in range(x0, x1):
            for d in range(D):
                saved[x - x0, d] = row[x, d]
                row[x, d] = acc[x - x0, d] * factor  # rounded to the volume's dtype
        enter = min(y + radius + 1, H - 1)
        leaving = ring[max(y - radius, 0) % size]
        if enter > y:
            entering = volume[enter]
            for x in range(x0, x1):
                for d in range(D):
                    acc[x - x0, d] += entering[x, d] - leaving[x - x0, d]
        else:
            entering = ring[enter % size]
            for x in range(x0, x1):
                for d in range(D):
                    acc[x - x0, d] += entering[x - x0, d] - leaving[x - x0, d]

# ----------------------------------------------------------------------------------------------------
# Census: the transform, Hamming distances, and both fused with the window sum (census_transform,
# hamming_costs, census_costs, in .costs)
# ----------------------------------------------------------------------------------------------------
@kernel
def _census_transform_kernel(gray, radius, words):
    H, W = gray.shape
    padded = np.empty((H + 2 * radius, W + 2 * radius), np.float32)
    for y in range(H + 2 * radius):
        source = min(max(y - radius, 0), H - 1)
        for x in range(W + 2 * radius):
            padded[y, x] = gray[source, min(max(x - radius, 0), W - 1)]
    out = np.zeros((H, W, words), np.uint64)
    for y in range(H):
        bit = 0
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                word = bit >> 6
                mask = np.uint64(1) << np.uint64(bit & 63)
                neighbours = padded[y + radius + dy]
                for x in range(W):
                    if neighbours[x + radius + dx] < gray[y, x]:
                        out[y, x, word] |= mask
                bit += 1
    return out


@kernel
def _popcount_kernel(value):
    value = value - ((value >> np.uint64(1)) & np.uint64(0x5555555555555555))
    value = ((value & np.uint64(0x3333333333333333))
             + ((value >> np.uint64(2)) & np.uint64(0x3333333333333333)))
    value = (value + (value >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((value * np.uint64(0x0101010101010101)) >> np.uint64(56))


@kernel
def _hamming_costs_kernel(codes_left, codes_right, out, y0, y1):
    _H, W, words = codes_left.shape
    disparities = out.shape[2]
    counts = np.zeros(disparities, np.int64)
    reversed_row = np.empty((words, W + disparities), np.uint64)
    for y in range(y0, y1):
        # reversed_row[w, (W - 1 - x) + d] = codes_right[y, max(x - d, 0), w]: the d loop reads forward
        for w in range(words):
            for j in range(W + disparities):
                reversed_row[w, j] = codes_right[y, max(W - 1 - j, 0), w]
        for x in range(W):
            base = W - 1 - x
            for d in range(disparities):
                counts[d] = 0
            for w in range(words):
                code = codes_left[y, x, w]
                for d in range(disparities):
                    counts[d] += _popcount_kernel(code ^ reversed_row[w, base + d])
            for d in range(disparities):
                out[y, x, d] = np.float32(counts[d])


@kernel
def _census_row_sums_kernel(codes_left, codes_right, source, radius, reversed_row, counts, dest):
    """Row ``source`` of the Hamming volume, summed over ``2 radius + 1`` columns (borders replicated), into
    ``dest`` ``(W, D)`` int32. ``reversed_row`` and ``counts`` are scratch buffers."""
    _H, W, words = codes_left.shape
    D = dest.shape[1]
    for w in range(words):  # reversed_row[w, (W - 1 - x) + d] = codes_right[source, max(x - d, 0), w]
        for j in range(W + D):
            reversed_row[w, j] = codes_right[source, max(W - 1 - j, 0), w]
    for x in range(W):
        base = W - 1 - x
        for d in range(D):
            counts[x, d] = 0
        for w in range(words):
            code = codes_left[source, x, w]
            for d in range(D):
                counts[x, d] += _popcount_kernel(code ^ reversed_row[w, base + d])
    sums = dest[0].copy()
    for d in range(D):
        sums[d] = 0
    for k in range(-radius, radius + 1):
        column = min(max(k, 0), W - 1)
        for d in range(D):
            sums[d] += counts[column, d]
    for x in range(W):
        enter = min(x + radius + 1, W - 1)
        leave = max(x - radius, 0)
        for d in range(D):
            dest[x, d] = sums[d]
            sums[d] += counts[enter, d] - counts[leave, d]


@kernel
def _census_costs_kernel(codes_left, codes_right, radius, factor, out, y0, y1, row0):
    """Rows ``y0:y1`` of the census cost volume in one pass: Hamming distances summed over the window
    (borders replicated) times ``factor``, written to ``out[y - row0]`` (float32; ``row0 = 0`` for the
    whole volume, ``row0 = y0`` for a band of rows of its own).

    Each row's Hamming distances are summed along the row as they are counted; a ring holds the
    row sums of the last ``2 radius + 2`` source rows and an integer accumulator slides down the
    columns. The sums are exact integers, so the result equals :func:`hamming_costs` followed by
    :func:`box_mean` (scaled), bit for bit, without writing the per-pixel volume.
    """
    H, W, words = codes_left.shape
    D = out.shape[2]
    size = 2 * radius + 2
    ring = np.empty((size, W, D), np.int32)
    held = np.full(size, -1, np.int64)  # the source row each slot of the ring holds
    reversed_row = np.empty((words, W + D), np.uint64)
    counts = np.empty((W, D), np.int32)
    acc = np.zeros((W, D), np.int32)
    for k in range(-radius, radius + 1):
        source = min(max(y0 + k, 0), H - 1)
        slot = source % size
        if held[slot] != source:
            _census_row_sums_kernel(codes_left, codes_right, source, radius, reversed_row, counts, ring[slot])
            held[slot] = source
        sums = ring[slot]
        for x in range(W):
            for d in range(D):
                acc[x, d] += sums[x, d]
    for y in range(y0, y1):
        target = out[y - row0]
        for x in range(W):
            for d in range(D):
                target[x, d] = np.float32(acc[x, d] * factor)
        if y + 1 >= y1:
            break
        enter = min(y + radius + 1, H - 1)
        leave = max(y - radius, 0)
        if enter == leave:  # a window taller than the image: nothing changes
            continue
        slot = enter % size
        if held[slot] != enter:
            _census_row_sums_kernel(codes_left, codes_right, enter, radius, reversed_row, counts, ring[slot])
            held[slot] = enter
        entering = ring[slot]
        leaving = ring[leave % size]
        for x in range(W):
            for d in range(D):
                acc[x, d] += entering[x, d] - leaving[x, d]

# ----------------------------------------------------------------------------------------------------
# NCC from float64 window moments (in .costs)
# ----------------------------------------------------------------------------------------------------
@kernel
def _ncc_from_moments_kernel(mean_a, var_a, mean_b, mean_bb, mean_ab, flat_variance, out, d0):
    """``out[:, :, d0 + j] = 1 - clip(NCC, -1, 1)`` from float64 window means of ``b``, ``b^2`` and ``a b``
    ``(H, W, k)`` and those of the left image; NCC = 0 where either window is flat."""
    H, W, k = mean_b.shape
    for y in range(H):
        for x in range(W):
            ma = mean_a[y, x]
            va = var_a[y, x]
            for j in range(k):
                mb = mean_b[y, x, j]
                vb = max(mean_bb[y, x, j] - mb * mb, 0.0)
                ncc = 0.0
                if va >= flat_variance and vb >= flat_variance:
                    ncc = min(max((mean_ab[y, x, j] - ma * mb) / np.sqrt(va * vb), -1.0), 1.0)
                out[y, x, d0 + j] = 1.0 - ncc

# ----------------------------------------------------------------------------------------------------
# Semi-global matching (semi_global_matching, volume_range, in .sgm)
# ----------------------------------------------------------------------------------------------------
# The two row kernels below repeat one loop (the path update of Hirschmüller's equation 13) on
# purpose: written once as an inlined helper it runs about 1.7 times slower under Numba.
@kernel
def _sgm_row_from_previous_kernel(costs_row, previous, previous_min, current, current_min, total, shift,
                                  start, P1, P2):
    """Paths arriving from the previous row at column ``x - shift``; adds their ``L`` to ``total`` ``(W, D)``.

    ``previous``/``current`` are ``(W, D + 2)`` int16 with a large value in columns 0 and D + 1, so
    ``L(d - 1)`` and ``L(d + 1)`` need no bounds test; 16-bit integers keep 16 costs in a SIMD register.
    """
    W, D = costs_row.shape
    for x in range(W):
        source = x - shift
        best = np.int16(SGM_LARGEST)
        if start or source < 0 or source >= W:  # the path starts here: L = C
            for d in range(D):
                value = costs_row[x, d]
                current[x, d + 1] = value
                total[x, d] += value
                best = min(best, value)
        else:
            floor = previous_min[source]
            jump = np.int16(floor + P2)
            for d in range(D):
                stay = min(previous[source, d + 1], jump)
                step = np.int16(min(previous[source, d], previous[source, d + 2]) + P1)
                value = np.int16(np.int16(costs_row[x, d] - floor) + min(stay, step))
                current[x, d + 1] = value
                total[x, d] += value
                best = min(best, value)
        current_min[x] = best


@kernel
def _sgm_row_horizontal_kernel(costs_row, buffer, total, forward, P1, P2):
    """The path along the row (left to right when ``forward``); writes its ``L`` into ``total`` ``(W, D)``."""
    W, D = costs_row.shape
    floor = np.int16(0)
    for i in range(W):
        x = i if forward else W - 1 - i
        now = i & 1
        before = 1 - now
        best = np.int16(SGM_LARGEST)
        if i == 0:  # the path starts here: L = C
            for d in range(D):
                value = costs_row[x, d]
                buffer[now, d + 1] = value
                total[x, d] = value
                best = min(best, value)
        else:
            jump = np.int16(floor + P2)
            for d in range(D):
                stay = min(buffer[before, d + 1], jump)
                step = np.int16(min(buffer[before, d], buffer[before, d + 2]) + P1)
                value = np.int16(np.int16(costs_row[x, d] - floor) + min(stay, step))
                buffer[now, d + 1] = value
                total[x, d] = value
                best = min(best, value)
        floor = best


@kernel
def _sgm_row_paths_kernel(source, quantum, P1, P2, forward, diagonals, i, paths, path_mins, buffer, row,
                          total):
    """Row ``i`` of a sweep (top-down when ``forward``, else bottom-up): its costs ``source`` ``(W, D)``
    rounded to integers, ``floor(source * quantum + 0.5)``, then ``total`` ``(W, D)`` int32 = the sum of
    the ``L`` of the path along the row and of the 1 or 3 paths from the row before.

    ``paths`` ``(2, 3, W, D + 2)`` int16 and ``path_mins`` ``(2, 3, W)`` hold the path costs of the row
    before (slot ``1 - i & 1``) and of this one (slot ``i & 1``); ``buffer`` ``(2, D + 2)`` and ``row``
    ``(W, D)`` int16 are scratch. Every path starts at row 0 of the sweep.
    """
    W, D = source.shape
    half = np.float32(0.5)
    now = i & 1
    for x in range(W):
        for d in range(D):
            row[x, d] = np.int16(source[x, d] * quantum + half)
    _sgm_row_horizontal_kernel(row, buffer, total, forward, P1, P2)
    for k in range(3):
        if k != 1 and not diagonals:
            continue
        _sgm_row_from_previous_kernel(row, paths[1 - now, k], path_mins[1 - now, k], paths[now, k],
                                      path_mins[now, k], total, 1 - k, i == 0, P1, P2)


@kernel
def _sgm_sweep_kernel(volume, quantum, P1, P2, forward, diagonals, out, scale, add):
    """One sweep over the image (top-down when ``forward``, else bottom-up) that runs 2 or 4 paths at once.

    Forward: left-to-right, top-down, and the two diagonals from the row above; backward: the
    four opposite directions (:func:`_sgm_row_paths_kernel`, row by row); then
    ``out[y] (+)= scale * (sum of the paths' L)`` (float32, exact for the integer sums below 2**24 that
    :func:`semi_global_matching` guarantees).
    """
    H, W, D = volume.shape
    big = np.int16(SGM_LARGEST)
    paths = np.full((2, 3, W, D + 2), big, np.int16)
    path_mins = np.zeros((2, 3, W), np.int16)
    buffer = np.full((2, D + 2), big, np.int16)
    total = np.empty((W, D), np.int32)
    row = np.empty((W, D), np.int16)
    for i in range(H):
        y = i if forward else H - 1 - i
        _sgm_row_paths_kernel(volume[y], quantum, P1, P2, forward, diagonals, i, paths, path_mins, buffer,
                              row, total)
        target = out[y]
        if add:
            for x in range(W):
                for d in range(D):
                    target[x, d] += np.float32(total[x, d]) * scale
        else:
            for x in range(W):
                for d in range(D):
                    target[x, d] = np.float32(total[x, d]) * scale
    return out


@kernel
def _volume_range_kernel(volume, lows, highs, y0, y1, slot):
    """Smallest and largest entry of rows ``y0:y1`` into ``lows[slot]``, ``highs[slot]`` (NaN if one is
    NaN)."""
    _H, W, D = volume.shape
    low = np.inf
    high = -np.inf
    nan = False
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                value = volume[y, x, d]
                low = min(low, value)
                high = max(high, value)
                nan |= value != value
    lows[slot] = np.nan if nan else low
    highs[slot] = np.nan if nan else high


@kernel
def _add_kernel(target, other, y0, y1):
    _H, W, D = target.shape
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                target[y, x, d] += other[y, x, d]

# ----------------------------------------------------------------------------------------------------
# Semi-global matching by rows in bounded memory (.lean): the sweeps of _sgm_sweep_kernel one band of
# rows at a time, the forward paths' sums kept in 16 bits, each row's winners taken as the backward
# sweep finishes it
# ----------------------------------------------------------------------------------------------------
@kernel
def _row_winners_kernel(values, y, winner, right, around, best, second):
    """What the steps after aggregation read of row ``y`` of a volume, from its costs ``values`` ``(W, D)``
    float32: the first lowest cost's disparity (``np.argmin``), the right image's winner (as
    :func:`_right_disparity_kernel`), the three costs around the winner clipped to ``[1, D - 2]`` (as
    :func:`_costs_around_kernel`, float64) and the best two costs (as :func:`_best_two_costs_kernel`)."""
    W, D = values.shape
    for x in range(W):
        low = np.float32(np.inf)
        chosen = 0
        for d in range(D):
            value = values[x, d]
            if value < low:
                low = value
                chosen = d
        other = np.float32(np.inf)
        for d in range(D):
            value = values[x, d]
            if (d < chosen - 1 or d > chosen + 1) and value < other:
                other = value
        winner[y, x] = chosen
        best[y, x] = low
        second[y, x] = other
        if D >= 3:
            centre = min(max(chosen, 1), D - 2)
            for k in range(3):
                around[k, y, x] = values[x, centre - 1 + k]
    for xr in range(W):
        low = np.float32(np.inf)
        chosen = 0
        for d in range(min(D, W - xr)):
            value = values[xr + d, d]
            if value < low:
                low = value
                chosen = d
        right[y, xr] = chosen


@kernel
def _band_winners_kernel(band, y0, winner, right, around, best, second):
    """:func:`_row_winners_kernel` on every row of ``band`` ``(n, W, D)``, rows ``y0 .. y0 + n``."""
    for j in range(band.shape[0]):
        _row_winners_kernel(band[j], y0 + j, winner, right, around, best, second)


@kernel
def _sgm_band_kernel(band, y0, H, quantum, P1, P2, forward, diagonals, paths, path_mins, buffer, row, total,
                     stored, scale, winner, right, around, best, second):
    """The rows of ``band`` ``(n, W, D)`` float32 (the costs of rows ``y0 .. y0 + n``) in sweep order
    (top-down when ``forward``, else bottom-up), with the path updates of :func:`_sgm_sweep_kernel`
    (:func:`_sgm_row_paths_kernel`; its ``paths``, ``path_mins``, ``buffer``, ``row`` and ``total`` are
    passed in, so that a sweep goes on across calls).

    Forward: the row's sum of its 2 or 4 paths goes to ``stored[y]`` (uint16: each path cost is below
    16383). Backward: ``S = stored[y] +`` the other paths, and ``float32(S) * scale`` (exact, as in the
    full volume: ``S < 2**24``, ``scale`` a power of two) is reduced to the row's winners
    (:func:`_row_winners_kernel`); the band is overwritten.
    """
    n, W, D = band.shape
    for j in range(n):
        k_row = j if forward else n - 1 - j
        y = y0 + k_row
        source = band[k_row]
        _sgm_row_paths_kernel(source, quantum, P1, P2, forward, diagonals, y if forward else H - 1 - y, paths,
                              path_mins, buffer, row, total)
        kept = stored[y]
        if forward:
            for x in range(W):
                for d in range(D):
                    kept[x, d] = np.uint16(total[x, d])
        else:
            for x in range(W):
                for d in range(D):
                    source[x, d] = np.float32(total[x, d] + np.int32(kept[x, d])) * scale
            _row_winners_kernel(source, y, winner, right, around, best, second)


# ----------------------------------------------------------------------------------------------------
# Winners: the right image's, the costs around each, the best two (in .winners)
# ----------------------------------------------------------------------------------------------------
@kernel
def _right_disparity_kernel(volume, out, y0, y1):
    _H, W, D = volume.shape
    slices = np.empty((D, W), np.float32)  # one row of the volume, disparity-major
    best = np.empty(W, np.float32)
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                slices[d, x] = volume[y, x, d]
        for x in range(W):
            best[x] = np.inf
            out[y, x] = 0
        for d in range(D):
            for xr in range(W - d):
                value = slices[d, xr + d]
                better = value < best[xr]
                best[xr] = value if better else best[xr]
                out[y, xr] = d if better else out[y, xr]


@kernel
def _costs_around_kernel(volume, centre, out, y0, y1):
    _H, W, _ = volume.shape
    for y in range(y0, y1):
        for x in range(W):
            c = centre[y, x]
            for k in range(3):
                out[k, y, x] = volume[y, x, c - 1 + k]


@kernel
def _best_two_costs_kernel(volume, best, second, y0, y1):
    _H, W, D = volume.shape
    slices = np.empty((D, W), np.float32)
    winner = np.empty(W, np.int64)
    for y in range(y0, y1):
        for x in range(W):
            for d in range(D):
                slices[d, x] = volume[y, x, d]
        low = best[y]
        other = second[y]
        for x in range(W):
            low[x] = np.inf
            other[x] = np.inf
            winner[x] = 0
        for d in range(D):
            for x in range(W):
                value = slices[d, x]
                better = value < low[x]
                low[x] = value if better else low[x]
                winner[x] = d if better else winner[x]
        for d in range(D):
            for x in range(W):
                value = slices[d, x]
                far = (d < winner[x] - 1) or (d > winner[x] + 1)
                other[x] = value if far and value < other[x] else other[x]


# ----------------------------------------------------------------------------------------------------
# Real-time block matching: integer SAD by running column sums (block_match_realtime, in .realtime)
# ----------------------------------------------------------------------------------------------------
@kernel
def _block_match_realtime_kernel(left, right, max_disparity, radius, out, y0, y1):
    """Rows ``y0:y1`` of the valid region: the winner-take-all disparity of the integer SAD over
    ``(2 radius + 1)^2`` windows, written to ``out`` (the caller fills the rest with -1).

    ``columns[x, d]`` holds the SAD down the window's column ``x`` (rows ``y - radius .. y + radius``)
    at disparity ``d``; moving to the next row adds the row that enters and subtracts the one that
    leaves, and each window sum is the running sum of ``2 radius + 1`` of them along the row, so the
    work is O(W D) per row whatever the window. Ties go to the smaller disparity (``np.argmin``)."""
    _H, W = left.shape
    D = max_disparity + 1
    x0 = max_disparity  # every disparity's right column x - d stays in the image from here
    columns = np.zeros((W, D), np.int32)
    sums = np.zeros(D, np.int32)
    for k in range(y0 - radius, y0 + radius + 1):
        for x in range(x0, W):
            a = np.int32(left[k, x])
            for d in range(D):
                columns[x, d] += abs(a - np.int32(right[k, x - d]))
    for y in range(y0, y1):
        if y > y0:
            enter, leave = y + radius, y - radius - 1
            for x in range(x0, W):
                a = np.int32(left[enter, x])
                b = np.int32(left[leave, x])
                for d in range(D):
                    columns[x, d] += (abs(a - np.int32(right[enter, x - d]))
                                      - abs(b - np.int32(right[leave, x - d])))
        for d in range(D):
            sums[d] = 0
        for x in range(x0, x0 + 2 * radius + 1):
            for d in range(D):
                sums[d] += columns[x, d]
        for x in range(x0 + radius, W - radius):
            best = sums[0]
            winner = 0
            for d in range(1, D):
                if sums[d] < best:
                    best = sums[d]
                    winner = d
            out[y, x] = winner
            if x + radius + 1 < W:
                for d in range(D):
                    sums[d] += columns[x + radius + 1, d] - columns[x - radius, d]


# ----------------------------------------------------------------------------------------------------
# Warm-up (lab.core.kernels): every cost, SGM on 4 and 8 paths, the winners, the filters, on a tiny pair
# ----------------------------------------------------------------------------------------------------
def _warm_up() -> None:
    """The steps from the cost volume to the filtered disparity on a 64 x 48 synthetic pair, once per cost,
    the Hamming costs of census codes (the lesson's helper; the step sums them by rows), and SGM and block
    matching by rows (the path of volumes too large to keep) on a 16 x 12 pair, and real-time block
    matching (8-bit SAD) on a 24 x 12 pair."""
    from lab.modules.stereo import (COSTS, PIPELINE, block_match_realtime, block_matching_rows, census_rows,
                                    census_transform, hamming_costs, semi_global_matching_rows)

    codes = census_transform(np.zeros((8, 12), np.float32), 5)
    hamming_costs(codes, codes, 4)
    for index, cost in enumerate(COSTS):
        params: dict[str, dict[str, object]] = {"cost_volume": {"cost": cost, "max_disparity": 8},
                                                "aggregate_costs": {"paths": 4 if index % 2 else 8}}
        warm_up_steps(PIPELINE, "synthetic", {"width": 64, "height": 48}, "filter_disparity", params)
    rows = census_rows(np.zeros((12, 16), np.float32), np.ones((12, 16), np.float32), 4, 5)  # volumes by rows
    semi_global_matching_rows(rows, P1=0.05, P2=1.0, paths=8)
    block_matching_rows(rows)
    block_match_realtime(np.zeros((12, 24), np.uint8), np.zeros((12, 24), np.uint8), max_disparity=4, block=3)


register_warm_up("stereo", ("cost_volume", "aggregate_costs", "left_right_check", "refine_subpixel",
                            "filter_disparity"), dispatchers_in(globals()), _warm_up)
