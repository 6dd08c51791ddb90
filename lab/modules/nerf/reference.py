"""The readable versions of NeRF's fast functions: the tests' oracles (gsplat's ``_torch_impl`` pattern).

Each ``x_reference`` computes what the public vectorized torch function ``x`` computes, in NumPy and
plain Python loops (one camera, ray, sample or frequency at a time), slowly, in float64, written as the
paper writes it (Mildenhall et al. 2020): products where the fast code uses sums of logarithms,
explicit searches where it uses ``searchsorted``. ``grid_candidates_reference`` is the direct version of
the grid's two-level search (dense torch arrays: every step of every ray); ``composite_grid_reference``
is the grid's compiled march-and-composite loop (:mod:`lab.modules.nerf._kernels`) written plainly.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch


def camera_rays_reference(K: np.ndarray, R: np.ndarray, t: np.ndarray,
                          pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~lab.modules.nerf.rays.camera_rays`: for each camera and pixel ``(u, v)``, solve
    ``K x = (u, v, 1)`` for the camera-frame direction ``x`` (z = 1), rotate it into the world with
    ``R^T`` and start it at the centre ``-R^T t``. Returns ``(V, M, 3)`` origins and directions."""
    views, count = len(K), len(pixels)
    origins, directions = np.zeros((views, count, 3)), np.zeros((views, count, 3))
    for v in range(views):
        centre = -R[v].T @ t[v]
        for m in range(count):
            x = np.linalg.solve(K[v], np.array([pixels[m][0], pixels[m][1], 1.0]))
            origins[v, m] = centre
            directions[v, m] = R[v].T @ x
    return origins, directions


def stratified_samples_reference(near: float, far: float, u: np.ndarray) -> np.ndarray:
    """:func:`~lab.modules.nerf.rays.stratified_samples` with the uniform draws ``u`` ``(R, N)`` given:
    sample ``i`` of a ray lies at fraction ``u`` of the ``i``-th of ``N`` equal bins of ``[near, far]``."""
    rays, count = u.shape
    out = np.zeros((rays, count))
    width = (far - near) / count
    for r in range(rays):
        for i in range(count):
            out[r, i] = near + i * width + u[r, i] * width
    return out


def positional_encoding_reference(p: np.ndarray, frequencies: int, *,
                                  include_input: bool = True) -> np.ndarray:
    """:func:`~lab.modules.nerf.encoding.positional_encoding` of ``p`` ``(N, D)``: ``p``, then for each
    ``k < L`` the block ``sin(2^k pi p_d)`` over ``d`` and the block ``cos(2^k pi p_d)``."""
    rows = []
    for point in np.asarray(p, dtype=np.float64):
        row = list(point) if include_input else []
        for k in range(frequencies):
            row += [math.sin(2.0 ** k * math.pi * x) for x in point]
            row += [math.cos(2.0 ** k * math.pi * x) for x in point]
        rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(len(rows), -1)


def volume_render_reference(sigma: np.ndarray, rgb: np.ndarray, t: np.ndarray, far: float,
                            direction_norm: np.ndarray | None = None,
                            background: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """:func:`~lab.modules.nerf.rendering.volume_render`, one ray and one sample at a time, with the
    transmittance as the product ``T_i = prod_(j < i) (1 - alpha_j)``. Returns a dict of the
    :class:`~lab.modules.nerf.rendering.VolumeRendering` fields as float64 arrays."""
    rays, samples = sigma.shape
    out = {"color": np.zeros((rays, 3)), "depth": np.zeros(rays), "opacity": np.zeros(rays),
           "weights": np.zeros((rays, samples)), "transmittance": np.zeros((rays, samples)),
           "alpha": np.zeros((rays, samples))}
    back = np.zeros(3) if background is None else np.asarray(background, dtype=np.float64)
    for r in range(rays):
        norm = 1.0 if direction_norm is None else float(direction_norm[r])
        transmittance = 1.0
        for i in range(samples):
            following = t[r, i + 1] if i + 1 < samples else far
            delta = (following - t[r, i]) * norm
            alpha = 1.0 - math.exp(-sigma[r, i] * delta)
            weight = transmittance * alpha
            out["transmittance"][r, i] = transmittance
            out["alpha"][r, i] = alpha
            out["weights"][r, i] = weight
            out["color"][r] += weight * rgb[r, i]
            out["depth"][r] += weight * t[r, i]
            out["opacity"][r] += weight
            transmittance *= 1.0 - alpha
        out["color"][r] += (1.0 - out["opacity"][r]) * back
        out["depth"][r] += (1.0 - out["opacity"][r]) * far
    return out


def sample_pdf_reference(edges: np.ndarray, weights: np.ndarray, u: np.ndarray,
                         epsilon: float = 1e-5) -> np.ndarray:
    """:func:`~lab.modules.nerf.rendering.sample_pdf` with the uniform draws ``u`` ``(R, K)`` given:
    normalize the weights into a PDF over the bins, walk the bins accumulating the CDF until the one
    that holds ``u``, and place the sample linearly inside it."""
    rays, bins = weights.shape
    out = np.zeros(u.shape)
    for r in range(rays):
        pdf = (weights[r] + epsilon) / np.sum(weights[r] + epsilon)
        for k, target in enumerate(u[r]):
            below = 0.0
            j = 0
            while j < bins - 1 and below + pdf[j] <= target:
                below += pdf[j]
                j += 1
            fraction = (target - below) / pdf[j] if pdf[j] > 0 else 0.0
            out[r, k] = edges[r, j] + min(max(fraction, 0.0), 1.0) * (edges[r, j + 1] - edges[r, j])
    return out


def grid_candidates_reference(origins: torch.Tensor, directions: torch.Tensor, bounds: Any, step: float,
                occupied: torch.Tensor | None, jitter: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """:func:`~lab.modules.nerf.grid.grid_candidates` the direct way: make every step of every ray, look up
    the occupancy at each, keep those that are occupied (torch, dense ``(R, S)`` arrays)."""
    norm = directions.norm(dim=-1)
    depth_step = step * bounds.radius / norm                                              # (R,)
    count = math.ceil((bounds.far - bounds.near) / float(depth_step.min()))
    offsets = torch.arange(count, dtype=origins.dtype, device=origins.device)[None]
    offsets = offsets + (0.5 if jitter is None else jitter)
    t = bounds.near + offsets * depth_step[:, None]                                      # (R, S)
    centre = torch.as_tensor(bounds.center, dtype=origins.dtype, device=origins.device)
    x = (origins[:, None, :] - centre + t[..., None] * directions[:, None, :]) / bounds.radius
    if occupied is None:
        occupied = torch.ones((2, 2, 2), dtype=torch.bool, device=origins.device)
    r = occupied.shape[0]
    padded = torch.nn.functional.pad(occupied, (1, 1, 1, 1, 1, 1))                       # outside: empty
    cell = ((x + 1.0) * (0.5 * (r - 1))).round_().add_(1).clamp_(0, r + 1).long()
    candidate = padded[cell[..., 0], cell[..., 1], cell[..., 2]] & (t < bounds.far)
    ray, column = candidate.nonzero(as_tuple=True)
    t_k = t[ray, column]
    delta = torch.minimum(depth_step[ray], bounds.far - t_k) * norm[ray]
    return ray, t_k, x[ray, column], delta


def composite_grid_reference(density: np.ndarray, color: np.ndarray, cells: np.ndarray, origins: np.ndarray,
                             directions: np.ndarray, shift: np.ndarray, bounds: Any, step: float, stop: float,
                             background: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`~lab.modules.nerf.grid.composite_grid` one ray and one step at a time: walk every step
    ``t = near + (k + shift) s`` (``s = step radius / |d|``) before far, look up the occupancy vertex nearest
    the normalized point, interpolate the raw ``density`` ``(R, R, R)`` and ``color`` ``(R, R, R, 3)``
    trilinearly between the 8 vertices around it, ``sigma = 50 softplus(raw - 5 - ln 50)`` (the grid's
    :func:`~lab.modules.nerf.grid.grid_density`), ``c = sigmoid(raw)``, and
    composite with the product form of eq. 3 until the transmittance falls below ``stop``. Returns colour
    ``(N, 3)``, depth, opacity and samples used ``(N,)``, float64."""
    r, side = density.shape[0], cells.shape[0]
    centre = np.asarray(bounds.center, dtype=np.float64)
    out = {"color": np.zeros((len(origins), 3)), "depth": np.zeros(len(origins)),
           "opacity": np.zeros(len(origins)), "samples": np.zeros(len(origins))}
    for n, (o, d) in enumerate(zip(origins.astype(np.float64), directions.astype(np.float64), strict=True)):
        norm = float(np.linalg.norm(d))
        depth_step = step * bounds.radius / norm
        transmittance, k = 1.0, 0
        while transmittance >= stop:
            t = bounds.near + (k + float(shift[n])) * depth_step
            k += 1
            if t >= bounds.far:
                break
            x = (o + t * d - centre) / bounds.radius
            nearest = np.round((x + 1.0) * 0.5 * (side - 1)).astype(int)
            if np.any(nearest < 0) or np.any(nearest >= side) or not cells[tuple(nearest)]:
                continue
            g = (x + 1.0) * 0.5 * (r - 1)
            base = np.clip(np.floor(g), 0, r - 2).astype(int)
            f = g - base
            raw, rgb_raw = 0.0, np.zeros(3)
            for corner in np.ndindex(2, 2, 2):
                weight = math.prod(f[a] if corner[a] else 1.0 - f[a] for a in range(3))
                vertex = tuple(base + np.array(corner))
                raw += weight * float(density[vertex])
                rgb_raw += weight * color[vertex].astype(np.float64)
            sigma = 50.0 * math.log1p(math.exp(raw - 5.0 - math.log(50.0)))
            rgb = 1.0 / (1.0 + np.exp(-rgb_raw))
            alpha = 1.0 - math.exp(-sigma * min(depth_step, bounds.far - t) * norm)
            weight = transmittance * alpha
            out["color"][n] += weight * rgb
            out["depth"][n] += weight * t
            out["opacity"][n] += weight
            out["samples"][n] += 1
            transmittance *= 1.0 - alpha
        out["color"][n] += transmittance * np.asarray(background, dtype=np.float64)
        out["depth"][n] += transmittance * bounds.far
    return out


__all__ = ["camera_rays_reference", "composite_grid_reference", "grid_candidates_reference",
           "positional_encoding_reference", "sample_pdf_reference", "stratified_samples_reference",
           "volume_render_reference"]
