"""Real spherical harmonics up to degree 3, as 3D Gaussian splatting evaluates its view-dependent colour.

The basis, its constants and its signs are those of the paper's code (``utils/sh_utils.py`` and
``computeColorFromSH``, after Plenoxels/PlenOctrees, Yu et al. 2021): the real, orthonormal spherical
harmonics ``Y_lm`` over the unit sphere, in the order ``l = 0; l = 1: m = -1, 0, 1; ...`` (16 functions up
to degree 3). Colour of a Gaussian seen along unit direction ``d``: ``max(0, sum_k c_k Y_k(d) + 0.5)``.
"""

from __future__ import annotations

import torch

from lab.core import InvalidValue

#: The largest degree the representation holds (16 coefficients per channel).
MAX_SH_DEGREE = 3
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def sh_count(degree: int) -> int:
    """Coefficients per channel up to ``degree``: ``(degree + 1)^2``."""
    return (degree + 1) ** 2


def check_sh(degree: int, coefficients: int) -> None:
    """Refuse a degree outside ``0 .. MAX_SH_DEGREE`` or fewer than its ``(degree + 1)^2`` coefficients per
    channel (``coefficients``)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise InvalidValue("sh_degree", f"must be 0 to {MAX_SH_DEGREE}, got {degree}")
    if coefficients < sh_count(degree):
        raise InvalidValue("sh", f"degree {degree} needs {sh_count(degree)} coefficients per channel, got "
                                 f"{coefficients}")


def sh_basis(directions: torch.Tensor, degree: int) -> torch.Tensor:
    """The real spherical harmonics ``Y_k(d)`` ``(N, (degree + 1)^2)`` at unit directions ``d`` (N, 3)."""
    return torch.stack(_basis_terms(directions, degree), dim=-1)


def _basis_terms(directions: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """:func:`sh_basis`'s columns, each (N,)."""
    check_sh(degree, sh_count(degree))
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, C0)]
    if degree >= 1:
        terms += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        terms += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                  C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                  C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return terms


def sh_colors(sh: torch.Tensor, directions: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB ``(N, 3)`` = ``max(0, sum_k sh[:, k] Y_k(d) + 0.5)`` over the first ``(degree + 1)^2`` of the
    coefficients ``sh`` (N, K, 3) (K >= that count)."""
    count = sh_count(degree)
    check_sh(degree, sh.shape[-2])
    terms = _basis_terms(directions, degree)
    total = C0 * sh[:, 0] + 0.5                # Y_0 = C0
    for k in range(1, count):          # term by term: on the CPU faster than one (N, K) x (N, K, 3) product
        total = total + terms[k][:, None] * sh[:, k]
    return torch.clamp_min(total, 0.0)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """The degree-0 coefficient giving colour ``rgb`` (the code's ``RGB2SH``: ``(rgb - 0.5) / C0``)."""
    return (rgb - 0.5) / C0


def sh_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """The view-independent colour of a degree-0 coefficient, ``C0 dc + 0.5`` (``SH2RGB``)."""
    return dc * C0 + 0.5


__all__ = ["C0", "C1", "C2", "C3", "MAX_SH_DEGREE", "check_sh", "rgb_to_sh", "sh_basis", "sh_colors",
           "sh_count", "sh_to_rgb"]
