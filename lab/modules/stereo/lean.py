"""Semi-global matching at full resolution in bounded memory: census costs by bands of rows, the forward
paths' sums in 16 bits, each row's winners taken as the backward sweep passes it.

A 1282 x 1110 pair with 257 disparities has 366 million costs: 1.4 GB as one float32 volume, twice
that with the aggregated one. What the steps after aggregation read of a volume is small: each
pixel's winner, the right image's winner, the three costs around the winner and the best two
costs. So a cost volume over :data:`lab.modules.stereo.MAX_VOLUME_ENTRIES` is kept as what computes
it (:class:`CensusRows`: the census strings of both images), and aggregation keeps only those
reductions (:class:`RowWinners`):

1. the largest cost, which fixes SGM's integer scale (:func:`~lab.modules.stereo.sgm.sgm_scale`),
   from one pass over bands of rows;
2. the forward sweep (the paths from the left and from the row above) on bands of rows computed on
   the fly, each pixel's sum of those paths stored in 16 bits: every path cost stays below 16383,
   so 4 of them fit a uint16 (``H x W x D x 2`` bytes, the one large array);
3. the backward sweep (the other paths), bands from the bottom: each row's total ``S`` is the
   stored sum plus its paths, and the row is reduced to its winners at once.

The costs, their rounding and the path updates are those of the full-volume path
(:func:`~lab.modules.stereo.census_costs` and :func:`~lab.modules.stereo.semi_global_matching`),
in integers, so the winners, the costs around them and the best two costs are the same bit for bit;
the full-volume path stays the readable reference and the tests' oracle. The next band's costs are
computed on the thread pool while the current band is aggregated.

This is OpenCV's ``StereoSGBM`` in its full 8-path mode (``MODE_HH``: 16-bit costs, path sums kept
for the whole image, row buffers for the paths) with census costs. Reference: H. Hirschmüller,
"Stereo processing by semiglobal matching and mutual information", TPAMI 30(2), 2008, sections
3.3 and 4.1 (memory-efficient implementation).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core import CapacityExceeded, InvalidControl, budgets
from lab.core.kernels import in_parallel, workers
from lab.modules.stereo import _checks
from lab.modules.stereo._kernels import (SGM_LARGEST, _band_winners_kernel, _census_costs_kernel,
                                         _sgm_band_kernel, _volume_range_kernel)
from lab.modules.stereo.costs import census_transform, census_words
from lab.modules.stereo.sgm import check_penalties, sgm_scale

#: Entries of one band of float32 costs computed at once (32 MiB; two bands live at a time).
BAND_ENTRIES = 2**23


@dataclass(frozen=True, eq=False)
class CensusRows:
    """A census cost volume ``(H, W, D)`` too large to keep, held as what computes any band of its rows.

    ``codes_left``, ``codes_right`` ``(H, W, words)`` uint64 are the census strings of the two images
    (:func:`~lab.modules.stereo.census_transform` over ``window``); ``disparities`` is ``D``.
    :meth:`band` gives rows ``y0:y1`` of :func:`~lab.modules.stereo.census_costs`'s volume, bit for bit.
    """

    codes_left: np.ndarray
    codes_right: np.ndarray
    window: int
    disparities: int

    @property
    def shape(self) -> tuple[int, int, int]:
        H, W, _ = self.codes_left.shape
        return int(H), int(W), int(self.disparities)

    @property
    def ndim(self) -> int:
        """3, as the volume's (``np.ndim`` and ``np.shape`` read the volume's shape)."""
        return 3

    def band_job(self, y0: int, y1: int, out: np.ndarray) -> tuple[Any, ...]:
        """The kernel call (for :func:`lab.core.kernels.in_parallel`) writing rows ``y0:y1`` into ``out``."""
        factor = 1.0 / (self.window * self.window * (self.window * self.window - 1))
        return (_census_costs_kernel, self.codes_left, self.codes_right, self.window // 2, factor, out,
                y0, y1, y0)

    def band(self, y0: int, y1: int, out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``y0:y1`` of the cost volume, ``(y1 - y0, W, D)`` float32 (into ``out`` when given)."""
        _, W, D = self.shape
        if out is None:
            out = np.empty((y1 - y0, W, D), np.float32)
        _call(*self.band_job(y0, y1, out))
        return out


@dataclass(frozen=True, eq=False)
class RowWinners:
    """What the steps after aggregation read of a volume ``(H, W, D)`` too large to keep, row by row.

    ``winner`` ``(H, W)`` int64: the first lowest cost's disparity (``np.argmin``); ``right``
    ``(H, W)`` int64: the right image's winner (:func:`~lab.modules.stereo.right_disparity`);
    ``around`` ``(3, H, W)`` float64: the costs at ``c - 1, c, c + 1`` for ``c`` the winner clipped to
    ``[1, D - 2]`` (:func:`~lab.modules.stereo.costs_around`); ``best``, ``second`` ``(H, W)``
    float32: :func:`~lab.modules.stereo.best_two_costs`. ``disparities`` is ``D``.
    """

    winner: np.ndarray
    right: np.ndarray
    around: np.ndarray
    best: np.ndarray
    second: np.ndarray
    disparities: int

    @classmethod
    def empty(cls, height: int, width: int, disparities: int) -> RowWinners:
        return cls(np.zeros((height, width), np.int64), np.zeros((height, width), np.int64),
                   np.zeros((3, height, width), np.float64), np.zeros((height, width), np.float32),
                   np.zeros((height, width), np.float32), int(disparities))

    @property
    def shape(self) -> tuple[int, int, int]:
        H, W = self.winner.shape
        return int(H), int(W), self.disparities

    @property
    def ndim(self) -> int:
        return 3

    @property
    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.winner, self.right, self.around, self.best, self.second


def census_rows(gray_left: np.ndarray, gray_right: np.ndarray, disparities: int, window: int) -> CensusRows:
    """The census strings of both ``(H, W)`` images over ``window``: a :class:`CensusRows` of
    ``disparities``."""
    return CensusRows(census_transform(gray_left, window), census_transform(gray_right, window), int(window),
                      int(disparities))


def band_height(width: int, disparities: int) -> int:
    """Rows per band: :data:`BAND_ENTRIES` costs, at least 8 rows."""
    return max(8, BAND_ENTRIES // max(width * disparities, 1))


def lean_memory_bytes(height: int, width: int, disparities: int, window: int) -> int:
    """What :func:`semi_global_matching_rows` holds at its peak, in bytes: the 16-bit path sums
    ``H x W x D x 2``, two bands of float32 costs, the census strings, the winners (36 bytes a pixel)
    and the row buffers."""
    H, W, D = int(height), int(width), int(disparities)
    bands = 2 * min(band_height(W, D), H) * W * D * 4
    codes = 2 * H * W * census_words(int(window)) * 8
    rows = 2 * 3 * W * (D + 2) * 2 + W * D * 6
    return H * W * D * 2 + bands + codes + H * W * 36 + rows


def check_lean_memory(height: int, width: int, disparities: int, window: int) -> None:
    """Refuse (CapacityExceeded on ``max_disparity``) a pair whose row-wise SGM would hold more than
    :data:`lab.core.budgets.MAX_STEREO_BYTES`, naming the memory it needs and the downsample option."""
    need = lean_memory_bytes(height, width, disparities, window)
    budget = budgets.MAX_STEREO_BYTES
    if need <= budget:
        return
    halved = lean_memory_bytes(height // 2, width // 2, disparities // 2 + 1, window)
    raise CapacityExceeded("max_disparity", f"semi-global matching of {width} x {height} pixels over "
                                            f"{disparities} disparities needs about {need / 2**20:,.0f} MiB "
                                            f"(16-bit path sums of every pixel and disparity), more than the "
                                            f"{budget / 2**20:,.0f} MiB allowed "
                                            "(lab.core.budgets.MAX_STEREO_BYTES): shrink the pair with the "
                                            f"dataset's downsample option (downsample=2 needs about "
                                            f"{halved / 2**20:,.0f} MiB) or lower max_disparity")


def check_by_rows(cost: str, height: int, width: int, disparities: int, window: int) -> None:
    """Refuse a volume too large to keep whole (over :data:`~lab.modules.stereo.MAX_VOLUME_ENTRIES`) that
    cannot be aggregated by rows either: a cost other than census (InvalidControl on ``max_disparity``),
    or a pair over the memory budget (:func:`check_lean_memory`)."""
    entries = height * width * disparities
    if cost != "census":
        need = lean_memory_bytes(height, width, disparities, window)
        raise InvalidControl("max_disparity", f"the {cost} cost volume would hold {height} x {width} x "
                                              f"{disparities} = {entries:,} costs "
                                              f"({entries * 4 / 2**20:,.0f} MiB), more than the "
                                              f"{_checks.MAX_VOLUME_ENTRIES:,} allowed whole; only census "
                                              "costs are aggregated by rows in bounded memory (about "
                                              f"{need / 2**20:,.0f} MiB here): use cost='census', lower "
                                              "max_disparity, or shrink the pair with the dataset's "
                                              "downsample option")
    check_lean_memory(height, width, disparities, window)


def _call(function: Callable[..., Any], *args: Any) -> Any:
    return function(*args)


def _spans(height: int, rows: int) -> list[tuple[int, int]]:
    return [(y0, min(y0 + rows, height)) for y0 in range(0, height, rows)]


def _sweep(costs: CensusRows, forward: bool, job: Callable[[np.ndarray, int], tuple[Any, ...]]) -> None:
    """``job(band, y0)`` (a kernel call) on every band of rows, top-down when ``forward`` else bottom-up,
    each band's costs computed on the thread pool while the one before it is worked on."""
    H, W, D = costs.shape
    spans = _spans(H, min(band_height(W, D), H))
    if not forward:
        spans.reverse()
    size = max(y1 - y0 for y0, y1 in spans)
    buffers = [np.empty((size, W, D), np.float32) for _ in range(min(2, len(spans)))]
    costs.band(*spans[0], out=buffers[0][:spans[0][1] - spans[0][0]])
    for k, (y0, y1) in enumerate(spans):
        jobs = [job(buffers[k % len(buffers)][:y1 - y0], y0)]
        if k + 1 < len(spans):
            a, b = spans[k + 1]
            jobs.append(costs.band_job(a, b, buffers[(k + 1) % 2][:b - a]))
        in_parallel(_call, jobs)


def _band_peaks(costs: CensusRows, spans: list[tuple[int, int]], slots: list[int], buffer: np.ndarray,
                lows: np.ndarray, highs: np.ndarray) -> None:
    for slot in slots:
        y0, y1 = spans[slot]
        band = costs.band(y0, y1, out=buffer[:y1 - y0])
        _volume_range_kernel(band, lows, highs, 0, y1 - y0, slot)


def cost_peak(costs: CensusRows) -> float:
    """The largest cost of the volume (one pass over bands of rows, one worker per share of the bands)."""
    H, W, D = costs.shape
    spans = _spans(H, min(band_height(W, D), H))
    lows, highs = np.empty(len(spans)), np.empty(len(spans))
    share = max(1, min(workers(), len(spans)))
    size = spans[0][1] - spans[0][0]
    in_parallel(_band_peaks, [(costs, spans, list(range(k, len(spans), share)),
                               np.empty((size, W, D), np.float32), lows, highs) for k in range(share)])
    return float(highs.max())


def semi_global_matching_rows(costs: CensusRows, *, P1: float, P2: float, paths: int = 8) -> RowWinners:
    """:func:`~lab.modules.stereo.semi_global_matching` of a :class:`CensusRows` volume, reduced to its
    :class:`RowWinners`, holding ``H x W x D`` 16-bit sums and a few bands of rows
    (:func:`lean_memory_bytes`).

    The same integer scale (from the largest cost, :func:`cost_peak`), rounding and path updates as
    the full-volume path, so every winner and cost it keeps equals what the steps read from the full
    aggregated volume, bit for bit.
    """
    P1, P2 = check_penalties(P1, P2, paths)
    H, W, D = costs.shape
    scale = sgm_scale(cost_peak(costs), P2, paths)  # census costs are never negative: no shift
    quantum, inverse = np.float32(scale), np.float32(1.0 / scale)
    p1, p2 = np.int16(round(P1 * scale)), np.int16(round(P2 * scale))
    stored = np.empty((H, W, D), np.uint16)
    out = RowWinners.empty(H, W, D)
    big = np.int16(SGM_LARGEST)
    for forward in (True, False):
        state = (np.full((2, 3, W, D + 2), big, np.int16), np.zeros((2, 3, W), np.int16),
                 np.full((2, D + 2), big, np.int16), np.empty((W, D), np.int16), np.empty((W, D), np.int32))

        def job(band: np.ndarray, y0: int, forward: bool = forward,
                state: tuple[np.ndarray, ...] = state) -> tuple[Any, ...]:
            return (_sgm_band_kernel, band, y0, H, quantum, p1, p2, forward, paths == 8, *state, stored,
                    inverse, *out.arrays)

        _sweep(costs, forward, job)
    return out


def block_matching_rows(costs: CensusRows) -> RowWinners:
    """The :class:`RowWinners` of the census costs themselves (``aggregate_costs(method="none")``)."""
    H, W, D = costs.shape
    out = RowWinners.empty(H, W, D)
    _sweep(costs, True, lambda band, y0: (_band_winners_kernel, band, y0, *out.arrays))
    return out
