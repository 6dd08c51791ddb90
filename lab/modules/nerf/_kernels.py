"""The NeRF grid's compiled loops (Numba, :func:`lab.core.kernels.kernel`): one ray at a time, march through
the voxel grid, skip empty space, interpolate density and colour, composite front to back and stop early.

:func:`lab.modules.nerf.grid.composite_grid` (forward, no gradient) and its autograd function
:class:`lab.modules.nerf.grid.CompositeGrid` call them; the readable version is
:func:`lab.modules.nerf.reference.composite_grid_reference`, and the gradient is checked against torch's
autograd through the vectorized path (:func:`lab.modules.nerf.grid.grid_candidates`, trilinear
:meth:`~lab.modules.nerf.grid.GridField.sample`, :func:`lab.modules.nerf.rendering.volume_render_packed`).

The samples are those of :func:`~lab.modules.nerf.grid.grid_candidates`: ray ``o + t d``, ``t = near + (k +
shift) s`` for ``k < count`` and ``t < far`` with the depth step ``s = step radius / |d|``, kept where the
grid vertex nearest the normalized point ``x = (o + t d - centre) / radius`` is occupied; interval length
``min(s, far - t) |d|``. ``params`` packs the scalars: ``near, far, centre_x, centre_y, centre_z, radius,
step, stop`` (``stop``: the ray ends once its transmittance falls below it; 0: never), then the normalized
box that holds the occupied vertices (lower corner, upper corner), outside which no step is looked at.
"""

from __future__ import annotations

import math

import numpy as np

from lab.core.kernels import dispatchers_in, kernel, register_warm_up

#: ``sigma = DENSITY_GAIN softplus(raw + DENSITY_SHIFT)`` (see :func:`lab.modules.nerf.grid.grid_density`).
DENSITY_GAIN = 50.0
#: Added to the interpolated raw density before the softplus: raw 0 gives sigma about 0.0067.
DENSITY_SHIFT = -5.0 - math.log(DENSITY_GAIN)
_GAIN, _SHIFT = DENSITY_GAIN, DENSITY_SHIFT


@kernel
def _sample_point_kernel(table: np.ndarray, r: int, x0: float, x1: float, x2: float, rows: np.ndarray,
                         weights: np.ndarray, rgb: np.ndarray) -> float:
    """Trilinear interpolation at normalized ``x`` of the ``(r^3, 4)`` table (row ``(i r + j) r + k``: raw
    density and raw RGB): fills the
    8 corner ``rows`` and ``weights`` and the colour ``rgb`` (sigmoid of the raw values), returns the raw
    density (before the shift and softplus). The base vertex is clamped to ``[0, r - 2]`` as
    :meth:`~lab.modules.nerf.grid.GridField.corners` does."""
    half = 0.5 * (r - 1)
    g0, g1, g2 = (x0 + 1.0) * half, (x1 + 1.0) * half, (x2 + 1.0) * half
    b0 = min(max(math.floor(g0), 0.0), r - 2.0)
    b1 = min(max(math.floor(g1), 0.0), r - 2.0)
    b2 = min(max(math.floor(g2), 0.0), r - 2.0)
    f0, f1, f2 = g0 - b0, g1 - b1, g2 - b2
    i0, i1, i2 = int(b0), int(b1), int(b2)
    raw = 0.0
    c0 = c1 = c2 = 0.0
    n = 0
    for a in range(2):
        wa = f0 if a else 1.0 - f0
        for b in range(2):
            wb = wa * (f1 if b else 1.0 - f1)
            for c in range(2):
                w = wb * (f2 if c else 1.0 - f2)
                row = ((i0 + a) * r + (i1 + b)) * r + (i2 + c)
                rows[n] = row
                weights[n] = w
                raw += w * table[row, 0]
                c0 += w * table[row, 1]
                c1 += w * table[row, 2]
                c2 += w * table[row, 3]
                n += 1
    rgb[0] = 1.0 / (1.0 + math.exp(-c0))
    rgb[1] = 1.0 / (1.0 + math.exp(-c1))
    rgb[2] = 1.0 / (1.0 + math.exp(-c2))
    return raw


@kernel
def _softplus_kernel(v: float) -> float:
    return v if v > 20.0 else math.log1p(math.exp(v))


@kernel
def _occupied_kernel(cells: np.ndarray, x0: float, x1: float, x2: float) -> bool:
    """Whether the vertex nearest normalized ``x`` of the occupancy grid is occupied (outside: empty)."""
    side = cells.shape[0]
    half = 0.5 * (side - 1)
    i = round((x0 + 1.0) * half)
    j = round((x1 + 1.0) * half)
    k = round((x2 + 1.0) * half)
    if i < 0 or j < 0 or k < 0 or i >= side or j >= side or k >= side:
        return False
    return bool(cells[int(i), int(j), int(k)])


@kernel
def _slab_kernel(o: float, d: float, lo: float, hi: float, enter: float, leave: float) -> tuple[float, float]:
    """The ray parameters ``(enter, leave)`` narrowed to where ``o + t d`` lies in ``[lo, hi]`` (one axis)."""
    if d == 0.0:
        return (enter, leave) if lo <= o <= hi else (np.inf, -np.inf)
    a, b = (lo - o) / d, (hi - o) / d
    return max(enter, min(a, b)), min(leave, max(a, b))


@kernel
def _step_range_kernel(params: np.ndarray, o0: float, o1: float, o2: float, d0: float, d1: float, d2: float,
                       ds: float, shift: float, count: int) -> tuple[int, int]:
    """The steps ``k0 <= k < k1`` of one ray that may lie in the box ``params[8:14]`` (normalized lower and
    upper corners holding every occupied vertex's half-voxel neighbourhood; slab test): no step outside
    it can be occupied, so the march skips them (the samples are those of every step checked)."""
    near, radius = params[0], params[5]
    enter, leave = _slab_kernel(o0, d0, params[8] * radius, params[11] * radius, -np.inf, np.inf)
    enter, leave = _slab_kernel(o1, d1, params[9] * radius, params[12] * radius, enter, leave)
    enter, leave = _slab_kernel(o2, d2, params[10] * radius, params[13] * radius, enter, leave)
    if leave < enter:
        return 0, 0
    k0 = max(0, math.floor((enter - near) / ds - shift))
    k1 = min(count, math.ceil((leave - near) / ds - shift) + 1)
    return k0, max(k0, k1)


@kernel
def _render_grid_kernel(table: np.ndarray, r: int, cells: np.ndarray,
                        origins: np.ndarray, directions: np.ndarray, shift: np.ndarray, params: np.ndarray,
                        count: int, background: np.ndarray, out_color: np.ndarray, out_depth: np.ndarray,
                        out_opacity: np.ndarray, out_samples: np.ndarray, start: int, stop: int) -> None:
    """Rays ``start .. stop``: march, composite (Mildenhall et al. eq. 3, front to back), stop early; write
    each ray's colour over ``background``, expected depth (the rest at far), opacity and samples used."""
    near, far, radius, step, end = params[0], params[1], params[5], params[6], params[7]
    rows = np.empty(8, np.int64)
    weights = np.empty(8)
    rgb = np.empty(3)
    for ray in range(start, stop):
        d0, d1, d2 = directions[ray, 0], directions[ray, 1], directions[ray, 2]
        norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        o0, o1, o2 = origins[ray, 0] - params[2], origins[ray, 1] - params[3], origins[ray, 2] - params[4]
        ds = step * radius / norm
        transmittance = 1.0
        acc0 = acc1 = acc2 = depth = 0.0
        used = 0
        k0, k1 = _step_range_kernel(params, o0, o1, o2, d0, d1, d2, ds, shift[ray], count)
        for k in range(k0, k1):
            t = near + (k + shift[ray]) * ds
            if t >= far:
                break
            x0, x1, x2 = (o0 + t * d0) / radius, (o1 + t * d1) / radius, (o2 + t * d2) / radius
            if not _occupied_kernel(cells, x0, x1, x2):
                continue
            raw = _sample_point_kernel(table, r, x0, x1, x2, rows, weights, rgb)
            sigma = _GAIN * _softplus_kernel(raw + _SHIFT)
            alpha = -math.expm1(-sigma * min(ds, far - t) * norm)
            w = transmittance * alpha
            acc0 += w * rgb[0]
            acc1 += w * rgb[1]
            acc2 += w * rgb[2]
            depth += w * t
            transmittance *= 1.0 - alpha
            used += 1
            if transmittance < end:
                break
        opacity = 1.0 - transmittance
        out_color[ray, 0] = acc0 + transmittance * background[0]
        out_color[ray, 1] = acc1 + transmittance * background[1]
        out_color[ray, 2] = acc2 + transmittance * background[2]
        out_depth[ray] = depth + transmittance * far
        out_opacity[ray] = opacity
        out_samples[ray] = used


@kernel
def _render_grid_backward_kernel(table: np.ndarray, r: int, cells: np.ndarray, origins: np.ndarray,
                                 directions: np.ndarray, shift: np.ndarray, params: np.ndarray, count: int,
                                 rendered: np.ndarray, grad: np.ndarray, grad_table: np.ndarray) -> None:
    """The gradient of ``sum(grad * colour)`` over the raw table, added into ``grad_table`` ``(N, 4)``: each
    ray marched again over the same samples, with its ``rendered`` colour ``C`` (background included).
    With ``acc_i = sum_(j <= i) w_j c_j`` (so ``C - acc_i`` is what lies behind sample ``i``),
    ``dC / dc_i = w_i`` and ``dC / dsigma_i = delta_i (T_(i+1) c_i - (C - acc_i))`` (Plenoxels' and DVGO's
    backward pass); then through the sigmoid, the scaled softplus and the 8 trilinear weights."""
    near, far, radius, step, end = params[0], params[1], params[5], params[6], params[7]
    rows = np.empty(8, np.int64)
    weights = np.empty(8)
    rgb = np.empty(3)
    for ray in range(origins.shape[0]):
        g0, g1, g2 = grad[ray, 0], grad[ray, 1], grad[ray, 2]
        if g0 == 0.0 and g1 == 0.0 and g2 == 0.0:
            continue
        d0, d1, d2 = directions[ray, 0], directions[ray, 1], directions[ray, 2]
        norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        o0, o1, o2 = origins[ray, 0] - params[2], origins[ray, 1] - params[3], origins[ray, 2] - params[4]
        ds = step * radius / norm
        total0, total1, total2 = rendered[ray, 0], rendered[ray, 1], rendered[ray, 2]
        transmittance = 1.0
        acc0 = acc1 = acc2 = 0.0
        k0, k1 = _step_range_kernel(params, o0, o1, o2, d0, d1, d2, ds, shift[ray], count)
        for k in range(k0, k1):
            t = near + (k + shift[ray]) * ds
            if t >= far:
                break
            x0, x1, x2 = (o0 + t * d0) / radius, (o1 + t * d1) / radius, (o2 + t * d2) / radius
            if not _occupied_kernel(cells, x0, x1, x2):
                continue
            raw = _sample_point_kernel(table, r, x0, x1, x2, rows, weights, rgb)
            sigma = _GAIN * _softplus_kernel(raw + _SHIFT)
            delta = min(ds, far - t) * norm
            alpha = -math.expm1(-sigma * delta)
            w = transmittance * alpha
            acc0 += w * rgb[0]
            acc1 += w * rgb[1]
            acc2 += w * rgb[2]
            after = transmittance * (1.0 - alpha)
            d_sigma = delta * (g0 * (after * rgb[0] - (total0 - acc0))
                               + g1 * (after * rgb[1] - (total1 - acc1))
                               + g2 * (after * rgb[2] - (total2 - acc2)))
            d_raw = _GAIN * d_sigma / (1.0 + math.exp(-(raw + _SHIFT)))   # softplus' = sigmoid
            e0 = g0 * w * rgb[0] * (1.0 - rgb[0])
            e1 = g1 * w * rgb[1] * (1.0 - rgb[1])
            e2 = g2 * w * rgb[2] * (1.0 - rgb[2])
            for n in range(8):
                row, wn = rows[n], weights[n]
                grad_table[row, 0] += wn * d_raw
                grad_table[row, 1] += wn * e0
                grad_table[row, 2] += wn * e1
                grad_table[row, 3] += wn * e2
            transmittance = after
            if transmittance < end:
                break


# ----------------------------------------------------------------------------------------------------
# Warm-up (lab.core.kernels): both passes on a 4^3 grid and two rays
# ----------------------------------------------------------------------------------------------------
def _warm_up() -> None:
    """Both kernels once on a 4^3 grid, with the dtypes :mod:`lab.modules.nerf.grid` passes."""
    r = 4
    table = np.zeros((r ** 3, 4), np.float32)
    cells = np.ones((r, r, r), np.bool_)
    origins = np.array([[0.0, 0.0, -3.0], [0.1, 0.0, -3.0]], np.float32)
    directions = np.array([[0.0, 0.0, 1.0], [0.0, 0.1, 1.0]], np.float32)
    shift = np.full(2, 0.5, np.float32)
    params = np.array([2.0, 4.0, 0.0, 0.0, 0.0, 1.0, 0.5, 1e-4, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    colors, depth = np.zeros((2, 3), np.float32), np.zeros(2, np.float32)
    opacity, used = np.zeros(2, np.float32), np.zeros(2, np.int32)
    _render_grid_kernel(table, r, cells, origins, directions, shift, params, 8,
                        np.ones(3, np.float32), colors, depth, opacity, used, 0, 2)
    _render_grid_backward_kernel(table, r, cells, origins, directions, shift, params, 8, colors,
                                 np.ones((2, 3), np.float32), np.zeros_like(table))


register_warm_up("nerf", ("train_nerf", "render_held_out", "render_view"), dispatchers_in(globals()),
                 _warm_up)
