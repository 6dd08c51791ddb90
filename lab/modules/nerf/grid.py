"""The accelerated variant: an explicit voxel grid of density and colour, trained coarse to fine, with an
occupancy grid that skips empty space and early ray termination (issue 17 item 3).

Plenoxels (Fridovich-Keil et al., CVPR 2022) and DVGO (Sun et al., CVPR 2022) showed that a radiance
field needs no network: trilinearly interpolated values on a grid, rendered by the same volume rendering
(:func:`~lab.modules.nerf.rendering.volume_render`), optimized directly with a high learning rate. Here:

- one density and one RGB value per vertex of an ``R^3`` grid over the normalized scene box ``[-1, 1]^3``
  (colour without view dependence: the lab's scenes are Lambertian), ``sigma = gain softplus(raw + shift)``
  (:func:`grid_density`) with a near-zero start (``shift`` = :data:`DENSITY_SHIFT`; DVGO's ``alpha_init``
  of 1e-2 never empties space on a CPU budget), colour ``sigmoid(raw)``;
- one interleaved table ``(R^3, 4)`` (raw density, raw RGB: a vertex is one cache line), updated by
  torch's fused Adam;
- coarse to fine: the grid starts at ``R / 4`` and is upsampled (trilinearly) to ``R / 2`` and ``R`` at a
  quarter and at half of the budget; the step along rays is half a voxel of the current grid;
- a total-variation penalty (:func:`total_variation`, Plenoxels' eq. 5) on the raw density and colours of
  randomly drawn occupied vertices, added to the photometric loss: without it the grid fits its 40
  training views to 43 dB and the held-out ones to 31 (each vertex free to explain the few rays that
  cross it); with a weight of 1e-3 on both, 38 and 33.6 dB after 120 CPU s;
- empty-space skipping: samples whose nearest vertex has a dilated density below :data:`EMPTY_SIGMA` are
  not evaluated (the occupancy grid is refreshed every :data:`OCCUPANCY_EVERY` iterations);
- on the CPU, one compiled loop per ray (:mod:`~lab.modules.nerf._kernels`, numba; :func:`composite_grid`
  and the autograd function :class:`CompositeGrid`): the ray is clipped to the box of occupied vertices,
  marched, interpolated, composited front to back and ended once its transmittance is below
  :data:`STOP_BELOW` (early termination); the backward pass marches it again and scatters Plenoxels'
  closed-form gradient into the table. Its oracle is
  :func:`~lab.modules.nerf.reference.composite_grid_reference`;
- elsewhere (CUDA) the vectorized path :func:`render_grid`: packed candidates by a two-level search
  (:func:`grid_candidates`), trilinear gathers of the 8 corner rows (``embedding_bag`` without gradient,
  ``index_select`` with it; :meth:`GridField.sample`), a first pass without gradient for every sample's
  weight, and only samples of weight >= :data:`SKIP_BELOW` evaluated with gradient (DVGO's "fast colour
  threshold"). It is also what draws the weights along one ray.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from lab.core import Cancelled, Image, InvalidValue, Progress
from lab.core.kernels import all_compiled, bands, in_parallel
from lab.modules.nerf._kernels import (DENSITY_GAIN, DENSITY_SHIFT, _render_grid_backward_kernel,
                                      _render_grid_kernel, _warm_up)
from lab.modules.nerf.evaluate import psnr_from_mse
from lab.modules.nerf.model import ImageRendering
from lab.modules.nerf.rendering import PackedRendering, volume_render_packed
from lab.modules.nerf.training import REPORT_EVERY, PreviewRays, TrainingRun
from lab.modules.nerf.values import RayBundle, SceneBounds

#: Steps along a ray checked together against a dilated occupancy first (see :func:`grid_candidates`).
GROUP = 4
#: Iterations between two refreshes of the occupancy grid.
OCCUPANCY_EVERY = 16
#: Samples of a smaller weight are not evaluated with gradient (behind surfaces, or nearly empty).
SKIP_BELOW = 1e-5
#: Training rays per pixel along each axis: a pixel's colour is fitted by the mean of ``SUPERSAMPLE^2``
#: rays through a regular grid of points inside it (see :func:`subpixel_offsets`). 1 by default: at a
#: fixed CPU budget 2 x 2 rays a pixel mean a quarter of the pixels a batch, which cost more than the
#: consistency with the supersampled images gave (31.3 against 31.5 dB held-out after 40 s).
SUPERSAMPLE = 1
#: Cells whose dilated density is below this are empty space (about 2 % absorbed across the whole scene
#: box). Checked from the second refresh of each grid on: the start, 0.0067, is below it.
EMPTY_SIGMA = 1e-2



def grid_density(raw: torch.Tensor) -> torch.Tensor:
    """The density ``sigma = DENSITY_GAIN softplus(raw + DENSITY_SHIFT)`` (per metre) of raw values.

    The gain is the reciprocal of a voxel, about (DVGO measures the interval in voxels, Sun et al. 2022
    section 4): a surface must reach ``sigma delta`` of a few within a step of half a voxel (sigma of some
    hundreds per metre), which at gain 1 needs raw values in the hundreds -- Adam moves a raw value by at
    most about its learning rate a step, so surfaces stayed soft (20 samples a ray behind their front).
    With the gain, raw values of 10 to 20 do; near zero (``softplus(v) ~ e^v``) the gain only shifts the
    start, which :data:`DENSITY_SHIFT` keeps at sigma 0.0067."""
    return DENSITY_GAIN * torch.nn.functional.softplus(raw + DENSITY_SHIFT)


def raw_density(sigma: float) -> float:
    """The raw value whose :func:`grid_density` is ``sigma`` > 0."""
    return math.log(math.expm1(sigma / DENSITY_GAIN)) - DENSITY_SHIFT


_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])  # (8, 3)


@dataclass(frozen=True, eq=False)
class GridCheckpoint:
    """A trained grid field: ``density`` ``(R, R, R)`` raw densities and ``color`` ``(R, R, R, 3)`` raw
    colours on the vertices of the normalized box ``[-1, 1]^3`` of ``bounds`` (axis order x, y, z), the
    ``background`` ``(3,)``."""

    density: np.ndarray
    color: np.ndarray
    bounds: SceneBounds
    background: np.ndarray

    def __post_init__(self) -> None:
        density = np.asarray(self.density, dtype=np.float32)
        if density.ndim != 3 or len(set(density.shape)) != 1:
            raise InvalidValue("model.density", f"expected an (R, R, R) grid, got {density.shape}")
        object.__setattr__(self, "density", density)
        object.__setattr__(self, "color", np.asarray(self.color, dtype=np.float32).reshape(*density.shape, 3))
        object.__setattr__(self, "background", np.asarray(self.background, dtype=np.float32).reshape(3))

    @property
    def resolution(self) -> int:
        return int(self.density.shape[0])


class GridField(torch.nn.Module):
    """One table ``(R^3, 4)`` (row ``(x R + y) R + z``: raw density, then raw RGB; interleaved so that a
    vertex is one cache line for the compiled loops), sampled trilinearly at normalized points;
    :attr:`density` ``(R^3, 1)`` and :attr:`color` ``(R^3, 3)`` are views of it."""

    def __init__(self, resolution: int, density: torch.Tensor | None = None,
                 color: torch.Tensor | None = None) -> None:
        super().__init__()
        cells = resolution ** 3
        self.resolution = resolution
        density = torch.zeros(cells, 1) if density is None else density.reshape(cells, 1)
        color = torch.zeros(cells, 3) if color is None else color.reshape(cells, 3)
        self.table = torch.nn.Parameter(torch.cat([density, color.to(density)], dim=1).contiguous())

    @property
    def density(self) -> torch.Tensor:
        """Raw densities ``(R^3, 1)`` (a view of the table)."""
        return self.table[:, :1]

    @property
    def color(self) -> torch.Tensor:
        """Raw colours ``(R^3, 3)`` (a view of the table)."""
        return self.table[:, 1:]

    def corners(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The 8 corner rows ``(N, 8)`` of points ``x`` ``(N, 3)`` in ``[-1, 1]^3`` and their trilinear
        weights ``(N, 8)``."""
        r = self.resolution
        g = (x + 1.0) * (0.5 * (r - 1))
        base = torch.floor(g).clamp(0, r - 2)
        f = g - base
        corners = _CORNERS.to(x.device)
        ijk = base.long()[:, None, :] + corners[None]                                   # (N, 8, 3)
        rows = (ijk[..., 0] * r + ijk[..., 1]) * r + ijk[..., 2]
        weights = torch.where(corners[None].bool(), f[:, None, :], 1.0 - f[:, None, :]).prod(dim=-1)
        return rows, weights

    def sample(self, table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """``sum_c weights_c table[rows_c]`` ``(N, C)``: without gradient one gather-and-sum kernel
        (``embedding_bag``); with gradient ``index_select``, whose backward is one ``index_add`` (the
        backward of ``embedding_bag`` sorts the rows first: ten times slower on a CPU)."""
        if not (torch.is_grad_enabled() and table.requires_grad):
            return torch.nn.functional.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")
        gathered = table.index_select(0, rows.reshape(-1)).reshape(*rows.shape, table.shape[1])
        return (gathered * weights[..., None]).sum(dim=-2)

    def upsampled(self, resolution: int) -> GridField:
        """This field trilinearly resampled on a finer grid (the same box)."""
        def up(table: torch.Tensor, channels: int) -> torch.Tensor:
            r = self.resolution
            volume = table.detach().reshape(r, r, r, channels).permute(3, 0, 1, 2)[None]
            fine = torch.nn.functional.interpolate(volume, size=(resolution,) * 3, mode="trilinear",
                                                   align_corners=True)
            return fine[0].permute(1, 2, 3, 0).reshape(-1, channels).contiguous()
        return GridField(resolution, up(self.density, 1), up(self.color, 3)).to(self.density.device)

    def occupancy(self) -> Occupancy:
        """The vertices whose density, dilated over their 26 neighbours, is at least :data:`EMPTY_SIGMA`,
        for sampling at :func:`grid_step` (the raw value is compared with the softplus' inverse; the
        dilation is a maximum along each axis in turn)."""
        r = self.resolution
        with torch.no_grad():
            cells = self.density.reshape(r, r, r) >= raw_density(EMPTY_SIGMA)
            for axis in range(3):
                padded = torch.nn.functional.pad(cells, _axis_pad(axis))
                cells = padded.narrow(axis, 0, r) | padded.narrow(axis, 1, r) | padded.narrow(axis, 2, r)
        return Occupancy.of(cells, grid_step(self))


def _axis_pad(axis: int) -> tuple[int, ...]:
    """``torch.nn.functional.pad``'s widths that pad one vertex on both sides of ``axis`` of a 3D array."""
    widths = [0] * 6
    widths[2 * (2 - axis)] = widths[2 * (2 - axis) + 1] = 1
    return tuple(widths)


@dataclass(frozen=True, eq=False)
class Occupancy:
    """Which vertices of an ``R^3`` grid may hold density: ``cells`` ``(R, R, R)`` bool, for sampling every
    ``step`` (normalized units). What each renderer needs is derived once, when first asked for:
    :attr:`wider` for the two levels of :func:`grid_candidates`, :attr:`box` for the compiled march."""

    cells: torch.Tensor
    step: float

    @classmethod
    def of(cls, cells: torch.Tensor, step: float) -> Occupancy:
        """The occupancy of ``cells`` for sampling every ``step``."""
        return cls(cells, step)

    @functools.cached_property
    def reach(self) -> int:
        """How far :attr:`wider` is dilated, in vertices: a group of :data:`GROUP` steps lies within
        ``(GROUP - 1) / 2`` steps of its middle, so that in voxels plus one (each end's nearest vertex is
        within half a voxel)."""
        return 1 + int((GROUP - 1) / 2 * self.step * (self.cells.shape[0] - 1) / 2)

    @functools.cached_property
    def wider(self) -> torch.Tensor:
        """The cells dilated by :attr:`reach` vertices, covering vertices ``-reach .. R - 1 + reach``."""
        reach = self.reach
        around = torch.nn.functional.pad(self.cells, (reach,) * 6)[None, None].float()
        return torch.nn.functional.max_pool3d(around, 2 * reach + 1, stride=1, padding=reach)[0, 0] > 0

    @functools.cached_property
    def array(self) -> np.ndarray:
        """The cells as a contiguous NumPy bool array (CPU)."""
        return np.ascontiguousarray(self.cells.detach().cpu().numpy())

    @functools.cached_property
    def rows(self) -> np.ndarray:
        """The table rows ``(x R + y) R + z`` of the occupied vertices ``(M,)`` int64."""
        return np.flatnonzero(self.array.reshape(-1)).astype(np.int64)

    @functools.cached_property
    def box(self) -> tuple[float, ...]:
        """Normalized lower and upper corners of a box holding every point whose nearest vertex is occupied
        (the occupied vertices' bounding box widened by a little over half a voxel); lower above upper
        when none is."""
        found = np.nonzero(self.array)
        if len(found[0]) == 0:
            return (1.0, 1.0, 1.0, -1.0, -1.0, -1.0)
        voxel = 2.0 / (self.array.shape[0] - 1)
        lower = [-1.0 + (float(axis.min()) - 0.501) * voxel for axis in found]
        upper = [-1.0 + (float(axis.max()) + 0.501) * voxel for axis in found]
        return (*lower, *upper)


@dataclass(frozen=True)
class GridOptions:
    """See :func:`train_grid_field`."""

    resolution: int
    batch_rays: int
    learning_rate: float
    iterations: int
    budget_seconds: float
    preview_every: int
    #: Fractions of the budget at which the grid is upsampled (R / 4 -> R / 2 -> R).
    upsample_at: tuple[float, float] = (0.25, 0.5)
    #: Rays per pixel along each axis (:data:`SUPERSAMPLE`; 1: one ray through each pixel's centre).
    supersample: int = SUPERSAMPLE
    #: The learning rate at the end of the budget, as a fraction of the initial one (exponential decay).
    lr_decay: float = 0.1
    #: Weights of the total-variation penalties on the raw density and the raw colours
    #: (:func:`total_variation`; 0: none).
    tv_density: float = 0.0
    tv_color: float = 0.0
    #: Occupied vertices drawn each iteration for the total-variation penalties.
    tv_vertices: int = 16384


def _occupied_at(occupied: torch.Tensor, x: torch.Tensor, resolution: int, margin: int = 0) -> torch.Tensor:
    """Whether the vertex nearest each normalized point ``x`` ``(..., 3)`` of an ``R^3`` grid is occupied;
    ``occupied`` covers the vertices ``-margin .. R - 1 + margin`` of each axis; beyond it: empty."""
    side = occupied.shape[0]
    padded = torch.nn.functional.pad(occupied, (1, 1, 1, 1, 1, 1))
    cell = ((x + 1.0) * (0.5 * (resolution - 1))).round_().add_(margin + 1).clamp_(0, side + 1).long()
    return padded[cell[..., 0], cell[..., 1], cell[..., 2]]


def grid_candidates(origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds, step: float,
                    occupied: Occupancy | None, jitter: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """The samples worth a look, packed ray after ray: every ``step`` (normalized units, so
    ``step radius / |d|`` in depth) from near to far, shifted by ``jitter`` ``(R, 1)`` of a step (half a
    step without), kept where their nearest vertex is occupied (``occupied``, made for this ``step``;
    None: the whole box). Returns the ray of each ``(K,)``, its depth ``(K,)``, normalized point
    ``(K, 3)`` and interval length ``(K,)`` (a distance).

    Two levels: the middles of groups of :data:`GROUP` steps are checked first against the occupancy
    dilated far enough to cover the whole group, and only the steps of the groups that pass are made and
    checked; the result equals checking every step
    (:func:`~lab.modules.nerf.reference.grid_candidates_reference`) at about a quarter of the work.
    """
    if occupied is None:
        occupied = Occupancy.of(torch.ones((2, 2, 2), dtype=torch.bool, device=origins.device), step)
    r = occupied.cells.shape[0]
    norm = directions.norm(dim=-1)
    depth_step = step * bounds.radius / norm                                              # (R,)
    count = math.ceil((bounds.far - bounds.near) / float(depth_step.min()))
    shift = torch.full((len(origins), 1), 0.5, dtype=origins.dtype, device=origins.device) \
        if jitter is None else jitter
    centre = torch.as_tensor(bounds.center, dtype=origins.dtype, device=origins.device)

    def points(rows: torch.Tensor, offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        t = bounds.near + offsets * depth_step[rows][..., None]
        x = (origins[rows][..., None, :] - centre + t[..., None] * directions[rows][..., None, :])
        return t, x / bounds.radius

    rows = torch.arange(len(origins), device=origins.device)
    groups = torch.arange(math.ceil(count / GROUP), dtype=origins.dtype, device=origins.device)
    _, x_mid = points(rows, groups[None] * GROUP + (GROUP - 1) / 2 + shift)
    ray, group = _occupied_at(occupied.wider, x_mid, r, occupied.reach).nonzero(as_tuple=True)
    column = (group[:, None] * GROUP + torch.arange(GROUP, device=origins.device)[None]).reshape(-1)
    ray = ray[:, None].expand(-1, GROUP).reshape(-1)
    t, x = points(ray, column.to(origins.dtype)[:, None] + shift[ray])
    t, x = t[:, 0], x[:, 0]
    keep = (column < count) & (t < bounds.far) & _occupied_at(occupied.cells, x, r)
    ray, t, x = ray[keep], t[keep], x[keep]
    delta = torch.minimum(depth_step[ray], bounds.far - t) * norm[ray]
    return ray, t, x, delta


def render_grid(field: GridField, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds, *,
                step: float, background: torch.Tensor, occupied: Occupancy | None,
                jitter: torch.Tensor | None = None) -> tuple[PackedRendering, torch.Tensor]:
    """Render rays ``(R, 3)`` through the grid with empty-space skipping and early termination (the module
    docstring). Returns the :class:`~lab.modules.nerf.rendering.PackedRendering` and the depths ``(K,)`` of
    the samples evaluated with gradient (ray after ray)."""
    rays = len(origins)
    ray, t, x, delta = grid_candidates(origins, directions, bounds, step, occupied, jitter)
    with torch.no_grad():  # pass 1: every candidate's weight, density only, no gradient
        rows, weights = field.corners(x)
        sigma = grid_density(field.sample(field.density, rows, weights)[:, 0])
        first = volume_render_packed(sigma, torch.zeros_like(x), t, delta, ray, rays, far=bounds.far)
        keep = first.weights >= SKIP_BELOW
    rows, weights = field.corners(x[keep])
    sigma = grid_density(field.sample(field.density, rows, weights)[:, 0])
    rgb = torch.sigmoid(field.sample(field.color, rows, weights))
    out = volume_render_packed(sigma, rgb, t[keep], delta[keep], ray[keep], rays, far=bounds.far,
                               background=background)
    return out, t[keep]


#: A ray ends once its transmittance falls below this (nerfacc's early-stop epsilon): what lies behind
#: adds at most this much to its colour.
STOP_BELOW = 1e-4


@dataclass(frozen=True, eq=False)
class GridMarch:
    """Rays ``(R, 3)`` (float32 NumPy, CPU) and how :mod:`~lab.modules.nerf._kernels` marches them: the
    ``shift`` ``(R,)`` of the first step (a fraction of a step), ``params`` (near, far, centre, radius, step,
    stop), the most steps ``count`` and the occupancy ``cells`` ``(r, r, r)`` bool."""

    origins: np.ndarray
    directions: np.ndarray
    shift: np.ndarray
    params: np.ndarray
    count: int
    cells: np.ndarray
    background: np.ndarray

    @classmethod
    def of(cls, field: GridField, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds, *,
           background: torch.Tensor, occupied: Occupancy | None, jitter: torch.Tensor | None = None,
           stop: float = STOP_BELOW) -> GridMarch:
        """The march of :func:`grid_candidates` at :func:`grid_step` (``occupied`` None: every vertex of the
        field; ``jitter`` None: half a step) ending at transmittance ``stop``."""
        o = origins.detach().cpu().numpy().astype(np.float32, copy=False)
        d = directions.detach().cpu().numpy().astype(np.float32, copy=False)
        step = grid_step(field)
        depth_step = step * bounds.radius / np.linalg.norm(d.astype(np.float64), axis=-1)
        count = math.ceil((bounds.far - bounds.near) / float(depth_step.min())) if len(d) else 0
        shift = np.full(len(o), 0.5, np.float32) if jitter is None else \
            jitter.detach().cpu().numpy().reshape(-1).astype(np.float32)
        if occupied is None:
            occupied = Occupancy.of(torch.ones((field.resolution,) * 3, dtype=torch.bool), step)
        centre = np.asarray(bounds.center, dtype=np.float64).reshape(3)
        params = np.array([bounds.near, bounds.far, *centre, bounds.radius, step, stop, *occupied.box],
                          dtype=np.float64)
        return cls(np.ascontiguousarray(o), np.ascontiguousarray(d), shift, params, count, occupied.array,
                   background.detach().cpu().numpy().astype(np.float32))


def _table(field: GridField) -> np.ndarray:
    """The field's raw table ``(N, 4)`` as a float32 NumPy view (CPU)."""
    return np.ascontiguousarray(field.table.detach().cpu().numpy())


def composite_grid(field: GridField, march: GridMarch, *, threads: int = 1) -> PackedRendering:
    """Render the rays of ``march`` through the field without gradient, by the compiled per-ray loop
    (:mod:`~lab.modules.nerf._kernels`: march, skip empty space, trilinear density and colour, composite
    front to back, stop at transmittance ``stop``), ``threads`` bands of rays at a time. Returns colour
    ``(R, 3)``, depth and opacity ``(R,)`` and, in ``weights``, the samples each ray used ``(R,)``.
    Oracle: :func:`~lab.modules.nerf.reference.composite_grid_reference`."""
    rays = len(march.origins)
    table = _table(field)
    colors, depth = np.empty((rays, 3), np.float32), np.empty(rays, np.float32)
    opacity, used = np.empty(rays, np.float32), np.empty(rays, np.int32)
    jobs = [(table, field.resolution, march.cells, march.origins, march.directions, march.shift,
             march.params, march.count, march.background, colors, depth, opacity, used, a, b)
            for a, b in bands(rays, parts=threads)] if rays else []
    in_parallel(_render_grid_kernel, jobs)
    return PackedRendering(torch.from_numpy(colors), torch.from_numpy(depth), torch.from_numpy(opacity),
                           torch.from_numpy(used))


class CompositeGrid(torch.autograd.Function):
    """:func:`composite_grid`'s colour ``(R, 3)`` (and samples used) as a function of the raw table, with its
    gradient from
    the compiled backward pass (``_render_grid_backward_kernel``: each ray marched again)."""

    @staticmethod
    def forward(ctx: Any, table: torch.Tensor, field: GridField,
                march: GridMarch) -> tuple[torch.Tensor, torch.Tensor]:
        out = composite_grid(field, march)
        ctx.field, ctx.march = field, march
        ctx.rendered = out.color.numpy()
        ctx.mark_non_differentiable(out.weights)
        return out.color, out.weights

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor, _: Any) -> tuple[torch.Tensor, None, None]:
        field, march = ctx.field, ctx.march
        table = _table(field)
        grad_table = np.zeros_like(table)
        _render_grid_backward_kernel(table, field.resolution, march.cells, march.origins, march.directions,
                                     march.shift, march.params, march.count, ctx.rendered,
                                     np.ascontiguousarray(grad.numpy(), dtype=np.float32), grad_table)
        return torch.from_numpy(grad_table), None, None


def batch_colors(field: GridField, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds, *,
                 background: torch.Tensor, occupied: Occupancy | None,
                 jitter: torch.Tensor) -> tuple[torch.Tensor, int]:
    """A training batch's rendered colours ``(R, 3)`` (with gradient to the tables) and the samples
    evaluated: on the CPU by the compiled loop (:class:`CompositeGrid`), elsewhere by :func:`render_grid`."""
    if field.density.device.type == "cpu":
        march = GridMarch.of(field, origins, directions, bounds, background=background, occupied=occupied,
                             jitter=jitter)
        color, used = CompositeGrid.apply(field.table, field, march)
        return color, int(used.sum())
    out, kept = render_grid(field, origins, directions, bounds, step=grid_step(field), background=background,
                            occupied=occupied, jitter=jitter)
    return out.color, len(kept)


def _adam(field: GridField, learning_rate: float) -> torch.optim.Adam:
    """Adam on the grid; the fused CPU / CUDA kernel (one pass over the tables) where torch has it."""
    try:
        return torch.optim.Adam(field.parameters(), lr=learning_rate, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(field.parameters(), lr=learning_rate)


def total_variation(field: GridField, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean isotropic total variation at vertices ``rows`` ``(N,)`` of the raw density and of the raw
    colours (Plenoxels, Fridovich-Keil et al. 2022, eq. 5: ``sqrt(dx^2 + dy^2 + dz^2)`` of forward
    differences to the next vertex along each axis, per channel, summed over colour channels), with
    gradient to the table. Vertices on a last face take their differences towards the previous vertex."""
    r = field.resolution
    ijk = torch.stack([rows // (r * r), (rows // r) % r, rows % r], dim=1).clamp_(max=r - 2)
    base = (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]
    centre = field.table.index_select(0, base)
    squares = torch.zeros_like(centre)
    for stride in (r * r, r, 1):
        squares = squares + (field.table.index_select(0, base + stride) - centre) ** 2
    norms = torch.sqrt(squares + 1e-8)
    return norms[:, 0].mean(), norms[:, 1:].sum(dim=1).mean()


def subpixel_offsets(supersample: int) -> np.ndarray:
    """The ``s^2`` points ``(s^2, 2)`` ``(du, dv)`` (pixels, from the centre) of a regular ``s x s`` grid
    inside a pixel, ``(k + 0.5) / s - 0.5`` along each axis: the points at which the shared renderer
    (:func:`lab.data.scenes.render`) averages a supersampled pixel, so that the mean of the rays through
    them is the same estimate of the pixel's area integral as the image's."""
    k = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(k, k, indexing="xy")
    return np.stack([du.reshape(-1), dv.reshape(-1)], axis=1)


def pixel_axes(rays: RayBundle) -> np.ndarray:
    """Each view's change of ray direction per pixel along ``u`` and along ``v``, ``(V, 2, 3)`` float64.

    A pinhole ray's direction ``R^T K^-1 (u, v, 1)`` is affine in the pixel, so the two axes are
    ``R^T K^-1 e_u`` and ``R^T K^-1 e_v``; they are read off the bundle, which holds each view's rays
    through its pixel centres in row-major order (:func:`~lab.modules.nerf.steps.generate_rays`): the row
    length is where the steps along ``u`` first jump, and the axes are the least-squares fit of the
    whole view. Raises :class:`InvalidValue` on ``rays`` for a view that is not such a grid."""
    views = np.asarray(rays.views)
    count = int(views.max()) + 1 if len(views) else 0
    axes = np.zeros((count, 2, 3))
    for view in range(count):
        index = np.flatnonzero(views == view)
        d = rays.directions[index].astype(np.float64)
        if len(index) < 4 or index[-1] - index[0] != len(index) - 1:
            raise InvalidValue("rays", f"view {view}'s rays are not one block of the bundle: the grid's "
                                       "supersampled training needs each view's pixel grid (generate_rays)")
        step_u = d[1] - d[0]
        off = np.linalg.norm(d - d[0] - np.arange(len(d))[:, None] * step_u, axis=1) > \
            0.25 * np.linalg.norm(step_u)
        width = int(np.argmax(off)) if off.any() else len(d)
        if width < 2 or len(d) % width or len(d) == width:
            raise InvalidValue("rays", f"view {view}'s {len(d)} rays are not a row-major pixel grid")
        i, j = np.divmod(np.arange(len(d)), width)
        design = np.stack([np.ones(len(d)), j, i], axis=1)
        fit, *_ = np.linalg.lstsq(design, d, rcond=None)
        if np.abs(design @ fit - d).max() > 0.05 * np.linalg.norm(fit[1]):
            raise InvalidValue("rays", f"view {view}'s rays are not the pinhole rays of a pixel grid")
        axes[view] = fit[1:]
    return axes


class _Batches:
    """Random training batches of pixels: for each, the rays through its :func:`subpixel_offsets`
    (``supersample`` 1: its centre), its colour, and each ray's jitter along itself (a fraction of a step)."""

    def __init__(self, rays: RayBundle, generator: torch.Generator, device: str, supersample: int) -> None:
        self.origins = torch.as_tensor(rays.origins, device=device)
        self.directions = torch.as_tensor(rays.directions, device=device)
        self.colors = torch.as_tensor(rays.colors, device=device)
        self.generator = generator
        self.device = device
        self.per_pixel = supersample ** 2
        if supersample > 1:
            offsets = torch.as_tensor(subpixel_offsets(supersample))                      # (s^2, 2)
            axes = torch.as_tensor(pixel_axes(rays))                                      # (V, 2, 3)
            self.views = torch.as_tensor(rays.views, device=device)
            # each view's s^2 direction offsets (V, s^2, 3)
            self.shifts = torch.einsum("sk,vkc->vsc", offsets, axes).to(torch.float32).to(device)

    def draw(self, count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``count`` rays (``count / s^2`` pixels, at least one): origins and directions ``(count, 3)``,
        pixel after pixel, the pixels' colours ``(count / s^2, 3)`` and the jitter ``(count, 1)``."""
        pixels = max(1, count // self.per_pixel)
        batch = torch.randint(len(self.origins), (pixels,), generator=self.generator).to(self.device)
        jitter = torch.rand((pixels * self.per_pixel, 1), generator=self.generator).to(self.device)
        origins, directions = self.origins[batch], self.directions[batch]
        if self.per_pixel > 1:
            directions = (directions[:, None, :] + self.shifts[self.views[batch]]).reshape(-1, 3)
            origins = origins.repeat_interleave(self.per_pixel, dim=0)
        return origins, directions, self.colors[batch], jitter


def train_grid_field(rays: RayBundle, options: GridOptions, *, background: torch.Tensor,
                     preview: PreviewRays | None, rng: np.random.Generator,
                     device: str) -> Generator[Progress, None, TrainingRun]:
    """Adam on the photometric loss of random ray batches, coarse to fine (the module docstring), the
    learning rate decaying to a tenth over the budget. Yields progress every :data:`REPORT_EVERY`
    iterations and a preview every ``preview_every``."""
    generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    batches = _Batches(rays, generator, device, options.supersample)
    compiled = all_compiled((_render_grid_kernel, _render_grid_backward_kernel))
    if torch.device(device).type == "cpu" and not compiled:
        _warm_up()  # compiled (or loaded from numba's cache) before the clock starts: not training time
    stages = [max(4, options.resolution // 4), max(4, options.resolution // 2), options.resolution]
    field = GridField(stages[0]).to(device)
    optimizer = _adam(field, options.learning_rate)
    losses: list[float] = []
    psnrs: list[float] = []
    evaluated: list[float] = []
    elapsed, occupied = 0.0, None
    budget = options.budget_seconds
    while len(losses) < options.iterations and (budget <= 0 or elapsed < budget):
        tick = time.perf_counter()
        spent = len(losses) / options.iterations
        if budget > 0:
            spent = max(spent, elapsed / budget)
        stage = 0 if spent < options.upsample_at[0] else 1 if spent < options.upsample_at[1] else 2
        if field.resolution != stages[stage]:
            field = field.upsampled(stages[stage])
            optimizer = _adam(field, options.learning_rate)
            occupied = field.occupancy()
        if len(losses) % OCCUPANCY_EVERY == 0:
            occupied = field.occupancy() if len(losses) >= OCCUPANCY_EVERY else None  # not before a warm-up
            if occupied is not None and not len(occupied.rows):
                occupied = None  # nothing dense yet (or any more): look everywhere rather than nowhere
        for group in optimizer.param_groups:
            group["lr"] = options.learning_rate * options.lr_decay ** min(spent, 1.0)
        origins, directions, target, jitter = batches.draw(options.batch_rays)
        color, used = batch_colors(field, origins, directions, rays.bounds, background=background,
                                   occupied=occupied, jitter=jitter)
        color = color.reshape(len(target), batches.per_pixel, 3).mean(dim=1)  # each pixel's mean ray
        mse = torch.mean((color - target) ** 2)
        loss = mse
        if (options.tv_density > 0 or options.tv_color > 0) and occupied is not None and len(occupied.rows):
            pick = torch.randint(len(occupied.rows), (options.tv_vertices,), generator=generator)
            tv_sigma, tv_rgb = total_variation(field, torch.as_tensor(occupied.rows)[pick].to(device))
            loss = mse + options.tv_density * tv_sigma + options.tv_color * tv_rgb
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(mse.detach()))
        psnrs.append(psnr_from_mse(losses[-1]))
        evaluated.append(used / len(origins))
        elapsed += time.perf_counter() - tick
        done = len(losses)
        last = done == options.iterations or 0 < budget <= elapsed
        if done % REPORT_EVERY == 0 or last:
            values = {}
            if preview is not None and (done % options.preview_every == 0 or last):
                image = render_grid_image(field, preview.origins, preview.directions, rays.bounds,
                                          preview.shape, background=background)
                values["preview"] = Image(image.color, name="training preview")
            per_ray = np.mean(evaluated[-REPORT_EVERY:])
            psnr = np.mean(psnrs[-REPORT_EVERY:])
            recent = float(np.mean(losses[-REPORT_EVERY:]))
            try:
                yield Progress(iteration=done, total=options.iterations, loss=recent, values=values,
                               message=f"grid {field.resolution}^3, PSNR {psnr:.2f} dB, "
                                       f"{per_ray:.1f} samples/ray, {elapsed:.1f} s")
            except Cancelled:  # the runner's Cancel: the grid trained so far is the result
                break
    tail = evaluated[-max(1, len(evaluated) // 10):]
    return TrainingRun(field, np.asarray(losses), np.asarray(psnrs), elapsed,
                       float(np.mean(tail)))


def grid_step(field: GridField) -> float:
    """The sampling step along rays: half a voxel (voxels are ``2 / (R - 1)`` wide in normalized units)."""
    return 1.0 / (field.resolution - 1)


def render_grid_image(field: GridField, origins: torch.Tensor, directions: torch.Tensor, bounds: SceneBounds,
                      shape: tuple[int, int], *, background: torch.Tensor,
                      chunk: int = 4096) -> ImageRendering:
    """Render one view's rays ``(H * W, 3)`` (row-major) through the grid, no jitter, no gradient, with the
    field's occupancy; :class:`~lab.modules.nerf.model.ImageRendering` of ``shape = (H, W)``."""
    height, width = shape
    with torch.no_grad():
        occupied = field.occupancy()
        if field.density.device.type == "cpu":
            march = GridMarch.of(field, origins, directions, bounds, background=background, occupied=occupied)
            out = composite_grid(field, march, threads=torch.get_num_threads())
            return ImageRendering(out.color.clamp(0, 1).reshape(height, width, 3).numpy(),
                                  out.depth.reshape(height, width).numpy(),
                                  out.opacity.reshape(height, width).numpy())
    colors, depths, opacities = [], [], []
    with torch.no_grad():
        for start in range(0, len(origins), chunk):
            out, _ = render_grid(field, origins[start:start + chunk], directions[start:start + chunk], bounds,
                                 step=grid_step(field), background=background, occupied=occupied)
            colors.append(out.color)
            depths.append(out.depth)
            opacities.append(out.opacity)
    return ImageRendering(torch.cat(colors).clamp(0, 1).reshape(height, width, 3).cpu().numpy(),
                          torch.cat(depths).reshape(height, width).cpu().numpy(),
                          torch.cat(opacities).reshape(height, width).cpu().numpy())


def grid_checkpoint_from(field: GridField, bounds: SceneBounds, background: np.ndarray) -> GridCheckpoint:
    """A :class:`GridCheckpoint` of the field's tables (copied to the CPU)."""
    r = field.resolution
    return GridCheckpoint(field.density.detach().cpu().numpy().reshape(r, r, r),
                          field.color.detach().cpu().numpy().reshape(r, r, r, 3), bounds, background)


def grid_from(checkpoint: GridCheckpoint, device: str = "cpu") -> GridField:
    """The :class:`GridField` of a checkpoint on ``device``."""
    return GridField(checkpoint.resolution, torch.as_tensor(checkpoint.density),
                     torch.as_tensor(checkpoint.color)).to(device)


__all__ = ["DENSITY_GAIN", "DENSITY_SHIFT", "EMPTY_SIGMA", "GROUP", "OCCUPANCY_EVERY", "SKIP_BELOW",
           "STOP_BELOW", "SUPERSAMPLE", "CompositeGrid", "GridCheckpoint", "GridField", "GridMarch",
           "GridOptions", "Occupancy", "batch_colors", "composite_grid", "grid_candidates",
           "grid_checkpoint_from", "grid_density", "grid_from", "grid_step", "pixel_axes", "raw_density",
           "render_grid", "render_grid_image", "subpixel_offsets", "total_variation", "train_grid_field"]
