"""Semi-global matching (Hirschmüller 2008, section 3.3): the aggregation of
:func:`~lab.modules.stereo.aggregate_costs`.

The costs are checked and quantized (:func:`sgm_inputs`, :func:`quantize_costs`), then the two
sweeps of the fast kernel run at once on the thread pool (:func:`semi_global_matching`); its
oracle, path by path, is :func:`lab.modules.stereo.reference.sgm_reference`.
"""

from __future__ import annotations

import numpy as np

from lab.core import InvalidControl, InvalidValue, kernels
from lab.core.kernels import bands, in_parallel
from lab.modules.stereo._checks import check_volume
from lab.modules.stereo._kernels import SGM_LARGEST, _add_kernel, _sgm_sweep_kernel, _volume_range_kernel

#: Path directions ``r = (dy, dx)``: ``L_r(p)`` follows from ``L_r(p - r)``. The first four are the 4-path
#: set.
SGM_DIRECTIONS: tuple[tuple[int, int], ...] = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, -1),
                                               (-1, 1))


def sgm_scale(peak: float, P2: float, paths: int) -> float:
    """A power of two ``s`` that turns costs into integers with 12 bits below the largest cost, while a path
    cost (at most ``peak + P2``) fits the kernel's 16 bits and the sum of ``paths`` paths stays below
    2**24 (exact in float32)."""
    exponent = 20
    while exponent > -40 and (peak * 2.0**exponent > 4096.0 or (peak + P2) * 2.0**exponent >= SGM_LARGEST
                              or paths * (peak + P2) * 2.0**exponent >= 2.0**24):
        exponent -= 1
    return 2.0**exponent


def quantize_costs(volume: np.ndarray, scale: float) -> np.ndarray:
    """The integer costs SGM works on, ``floor(volume * scale + 0.5)`` as int64 (``scale`` a power of two)."""
    return np.floor(np.asarray(volume, dtype=np.float64) * scale + 0.5).astype(np.int64)


def volume_range(volume: np.ndarray) -> tuple[float, float]:
    """``(volume.min(), volume.max())`` of a float32 ``(H, W, D)`` volume in one pass, bands of rows on the
    thread pool; NaN when the volume holds one."""
    rows = bands(volume.shape[0])
    lows = np.empty(len(rows), np.float64)
    highs = np.empty(len(rows), np.float64)
    in_parallel(_volume_range_kernel, [(volume, lows, highs, y0, y1, k) for k, (y0, y1) in enumerate(rows)])
    if np.isnan(lows).any() or np.isnan(highs).any():
        return float("nan"), float("nan")
    return float(lows.min()), float(highs.max())


def check_penalties(P1: float, P2: float, paths: int) -> tuple[float, float]:
    """``(P1, P2)`` as floats, refusing ``paths`` other than 4 or 8 and penalties not ``0 <= P1 <= P2``."""
    if paths not in (4, 8):
        raise InvalidControl("paths", f"must be 4 or 8, got {paths!r}")
    P1, P2 = float(P1), float(P2)
    if P1 < 0 or P2 < P1:
        raise InvalidControl("P2", f"the penalties must satisfy 0 <= P1 <= P2, got P1 = {P1}, P2 = {P2}")
    return P1, P2


def sgm_inputs(volume: np.ndarray, P1: float, P2: float, paths: int) -> tuple[np.ndarray, float, int, int]:
    """Checked non-negative costs, the quantization scale and the integer penalties."""
    volume = check_volume(volume, "cost_volume", finite=False)
    P1, P2 = check_penalties(P1, P2, paths)
    low, high = volume_range(volume) if volume.size else (0.0, 0.0)
    if not (np.isfinite(low) and np.isfinite(high)):
        raise InvalidValue("cost_volume", "contains NaN or infinite costs")
    if low < 0:  # SGM's result does not change when every cost moves by one constant
        volume = volume - np.float32(low)
        high -= low
    scale = sgm_scale(high, P2, paths)
    return volume, scale, round(P1 * scale), round(P2 * scale)


def semi_global_matching(volume: np.ndarray, *, P1: float, P2: float, paths: int = 8) -> np.ndarray:
    """Aggregate a cost volume ``(H, W, D)`` along ``paths`` (4 or 8) scanline directions; returns float32
    ``S``.

    Costs and penalties are scaled by a power of two and rounded to integers (OpenCV's SGBM works
    in 16-bit integers too; :func:`quantize_costs`); the fast kernel (:func:`_sgm_sweep_kernel`, two
    sweeps of 2 or 4 paths each) then computes exactly what :func:`sgm_reference` computes on
    those integers, and ``S`` is returned in cost units (negative costs are first shifted to 0).
    """
    volume, scale, p1, p2 = sgm_inputs(volume, P1, P2, paths)
    quantum, inverse = np.float32(scale), np.float32(1.0 / scale)
    out: np.ndarray = np.empty(volume.shape, np.float32)
    penalties, diagonals = (np.int16(p1), np.int16(p2)), paths == 8
    if kernels.workers() == 1:
        _sgm_sweep_kernel(volume, quantum, *penalties, True, diagonals, out, inverse, False)
        _sgm_sweep_kernel(volume, quantum, *penalties, False, diagonals, out, inverse, True)
        return out
    backward = np.empty(volume.shape, np.float32)  # the two sweeps run at once, each into its own volume
    sweeps = [(volume, quantum, *penalties, True, diagonals, out, inverse, False),
              (volume, quantum, *penalties, False, diagonals, backward, inverse, False)]
    in_parallel(_sgm_sweep_kernel, sweeps)
    in_parallel(_add_kernel, [(out, backward, y0, y1) for y0, y1 in bands(out.shape[0])])
    return out
