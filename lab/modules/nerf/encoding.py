"""Positional encoding (Mildenhall et al. 2020, section 5.1).

``gamma(p) = (sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p))``, applied to each
coordinate of ``p`` separately; the paper uses L = 10 for positions and L = 4 for view directions.
The paper's formula has no identity term, but its reference code (``run_nerf_helpers.get_embedder``,
``include_input=True``) puts ``p`` itself first, and so does this one by default
(``include_input=False`` is the formula alone). The paper's formula has the factor pi, the reference
code does not (it feeds ``sin(2^k p)``); this follows the paper, which is why positions are first
normalized to the unit ball (:class:`~lab.modules.nerf.values.SceneBounds`).

Layout of the last axis (as the reference code): ``[p, sin(2^0 pi p), cos(2^0 pi p), sin(2^1 pi p), ...]``,
each block ``D`` wide, so ``D (include_input + 2 L)`` values in all.
"""

from __future__ import annotations

import math

import torch

from lab.core import InvalidControl


def encoding_size(frequencies: int, *, include_input: bool = True, dim: int = 3) -> int:
    """Width of :func:`positional_encoding` of ``dim``-vectors: ``dim (include_input + 2 frequencies)``."""
    return dim * (int(include_input) + 2 * frequencies)


def positional_encoding(p: torch.Tensor, frequencies: int, *, include_input: bool = True) -> torch.Tensor:
    """``gamma(p)`` ``(..., D (include_input + 2 L))`` of points ``p`` ``(..., D)`` with ``L = frequencies``.

    Oracle: :func:`~lab.modules.nerf.reference.positional_encoding_reference`.
    """
    if frequencies < 0:
        raise InvalidControl("frequencies", f"must be >= 0, got {frequencies}")
    scales = math.pi * 2.0 ** torch.arange(frequencies, dtype=p.dtype, device=p.device)   # (L,)
    angles = p[..., None, :] * scales[:, None]                                            # (..., L, D)
    pairs = torch.stack([torch.sin(angles), torch.cos(angles)], dim=-2)                   # (..., L, 2, D)
    encoded = pairs.reshape(*p.shape[:-1], 2 * frequencies * p.shape[-1])
    return torch.cat([p, encoded], dim=-1) if include_input else encoded


__all__ = ["encoding_size", "positional_encoding"]
