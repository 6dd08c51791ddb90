"""Volume rendering of samples along rays, and hierarchical (inverse-CDF) sampling.

Mildenhall et al. 2020, section 4, eq. 3: with samples ``t_1 < ... < t_N`` on a ray ``o + t d``,
density ``sigma_i`` and colour ``c_i`` at each,

    delta_i = (t_(i+1) - t_i) |d|,  alpha_i = 1 - exp(-sigma_i delta_i),
    T_i = prod_(j < i) (1 - alpha_j) = exp(-sum_(j < i) sigma_j delta_j)   (exclusive: T_1 = 1),
    w_i = T_i alpha_i,  C = sum_i w_i c_i + (1 - sum_i w_i) c_background.

Sample ``i`` stands for the interval ``[t_i, t_(i+1)]``; the last one's ends at ``t_(N+1) = far``
(the reference code gives it 1e10, which makes every ray opaque and hides a white background). The
weights are the probability that the ray ends in each interval, so section 5.2's hierarchical sampling
draws fine samples from the piecewise-constant PDF over exactly these intervals (the reference code
uses the midpoints between samples and drops the two end weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from lab.core import InvalidValue

#: Added to every weight before they are normalized into a PDF (as the reference code): a ray whose
#: weights are all 0 samples uniformly instead of dividing by zero.
PDF_EPSILON = 1e-5


@dataclass(frozen=True, eq=False)
class VolumeRendering:
    """What :func:`volume_render` computes for ``R`` rays of ``S`` samples: ``color`` ``(R, 3)``,
    ``depth`` ``(R,)`` (expected termination depth ``sum w_i t_i``, with the unabsorbed rest at
    ``far``), ``opacity`` ``(R,)`` ``sum w_i``, and per sample ``weights``, ``transmittance`` ``T_i`` and
    ``alpha`` ``(R, S)``."""

    color: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    weights: torch.Tensor
    transmittance: torch.Tensor
    alpha: torch.Tensor


def interval_lengths(t: torch.Tensor, far: float | torch.Tensor,
                     direction_norm: torch.Tensor | None = None) -> torch.Tensor:
    """``delta_i = (t_(i+1) - t_i) |d|`` ``(R, S)`` with ``t_(S+1) = far``; ``direction_norm`` ``(R,)``
    (None: unit directions)."""
    far_t = torch.as_tensor(far, dtype=t.dtype, device=t.device).expand(t.shape[:-1])[..., None]
    delta = torch.diff(t, dim=-1, append=far_t)
    if torch.any(delta < 0):
        raise InvalidValue("t", "samples must be sorted along each ray and lie before far")
    return delta if direction_norm is None else delta * direction_norm[..., None]


def volume_render(sigma: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor, *, far: float | torch.Tensor,
                  direction_norm: torch.Tensor | None = None,
                  background: torch.Tensor | None = None) -> VolumeRendering:
    """Composite ``R`` rays of ``S`` samples (the module docstring's equations, Mildenhall et al. eq. 3).

    ``sigma`` ``(R, S)`` >= 0, ``rgb`` ``(R, S, 3)``, sorted depths ``t`` ``(R, S)`` < ``far``;
    ``direction_norm`` ``(R,)`` turns depth steps into distances; ``background`` ``(3,)`` is what is seen
    through what is left (None: black). ``T_i`` is computed as ``exp(-exclusive cumsum(sigma delta))``,
    which equals the product of ``1 - alpha_j`` and keeps its gradient finite. Oracle:
    :func:`~lab.modules.nerf.reference.volume_render_reference` (the product, one ray at a time).
    """
    if sigma.shape != t.shape or rgb.shape != (*t.shape, 3):
        raise InvalidValue("sigma", f"expected sigma (R, S), rgb (R, S, 3) and t (R, S), got "
                                    f"{tuple(sigma.shape)}, {tuple(rgb.shape)}, {tuple(t.shape)}")
    tau = sigma * interval_lengths(t, far, direction_norm)                 # optical depth of each interval
    alpha = -torch.expm1(-tau)                                             # 1 - exp(-tau)
    transmittance = torch.exp(-(torch.cumsum(tau, dim=-1) - tau))          # exclusive: T_1 = 1
    weights = transmittance * alpha
    opacity = weights.sum(dim=-1)
    color = (weights[..., None] * rgb).sum(dim=-2)
    if background is not None:
        color = color + (1.0 - opacity)[..., None] * background
    far_t = torch.as_tensor(far, dtype=t.dtype, device=t.device)
    depth = (weights * t).sum(dim=-1) + (1.0 - opacity) * far_t
    return VolumeRendering(color, depth, opacity, weights, transmittance, alpha)


def sample_pdf(edges: torch.Tensor, weights: torch.Tensor, count: int, *, deterministic: bool = False,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """Inverse-transform samples ``(R, count)`` of the piecewise-constant PDF of ``weights`` ``(R, M)`` over
    the bins ``[edges_j, edges_(j+1)]`` (``edges`` ``(R, M + 1)``, increasing): Mildenhall et al. 2020,
    section 5.2.

    ``pdf_j = (w_j + eps) / sum (w + eps)``, ``cdf = (0, pdf_1, pdf_1 + pdf_2, ..., 1)``; each
    ``u ~ U[0, 1)`` (from ``generator``, on the CPU; ``deterministic``: ``(k + 0.5) / count``) falls in
    the bin ``j`` with ``cdf_j <= u < cdf_(j+1)`` and maps linearly inside it:
    ``edges_j + (u - cdf_j) / pdf_j (edges_(j+1) - edges_j)``. No gradient flows through the samples.
    Oracle: :func:`~lab.modules.nerf.reference.sample_pdf_reference`.
    """
    if edges.ndim != 2 or weights.shape != (edges.shape[0], edges.shape[1] - 1):
        raise InvalidValue("weights", f"expected edges (R, M + 1) and weights (R, M), got "
                                      f"{tuple(edges.shape)} and {tuple(weights.shape)}")
    edges, weights = edges.detach(), weights.detach()
    w = weights + PDF_EPSILON
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    cdf[:, -1] = 1.0
    rays = edges.shape[0]
    if deterministic:
        u = ((torch.arange(count, dtype=edges.dtype, device=edges.device) + 0.5) / count).expand(rays, count)
    else:
        u = torch.rand((rays, count), generator=generator, dtype=edges.dtype).to(edges.device)
    u = u.contiguous()
    index = torch.searchsorted(cdf, u, right=True)                          # cdf[index - 1] <= u < cdf[index]
    below = (index - 1).clamp(0, weights.shape[1] - 1)
    cdf_lo, cdf_hi = cdf.gather(1, below), cdf.gather(1, below + 1)
    lo, hi = edges.gather(1, below), edges.gather(1, below + 1)
    span = cdf_hi - cdf_lo
    fraction = torch.where(span > 0, (u - cdf_lo) / torch.where(span > 0, span, 1.0), 0.0)
    return lo + fraction * (hi - lo)


def hierarchical_samples(t: torch.Tensor, weights: torch.Tensor, far: float | torch.Tensor, count: int, *,
                         deterministic: bool = False,
                         generator: torch.Generator | None = None) -> torch.Tensor:
    """Coarse depths ``t`` ``(R, S)`` and ``count`` fine ones drawn from their weights (:func:`sample_pdf`
    over the intervals ``[t_i, t_(i+1)]``, ``t_(S+1) = far``), merged and sorted: ``(R, S + count)``
    (section 5.2: the fine network is evaluated at the union)."""
    far_t = torch.as_tensor(far, dtype=t.dtype, device=t.device).expand(t.shape[:-1])[..., None]
    edges = torch.cat([t.detach(), far_t], dim=-1)
    fine = sample_pdf(edges, weights, count, deterministic=deterministic, generator=generator)
    merged, _ = torch.sort(torch.cat([t.detach(), fine], dim=-1), dim=-1)
    return merged


@dataclass(frozen=True, eq=False)
class PackedRendering:
    """What :func:`volume_render_packed` computes: per ray ``color`` ``(R, 3)``, ``depth`` and ``opacity``
    ``(R,)``; per sample ``weights`` ``(K,)``."""

    color: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    weights: torch.Tensor


def volume_render_packed(sigma: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor, delta: torch.Tensor,
                         ray: torch.Tensor, rays: int, *, far: float,
                         background: torch.Tensor | None = None) -> PackedRendering:
    """:func:`volume_render` of samples packed ray after ray (nerfacc's layout): sample ``k`` of density
    ``sigma`` ``(K,)``, colour ``rgb`` ``(K, 3)``, depth ``t`` ``(K,)`` and interval length ``delta`` ``(K,)``
    (a distance) belongs to ray ``ray[k]`` (non-decreasing, in ``[0, rays)``); samples left out of a ray
    are empty space (density 0), so rays keep different numbers of samples. ``T_k`` is the exclusive
    sum of ``sigma delta`` within the ray, from one float64 running sum over all samples minus its value
    where the ray starts. Oracle: :func:`volume_render` on the dense samples with zero densities where
    samples are left out.
    """
    tau = (sigma * delta).double()
    running = torch.cumsum(tau, dim=0) - tau                                # exclusive, across rays
    counts = torch.bincount(ray, minlength=rays)
    starts = torch.cumsum(counts, dim=0) - counts
    base = running[starts.clamp(max=max(len(tau) - 1, 0))] if len(tau) else running.new_zeros(rays)
    transmittance = torch.exp(-(running - base[ray])).to(sigma.dtype)
    weights = transmittance * -torch.expm1(-sigma * delta)
    opacity = torch.zeros(rays, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, weights)
    color = torch.zeros((rays, 3), dtype=sigma.dtype, device=sigma.device).index_add(0, ray,
                                                                                     weights[:, None] * rgb)
    if background is not None:
        color = color + (1.0 - opacity)[:, None] * background
    depth = torch.zeros(rays, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, weights * t)
    return PackedRendering(color, depth + (1.0 - opacity) * far, opacity, weights)


__all__ = ["PDF_EPSILON", "PackedRendering", "VolumeRendering", "hierarchical_samples", "interval_lengths",
           "sample_pdf", "volume_render", "volume_render_packed"]
