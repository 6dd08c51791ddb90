"""The representation of 3D Gaussian splatting and its projection to the image (Kerbl et al. 2023).

Each Gaussian has a mean ``mu`` (3,), a log-scale ``log s`` (3,), a rotation quaternion ``q = (w, x, y, z)``
(not necessarily of unit length: it is normalized where it is used, as in the paper's code), an opacity
logit (``o = sigmoid(logit)``) and spherical-harmonic colour coefficients ``(16, 3)`` up to degree 3
(``sh_dc`` the first, ``sh_rest`` the 15 others). Section 4 of the paper, and its code, define:

- the covariance ``Sigma = R S S^T R^T`` with ``S = diag(exp(log s))`` and ``R`` the quaternion's rotation
  (eq. 6);
- its image-space covariance ``Sigma' = J W Sigma W^T J^T`` (eq. 5, after Zwicker et al. 2001, EWA
  splatting, eq. 31), ``W`` the world-to-camera rotation and ``J`` the Jacobian of the perspective map at
  the mean, plus a low-pass dilation of 0.3 px^2 on the diagonal (the code's ``computeCov2D``);
- its conic ``Sigma'^-1`` (a, b, c), its screen radius ``ceil(3 sqrt(lambda_max))`` and the rectangle of
  16 x 16 px tiles it touches (section 6, ``getRect``);
- its colour seen along the view direction from the spherical harmonics (:mod:`.sh`).

Pixel coordinates are the lab's (pixel (0, 0)'s centre at (0, 0)), which is the paper's code's
``ndc2Pix`` convention too, so a pinhole ``K`` maps the mean straight to the pixel it is evaluated at.
Everything here is vectorized torch with autograd: the fast path's projection (the compositing is in
:mod:`.rasterize`); :mod:`.reference` has the per-Gaussian loop version.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from lab.core import Cameras, InvalidValue
from lab.modules.splatting.sh import sh_colors

#: Points nearer than this depth (camera z) are not drawn (the code's ``in_frustum``: ``p_view.z <= 0.2``).
NEAR_PLANE = 0.2
#: The low-pass filter added to the 2D covariance's diagonal (px^2; the code's ``cov[0][0] += 0.3``).
DILATION = 0.3
#: Side of a tile in pixels (the code's ``BLOCK_X = BLOCK_Y = 16``).
TILE_SIZE = 16


@dataclass(frozen=True, eq=False)
class View:
    """One pinhole camera for rendering, as float tensors: world-to-camera ``R`` (3, 3) and ``t`` (3,), the
    focal lengths and principal point in pixels, and the image size."""

    R: torch.Tensor
    t: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def center(self) -> torch.Tensor:
        """The camera centre in the world, ``-R^T t`` (3,)."""
        return -self.R.T @ self.t


def view_of(cameras: Cameras, index: int, *, dtype: torch.dtype = torch.float32,
            device: str | torch.device = "cpu") -> View:
    """Camera ``index`` of ``cameras`` as a :class:`View` (pinhole: distortion and skew must be absent)."""
    if not 0 <= index < len(cameras):
        raise InvalidValue("view", f"camera {index} does not exist: there are {len(cameras)}")
    K = cameras.K[index]
    if abs(K[0, 1]) > 1e-9:
        raise InvalidValue("cameras", f"camera {index} has skew {K[0, 1]:g}: splatting takes pinhole cameras")
    if cameras.dist is not None and np.any(cameras.dist[index] != 0):
        raise InvalidValue("cameras", f"camera {index} has lens distortion: undistort the images first")
    return View(torch.as_tensor(cameras.R[index], dtype=dtype, device=device),
                torch.as_tensor(cameras.t[index], dtype=dtype, device=device),
                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), cameras.width, cameras.height)


def _rotation_entries(quats: torch.Tensor) -> list[torch.Tensor]:
    """The nine entries ``R_00, R_01, ..., R_22`` (each (N,)) of the rotations of quaternions ``(N, 4)``
    ``(w, x, y, z)``, normalized first (the code's ``build_rotation``)."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]


def quaternion_rotations(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(N, 3, 3)`` of quaternions ``(N, 4)`` ``(w, x, y, z)``, normalized first (the
    code's ``build_rotation``)."""
    return torch.stack(_rotation_entries(quats), dim=-1).reshape(*quats.shape[:-1], 3, 3)


def covariances(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """``Sigma = R S S^T R^T`` ``(N, 3, 3)`` (Kerbl et al. 2023, eq. 6), ``S = diag(exp(log_scales))``."""
    M = quaternion_rotations(quats) * torch.exp(log_scales)[..., None, :]   # R S
    return M @ M.transpose(-1, -2)


@dataclass(frozen=True, eq=False)
class Projected:
    """Gaussians in the image (every tensor has the Gaussians' length ``N``): ``means2d`` (N, 2) px, the
    ``conics`` (N, 3) ``(a, b, c)`` of ``Sigma'^-1 = [[a, b], [b, c]]``, the camera ``depths`` (N,), the
    integer ``radii`` (N,) in pixels (0: not drawn: behind the near plane, degenerate, or off screen) and the
    tile rectangles ``rects`` (N, 4) ``(x0, y0, x1, y1)``, tiles ``x0 <= tx < x1``, ``y0 <= ty < y1``."""

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    rects: torch.Tensor


def image_covariances(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      view: View) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame means ``(N, 3)`` and ``Sigma' = J W Sigma W^T J^T + 0.3 I`` ``(N, 2, 2)`` (eq. 5 and the
    dilation) of the Gaussians' ``Sigma = R S S^T R^T`` (eq. 6); :func:`_image_footprints` the same as
    separate entries (what :func:`project` uses)."""
    (px, py, pz), (a, b, c) = _image_footprints(means, log_scales, quats, view)
    return torch.stack([px, py, pz], dim=-1), torch.stack([a, b, b, c], dim=-1).reshape(-1, 2, 2)


def _image_footprints(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      view: View) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """The camera-frame mean ``(x, y, z)`` and the image covariance's entries ``(a, b, c)`` of
    ``Sigma' = [[a, b], [b, c]] = J W Sigma W^T J^T + 0.3 I``, each (N,).

    ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` at the camera-frame mean, whose ``x/z`` and ``y/z``
    are first clamped to 1.3 times the half field of view (the code's ``limx``; gsplat's form of it for an
    off-centre principal point) so that Gaussians far outside the view stay finite. ``Sigma' = V V^T`` with
    ``V = J W R S`` (2 x 3), written out entry by entry: on the CPU a few dozen element-wise operations on
    (N,) vectors cost a tenth of the batched 3 x 3 products (and their autograd) they replace."""
    W = view.R.detach().cpu().tolist()
    t = view.t.detach().cpu().tolist()
    mx, my, mz = means.unbind(-1)
    x = W[0][0] * mx + W[0][1] * my + W[0][2] * mz + t[0]
    y = W[1][0] * mx + W[1][1] * my + W[1][2] * mz + t[1]
    z = W[2][0] * mx + W[2][1] * my + W[2][2] * mz + t[2]
    tan_x, tan_y = 0.5 * view.width / view.fx, 0.5 * view.height / view.fy
    u = torch.clamp(x / z, -(view.cx / view.fx + 0.3 * tan_x),
                    (view.width - view.cx) / view.fx + 0.3 * tan_x)
    v = torch.clamp(y / z, -(view.cy / view.fy + 0.3 * tan_y),
                    (view.height - view.cy) / view.fy + 0.3 * tan_y)
    fx_z, fy_z = view.fx / z, view.fy / z
    # the rows of T = J W: T_0j = fx/z (W_0j - u W_2j), T_1j = fy/z (W_1j - v W_2j)
    T0 = [fx_z * (W[0][j] - u * W[2][j]) for j in range(3)]
    T1 = [fy_z * (W[1][j] - v * W[2][j]) for j in range(3)]
    R = _rotation_entries(quats)
    s = torch.exp(log_scales).unbind(-1)
    V0 = [(T0[0] * R[k] + T0[1] * R[3 + k] + T0[2] * R[6 + k]) * s[k] for k in range(3)]
    V1 = [(T1[0] * R[k] + T1[1] * R[3 + k] + T1[2] * R[6 + k]) * s[k] for k in range(3)]
    a = V0[0] * V0[0] + V0[1] * V0[1] + V0[2] * V0[2] + DILATION
    b = V0[0] * V1[0] + V0[1] * V1[1] + V0[2] * V1[2]
    c = V1[0] * V1[0] + V1[1] * V1[1] + V1[2] * V1[2] + DILATION
    return (x, y, z), (a, b, c)


def tile_rects(means2d: torch.Tensor, radii: torch.Tensor, view: View, tile_size: int) -> torch.Tensor:
    """The tiles ``(N, 4)`` ``(x0, y0, x1, y1)`` that a square of half-side ``radius`` about the mean
    touches, clipped to the tile grid (the code's ``getRect``)."""
    grid = torch.tensor([math.ceil(view.width / tile_size), math.ceil(view.height / tile_size)],
                        device=means2d.device)
    centre = means2d.detach()
    r = radii[:, None].to(centre.dtype)
    low = torch.clamp(torch.floor((centre - r) / tile_size).long(), min=0)
    high = torch.clamp(torch.floor((centre + r + tile_size - 1) / tile_size).long(), min=0)
    return torch.cat([torch.minimum(low, grid), torch.minimum(high, grid)], dim=1)


def project(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, view: View, *,
            tile_size: int = TILE_SIZE, near: float = NEAR_PLANE) -> Projected:
    """Project Gaussians into ``view`` (Kerbl et al. 2023, section 4 and the code's ``preprocessCUDA``).

    Means go through the pinhole, ``u = fx x/z + cx``, ``v = fy y/z + cy``; the 2D covariance is
    :func:`image_covariances`; the conic is its inverse; the radius ``ceil(3 sqrt(lambda_max))`` of its
    larger eigenvalue ``lambda_max = m + sqrt(max(0.1, m^2 - det))``, ``m = (a + c) / 2``. A Gaussian whose
    depth is at most ``near``, whose 2D covariance is not positive definite, or whose tile rectangle is
    empty gets radius 0 (its conic and mean stay finite, it is not drawn).
    """
    (x, y, z), (a, b, c) = _image_footprints(means, log_scales, quats, view)
    safe_z = torch.where(z > near, z, torch.ones_like(z))
    means2d = torch.stack([view.fx * x / safe_z + view.cx, view.fy * y / safe_z + view.cy], dim=-1)
    det = a * c - b * b
    ok = (z > near) & (det > 0)
    safe_det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lambda_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radii = torch.where(ok, torch.ceil(3.0 * torch.sqrt(torch.clamp(lambda_max, min=0.0))),
                            torch.zeros_like(z)).long()
        rects = tile_rects(means2d, radii, view, tile_size)
        empty = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1]) == 0
        radii = torch.where(empty, torch.zeros_like(radii), radii)
        rects = torch.where((radii > 0)[:, None], rects, torch.zeros_like(rects))
    return Projected(means2d, conics, z, radii, rects)


def view_colors(means: torch.Tensor, sh: torch.Tensor, degree: int, view: View) -> torch.Tensor:
    """RGB ``(N, 3)`` of each Gaussian seen from ``view``'s centre: the spherical harmonics ``sh`` (N, K, 3)
    up to ``degree`` along the unit direction from the camera to the mean, plus 0.5, clamped at 0
    (the code's ``computeColorFromSH``)."""
    directions = means - view.center
    directions = directions / torch.linalg.vector_norm(directions, dim=-1, keepdim=True).clamp_min(1e-12)
    return sh_colors(sh, directions, degree)


def activated_opacities(opacity_logits: torch.Tensor) -> torch.Tensor:
    """``o = sigmoid(logit)`` (N,) in (0, 1) (the paper's activation of the opacity)."""
    return torch.sigmoid(opacity_logits)


__all__ = ["DILATION", "NEAR_PLANE", "TILE_SIZE", "Projected", "View", "activated_opacities", "covariances",
           "image_covariances", "project", "quaternion_rotations", "tile_rects", "view_colors", "view_of"]
